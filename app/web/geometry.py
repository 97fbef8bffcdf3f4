"""Pure geometry for the app's scene: a tube mesh around the rope, and picking a polyline by ray.

Hand-written rather than trimesh.creation.sweep_polygon: the tube is rebuilt for every animation
frame (30 a second), so its faces are computed once per rope size and only the rings move
(0.4 ms a frame for 41 nodes, measured); the general sweep needs shapely and re-triangulates
each call. trimesh checks the result in the tests (watertight, positive volume).
Shape suffixes: k = rope nodes, s = tube sides, v = vertices, p = polyline points.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np
from scipy.optimize import linprog
from scipy.spatial import ConvexHull, QhullError


@lru_cache(maxsize=8)
def tube_faces(n_nodes: int, sides: int) -> np.ndarray:
    """Triangles (F, 3) joining ``n_nodes`` rings of ``sides`` vertices, plus two end caps."""
    k = np.arange(n_nodes - 1)[:, None]
    j = np.arange(sides)[None, :]
    a = k * sides + j
    b = k * sides + (j + 1) % sides
    c = a + sides
    d = b + sides
    body = np.concatenate([np.stack([a, b, d], -1), np.stack([a, d, c], -1)], axis=1)
    centre0, centre1 = n_nodes * sides, n_nodes * sides + 1
    jj = np.arange(sides)
    cap0 = np.stack([np.full(sides, centre0), (jj + 1) % sides, jj], -1)
    last = (n_nodes - 1) * sides
    cap1 = np.stack([np.full(sides, centre1), last + jj, last + (jj + 1) % sides], -1)
    return np.concatenate([body.reshape(-1, 3), cap0, cap1]).astype(np.uint32)


def tube_vertices(nodes_k3: np.ndarray, radius: float, sides: int = 12) -> np.ndarray:
    """Vertices (K * sides + 2, 3) of a closed tube of ``radius`` along the rope's nodes."""
    nodes = np.asarray(nodes_k3, dtype=np.float64)
    tangent = np.gradient(nodes, axis=0)
    tangent /= np.maximum(np.linalg.norm(tangent, axis=1, keepdims=True), 1e-12)
    # A rope on a table is mostly horizontal: "up" gives a stable normal, except where the
    # tangent turns vertical, where x is used instead.
    up = np.where(np.abs(tangent[:, 2:3]) > 0.9, [[1.0, 0.0, 0.0]], [[0.0, 0.0, 1.0]])
    normal = np.cross(tangent, up)
    normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-12)
    binormal = np.cross(tangent, normal)
    angle = 2 * np.pi * np.arange(sides) / sides
    ring = (
        np.cos(angle)[None, :, None] * normal[:, None]
        + np.sin(angle)[None, :, None] * (binormal[:, None])
    )
    verts = (nodes[:, None, :] + radius * ring).reshape(-1, 3)
    return np.concatenate([verts, nodes[:1], nodes[-1:]]).astype(np.float32)


def ray_polyline_distance(
    origin_3: np.ndarray, direction_3: np.ndarray, points_p3: np.ndarray
) -> float:
    """Smallest distance between a ray and a polyline's segments (inf for an empty polyline)."""
    pts = np.asarray(points_p3, dtype=np.float64)
    if len(pts) < 2:
        if len(pts) == 1:
            return _ray_point_distance(origin_3, direction_3, pts[0])
        return float("inf")
    o = np.asarray(origin_3, dtype=np.float64)
    u = np.asarray(direction_3, dtype=np.float64)
    u = u / np.linalg.norm(u)
    a, v = pts[:-1], np.diff(pts, axis=0)
    w0 = a - o
    vv = np.einsum("ij,ij->i", v, v)
    vu = v @ u
    # Closest points of the line o + s u and each segment a + t v, then clamp t to [0, 1] and
    # s to s >= 0 (the ray), re-solving t for the clamped s: exact enough to pick a polyline.
    denom = vv - vu * vu
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(denom > 1e-12, (vu * (w0 @ u) - np.einsum("ij,ij->i", v, w0)) / denom, 0.0)
    t = np.clip(t, 0.0, 1.0)
    s = np.maximum(0.0, np.einsum("ij,j->i", w0 + t[:, None] * v, u))
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(vv > 1e-12, np.einsum("ij,ij->i", o + s[:, None] * u - a, v) / vv, 0.0)
    t = np.clip(t, 0.0, 1.0)
    gap = (a + t[:, None] * v) - (o + s[:, None] * u)
    return float(np.min(np.linalg.norm(gap, axis=1)))


