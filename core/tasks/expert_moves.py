"""What scripted experts are built from: one-gripper moves, points along the rope, start ropes.

Every task's expert works with the right gripper alone (the left one stays open and parked far
from the rope) and two kinds of move:
- **pick and place**: grasp a point, rise a little, move level, lower, release. A low lift drags
  the rest of the rope along the table, so what is moved passes over what it crosses.
- **pen laying**: grasp one end, lift it high so the rope hangs from it, and lay the rope down
  along a path while descending in proportion to the distance travelled. What is laid later lies
  on top, so one pen lay only makes crossings whose later-laid strand is over (a "descending"
  diagram, which alone is never knotted): every knot needs at least one pick-and-place that puts
  an earlier part over a later one.

Shape suffixes: k = rope nodes, t = waypoints, 2/3 = xy/xyz.
"""

from __future__ import annotations

import math
from enum import Enum

import numpy as np

from knotlab.core.errors import InvalidInputError
from knotlab.core.world.rope import arc_lengths, resample_by_arc_length
from knotlab.core.world.trajectory import GripperTrajectory, down_rotation

PARK_LEFT = np.array([-0.7, 0.4, 0.3])  # where the idle left gripper waits, far from the rope
LAY_BOTTOM = 0.02  # m: a pen lay ends this high, so the grasped end is set down, not pushed in


class RopeEnd(Enum):
    """One end of the rope: A is node 0, B the last node."""

    A = "A"
    B = "B"


def single_gripper_trajectory(
    points_t3: np.ndarray, closed_t: np.ndarray, speeds_t: np.ndarray
) -> GripperTrajectory:
    """Trajectory for the right gripper through `points`; leg t (ending at t) at speeds_t[t]."""
    points_t3 = np.asarray(points_t3, dtype=float)
    legs = np.linalg.norm(np.diff(points_t3, axis=0), axis=1)
    times_t = np.concatenate([[0.0], np.cumsum(legs / np.asarray(speeds_t, dtype=float)[1:])])
    n_t = points_t3.shape[0]
    pos_gt3 = np.stack([np.broadcast_to(PARK_LEFT, (n_t, 3)), points_t3])
    closed_gt = np.stack([np.zeros(n_t, dtype=bool), np.asarray(closed_t, dtype=bool)])
    rot_gt33 = np.broadcast_to(down_rotation(), (2, n_t, 3, 3))
    return GripperTrajectory(times_t, pos_gt3, rot_gt33, closed_gt)


def pick_place(
    pick_3: np.ndarray, lift: float, place_xy: np.ndarray, place_z: float, speed: float
) -> GripperTrajectory:
    """Pick at `pick_3`, rise by `lift`, move level to above `place_xy`, lower, release."""
    pick_3 = np.asarray(pick_3, dtype=float)
    up = pick_3 + np.array([0.0, 0.0, lift])
    over = np.array([place_xy[0], place_xy[1], up[2]])
    down = np.array([place_xy[0], place_xy[1], place_z])
    points = np.stack([pick_3, up, over, down, down])
    closed = np.array([True, True, True, True, False])
    # Lowering at half speed lets the rope touch down without bouncing.
    speeds = np.array([0.0, speed / 2, speed, speed / 2, speed])
    return single_gripper_trajectory(points, closed, speeds)


def pen_lay(
    nodes_k3: np.ndarray,
    end: RopeEnd,
    path_2: np.ndarray,
    top: float,
    *,
    grasp: float,
    speed: float,
) -> GripperTrajectory:
    """Grasp ``end`` ``grasp`` metres from its tip, lift it, and lay the rope along ``path_2``
    (xy waypoints) like a pen: from height ``top`` above the first waypoint down to
    `LAY_BOTTOM` at the last, in proportion to the distance travelled; then release."""
    path_2 = np.asarray(path_2, dtype=float)
    if path_2.ndim != 2 or path_2.shape[0] < 2 or path_2.shape[1] != 2:
        raise InvalidInputError(f"a pen path needs at least 2 xy waypoints, got {path_2.shape}")
    total = arc_lengths(nodes_k3)[-1]
    from_a = end is RopeEnd.A
    pick = point_at(nodes_k3, grasp if from_a else total - grasp)
    # Rise first above a point 4 cm further along the rope, so the end leaves the table before
    # it travels and does not drag through its neighbours.
    back = point_at(nodes_k3, grasp + 0.04 if from_a else total - grasp - 0.04)
    lift = np.array([back[0], back[1], 0.10])
    legs = np.linalg.norm(np.diff(path_2, axis=0), axis=1)
    if legs.sum() <= 0:
        raise InvalidInputError("a pen path must have length")
    frac = np.concatenate([[0.0], np.cumsum(legs)]) / legs.sum()
    path_z = top + (LAY_BOTTOM - top) * frac
    laying = np.column_stack([path_2, path_z])
    points = np.vstack([pick, lift, laying, laying[-1:]])
    closed = np.ones(points.shape[0], dtype=bool)
    closed[-1] = False
    speeds = np.full(points.shape[0], speed)
    return single_gripper_trajectory(points, closed, speeds)


