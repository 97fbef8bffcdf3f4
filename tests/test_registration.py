"""Bidirectional TPS-RPM: accuracy on warped rope clouds, costs, batch = single pair, bad input."""

from __future__ import annotations

import warnings
from dataclasses import replace

import numpy as np
import pytest

from core.errors import InvalidInputError
from core.registration import (
    COST_NAMES,
    EXACT,
    SCAN,
    LibraryRegistrar,
    RegistrationParams,
    register,
)
from core.synthetic import SmoothWarp, corrupt, rope_cloud, smooth_warp

# The test clouds carry 5 % outliers, so the expected outlier fraction is set to match; with the
# paper's 1 % the outlier row can absorb only ~1 point and Sinkhorn forces the rest onto the rope.
EXACT_5PC = replace(EXACT, outlier_frac=0.05)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_exact_recovers_moderate_warp_within_1cm(seed: int) -> None:
    rng = np.random.default_rng(seed)
    demo = rope_cloud(rng, 100)
    warp = smooth_warp(rng, magnitude_m=0.03, angle_rad=0.05)
    scene = corrupt(rng, warp(demo), noise_m=0.002, outlier_frac=0.05)
    reg = register(demo, scene, EXACT_5PC)
    assert reg.ok
    err = np.linalg.norm(reg.f(demo) - warp(demo), axis=1)
    assert err.mean() < 0.01, err.mean()
    # g maps the scene back: the scene's true points return near their demo originals
    back = np.linalg.norm(reg.g(warp(demo)) - demo, axis=1)
    assert np.median(back) < 0.01


@pytest.mark.parametrize("params", [SCAN, EXACT], ids=["scan", "exact"])
def test_identical_clouds_give_near_zero_cost(params: RegistrationParams) -> None:
    rng = np.random.default_rng(4)
    demo = rope_cloud(rng, 100)
    same = register(demo, demo, params)
    warped = register(demo, smooth_warp(rng, 0.04)(demo), params)
    assert same.nn_cost < 0.1 * warped.nn_cost
    assert same.nn_cost < 0.05
    np.testing.assert_allclose(same.f(demo), demo, atol=0.01)


@pytest.mark.parametrize("params", [SCAN, EXACT], ids=["scan", "exact"])
def test_cost_grows_with_deformation(params: RegistrationParams) -> None:
    rng = np.random.default_rng(0)
    demo = rope_cloud(rng, 100)
    base = smooth_warp(rng, 1.0, angle_rad=0.0)
    noise = np.random.default_rng(9).normal(0, 0.002, demo.shape)
    costs = []
    for mag in (0.0, 0.02, 0.04, 0.08):
        warp = SmoothWarp(np.eye(3), np.zeros(3), base.amp_k3 * mag, base.omega_k3, base.phase_k)
        costs.append(register(demo, warp(demo) + noise, params).nn_cost)
    assert np.all(np.diff(costs) > 0), costs


def _library(seed: int, sizes: list[int]) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    return [rope_cloud(rng, n) for n in sizes]


def test_batched_scan_agrees_with_single_pair() -> None:
    demos = _library(5, [80, 120, 95, 110, 100, 90])
    rng = np.random.default_rng(6)
    scene = corrupt(rng, smooth_warp(rng, 0.03)(demos[2]))
    registrar = LibraryRegistrar(SCAN, chunk_size=4, n_workers=2)
    result = registrar.scan(scene, demos, key="lib-a")
    assert result.ok_a.all()
    for a, demo in enumerate(demos):
        single = register(demo, scene, SCAN)
        np.testing.assert_allclose(result.costs(a).as_array(), single.costs.as_array(), rtol=1e-4)
        assert result.nn_cost_a[a] == pytest.approx(single.nn_cost, rel=1e-5)
        np.testing.assert_allclose(result.f(a)(demo), single.f(demo), atol=1e-5)
        np.testing.assert_allclose(result.g(a)(scene), single.g(scene), atol=1e-5)
    # a slightly moved, noisy copy of demo 2 finds demo 2 as its nearest neighbour
    near = corrupt(rng, demos[2] + [0.01, -0.01, 0.0], noise_m=0.002, outlier_frac=0.0)
    assert int(np.argmin(registrar.scan(near, demos, key="lib-a").nn_cost_a)) == 2


def test_scan_reports_bad_demos_without_stopping() -> None:
    demos = _library(7, [90, 90, 90])
    huge = demos[0] * 1e25  # overflows float32: a non-finite fit
    bad = [demos[0], np.full((50, 3), np.nan), np.zeros((0, 3)), np.ones((9, 3)), huge, demos[1]]
    scene = demos[1] + 0.01
    result = LibraryRegistrar(SCAN).scan(scene, bad)
    assert result.ok_a.tolist() == [True, False, False, False, False, True]
    assert "no finite points" in result.reason_a[1]
    assert "empty" in result.reason_a[2]
    assert "at least 5 distinct" in result.reason_a[3]
    assert result.reason_a[4]
    assert np.isinf(result.nn_cost_a[1:5]).all()
    assert np.isfinite(result.nn_cost_a[[0, 5]]).all()
    assert int(np.argmin(result.nn_cost_a)) == 5


def test_bad_inputs_raise_clear_errors() -> None:
    cloud = rope_cloud(np.random.default_rng(0), 60)
    with pytest.raises(InvalidInputError, match="empty"):
        register(cloud, np.zeros((0, 3)))
    with pytest.raises(InvalidInputError, match="no finite points"):
        register(np.full((10, 3), np.nan), cloud)
    with pytest.raises(InvalidInputError, match=r"shape \(n, 3\)"):
        register(cloud[:, :2], cloud)
    with pytest.raises(InvalidInputError, match=r"shape \(n, 3\)"):
        LibraryRegistrar().scan(cloud, [cloud, cloud[:, :2]])
    with pytest.raises(InvalidInputError, match="empty"):
        LibraryRegistrar().scan(cloud, [])


def test_nan_rows_dropped_and_big_clouds_capped_with_warnings() -> None:
    rng = np.random.default_rng(1)
    cloud = rope_cloud(rng, 200)
    with_nan = cloud[:120].copy()
    with_nan[::10] = np.nan
    params = replace(SCAN, max_points=150)
    with pytest.warns(RuntimeWarning, match="non-finite rows"):
        reg = register(with_nan, cloud[:120], params)
    assert reg.ok and reg.corr_nm.shape == (108, 120)
    with pytest.warns(RuntimeWarning, match="exceed the cap of 150"):
        first = register(cloud, cloud, params)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        second = register(cloud, cloud, params)
    assert first.corr_nm.shape == (150, 150)
    assert first.nn_cost == second.nn_cost  # deterministic subsample


def test_disk_and_memory_cache_give_identical_scans(tmp_path) -> None:
    demos = _library(8, [70, 85, 90])
    scene = demos[0] + 0.02
    first = LibraryRegistrar(SCAN, cache_dir=tmp_path)
    res1 = first.scan(scene, demos, key="hash-1")
    assert list((tmp_path / ".cache").glob("*.npz"))
    assert first.prepare(demos, key="hash-1") is first.prepare(demos, key="hash-1")
    second = LibraryRegistrar(SCAN, cache_dir=tmp_path)
    res2 = second.scan(scene, demos, key="hash-1")
    np.testing.assert_array_equal(res1.costs_ac, res2.costs_ac)
    assert res2.costs_ac.shape == (3, len(COST_NAMES))
    np.testing.assert_allclose(res2.f(1)(demos[1]), res1.f(1)(demos[1]))