def _ray_point_distance(origin_3: np.ndarray, direction_3: np.ndarray, point_3) -> float:
    u = np.asarray(direction_3, float) / np.linalg.norm(direction_3)
    w = np.asarray(point_3, float) - np.asarray(origin_3, float)
    s = max(0.0, float(w @ u))
    return float(np.linalg.norm(w - s * u))


def pick_polyline(
    origin_3: np.ndarray,
    direction_3: np.ndarray,
    polylines: dict[int, list[np.ndarray]],
    max_distance: float = 0.03,
) -> int | None:
    """The key of the polyline set the ray passes closest to, if within ``max_distance`` (m)."""
    best_key, best = None, max_distance
    for key, lines in polylines.items():
        for line in lines:
            d = ray_polyline_distance(origin_3, direction_3, line)
            if d < best:
                best_key, best = key, d
    return best_key


def pick_marker(
    origin_3: np.ndarray,
    direction_3: np.ndarray,
    markers: dict[int, list[tuple[np.ndarray, float]]],
) -> int | None:
    """The key of the marker (centre, radius) the ray passes through nearest its centre.

    Candidates often grasp the same rope end, so their markers overlap and the selected one is
    drawn larger: the marker whose centre the click is nearest is the one the labeller aimed at,
    not the one whose surface is in front. Centres within 1 mm of the ray tie; the front one wins.
    """
    o = np.asarray(origin_3, dtype=np.float64)
    u = np.asarray(direction_3, dtype=np.float64)
    u = u / np.linalg.norm(u)
    hits: list[tuple[float, float, int]] = []
    for key, spheres in markers.items():
        for centre, radius in spheres:
            w = np.asarray(centre, dtype=np.float64) - o
            along = float(w @ u)
            miss = float(np.sqrt(max(float(w @ w) - along * along, 0.0)))
            if along > 0 and miss <= radius:  # in front of the camera, and the ray enters it
                hits.append((miss, along, key))
    if not hits:
        return None
    nearest = min(miss for miss, _, _ in hits)
    return min((along, key) for miss, along, key in hits if miss <= nearest + 1e-3)[1]


def pick_candidate(
    origin_3: np.ndarray,
    direction_3: np.ndarray,
    markers: dict[int, list[tuple[np.ndarray, float]]],
    polylines: dict[int, list[np.ndarray]],
) -> int | None:
    """What one click selects: the marker under the ray (pick_marker), else the nearest polyline.

    One function decides so that one click has one answer; viser would otherwise fire a marker's
    own handler and the scene's handler on two threads, and they can disagree where a
    candidate's path passes in front of another's marker.
    """
    hit = pick_marker(origin_3, direction_3, markers)
    return hit if hit is not None else pick_polyline(origin_3, direction_3, polylines)


# --------------------------------------------------------------------------- camera framing
# Camera frames follow viser's (OpenCV) convention: x right, y down, z forward.


def camera_rotation(forward_3: np.ndarray, up_3: np.ndarray) -> np.ndarray:
    """The world-from-camera rotation (3, 3) of a camera looking along ``forward_3``, with
    ``up_3`` up on screen (columns: right, down, forward)."""
    z = np.asarray(forward_3, dtype=np.float64)
    z = z / np.linalg.norm(z)
    up = np.asarray(up_3, dtype=np.float64)
    down = -(up - (up @ z) * z)
    down = down / np.linalg.norm(down)
    return np.stack([np.cross(down, z), down, z], axis=1)


def project(
    points_p3: np.ndarray,
    rotation_33: np.ndarray,
    position_3: np.ndarray,
    fov: float,
    size_px: tuple[int, int],
) -> np.ndarray:
    """Pixel coordinates (P, 2) of world points on a (width, height) canvas of vertical field
    of view ``fov`` (rad); points behind the camera come out as NaN."""
    w, h = size_px
    q = (np.asarray(points_p3, dtype=np.float64) - position_3) @ rotation_33
    t = np.tan(fov / 2)
    with np.errstate(divide="ignore", invalid="ignore"):
        x = q[:, 0] / q[:, 2] / (t * w / h)
        y = q[:, 1] / q[:, 2] / t
    uv = np.stack([(1 + x) / 2 * w, (1 + y) / 2 * h], axis=1)
    uv[q[:, 2] <= 0] = np.nan
    return uv


