"""The labelling scene's colours (every candidate's rank colour stands apart from the rope) and
its table (cheap to draw in software WebGL when the app is told to render lite)."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
import viser

from knotlab.app.web.scene import (
    CLOUD_COLOUR,
    GREY,
    RANK_COLOURS,
    ROPE_COLOUR,
    add_table,
    grid_segments,
)


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


def test_the_grid_lines_cover_the_table_every_cell_with_darker_centre_lines():
    cells, centre = grid_segments(1.6, 1.2, 0.1)
    along_y = sorted({round(float(s[0, 0]), 6) for s in cells if s[0, 0] == s[1, 0]})
    along_x = sorted({round(float(s[0, 1]), 6) for s in cells if s[0, 1] == s[1, 1]})
    assert along_y == [round(k / 10, 6) for k in range(-8, 9) if k != 0]  # edges included
    assert along_x == [round(k / 10, 6) for k in range(-6, 7) if k != 0]
    assert len(cells) == len(along_y) + len(along_x)
    assert np.allclose(np.abs(cells[:, :, :2]).max(axis=(0, 1)), (0.8, 0.6))
    assert np.allclose(centre, [[(0, -0.6, 0), (0, 0.6, 0)], [(-0.8, 0, 0), (0.8, 0, 0)]])


@pytest.fixture
def server():
    s = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    yield s
    s.stop()


def test_a_lite_table_is_toon_and_its_grid_plain_lines_else_lit_and_shaded(server):
    table, grid = add_table(server.scene, lite=False)
    assert table.material == "standard" and table.receive_shadow
    assert isinstance(grid, viser.GridHandle)
    table, frame, cells, centre = add_table(server.scene, lite=True)  # replaces them
    assert table.material == "toon3" and not table.receive_shadow
    assert isinstance(cells, viser.LineSegmentsHandle) and isinstance(
        centre, viser.LineSegmentsHandle
    )
    assert np.asarray(cells.points).shape == (28, 2, 3)
    assert tuple(frame.position) == (0.0, 0.0, 0.0005)
