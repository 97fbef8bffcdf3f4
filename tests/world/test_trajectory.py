"""GripperTrajectory validation: malformed shapes, NaN, non-rotations, bad times and flags."""

from __future__ import annotations

import numpy as np
import pytest

from knotlab.core.errors import InvalidInputError
from knotlab.core.world.trajectory import GripperTrajectory, down_rotation


def parts(n_t: int = 3) -> dict:
    return {
        "times_t": np.arange(n_t, dtype=float),
        "positions_gt3": np.zeros((2, n_t, 3)),
        "rotations_gt33": np.broadcast_to(down_rotation(), (2, n_t, 3, 3)).copy(),
        "closed_gt": np.zeros((2, n_t), dtype=bool),
    }


def test_valid_trajectory_is_frozen_and_typed() -> None:
    traj = GripperTrajectory(**parts())
    assert traj.n_waypoints == 3 and traj.duration == 2.0
    assert traj.closed_gt.dtype == bool
    with pytest.raises(ValueError):
        traj.positions_gt3[0, 0, 0] = 1.0


@pytest.mark.parametrize(
    ("field", "value", "message"),
    [
        ("positions_gt3", np.zeros((3, 3)), "positions_gt3 must have shape"),
        ("positions_gt3", np.zeros((2, 4, 3)), "positions_gt3 must have shape"),
        ("rotations_gt33", np.zeros((2, 3, 3)), "rotations_gt33 must have shape"),
        ("closed_gt", np.zeros((3,), bool), "closed_gt must have shape"),
        ("closed_gt", np.full((2, 3), 2), "closed_gt must hold booleans"),
        ("times_t", np.zeros((0,)), "times_t must have shape"),
        ("times_t", np.array([0.0, 2.0, 1.0]), "non-decreasing"),
    ],
)
def test_malformed_fields_are_rejected_with_the_field_named(field, value, message) -> None:
    kw = parts()
    kw[field] = value
    with pytest.raises(InvalidInputError, match=message):
        GripperTrajectory(**kw)


@pytest.mark.parametrize("field", ["times_t", "positions_gt3", "rotations_gt33"])
def test_nan_is_rejected(field: str) -> None:
    kw = parts()
    arr = np.array(kw[field], dtype=float)
    arr.reshape(-1)[0] = np.nan
    kw[field] = arr
    with pytest.raises(InvalidInputError, match=f"{field} contains NaN"):
        GripperTrajectory(**kw)


@pytest.mark.parametrize(
    "bad",
    [np.diag([1.0, 1.0, -1.0]), 2 * np.eye(3), np.ones((3, 3))],
    ids=["mirror", "scaled", "junk"],
)
def test_non_rotations_are_rejected(bad: np.ndarray) -> None:
    kw = parts()
    kw["rotations_gt33"][1, 2] = bad
    with pytest.raises(InvalidInputError, match="proper rotations"):
        GripperTrajectory(**kw)
