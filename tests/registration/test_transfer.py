"""Trajectory transfer: rotations stay orthonormal, keep the approach axis; identity stays."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from knotlab.core.errors import InvalidInputError
from knotlab.core.registration.tps import ThinPlateSpline, fit_tps
from knotlab.core.registration.transfer import orthonormalise_keep_z, warp_trajectory
from knotlab.core.world.trajectory import GripperTrajectory, down_rotation


def _random_rotations(rng: np.random.Generator, k: int) -> np.ndarray:
    q, _ = np.linalg.qr(rng.normal(size=(k, 3, 3)))
    return q * np.sign(np.linalg.det(q))[:, None, None]


def _trajectory(rng: np.random.Generator, n_t: int = 6) -> GripperTrajectory:
    rot = _random_rotations(rng, 2 * n_t).reshape(2, n_t, 3, 3)
    rot[0, 0] = down_rotation()
    closed = np.zeros((2, n_t), dtype=bool)
    closed[0, 2:4] = True
    return GripperTrajectory(
        np.linspace(0, 1, n_t), rng.uniform(-0.3, 0.3, (2, n_t, 3)), rot, closed
    )


def _warp(rng: np.random.Generator) -> ThinPlateSpline:
    x = rng.uniform(-0.4, 0.4, (30, 3)) * [1, 1, 0.1]
    y = x + 0.05 * np.sin(4 * x[:, [1, 0, 2]]) + [0.02, -0.01, 0.0]
    return fit_tps(x, y, 0.01)


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 2**31 - 1))
def test_warped_rotations_orthonormal_and_keep_approach_axis(seed: int) -> None:
    rng = np.random.default_rng(seed)
    traj = _trajectory(rng)
    f = _warp(rng)
    out = warp_trajectory(traj, f)
    rot = out.rotations_gt33
    np.testing.assert_allclose(
        np.einsum("gtji,gtjk->gtik", rot, rot), np.broadcast_to(np.eye(3), rot.shape), atol=1e-10
    )
    np.testing.assert_allclose(np.linalg.det(rot), 1.0, atol=1e-10)
    jac = f.jacobian(traj.positions_gt3.reshape(-1, 3)).reshape(2, -1, 3, 3)
    warped_z = np.einsum("gtij,gtj->gti", jac, traj.rotations_gt33[..., :, 2])
    warped_z /= np.linalg.norm(warped_z, axis=-1, keepdims=True)
    np.testing.assert_allclose(rot[..., :, 2], warped_z, atol=1e-12)
    np.testing.assert_allclose(
        out.positions_gt3, f(traj.positions_gt3.reshape(-1, 3)).reshape(2, -1, 3)
    )
    np.testing.assert_array_equal(out.closed_gt, traj.closed_gt)
    np.testing.assert_array_equal(out.times_t, traj.times_t)


def test_identity_warp_is_identity() -> None:
    rng = np.random.default_rng(0)
    traj = _trajectory(rng)
    x = rng.normal(size=(20, 3))
    fitted_identity = fit_tps(x, x, 0.1)
    for f in (ThinPlateSpline.identity(), fitted_identity):
        out = warp_trajectory(traj, f)
        np.testing.assert_allclose(out.positions_gt3, traj.positions_gt3, atol=1e-9)
        np.testing.assert_allclose(out.rotations_gt33, traj.rotations_gt33, atol=1e-9)


def test_rigid_warp_rotates_gripper_frames() -> None:
    rng = np.random.default_rng(1)
    traj = _trajectory(rng)
    ang = 0.4
    rz = np.array([[np.cos(ang), -np.sin(ang), 0], [np.sin(ang), np.cos(ang), 0], [0, 0, 1]])
    f = ThinPlateSpline(np.zeros((0, 3)), np.zeros((0, 3)), rz.T, np.array([0.1, 0.0, 0.0]))
    out = warp_trajectory(traj, f)
    np.testing.assert_allclose(out.rotations_gt33, rz @ traj.rotations_gt33, atol=1e-12)


def test_degenerate_jacobian_raises() -> None:
    m = np.zeros((1, 3, 3))
    with pytest.raises(InvalidInputError, match="approach axis"):
        orthonormalise_keep_z(m)


def test_transferer_cached_sides_give_the_fresh_registration_bit_for_bit() -> None:
    """The transferer keeps factorised demo and scene sides; a reused side changes nothing."""
    from knotlab.core.registration import register
    from knotlab.core.registration.planner import DemoTransferer
    from tests.minilib import mini_library

    lib = mini_library(2)
    scene = lib[1].pre_cloud_n3 + np.array([0.01, -0.02, 0.0])
    cached = DemoTransferer(lib)
    first = [cached.plan(scene, a) for a in range(len(lib))]
    again = [cached.plan(scene, a) for a in range(len(lib))]  # both sides from the caches
    for a, (p1, p2) in enumerate(zip(first, again, strict=True)):
        fresh = register(lib[a].pre_cloud_n3, scene, cached.params)
        assert p1.ok and p2.ok
        assert np.array_equal(p1.trajectory.positions_gt3, p2.trajectory.positions_gt3)
        assert np.array_equal(p1.trajectory.rotations_gt33, p2.trajectory.rotations_gt33)
        assert p1.registration.costs == fresh.costs == p2.registration.costs
        assert np.array_equal(p2.registration.f.evaluate(scene), fresh.f.evaluate(scene))
        assert np.array_equal(p2.registration.corr_nm, fresh.corr_nm)
    bad = cached.plan(np.full((5, 3), np.nan), 0)  # a bad scene: a failed plan, not a raise
    assert not bad.ok and "registration" in (bad.failure or "")
