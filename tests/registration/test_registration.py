"""Bidirectional TPS-RPM: accuracy on warped rope clouds, costs, batch = single pair, bad input."""

from __future__ import annotations

import os
import select
import signal
import warnings
from dataclasses import replace

import numpy as np
import pytest

from knotlab.core.errors import InvalidInputError, SolverError
from knotlab.core.registration import (
    COST_NAMES,
    EXACT,
    SCAN,
    LibraryRegistrar,
    RegistrationParams,
    register,
)
from knotlab.core.registration.synthetic import SmoothWarp, corrupt, rope_cloud, smooth_warp

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


@pytest.mark.parametrize("scale", [0.25, 1.0, 2.0])
def test_internal_scale_does_not_change_the_world_fit(scale: float) -> None:
    # Regularisers are stated in world units and converted once: the kernel's internal length
    # scale_m is a numerical detail, so the warp in metres must not move when it changes.
    rng = np.random.default_rng(3)
    demo = rope_cloud(rng, 80)
    scene = corrupt(rng, smooth_warp(rng, 0.03, angle_rad=0.3)(demo), 0.002, 0.0)
    probe = demo + np.array([0.0, 0.0, 0.3])  # gripper waypoints above the rope
    base = register(demo, scene, EXACT)
    other = register(demo, scene, replace(EXACT, scale_m=EXACT.scale_m * scale))
    np.testing.assert_allclose(other.f(probe), base.f(probe), atol=1e-6)
    np.testing.assert_allclose(other.g(scene), base.g(scene), atol=1e-6)
    assert other.costs.residual_fwd_m == pytest.approx(base.costs.residual_fwd_m, abs=1e-8)


def test_identity_pull_is_stated_in_world_units() -> None:
    # R / s^2 in the kernel's coordinates: (1e-3, 1e-3, 0.1) m^2 at s = 0.5 m is (4e-3, 4e-3, 0.4).
    np.testing.assert_allclose(SCAN.normalised_rot_coef, (4e-3, 4e-3, 0.4))
    lams, temps = SCAN.normalised_schedule()
    np.testing.assert_allclose([lams[0], temps[0]], [0.1, 0.1])


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


@pytest.mark.parametrize("params", [SCAN, replace(EXACT, n_iter=8)], ids=["scan", "exact"])
def test_scan_results_do_not_depend_on_chunks_or_workers(params: RegistrationParams) -> None:
    """Chunking only schedules work: every output is bit-identical, a pair scan included.

    (Before the costs moved into the kernel, a chunk's zero padding could change the last bit
    of a cost, so the same scan with another chunk size was not bit-identical.)
    """
    demos = _library(7, [60, 120, 95, 75, 110, 100, 90, 85, 70])
    rng = np.random.default_rng(8)
    scene = corrupt(rng, smooth_warp(rng, 0.03)(demos[1]))
    runs = [
        LibraryRegistrar(params, chunk_size=size, n_workers=workers).scan(
            scene, demos, keep_correspondence=True
        )
        for size, workers in [(16, 1), (1, 1), (4, 2), (3, 2)]
    ]
    assert runs[0].ok_a.all()
    for run in runs[1:]:
        for name in ("costs_ac", "e_f_ak3", "e_g_ak3", "corr_anm"):
            np.testing.assert_array_equal(getattr(run, name), getattr(runs[0], name), name)
    single = register(demos[3], scene, params)
    np.testing.assert_array_equal(single.costs.as_array(), runs[0].costs_ac[3])


