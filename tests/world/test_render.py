"""Top-down drawings: the still picture of a rope and the set-up the playback frames share."""

from __future__ import annotations

import numpy as np
from PIL import Image

from knotlab.core.world.render import render_topdown, rope_width_pt, table_axes, table_figure


def _wavy_nodes() -> np.ndarray:
    u = np.linspace(0, 1, 41)
    return np.column_stack([u - 0.5, 0.05 * np.sin(2 * np.pi * u), np.full(len(u), 0.01)])


def _looped_nodes() -> np.ndarray:
    """A rope that crosses itself once: the lower strand at z = 0.01, the upper one above it."""
    t = np.linspace(-1.0, 1.0, 41)
    x, y = 0.3 * t, 0.15 * (1 - t**2) - 0.05
    z = np.where(t > 0.5, 0.03, 0.01)
    return np.column_stack([x * np.cos(np.pi * t), y, z])


def test_render_topdown_writes_a_png_one_panel_wide_without_crossings(tmp_path) -> None:
    out = render_topdown(_wavy_nodes(), tmp_path / "sub" / "rope.png", radius=0.01, size=200)
    data = out.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 1000
    assert Image.open(out).size == (200, 200)


def test_render_topdown_adds_a_close_up_where_the_rope_crosses(tmp_path) -> None:
    out = render_topdown(_looped_nodes(), tmp_path / "knot.png", radius=0.01, size=200, title="t")
    assert Image.open(out).size == (400, 200)


def test_table_set_up_has_the_asked_pixels_limits_and_rope_width() -> None:
    fig, canvas = table_figure(300, 200)
    ax = table_axes(fig, (0.0, 0.0, 1.0, 1.0), np.array([0.1, -0.2]), 0.5)
    canvas.draw()
    assert np.asarray(canvas.buffer_rgba()).shape == (200, 300, 4)
    assert ax.get_xlim() == (0.1 - 0.25, 0.1 + 0.25) and ax.get_ylim() == (-0.2 - 0.25, -0.2 + 0.25)
    # 2 cm over a 1 m span drawn 500 px tall is 10 px: 7.2 points at 100 dpi
    assert np.isclose(rope_width_pt(0.02, 500, 1.0), 7.2)
