"""The voxel grid, written once: group points by the cubic voxel they fall in."""

from __future__ import annotations

import numpy as np


def voxel_groups(points_n3: np.ndarray, voxel: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(voxel index of each point (n,), points per voxel (v,), mean point of each voxel (v, 3)).

    Voxels are the cells floor(p / voxel), numbered in lexicographic order of their cell index,
    so the grouping is deterministic and independent of the order of the points.
    """
    keys = np.floor(points_n3 / voxel).astype(np.int64)
    _, inverse, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    inverse = inverse.reshape(-1)
    mean_v3 = np.zeros((counts.size, 3))
    np.add.at(mean_v3, inverse, points_n3)
    mean_v3 /= counts[:, None]
    return inverse, counts, mean_v3