# ---------------------------------------------------------------------- points on the rope
def pick_beyond_tip(
    section_k3: np.ndarray,
    tip_2: np.ndarray,
    along_2: np.ndarray,
    normal_2: np.ndarray,
    beyond: float,
    min_height: float,
) -> np.ndarray:
    """Where a rope section crosses the line ``beyond`` metres past a tip along ``along_2``,
    at least ``min_height`` to the ``normal_2`` side of the tip's line (the crossing nearest that
    line); else the section's farthest point along ``along_2`` on that side.

    This is how a loop's arm is picked to be dragged across a tail: beyond the tail's tip, so that
    only one leg of the dragged arm crosses the tail.
    """
    rel = section_k3[:, :2] - tip_2
    u = rel @ along_2  # along the tail
    v = rel @ normal_2  # towards the loop
    above = v > min_height
    best = None
    for a in range(len(section_k3) - 1):
        if not (above[a] and above[a + 1]) or u[a] == u[a + 1]:
            continue
        if (u[a] - beyond) * (u[a + 1] - beyond) <= 0:
            w = (beyond - u[a]) / (u[a + 1] - u[a])
            vv = v[a] + w * (v[a + 1] - v[a])
            if best is None or vv < best[0]:
                best = (vv, section_k3[a] + w * (section_k3[a + 1] - section_k3[a]))
    if best is not None:
        return best[1]
    # The section ends short of the line: take its farthest point along the tail.
    return section_k3[int(np.argmax(np.where(above, u, -np.inf)))]


def point_at(nodes_k3: np.ndarray, s: float) -> np.ndarray:
    """Point at arc length s from end A along the polyline (clamped to the ends)."""
    arc = arc_lengths(nodes_k3)
    return np.array([np.interp(s, arc, nodes_k3[:, d]) for d in range(3)])


def unit(v: np.ndarray) -> np.ndarray:
    """``v`` scaled to length 1; a degenerate direction is refused (one line)."""
    n = float(np.linalg.norm(v))
    if n < 1e-9:
        raise InvalidInputError("degenerate direction in the observed rope")
    return v / n


def perp(v_2: np.ndarray) -> np.ndarray:
    """``v_2`` rotated by +90 degrees."""
    return np.array([-v_2[1], v_2[0]])


def end_grasp_point(nodes_k3: np.ndarray, end: RopeEnd, offset: float) -> np.ndarray:
    """Point ``offset`` metres from ``end``'s tip along the rope."""
    if end is RopeEnd.A:
        return point_at(nodes_k3, offset)
    return point_at(nodes_k3, arc_lengths(nodes_k3)[-1] - offset)


# ---------------------------------------------------------------------- start ropes
def sample_start_rope(
    rng: np.random.Generator,
    bend_amplitude: float = 0.03,
    n_nodes: int = 41,
    length: float = 1.0,
    height: float = 0.01,
    max_rotation: float = math.pi,
    max_translation: float = 0.15,
) -> np.ndarray:
    """A gently curved rope on the table (n_nodes, 3), arc length ``length``.

    y(x) = sum_{k=1..3} a_k / k sin(k pi u + phi_k), u in [0, 1], a_k ~ U(-amp, amp),
    phi_k ~ U(0, 2 pi); then a rotation by U(-max_rotation, max_rotation) about z and a translation
    by U(-max_translation, max_translation) in x and y.
    """
    if bend_amplitude < 0 or n_nodes < 3 or length <= 0:
        raise InvalidInputError("need bend_amplitude >= 0, n_nodes >= 3 and length > 0")
    a_k = rng.uniform(-bend_amplitude, bend_amplitude, size=3)
    phi_k = rng.uniform(0.0, 2 * math.pi, size=3)
    u = np.linspace(0.0, 1.0, 401)
    y = sum(a_k[k] / (k + 1) * np.sin((k + 1) * math.pi * u + phi_k[k]) for k in range(3))
    y = y - y.mean()
    xy = np.stack([u - 0.5, y], axis=1)
    arc = np.linalg.norm(np.diff(xy, axis=0), axis=1).sum()
    xy *= length / arc  # exact arc length (uniform scaling keeps the shape)
    theta = rng.uniform(-max_rotation, max_rotation)
    rot = np.array([[math.cos(theta), -math.sin(theta)], [math.sin(theta), math.cos(theta)]])
    shift = rng.uniform(-max_translation, max_translation, size=2)
    xy = xy @ rot.T + shift
    nodes = np.column_stack([xy, np.full(len(xy), height)])
    return resample_by_arc_length(nodes, n_nodes)
