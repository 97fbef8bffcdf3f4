"""Validation of the arrays that cross module boundaries (clouds, rope nodes, feature matrices).

One place for these checks, so every module names a bad input the same way.
"""

from __future__ import annotations

import hashlib

import numpy as np

from knotlab.core.errors import InvalidInputError


def points_n3(name: str, arr: np.ndarray, min_points: int = 1, unit: str = "points") -> np.ndarray:
    """``arr`` as a float (n, 3) array with n >= min_points, all finite, else a named error.

    The one (n, 3) check of knotlab: clouds, rope nodes and task starts all go through it, so a
    bad array is reported the same way everywhere (its name, its shape, the first bad rows).
    """
    a = np.asarray(arr, dtype=float)
    if a.ndim != 2 or a.shape[1] != 3:
        raise InvalidInputError(f"{name} must have shape (n, 3), got {a.shape}")
    if a.shape[0] < min_points:
        raise InvalidInputError(f"{name}: need at least {min_points} {unit}, got {a.shape[0]}")
    if not np.all(np.isfinite(a)):
        bad = np.flatnonzero(~np.isfinite(a).all(axis=1))
        raise InvalidInputError(f"{name} contains NaN or infinite values (rows {bad[:5].tolist()})")
    return a


def optional_points_n3(name: str, arr: np.ndarray | None) -> np.ndarray | None:
    """Like :func:`points_n3`, but None passes through."""
    return None if arr is None else points_n3(name, arr)


def finite_matrix(name: str, arr: np.ndarray) -> np.ndarray:
    """``arr`` as a non-empty finite float 2-D array, else an error naming the first bad cell."""
    a = np.asarray(arr, dtype=float)
    if a.ndim != 2 or a.shape[0] < 1 or a.shape[1] < 1:
        raise InvalidInputError(f"{name} must be a non-empty 2-D array, got shape {a.shape}")
    if not np.all(np.isfinite(a)):
        bad = np.argwhere(~np.isfinite(a))[0]
        raise InvalidInputError(f"{name} has a non-finite value at row {bad[0]}, column {bad[1]}")
    return a


def cloud_digest(cloud_n3: np.ndarray) -> str:
    """sha1 of a cloud's float64 bytes and shape: equal digests mean an identical cloud."""
    arr = np.ascontiguousarray(np.asarray(cloud_n3, dtype=np.float64))
    return hashlib.sha1(str(arr.shape).encode() + arr.tobytes()).hexdigest()
