"""The labelling scene's colours: every candidate's rank colour stands apart from the rope."""

from __future__ import annotations

import itertools

import numpy as np

from knotlab.app.web.scene import CLOUD_COLOUR, GREY, RANK_COLOURS, ROPE_COLOUR


def _lab(rgb: tuple[int, int, int]) -> np.ndarray:
    """CIELAB (D65) of an sRGB colour."""
    c = np.asarray(rgb, dtype=float) / 255
    c = np.where(c > 0.04045, ((c + 0.055) / 1.055) ** 2.4, c / 12.92)
    m = np.array([[0.4124, 0.3576, 0.1805], [0.2126, 0.7152, 0.0722], [0.0193, 0.1192, 0.9505]])
    xyz = m @ c / np.array([0.95047, 1.0, 1.08883])
    f = np.where(xyz > 0.008856, np.cbrt(xyz), 7.787 * xyz + 16 / 116)
    return np.array([116 * f[1] - 16, 500 * (f[0] - f[1]), 200 * (f[1] - f[2])])


def _distance(a: tuple[int, int, int], b: tuple[int, int, int]) -> float:
    return float(np.linalg.norm(_lab(a) - _lab(b)))


def test_the_shown_ranks_are_coloured_far_from_the_rope_the_cloud_and_each_other():
    shown = RANK_COLOURS[:5]  # the app shows five candidates
    for colour in shown:
        # 40 CIELAB units: clearly another colour (the old orange #2 was 34 from the rope).
        assert _distance(colour, ROPE_COLOUR) > 40, colour
        assert _distance(colour, CLOUD_COLOUR) > 40, colour
        assert _distance(colour, GREY) > 30, colour
    assert min(_distance(a, b) for a, b in itertools.combinations(shown, 2)) > 40