@pytest.mark.parametrize("params", [SCAN, replace(EXACT, n_iter=8)], ids=["scan", "exact"])
def test_first_iteration_run_early_resumes_bit_identically(params: RegistrationParams) -> None:
    """Demos whose first iteration ran before the scene basis existed end exactly as a plain scan.

    Forced here (every other demo, uneven clouds, a bad demo skipped); in a 2-worker scan which
    demos run early depends on timing, so the scan itself is checked on its outputs too.
    """
    from knotlab.core.registration.chunks import run_chunks
    from knotlab.core.registration.params import clean_cloud
    from knotlab.core.registration.rpm import (
        FirstIteration,
        first_iteration_batch,
        first_iteration_inputs,
    )
    from knotlab.core.registration.sides import normalise_cloud, scene_side

    demos = _library(8, [60, 120, 95, 75, 110, 100, 90, 85, 70])
    demos[4] = np.ones((9, 3))  # not ok: never run early, reported as before
    rng = np.random.default_rng(9)
    scene = corrupt(rng, smooth_warp(rng, 0.03)(demos[2]))
    plain = LibraryRegistrar(params, chunk_size=3).scan(scene, demos)
    registrar = LibraryRegistrar(params)
    demo = registrar.prepare(demos)
    cloud = clean_cloud(scene, "scene cloud", params.max_points)
    side = scene_side(cloud, params, cleaned=True)
    dt = np.dtype(params.dtype)
    first = FirstIteration.allocate(len(demo), demo.x_an3.shape[1], int(side.n_a[0]), dt)
    inputs = first_iteration_inputs(normalise_cloud(cloud, params)[1], params)
    first_iteration_batch(demo, np.array([0, 2, 3, 6, 8]), inputs, params, first)
    assert first.done_a.tolist() == [True, False, True, True, False, False, True, False, True]
    resumed = run_chunks(
        demo, side, params, chunk_size=2, n_workers=1, keep_corr=False, first=first
    )
    for name in ("costs_ac", "ok_a", "e_f_ak3", "e_g_ak3"):
        np.testing.assert_array_equal(getattr(resumed, name), getattr(plain, name), err_msg=name)
    assert resumed.reason_a == plain.reason_a
    early = LibraryRegistrar(params, chunk_size=2, n_workers=2)
    for _ in range(3):
        scanned = early.scan(scene, demos)
        np.testing.assert_array_equal(scanned.costs_ac, plain.costs_ac)
        np.testing.assert_array_equal(scanned.e_g_ak3, plain.e_g_ak3)
    early.close()
    with pytest.raises(InvalidInputError, match="no correspondence"):
        run_chunks(demo, side, params, chunk_size=2, n_workers=1, keep_corr=True, first=first)


def test_bad_scene_with_an_early_first_iteration_raises_and_leaves_the_registrar_usable() -> None:
    demos = _library(10, [80, 90, 100])
    registrar = LibraryRegistrar(SCAN, n_workers=2)
    # a clean cloud whose basis fails: found only after the early first iteration started
    with pytest.raises(SolverError, match="scene cloud: TPS normal matrix is singular"):
        registrar.scan(demos[0] * 1e30, demos)
    good = registrar.scan(demos[1] + 0.01, demos)
    assert good.ok_a.all() and int(np.argmin(good.nn_cost_a)) == 1
    registrar.close()


