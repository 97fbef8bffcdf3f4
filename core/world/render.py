"""Top-down drawings of the rope on the table (matplotlib, Agg backend, no display needed).

`render_topdown` writes the still picture of a rope (`knotlab tie`); `table_figure`,
`table_axes`, `rope_width_pt` and `thick_line` are the set-up it shares with the playback
animation's frames, so both views draw the table, the limits and the rope the same way.
Shape suffixes: k = rope nodes, m = segment midpoints, 2/3 = xy/xyz.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:  # matplotlib is imported when something is drawn, not with this module
    from matplotlib.axes import Axes
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from matplotlib.lines import Line2D

DPI = 100
TABLE_COLOUR = "#e9e4d8"


def table_figure(width_px: int, height_px: int) -> tuple[Figure, FigureCanvasAgg]:
    """A figure of width_px x height_px pixels and the Agg canvas it draws on."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width_px / DPI, height_px / DPI), dpi=DPI)
    return fig, FigureCanvasAgg(fig)


def table_axes(
    fig: Figure, rect: tuple[float, float, float, float], centre_2: np.ndarray, span: float
) -> Axes:
    """Axes at ``rect`` showing the square of side ``span`` (m) around ``centre_2`` on the table."""
    ax = fig.add_axes(rect)
    ax.set_facecolor(TABLE_COLOUR)
    ax.set_xlim(centre_2[0] - span / 2, centre_2[0] + span / 2)
    ax.set_ylim(centre_2[1] - span / 2, centre_2[1] + span / 2)
    ax.set_aspect("equal")
    ax.set_xticks([])
    ax.set_yticks([])
    return ax


def rope_width_pt(diameter_m: float, px: float, span: float) -> float:
    """Line width (points) drawing ``diameter_m`` to scale where ``span`` m cover ``px`` pixels."""
    return diameter_m * px / DPI * 72 / span


def thick_line(
    ax: Axes,
    x: Sequence[float] | np.ndarray,
    y: Sequence[float] | np.ndarray,
    *,
    color: str | np.ndarray,
    width: float,
) -> Line2D:
    """A polyline of ``width`` points with round caps: the rope, or one of its segments."""
    (line,) = ax.plot(x, y, color=color, lw=width, solid_capstyle="round")
    return line


def render_topdown(
    nodes_k3: np.ndarray,
    path: str | Path,
    *,
    radius: float,
    size: int = 800,
    title: str | None = None,
) -> Path:
    """Write a top-down PNG of the rope (left) and a close-up of where it crosses (right).

    Segments are drawn from lowest to highest with a white rim, so the strand on top at a
    crossing visibly covers the one below. ``radius`` (m) sets the drawn rope's thickness.
    """
    nodes = np.asarray(nodes_k3, dtype=float)
    xy = nodes[:, :2]
    # Close-up: nodes within 3 cm (in xy) of a node at least 3 links away along the rope.
    gap_kk = np.linalg.norm(xy[:, None] - xy[None], axis=2)
    far_kk = np.abs(np.arange(len(xy))[:, None] - np.arange(len(xy))[None]) >= 3
    near = (gap_kk < 0.03) & far_kk
    busy = xy[near.any(axis=1)]
    panels = [(xy.min(axis=0), xy.max(axis=0), 0.08)]
    if len(busy):
        panels.append((busy.min(axis=0), busy.max(axis=0), 0.04))
    fig, _ = table_figure(size * len(panels), size)
    top = 0.9 if title else 0.98
    for p_i, (lo, hi, margin) in enumerate(panels):
        centre, span = 0.5 * (lo + hi), float((hi - lo).max()) + 2 * margin
        ax = table_axes(
            fig, (p_i / len(panels) + 0.01, 0.02, 1 / len(panels) - 0.02, top - 0.02), centre, span
        )
        _draw_rope(ax, nodes, rope_width_pt(2 * radius, size * (top - 0.02), span))
        if p_i == 1:
            ax.set_title("close-up of the crossings", fontsize=10)
    if title:
        fig.suptitle(title)
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=DPI)
    return out


def _draw_rope(ax: Axes, nodes_k3: np.ndarray, width: float) -> None:
    """The rope segment by segment, coloured along its length, ends labelled A and B."""
    import matplotlib

    n = len(nodes_k3) - 1
    colours = matplotlib.colormaps["viridis"](np.linspace(0.1, 0.9, n))
    rim = max(1.5, 0.25 * width)
    mid_m3 = 0.5 * (nodes_k3[:-1] + nodes_k3[1:])
    # A white rim only where a segment lies over another one: elsewhere rims would show
    # as white ticks at every joint.
    close = np.linalg.norm(mid_m3[:, None, :2] - mid_m3[None, :, :2], axis=2) < 0.03
    apart = np.abs(np.arange(n)[:, None] - np.arange(n)[None]) >= 2
    above = mid_m3[:, None, 2] > mid_m3[None, :, 2] + 0.005
    on_top = (close & apart & above).any(axis=1)
    for i in np.argsort(mid_m3[:, 2], kind="stable"):
        seg = nodes_k3[i : i + 2]
        if on_top[i]:
            thick_line(ax, seg[:, 0], seg[:, 1], color="white", width=width + rim)
        thick_line(ax, seg[:, 0], seg[:, 1], color=colours[i], width=width)
    a_x, a_y, _ = nodes_k3[0]
    b_x, b_y, _ = nodes_k3[-1]
    ax.annotate("A", (a_x, a_y), xytext=(-14, -14), textcoords="offset points")
    ax.annotate("B", (b_x, b_y), xytext=(6, 6), textcoords="offset points")
