"""Trajectory transfer: warp a demo's gripper trajectory through a registration's f (demo -> scene).

Shape suffixes: g gripper, t waypoint, 3 xyz, 33 rotation (columns = gripper axes; z = approach).
"""

from __future__ import annotations

import numpy as np

from knotlab.core.errors import InvalidInputError
from knotlab.core.registration.tps import ThinPlateSpline
from knotlab.core.world.trajectory import GripperTrajectory


def orthonormalise_keep_z(m_k33: np.ndarray) -> np.ndarray:
    """z' = n(M e_z), y' = n(z' x M e_x), x' = y' x z': rotation, approach axis along M e_z."""
    z = m_k33[..., :, 2]
    x_in = m_k33[..., :, 0]
    z_norm = np.linalg.norm(z, axis=-1, keepdims=True)
    if np.any(z_norm < 1e-12):
        raise InvalidInputError("warp collapses a gripper's approach axis (singular Jacobian)")
    z = z / z_norm
    y = np.cross(z, x_in)
    y_norm = np.linalg.norm(y, axis=-1, keepdims=True)
    if np.any(y_norm < 1e-12):
        raise InvalidInputError("warped gripper x axis is parallel to its approach axis")
    y = y / y_norm
    x = np.cross(y, z)
    return np.stack([x, y, z], axis=-1)


def warp_trajectory(traj: GripperTrajectory, f: ThinPlateSpline) -> GripperTrajectory:
    """Positions p -> f(p); rotations R -> orthonormalise_keep_z(J_f(p) R); times, closed copied."""
    pos = traj.positions_gt3.reshape(-1, 3)
    rot = traj.rotations_gt33.reshape(-1, 3, 3)
    new_pos = f.evaluate(pos)
    new_rot = orthonormalise_keep_z(f.jacobian(pos) @ rot)
    shape = traj.positions_gt3.shape
    return GripperTrajectory(
        traj.times_t,
        new_pos.reshape(shape),
        new_rot.reshape(traj.rotations_gt33.shape),
        traj.closed_gt,
    )
