"""A rope tracker's correction at the camera's rate: one frame pulls the chain to the rope seen.

The video tracker (core/world/estimate.py) simulates each executed trajectory in the agent's
model from its last estimate and, at every camera frame, moves the model's rope by
`follow_frame`: each node is pulled across the chain, in the table's plane, to the visible rope
at its height, and a node with nothing near it (hidden under a crossing) keeps its place.
Shape suffixes: k = rope nodes, n = cloud points.
"""

from __future__ import annotations

import numpy as np

DEAD_BAND = 0.005  # m: a node's move shrinks by this much (the mean of noisy points wanders)


def follow_frame(
    nodes_k3: np.ndarray, surface_n3: np.ndarray, *, radius: float, reach: float
) -> np.ndarray:
    """The chain (K, 3) moved in the table's plane to one camera frame's visible rope.

    A node takes the mean xy of the surface points within ``reach`` of it in xy whose centre
    height (z - radius) is within one radius of its own (the other strand at a crossing never
    pulls); with none it keeps its place (hidden), with no noise added (at a camera's rate noise
    on a hidden node would random-walk it). Heights are left to the model's physics (the
    visible surface's mean height sits half a radius below the top, and a push into the table
    or another strand is a push the simulator answers). Only the move across the chain is kept
    (a cloud says where the rope is, not which part of it), shrunk by ``DEAD_BAND`` and smoothed
    1-2-1 along the chain.
    """
    from scipy.spatial import cKDTree

    nodes = np.asarray(nodes_k3, dtype=float)
    move = np.zeros_like(nodes)
    if len(surface_n3):
        surface = np.asarray(surface_n3, dtype=float)
        near_k = cKDTree(surface[:, :2]).query_ball_point(nodes[:, :2], reach)
        for i, near in enumerate(near_k):
            if not near:
                continue
            pts = surface[near]
            pts = pts[np.abs(pts[:, 2] - radius - nodes[i, 2]) < radius]
            if len(pts):
                move[i, :2] = pts[:, :2].mean(axis=0) - nodes[i, :2]
    tangent = np.gradient(nodes[:, :2], axis=0)
    tangent /= np.maximum(np.linalg.norm(tangent, axis=1, keepdims=True), 1e-12)
    move[:, :2] -= np.einsum("ij,ij->i", move[:, :2], tangent)[:, None] * tangent
    # A move within the camera's noise is no evidence against the model's prediction.
    size = np.linalg.norm(move[:, :2], axis=1, keepdims=True)
    move[:, :2] *= np.maximum(0.0, 1.0 - DEAD_BAND / np.maximum(size, 1e-12))
    smooth = move.copy()
    smooth[1:-1] = 0.25 * move[:-2] + 0.5 * move[1:-1] + 0.25 * move[2:]
    return nodes + smooth
