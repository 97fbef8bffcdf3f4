"""Thin-plate spline: affine reproduction, interpolation, Jacobian, optimality, bad input."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from knotlab.core.errors import InvalidInputError, SolverError
from knotlab.core.registration.tps import ThinPlateSpline, fit_tps, tps_basis, tps_kernel

seeds = st.integers(min_value=0, max_value=2**31 - 1)


def _cloud(seed: int, n: int = 25) -> np.ndarray:
    return np.random.default_rng(seed).normal(size=(n, 3))


@settings(max_examples=25, deadline=None)
@given(seed=seeds, bend=st.floats(1e-4, 10.0))
def test_affine_map_reproduced_exactly_with_zero_bending(seed: int, bend: float) -> None:
    rng = np.random.default_rng(seed)
    x = _cloud(seed)
    a = np.eye(3) + 0.5 * rng.normal(size=(3, 3))
    t = rng.normal(size=3)
    f = fit_tps(x, x @ a + t, bend, rot_coef=(0.0, 0.0, 0.0))
    np.testing.assert_allclose(f(x), x @ a + t, atol=1e-8)
    np.testing.assert_allclose(f.b_33, a, atol=1e-8)
    assert abs(f.bending_energy()) < 1e-10
    probe = rng.normal(size=(7, 3))
    np.testing.assert_allclose(f(probe), probe @ a + t, atol=1e-8)


def test_rotation_regulariser_pulls_b_toward_identity() -> None:
    x = _cloud(1)
    a = np.diag([1.5, 0.7, 2.0])
    free = fit_tps(x, x @ a, 1.0, rot_coef=(0.0, 0.0, 0.0))
    pulled = fit_tps(x, x @ a, 1.0, rot_coef=(100.0, 100.0, 100.0))
    assert np.linalg.norm(pulled.b_33 - np.eye(3)) < 0.1 * np.linalg.norm(free.b_33 - np.eye(3))


@settings(max_examples=20, deadline=None)
@given(seed=seeds)
def test_small_lambda_interpolates(seed: int) -> None:
    rng = np.random.default_rng(seed)
    x = _cloud(seed)
    y = x + 0.2 * np.sin(2 * x[:, ::-1]) + 0.05 * rng.normal(size=x.shape)
    f = fit_tps(x, y, 1e-9, rot_coef=(1e-9, 1e-9, 1e-9))
    np.testing.assert_allclose(f(x), y, atol=1e-5)


@settings(max_examples=20, deadline=None)
@given(seed=seeds)
def test_jacobian_matches_finite_differences(seed: int) -> None:
    rng = np.random.default_rng(seed)
    x = _cloud(seed, 15)
    f = fit_tps(x, x + 0.3 * np.cos(x), 0.05)
    p = rng.normal(size=(6, 3))
    eps = 1e-6
    numeric = np.stack([(f(p + eps * e) - f(p - eps * e)) / (2 * eps) for e in np.eye(3)], axis=-1)
    np.testing.assert_allclose(f.jacobian(p), numeric, atol=1e-6)


def _objective(f: ThinPlateSpline, x, y, w, bend, rot) -> float:
    k = tps_kernel(x, x)
    data = np.sum(w * np.sum((y - f(x)) ** 2, axis=1))
    reg = np.sum(np.asarray(rot)[:, None] * (f.b_33 - np.eye(3)) ** 2)
    return data + bend * np.trace(f.w_n3.T @ k @ f.w_n3) + reg


def test_weighted_fit_minimises_stated_objective_under_constraint() -> None:
    rng = np.random.default_rng(3)
    x = _cloud(3, 20)
    y = x + 0.3 * np.sin(x)
    w = rng.uniform(0.1, 1.0, 20)
    rot = (1e-4, 1e-4, 0.1)
    f = fit_tps(x, y, 0.1, rot_coef=rot, weights_n=w)
    ones_x = np.hstack([np.ones((20, 1)), x])
    np.testing.assert_allclose(ones_x.T @ f.w_n3, 0.0, atol=1e-10)
    best = _objective(f, x, y, w, 0.1, rot)
    null = np.linalg.svd(ones_x)[0][:, 4:]
    for _ in range(10):  # feasible perturbations never lower the objective
        dw = null @ rng.normal(size=(16, 3)) * 1e-3
        other = ThinPlateSpline(
            f.centres_n3, f.w_n3 + dw, f.b_33 + 1e-3 * rng.normal(size=(3, 3)), f.t_3 + 1e-3
        )
        assert _objective(other, x, y, w, 0.1, rot) > best


def test_bending_energy_equals_spectral_sum() -> None:
    x = _cloud(5)
    y = x + 0.3 * np.sin(x)
    basis = tps_basis(x)
    e = basis.solve(y, 0.1)
    assert np.isclose(np.sum(basis.mu_k[:, None] * e**2), basis.spline(e).bending_energy())


def test_bad_input_raises() -> None:
    x = _cloud(0)
    with pytest.raises(InvalidInputError, match="shape"):
        fit_tps(x, x[:-1], 0.1)
    with pytest.raises(InvalidInputError, match="NaN"):
        fit_tps(np.full((5, 3), np.nan), np.zeros((5, 3)), 0.1)
    with pytest.raises(InvalidInputError, match=r"\(n, 3\)"):
        fit_tps(np.zeros((5, 2)), np.zeros((5, 2)), 0.1)
    with pytest.raises(SolverError, match="singular"):
        fit_tps(np.zeros((6, 3)), np.zeros((6, 3)), 0.1)
