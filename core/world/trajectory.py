"""GripperTrajectory: timed waypoints for the two point grippers, in metres and seconds.

Shape suffixes: g = gripper (2: left, right), t = waypoint, 3 = xyz, 33 = rotation matrix.
A gripper's ``closed_gt[g, t]`` is the state it should be in *on arrival* at waypoint t:
a False -> True change closes (grasps) at that waypoint, True -> False opens (releases) there.
Rotations are kept because trajectory transfer warps them (approach axis = rotation column z),
even though the simulated point grippers ignore orientation.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from knotlab.core.errors import InvalidInputError

GRIPPERS: tuple[str, str] = ("left", "right")


def _check_finite(name: str, arr: np.ndarray) -> None:
    if not np.all(np.isfinite(arr)):
        raise InvalidInputError(f"GripperTrajectory.{name} contains NaN or infinite values")


@dataclass(frozen=True, eq=False)
class GripperTrajectory:
    """Both grippers' poses and closed flags at T shared waypoint times."""

    times_t: np.ndarray  # (T,) seconds, non-decreasing, starting anywhere
    positions_gt3: np.ndarray  # (2, T, 3) metres
    rotations_gt33: np.ndarray  # (2, T, 3, 3) proper rotations
    closed_gt: np.ndarray  # (2, T) bool

    def __post_init__(self) -> None:
        times = np.asarray(self.times_t, dtype=float)
        pos = np.asarray(self.positions_gt3, dtype=float)
        rot = np.asarray(self.rotations_gt33, dtype=float)
        closed = np.asarray(self.closed_gt)
        if times.ndim != 1 or times.shape[0] < 1:
            raise InvalidInputError(f"times_t must have shape (T,) with T >= 1, got {times.shape}")
        n_t = times.shape[0]
        if pos.shape != (2, n_t, 3):
            raise InvalidInputError(f"positions_gt3 must have shape (2, {n_t}, 3), got {pos.shape}")
        if rot.shape != (2, n_t, 3, 3):
            raise InvalidInputError(
                f"rotations_gt33 must have shape (2, {n_t}, 3, 3), got {rot.shape}"
            )
        if closed.shape != (2, n_t):
            raise InvalidInputError(f"closed_gt must have shape (2, {n_t}), got {closed.shape}")
        if closed.dtype != bool:
            if not np.isin(closed, (0, 1)).all():
                raise InvalidInputError("closed_gt must hold booleans (or 0/1)")
            closed = closed.astype(bool)
        _check_finite("times_t", times)
        _check_finite("positions_gt3", pos)
        _check_finite("rotations_gt33", rot)
        if np.any(np.diff(times) < 0):
            raise InvalidInputError("times_t must be non-decreasing")
        ortho_err = np.abs(np.einsum("gtji,gtjk->gtik", rot, rot) - np.eye(3)).max()
        if ortho_err > 1e-4 or np.any(np.linalg.det(rot) < 0):
            raise InvalidInputError(
                f"rotations_gt33 must be proper rotations (orthogonality error {ortho_err:.2g})"
            )
        # Freeze validated, canonical-dtype copies so the record is immutable in practice.
        for name, arr in (
            ("times_t", times),
            ("positions_gt3", pos),
            ("rotations_gt33", rot),
            ("closed_gt", closed),
        ):
            arr = np.array(arr, copy=True)
            arr.setflags(write=False)
            object.__setattr__(self, name, arr)

    @property
    def n_waypoints(self) -> int:
        """Number of waypoints T."""
        return int(self.times_t.shape[0])

    @property
    def duration(self) -> float:
        """Nominal duration in seconds (last minus first waypoint time)."""
        return float(self.times_t[-1] - self.times_t[0])

    def gripper_index(self, name: str) -> int:
        """Index of gripper ``name`` ('left' or 'right')."""
        if name not in GRIPPERS:
            raise InvalidInputError(f"unknown gripper {name!r}; expected one of {GRIPPERS}")
        return GRIPPERS.index(name)

    def active_grippers(self) -> tuple[int, ...]:
        """Indices of grippers that close at some waypoint (the others stay open)."""
        return tuple(int(g) for g in np.flatnonzero(self.closed_gt.any(axis=1)))

    def with_positions(
        self, positions_gt3: np.ndarray, rotations_gt33: np.ndarray
    ) -> GripperTrajectory:
        """A copy with new positions and rotations, same times and closed flags."""
        return GripperTrajectory(self.times_t, positions_gt3, rotations_gt33, self.closed_gt)

    def equals(self, other: GripperTrajectory) -> bool:
        """Exact, element-wise equality of every array."""
        return (
            np.array_equal(self.times_t, other.times_t)
            and np.array_equal(self.positions_gt3, other.positions_gt3)
            and np.array_equal(self.rotations_gt33, other.rotations_gt33)
            and np.array_equal(self.closed_gt, other.closed_gt)
        )


def down_rotation() -> np.ndarray:
    """Rotation whose z (approach) axis points down -z: the pose of a top-down grasp."""
    return np.diag([1.0, -1.0, -1.0])
