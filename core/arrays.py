"""Validation of the arrays that cross module boundaries (clouds, rope nodes, feature matrices).

One place for these checks, so every module names a bad input the same way.
"""

from __future__ import annotations

import numpy as np

from knotlab.core.errors import InvalidInputError


def points_n3(name: str, arr: np.ndarray) -> np.ndarray:
    """``arr`` as a float (n, 3) array with n >= 1 and finite values, else a named error."""
    a = np.asarray(arr, dtype=float)
    if a.ndim != 2 or a.shape[1] != 3 or a.shape[0] < 1:
        raise InvalidInputError(f"{name} must have shape (n, 3) with n >= 1, got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise InvalidInputError(f"{name} contains NaN or infinite values")
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
