"""Where a rope's ends are: the one place a camera cloud says *which part* of the rope it sees.

A tracker's pull moves its chain across the rope only (points say where the rope is, not which
part of it), so a chain that slid along the rope while the model predicted a motion stays slid:
its shape fits the cloud while every node names another piece of rope, and the slide grows step
by step. The cloud's two ends do tell: a chain slid by d overshoots the visible rope by d at one
end and stops d short of it at the other. `slide_to_ends` measures that slide at both ends and,
where the two agree in direction and the slide leaves the chain's crossings as they were, moves
the chain's nodes along the chain's own curve by it (docs/robustness.md, "The rope's ends").
Shape suffixes: k = rope nodes, n = cloud points, m = segments.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from knotlab.core.world.knot import canonical_code, gauss_code
from knotlab.core.world.rope import arc_lengths, segment_feet

END_SEARCH = 0.08  # m: how far past a chain's end its extension looks for the rope
END_DEAD_BAND = 0.005  # m: a slide within the cloud's voxel and noise is no evidence
TRACE_STEP = 0.01  # m: the step of an extension that follows the visible rope past an end
# Where the visible rope ends, relative to the end nodes: about 3 mm before the first node (the
# camera's noise spreads the tube's end outwards) and 3 mm before the last (the surface samples
# of a link stop short of its far node), so both readings add this: measured on the main
# training starts' ropes and their own noisy clouds; the tests check it on seeded curves.
END_OFFSET = 0.003  # m


@dataclass(frozen=True)
class EndReading:
    """What a cloud says of a chain's ends: the slide (m, positive = the rope lies further
    along the chain than its nodes say) read at the first and at the last end (None: no rope
    seen near that end), and the slide applied (0.0 unless both ends read a slide beyond the
    dead band in the same direction and it leaves the chain's crossings as they were; then the
    overshooting end's reading)."""

    first: float | None
    last: float | None
    applied: float


def read_ends(
    nodes_k3: np.ndarray, surface_n3: np.ndarray, *, radius: float, reach: float
) -> EndReading:
    """The slide of the chain (K, 3) along the rope that the cloud's two visible ends say."""
    return _read(
        np.asarray(nodes_k3, dtype=float), np.asarray(surface_n3, dtype=float), radius, reach
    )[0]


def _read(
    nodes: np.ndarray, surface: np.ndarray, radius: float, reach: float
) -> tuple[EndReading, tuple[np.ndarray, np.ndarray, float] | None]:
    """`read_ends`'s reading and the extended chain it was read along (None: no cloud)."""
    if len(surface) == 0 or len(nodes) < 2:
        return EndReading(None, None, 0.0), None
    extended = _extended(nodes, surface, radius)
    path_p3, arc_p, length = extended
    s_n, z_n, dist_n = _project_xy(path_p3, arc_p, surface)
    # The same height test as the pull's: the other strand at a crossing is a diameter away.
    mine = (dist_n < reach) & (np.abs(surface[:, 2] - radius - z_n) < radius)
    if not np.any(mine):
        return EndReading(None, None, 0.0), extended
    s = s_n[mine]
    # An end reading counts only when the rope is seen near that end at all.
    first = float(s.min()) + END_OFFSET if s.min() < END_SEARCH else None
    last = float(s.max()) + END_OFFSET - length if s.max() > length - END_SEARCH else None
    if first is None or last is None or min(abs(first), abs(last)) <= END_DEAD_BAND:
        return EndReading(first, last, 0.0), extended
    if (first > 0) != (last > 0):  # a chain too long or too short, or a hidden end: not a slide
        return EndReading(first, last, 0.0), extended
    # The end that overshoots the visible rope reads the slide along the chain itself; the end
    # that stops short reads it along an extension traced through the cloud, which loses a rope
    # that curls tightly or dips under a strand, so it only confirms the direction.
    return EndReading(first, last, first if first > 0 else last), extended


def slide_to_ends(
    nodes_k3: np.ndarray, surface_n3: np.ndarray, *, radius: float, reach: float
) -> tuple[np.ndarray, EndReading]:
    """The chain (K, 3) moved along its own curve by the slide its two ends agree on, unless
    that changes how it crosses itself (then, or where the ends disagree, the chain unchanged),
    and the reading acted on."""
    nodes = np.asarray(nodes_k3, dtype=float)
    reading, extended = _read(nodes, np.asarray(surface_n3, dtype=float), radius, reach)
    if reading.applied == 0.0 or extended is None:
        return nodes, reading
    path_p3, arc_p, _ = extended
    node_arc_k = arc_lengths(nodes) + np.clip(reading.applied, -END_SEARCH, END_SEARCH)
    moved = np.stack([np.interp(node_arc_k, arc_p, path_p3[:, d]) for d in range(3)], axis=1)
    # A slide that changes how the chain crosses itself (a tail carried across a strand, or
    # drawn back from one) trades the knot's topology for position: not taken.
    if canonical_code(gauss_code(moved)[0]) != canonical_code(gauss_code(nodes)[0]):
        return nodes, replace(reading, applied=0.0)
    return moved, reading


def _extended(
    nodes_k3: np.ndarray, surface_n3: np.ndarray, radius: float
) -> tuple[np.ndarray, np.ndarray, float]:
    """The chain with an ``END_SEARCH`` extension past each end (`_traced`), the arc
    coordinates of its points with the chain's first node at 0, and the chain's length."""
    first = _traced(nodes_k3[0], nodes_k3[1], surface_n3, radius)
    last = _traced(nodes_k3[-1], nodes_k3[-2], surface_n3, radius)
    path = np.vstack([first[::-1], nodes_k3, last])
    seg_m = np.linalg.norm(np.diff(path, axis=0), axis=1)
    arc = np.concatenate([[0.0], np.cumsum(seg_m)])
    arc -= arc[len(first)]
    return path, arc, float(arc[len(first) + len(nodes_k3) - 1])


def _traced(
    end_3: np.ndarray, inner_3: np.ndarray, surface_n3: np.ndarray, radius: float
) -> np.ndarray:
    """``END_SEARCH`` of path past a chain's end, in ``TRACE_STEP`` steps (M, 3): each step
    follows the visible rope ahead where the cloud shows it (points a step away, ahead within
    45 degrees, at the end's height), else goes straight on; flat at the end's height. A
    straight extension would leave a curling tail and cross strands the rope does not."""
    heading = end_3[:2] - inner_3[:2]
    heading = heading / max(float(np.linalg.norm(heading)), 1e-12)
    level = np.abs(surface_n3[:, 2] - radius - end_3[2]) < radius if len(surface_n3) else []
    pts = surface_n3[level, :2] if len(surface_n3) else np.zeros((0, 2))
    here = end_3[:2].copy()
    out = []
    for _ in range(round(END_SEARCH / TRACE_STEP)):
        ahead = pts - here
        dist = np.linalg.norm(ahead, axis=1)
        near = (dist > 0.5 * TRACE_STEP) & (dist < 2.0 * TRACE_STEP)
        near &= ahead @ heading > np.cos(np.pi / 4) * dist
        if np.any(near):
            towards = ahead[near].mean(axis=0)
            heading = towards / max(float(np.linalg.norm(towards)), 1e-12)
        here = here + TRACE_STEP * heading
        out.append([here[0], here[1], end_3[2]])
    return np.asarray(out)


def _project_xy(
    path_p3: np.ndarray, arc_p: np.ndarray, points_n3: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each point's nearest place on the path in xy: its arc coordinate, the path's height
    there, and the xy distance (all (N,))."""
    t_nm, foot_nm3, dist_nm = segment_feet(points_n3, path_p3, xy_only=True)
    best_n = np.argmin(dist_nm, axis=1)
    rows = np.arange(len(points_n3))
    t_n = t_nm[rows, best_n]
    s_n = arc_p[best_n] + t_n * (arc_p[best_n + 1] - arc_p[best_n])
    return s_n, foot_nm3[rows, best_n, 2], dist_nm[rows, best_n]