def frame_points(
    points_p3: np.ndarray,
    forward_3: np.ndarray,
    up_3: np.ndarray,
    fov: float,
    size_px: tuple[int, int],
    box_px: tuple[float, float, float, float] | np.ndarray,
    near: float = 0.05,
) -> tuple[np.ndarray, np.ndarray]:
    """The closest camera (position, look-at point) looking along ``forward_3`` that shows every
    point inside the pixel box (left, top, right, bottom) of the canvas; ``box_px`` is one box,
    or one per point (P, 4), e.g. narrower for a point that carries text.

    With the viewing direction fixed, "point p projects inside the box" is linear in the camera
    position c' (camera frame): q = p' - c', s0 <= q_x / q_z <= s1 (and so for y) with q_z > 0
    is s0 q_z <= q_x <= s1 q_z. So the closest such camera (largest c'_z) is a linear program.
    The look-at point is on the view axis at the depth of the points' centre, so orbiting turns
    about the content.
    """
    pts = np.asarray(points_p3, dtype=np.float64)
    rot = camera_rotation(forward_3, up_3)
    p = pts @ rot  # the points in camera axes (world origin)
    w, h = size_px
    left, top, right, bottom = np.broadcast_to(np.asarray(box_px, dtype=np.float64), (len(p), 4)).T
    t = np.tan(fov / 2)
    sx0, sx1 = (2 * left / w - 1) * t * w / h, (2 * right / w - 1) * t * w / h
    sy0, sy1 = (2 * top / h - 1) * t, (2 * bottom / h - 1) * t
    one, zero = np.ones(len(p)), np.zeros(len(p))
    # Rows over (a, b, c) = c', each "<= rhs":
    a_ub = np.concatenate(
        [
            np.c_[one, zero, -sx0 * one],  # q_x >= sx0 q_z
            np.c_[-one, zero, sx1 * one],  # q_x <= sx1 q_z
            np.c_[zero, one, -sy0 * one],  # q_y >= sy0 q_z
            np.c_[zero, -one, sy1 * one],  # q_y <= sy1 q_z
            np.c_[zero, zero, one],  # q_z >= near
        ]
    )
    b_ub = np.concatenate(
        [
            p[:, 0] - sx0 * p[:, 2],
            sx1 * p[:, 2] - p[:, 0],
            p[:, 1] - sy0 * p[:, 2],
            sy1 * p[:, 2] - p[:, 1],
            p[:, 2] - near,
        ]
    )
    res = linprog(
        c=[0.0, 0.0, -1.0], A_ub=a_ub, b_ub=b_ub, bounds=[(None, None)] * 3, method="highs"
    )
    if not res.success:  # cannot happen for finite points (backing off always fits); say so
        raise ValueError(f"no camera frames these {len(p)} points: {res.message}")
    cam = np.asarray(res.x, dtype=np.float64)
    # At that distance the sideways position is free within an interval per axis (the LP
    # returns one of its ends, the content then hugs an edge): take each interval's middle.
    q_z = p[:, 2] - cam[2]
    cam[0] = (np.max(p[:, 0] - sx1 * q_z) + np.min(p[:, 0] - sx0 * q_z)) / 2
    cam[1] = (np.max(p[:, 1] - sy1 * q_z) + np.min(p[:, 1] - sy0 * q_z)) / 2
    depth = float(np.mean(p[:, 2]) - cam[2])
    position = rot @ cam
    return position, position + depth * rot[:, 2]


def hull_points(points_p3: np.ndarray) -> np.ndarray:
    """The points of a cloud a camera must frame: its convex hull's corners (a box holds the
    cloud when it holds them, the framing constraints being linear), or all of them when the
    cloud is flat or too small for a hull. Keeps framing a whole episode's frames cheap."""
    pts = np.asarray(points_p3, dtype=np.float64).reshape(-1, 3)
    pts = pts[np.isfinite(pts).all(axis=1)]
    if len(pts) < 5:
        return pts
    try:
        return pts[ConvexHull(pts).vertices]
    except QhullError:  # all in a plane or a line
        return pts