@pytest.mark.parametrize(
    "n_items,chunk_size,n_workers", [(148, 16, 2), (148, 8, 3), (5, 16, 2), (37, 4, 1), (0, 8, 2)]
)
def test_chunk_plan_covers_every_item_once_and_shrinks_at_the_end(
    n_items: int, chunk_size: int, n_workers: int
) -> None:
    from knotlab.core.registration.chunks import chunk_plan

    plan = chunk_plan(n_items, chunk_size, n_workers)
    covered = [i for start, stop in plan for i in range(start, stop)]
    assert covered == list(range(n_items))
    sizes = [stop - start for start, stop in plan]
    assert all(1 <= size <= chunk_size for size in sizes)
    assert sizes == sorted(sizes, reverse=True)  # never a big chunk after a small one
    if n_workers == 1:
        assert sizes[:-1] == [chunk_size] * (len(sizes) - 1)
    elif n_items >= 4 * n_workers:
        # the tail is fine-grained: the last chunk is one item, the first ones full size
        assert sizes[-1] == 1 and sizes[0] == min(chunk_size, -(-n_items // (2 * n_workers)))


def test_registrar_keeps_its_threads_and_survives_pickling_and_close() -> None:
    import pickle

    demos = _library(9, [70, 80, 90, 75, 85])
    scene = demos[2] + 0.01
    registrar = LibraryRegistrar(SCAN, chunk_size=1, n_workers=2)
    first = registrar.scan(scene, demos)
    pool = registrar._worker_pool()
    registrar.scan(scene, demos)
    assert registrar._worker_pool() is pool  # one pool for the registrar's life, not per scan
    copy = pickle.loads(pickle.dumps(registrar))  # e.g. shipped to a worker process
    np.testing.assert_array_equal(copy.scan(scene, demos).costs_ac, first.costs_ac)
    registrar.close()
    np.testing.assert_array_equal(registrar.scan(scene, demos).costs_ac, first.costs_ac)
    # a forked child (multiprocessing's default here) has none of the parent's threads: it
    # starts its own instead of waiting for ever on the parent's
    read_end, write_end = os.pipe()
    pid = os.fork()
    if pid == 0:  # pragma: no cover - the child
        try:
            os.write(write_end, registrar.scan(scene, demos).costs_ac.tobytes())
        finally:
            os._exit(0)
    os.close(write_end)
    try:
        ready, _, _ = select.select([read_end], [], [], 60.0)
        assert ready, "the forked child's scan hung"
        data = b"".join(iter(lambda: os.read(read_end, 1 << 16), b""))
    finally:
        os.close(read_end)
        os.kill(pid, signal.SIGKILL) if not ready else None
        os.waitpid(pid, 0)
    np.testing.assert_array_equal(np.frombuffer(data).reshape(first.costs_ac.shape), first.costs_ac)
    registrar.close()
    copy.close()


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


def test_rows_of_a_demo_side_are_the_side_of_those_demos_and_scan_alike() -> None:
    from dataclasses import fields

    from knotlab.core.registration.sides import demo_side

    demos = _library(11, [90, 120, 60, 150])
    demos += [np.ones((9, 3)), rope_cloud(np.random.default_rng(3), 70)]  # one cannot factorise
    full = demo_side(demos, SCAN)
    for pick in ([2, 0], [5, 4, 1], [3], [4]):
        cut, built = full.rows(pick), demo_side([demos[a] for a in pick], SCAN)
        for f in fields(full):
            if f.name == "_casts":
                continue
            a, b = getattr(cut, f.name), getattr(built, f.name)
            if f.name == "clouds":
                assert all(np.array_equal(x, y) for x, y in zip(a, b, strict=True))
            elif f.name == "reason_a":  # the same reasons, naming each demo's library index
                assert a == tuple(full.reason_a[i] for i in pick)
                assert [bool(r) for r in a] == [bool(r) for r in b]
            else:
                assert a.shape == b.shape and np.array_equal(a, b), f.name
        scene = demos[0] + 0.01
        by_rows = LibraryRegistrar(SCAN).scan_side(scene, cut)
        by_clouds = LibraryRegistrar(SCAN).scan(scene, [demos[a] for a in pick])
        assert np.array_equal(by_rows.costs_ac, by_clouds.costs_ac, equal_nan=True)
        assert by_rows.ok_a.tolist() == by_clouds.ok_a.tolist()


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


# ----------------------------------------------------------------------------- numba kernel


@pytest.mark.parametrize("dtype", ["float32", "float64"])
def test_kernel_exp_matches_numpy(dtype: str) -> None:
    from knotlab.core.registration.kernel import _exp_neg_row, exp_bits_constants, kernel_constants

    dt = np.dtype(dtype)
    s = np.concatenate([np.linspace(0, 100, 997), np.random.default_rng(0).uniform(0, 90, 500)])
    s = s.astype(dt)
    p = np.empty((1, len(s)), dt)
    bits = np.empty(len(s), np.int32 if dt == np.float32 else np.int64)
    bias_shift = exp_bits_constants(dt)
    _exp_neg_row(
        s.copy(), p, 0, bits, bits.view(dt), *bias_shift, kernel_constants(dt, SCAN), len(s)
    )
    want = np.exp(-np.minimum(s.astype(float), 80.0))
    rel = np.abs(p[0] / want - 1)
    assert rel.max() < (2.5e-7 if dt == np.float32 else 1e-12), rel.max()


@pytest.mark.parametrize("length", [1, 160, 161])
def test_kernel_exp_two_chains_give_the_bits_of_one_chain(length: int) -> None:
    """Elements j and j + m/2 share a pass; each gets one chain's operations in its order."""
    from knotlab.core.registration.kernel import _exp_neg_row, exp_bits_constants, kernel_constants

    dt = np.dtype(np.float32)
    s = np.random.default_rng(length).uniform(0, 90, length).astype(dt)
    cst = kernel_constants(dt, SCAN)
    p = np.empty((1, length), dt)
    bits = np.empty(length, np.int32)
    _exp_neg_row(s.copy(), p, 0, bits, bits.view(dt), *exp_bits_constants(dt), cst, length)
    # one chain, operation by operation, in NumPy's float32 (each operation rounded once)
    v = np.minimum(s, cst[4])
    k = np.floor(v * cst[0] + cst[1])
    r = k * cst[3] - (v - k * cst[2])
    poly = np.full(length, cst[15], dt)
    for q in range(14, 4, -1):
        poly = poly * r + cst[q]
    two_to_minus_k = ((np.float32(127.0) - k) * np.float32(2.0**23)).astype(np.int32).view(dt)
    assert np.array_equal(p[0].view(np.int32), (poly * two_to_minus_k).view(np.int32))


@pytest.mark.parametrize("rows", [1, 4, 7, 150])
def test_kernel_weighted_rows_add_in_row_order_bit_for_bit(rows: int) -> None:
    """The 4-rows-a-pass axpy adds row by row in order: equal bits to the plain loop."""
    from knotlab.core.registration.kernel import _add_weighted_rows

    rng = np.random.default_rng(rows)
    mat = rng.uniform(0, 1, (rows, 13)).astype(np.float32)
    w = rng.uniform(0, 3, rows).astype(np.float32)
    start = rng.uniform(-1, 1, 13).astype(np.float32)
    got = start.copy()
    _add_weighted_rows(mat, w, got, rows, 11)  # the last two entries are past `length`
    want = start.copy()
    for r in range(rows):
        for x in range(11):
            want[x] = np.float32(want[x] + np.float32(mat[r, x] * w[r]))
    np.testing.assert_array_equal(got, want)


@pytest.mark.parametrize("rows", [1, 4, 7, 150])
@pytest.mark.parametrize("dt", [np.float32, np.float64])
def test_fused_weighted_rows_equal_one_call_per_output_bit_for_bit(rows: int, dt) -> None:
    """The 3- and 4-output axpys give each output the bits of its own single-output call."""
    from knotlab.core.registration.kernel import (
        _add_weighted_rows,
        _add_weighted_rows3,
        _add_weighted_rows4,
    )

    rng = np.random.default_rng(rows)
    mat = rng.uniform(-1, 1, (rows, 13)).astype(dt)
    w = rng.uniform(-3, 3, (4, rows)).astype(dt)
    start = rng.uniform(-1, 1, (4, 13)).astype(dt)
    want = start.copy()
    for d in range(4):
        _add_weighted_rows(mat, w[d], want[d], rows, 11)
    got3, got4 = start.copy(), start.copy()
    _add_weighted_rows3(mat, w[0], w[1], w[2], got3[0], got3[1], got3[2], rows, 11)
    _add_weighted_rows4(mat, *w, *got4, rows, 11)
    np.testing.assert_array_equal(got3[:3].view(np.uint8), want[:3].view(np.uint8))
    np.testing.assert_array_equal(got3[3], start[3])  # untouched
    np.testing.assert_array_equal(got4.view(np.uint8), want.view(np.uint8))
    np.testing.assert_array_equal(got4[:, 11:], start[:, 11:])  # past `length`: untouched


@pytest.mark.parametrize("dt", [np.float32, np.float64])
def test_transpose_block_copies_exactly_one_block(dt) -> None:
    """The shuffle intrinsic writes dst[j0 + c, i0 + r] = src[i0 + r, j0 + c], nothing else."""
    from numba import njit

    from knotlab.core.registration.simd import BLOCK, transpose_block

    @njit
    def blocks(src, dst, corners):
        for q in range(corners.shape[0]):
            transpose_block(src, corners[q, 0], corners[q, 1], dst)

    rng = np.random.default_rng(5)
    src = rng.standard_normal((29, 37)).astype(dt)
    corners = np.array([[0, 0], [3, 11], [21, 29], [8, 16]])  # off the block grid too
    dst = np.full((40, 33), 7.5, dt)
    blocks(src, dst, corners)
    want = np.full((40, 33), 7.5, dt)
    for i0, j0 in corners:
        want[j0 : j0 + BLOCK, i0 : i0 + BLOCK] = src[i0 : i0 + BLOCK, j0 : j0 + BLOCK].T
    np.testing.assert_array_equal(dst.view(np.uint8), want.view(np.uint8))


def test_kernel_refuses_inputs_without_the_vector_padding() -> None:
    """Numba does not check bounds: unpadded TPS bases must raise, not read past the arrays."""
    from knotlab.core.registration.rpm import rpm_batch
    from knotlab.core.registration.sides import demo_side, scene_side

    demos = _library(3, [40, 33, 40])
    demo, scene = demo_side(demos, SCAN), scene_side(demos[1], SCAN)
    idx = np.arange(3)
    rpm_batch(demo, idx, scene, SCAN, False)  # padded by `cast`: runs
    cast = demo.cast(np.dtype(SCAN.dtype))
    cast["gt_akn"] = np.ascontiguousarray(cast["gt_akn"][..., : demo.x_an3.shape[1]])
    with pytest.raises(ValueError, match="not padded"):
        rpm_batch(demo, idx, scene, SCAN, False)


def _numpy_reference(demo, scene, params):
    """The RPM loop written plainly in float64 NumPy (one demo, batch or weighted rule)."""
    from knotlab.core.registration.tps import tps_basis

    x, y = demo / params.scale_m, scene / params.scale_m  # the kernel's coordinates
    bx, by = tps_basis(x, params.normalised_rot_coef), tps_basis(y, params.normalised_rot_coef)
    n, m = len(x), len(y)
    prior, frac, cutoff = params.outlier_prior, params.outlier_frac, params.outlier_cutoff
    weighted = params.target_rule == "weighted"
    corner = (prior if weighted else frac) * np.sqrt(n * m)
    fx, gy = x.copy(), y.copy()
    for lam, temp in zip(*params.normalised_schedule(), strict=True):
        d = np.linalg.norm(fx[:, None] - y[None], axis=2) + np.linalg.norm(
            x[:, None] - gy[None], axis=2
        )
        p = np.exp(-np.minimum(d / (2 * temp), 80.0))
        c, c_out = np.ones(m), 1.0
        for _ in range(params.sinkhorn_iters):
            r = 1.0 / (p @ c + prior * c_out)
            r_out = m * frac / (prior * c.sum() + corner * c_out)
            c_prev, c = c, 1.0 / (p.T @ r + prior * r_out)
            c_out = n * frac / (prior * r.sum() + corner * r_out)
        mr = r[:, None] * p * c_prev[None]
        mc = r[:, None] * p * c[None]
        w_f, w_g = mr.sum(1), mc.sum(0)
        mean_f = xhat = (mr @ y) / w_f[:, None]
        mean_g = yhat = (mc.T @ x) / w_g[:, None]
        if weighted:
            e_f, e_g = bx.solve(xhat, lam, w_f), by.solve(yhat, lam, w_g)
        else:
            xhat = np.where((w_f >= cutoff)[:, None], xhat, fx)
            yhat = np.where((w_g >= cutoff)[:, None], yhat, gy)
            e_f, e_g = bx.solve(xhat, lam), by.solve(yhat, lam)
        fx, gy = bx.g_nk @ e_f, by.g_nk @ e_g
    costs = {
        "map_fwd": np.sum((w_f if weighted else 1.0) * ((fx - xhat) ** 2).sum(1)),
        "map_bwd": np.sum((w_g if weighted else 1.0) * ((gy - yhat) ** 2).sum(1)),
        "bend_f": np.sum(bx.mu_k[:, None] * e_f**2),
        "bend_g": np.sum(by.mu_k[:, None] * e_g**2),
        "inlier_frac_fwd": w_f.sum() / n,
        "inlier_frac_bwd": w_g.sum() / m,
        "affine_dev_f": np.linalg.norm(bx.theta_pk[1:4] @ e_f - np.eye(3)),
        "affine_dev_g": np.linalg.norm(by.theta_pk[1:4] @ e_g - np.eye(3)),
        "residual_fwd_m": np.sum(w_f * np.linalg.norm(fx - mean_f, axis=1))
        / w_f.sum()
        * params.scale_m,
        "residual_bwd_m": np.sum(w_g * np.linalg.norm(gy - mean_g, axis=1))
        / w_g.sum()
        * params.scale_m,
    }
    return e_f, e_g, np.array([costs[name] for name in COST_NAMES])


@pytest.mark.parametrize("scale_m", [1.0, 0.5])
@pytest.mark.parametrize("rule", ["batch", "weighted"])
def test_kernel_matches_numpy_reference_on_random_clouds(rule: str, scale_m: float) -> None:
    from knotlab.core.registration.rpm import rpm_batch
    from knotlab.core.registration.sides import demo_side, scene_side

    rng = np.random.default_rng(11)
    params = replace(SCAN, target_rule=rule, dtype="float64", n_iter=6, scale_m=scale_m)
    for n, m in [(23, 31), (40, 17)]:
        demo = rng.normal(scale=0.3, size=(n, 3))
        scene = demo[: min(n, m)] + rng.normal(scale=0.05, size=(min(n, m), 3))
        scene = np.vstack([scene, rng.normal(scale=0.3, size=(m - len(scene), 3))])
        # clouds already median-centred so the reference needs no normalisation
        demo -= np.median(demo, axis=0)
        scene -= np.median(scene, axis=0)
        e_f, e_g, costs = _numpy_reference(demo, scene, params)
        out = rpm_batch(
            demo_side([demo], params), np.array([0]), scene_side(scene, params), params, False
        )
        np.testing.assert_allclose(out.e_f[0, : len(e_f)], e_f, rtol=1e-7, atol=1e-9)
        np.testing.assert_allclose(out.e_g[0, : len(e_g)], e_g, rtol=1e-7, atol=1e-9)
        # every cost column, computed in the kernel, against the plain formulas
        np.testing.assert_allclose(out.costs_bc[0], costs, rtol=1e-7, atol=1e-12)
        # float32 (the SCAN dtype) stays close to the float64 result
        p32 = replace(params, dtype="float32")
        out32 = rpm_batch(demo_side([demo], p32), np.array([0]), scene_side(scene, p32), p32, False)
        np.testing.assert_allclose(out32.e_f[0, : len(e_f)], e_f, rtol=2e-3, atol=2e-3)
