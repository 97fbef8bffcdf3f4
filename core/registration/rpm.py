"""Bidirectional TPS-RPM (deterministic annealing) for one pair or a whole demo library at once.

One implementation, `rpm_batch`, registers a batch of demo clouds X_a against one scene cloud Y;
a single pair is a batch of one. For each demo a it fits f_a: X_a -> Y and g_a: Y -> X_a
(`tps` conventions) by alternating, for iteration i with bending lambda_i and temperature T_i
(both geometric from init to final, as lfd's `loglinspace`):

  1. affinity   p_ij = exp(-(||f(x_i) - y_j|| + ||x_i - g(y_j)||) / (2 T_i))  (not squared)
  2. an outlier row and column (prior 0.1, marginals n*frac and m*frac) and `sinkhorn_iters`
     Sinkhorn sweeps, rows first, giving row- and column-normalised matches M^r, M^c;
  3. targets x^_i = sum_j M^r_ij y_j (and y^_j = sum_i M^c_ij x_i) and a TPS fit for f and g.

Target rules (`RegistrationParams.target_rule`), all through the same kernel:
  * "batch"    targets x^_i = sum_j M^r_ij y_j / w_i (divided by the inlier mass w_i); a point
               whose inlier mass is below `outlier_cutoff` keeps its current warped position as
               target; the fit is unweighted, so with the spectral basis of `tps.TpsBasis`
               each fit is e = (G^T x^ + h) / (1 + lambda mu): products only, precomputed per
               cloud. Used by `SCAN` (features, nearest-neighbour cost). Corner frac*sqrt(nm).
  * "gpu"      as "batch" but targets NOT divided by w_i (the literal GPU `getTargPts` rule).
  * "weighted" the paper-era CPU rule: x^_i = sum_j M^r_ij y_j / w_i and a fit weighted by w_i
               (one k x k solve per demo per iteration). Used by `EXACT` (transfer).
               Outlier corner prior*sqrt(nm).

Normalisation: every cloud is translated by its own median (so the identity start is lfd's
median-translation initialisation) and divided by ONE fixed isotropic length `scale_m` shared by
all clouds. Not a per-cloud bounding box: per-axis boxes blow up on straight ropes, and because
the kernel -r is 1-homogeneous, scaling a pair by s is the same as dividing lambda by s, so a
pair-dependent scale would make the per-demo precomputation scene-dependent. Costs are in these
normalised ("unit-box") coordinates; f and g are returned in world coordinates.

The annealing loop itself is one numba kernel (`rpm_kernel`, see the comment above it); the
single-pair `register` runs it as a batch of one, so a scan and a pair use the same code.

Shape suffixes: a demos, b demos in a chunk, n demo points (padded), m scene points, k TPS
basis coefficients, 3 xyz.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from concurrent.futures import Executor, ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np

from knotlab.core.errors import InvalidInputError, SolverError
from knotlab.core.registration.kernel import (
    PHASES,
    TARGET_RULES,
    exp_bits_constants,
    kernel_constants,
    padded_length,
    rpm_kernel,
)
from knotlab.core.registration.params import (
    COST_NAMES,
    EXACT,
    RegistrationCosts,
    RegistrationParams,
    clean_cloud,
)
from knotlab.core.registration.tps import ThinPlateSpline, TpsBasis, tps_basis


def _pad_last_axis(arr: np.ndarray, dtype: np.dtype) -> np.ndarray:
    """arr in dtype, C-contiguous, its last axis zero-padded to `padded_length`."""
    out = np.zeros((*arr.shape[:-1], padded_length(arr.shape[-1])), dtype)
    out[..., : arr.shape[-1]] = arr
    return out


@dataclass(frozen=True, eq=False)
class CloudSide:
    """One side's clouds, normalised and factorised, padded to a common size (float64)."""

    clouds: tuple[np.ndarray, ...]  # cleaned world clouds (empty array for a bad one)
    centre_a3: np.ndarray  # median of each cloud (world)
    x_an3: np.ndarray  # normalised, zero-padded
    mask_an: np.ndarray  # bool, valid points
    g_ank: np.ndarray
    mu_ak: np.ndarray
    h_ak3: np.ndarray
    theta_apk: np.ndarray  # [t; B; W] = theta e, W rows padded
    n_a: np.ndarray  # valid points per cloud
    ok_a: np.ndarray
    reason_a: tuple[str, ...]
    _casts: dict = field(default_factory=dict, repr=False)

    def cast(self, dtype: np.dtype) -> dict[str, np.ndarray]:
        """The arrays the RPM loop reads, in its dtype, converted once and kept."""
        key = np.dtype(dtype).str
        if key not in self._casts:
            self._casts[key] = {
                "x_an3": self.x_an3.astype(dtype),
                # rows zero-padded to the kernel's vector length (`padded_length`)
                "g_ank": _pad_last_axis(self.g_ank, dtype),
                "gt_akn": _pad_last_axis(np.swapaxes(self.g_ank, 1, 2), dtype),
                "mu_ak": self.mu_ak.astype(dtype),
                "h_ak3": self.h_ak3.astype(dtype),
            }
        return self._casts[key]

    def __len__(self) -> int:
        return int(self.n_a.shape[0])

    def basis(self, a: int) -> TpsBasis:
        """The TpsBasis of cloud a (normalised coordinates)."""
        n = int(self.n_a[a])
        k = n + 4  # coefficients past the cloud's own count are zero padding
        return TpsBasis(
            self.x_an3[a, :n],
            np.zeros(3),
            self.g_ank[a, :n, :k],
            self.mu_ak[a, :k],
            self.h_ak3[a, :k],
            self.theta_apk[a, : 4 + n, :k],
        )


def normalise_cloud(cloud: np.ndarray, params: RegistrationParams) -> tuple[np.ndarray, np.ndarray]:
    """(median centre, cloud translated by it and divided by scale_m): the normalised cloud."""
    centre = np.median(cloud, axis=0)
    return centre, (cloud - centre) / params.scale_m


def _build_side(
    clouds: Sequence[np.ndarray | None], reasons: Sequence[str], params: RegistrationParams
) -> CloudSide:
    """Normalise and factorise each cloud; a cloud that cannot be factorised is marked not ok."""
    n_max = max([len(c) for c in clouds if c is not None] + [5])
    k_max = n_max + 4
    n_clouds = len(clouds)
    side = dict(
        centre_a3=np.zeros((n_clouds, 3)),
        x_an3=np.zeros((n_clouds, n_max, 3)),
        mask_an=np.zeros((n_clouds, n_max), dtype=bool),
        g_ank=np.zeros((n_clouds, n_max, k_max)),
        mu_ak=np.zeros((n_clouds, k_max)),
        h_ak3=np.zeros((n_clouds, k_max, 3)),
        theta_apk=np.zeros((n_clouds, 4 + n_max, k_max)),
        n_a=np.zeros(n_clouds, dtype=int),
    )
    ok = np.zeros(n_clouds, dtype=bool)
    reason = list(reasons)
    kept: list[np.ndarray] = []
    for a, cloud in enumerate(clouds):
        kept.append(np.zeros((0, 3)) if cloud is None else cloud)
        if cloud is None:
            continue
        centre, x = normalise_cloud(cloud, params)
        try:
            basis = tps_basis(x, params.normalised_rot_coef)
        except SolverError as exc:
            reason[a] = str(exc)
            continue
        n, k = len(x), basis.n_coef
        side["centre_a3"][a] = centre
        side["x_an3"][a, :n] = x
        side["mask_an"][a, :n] = True
        side["g_ank"][a, :n, :k] = basis.g_nk
        side["mu_ak"][a, :k] = basis.mu_k
        side["h_ak3"][a, :k] = basis.h_k3
        side["theta_apk"][a, : 4 + n, :k] = basis.theta_pk
        side["n_a"][a] = n
        ok[a] = True
    return CloudSide(clouds=tuple(kept), ok_a=ok, reason_a=tuple(reason), **side)  # type: ignore[arg-type]


def demo_side(demo_clouds: Sequence[np.ndarray], params: RegistrationParams) -> CloudSide:
    """Demo side of a library: a bad demo cloud is reported (not ok + reason), never raised."""
    cleaned: list[np.ndarray | None] = []
    reasons: list[str] = []
    for a, cloud in enumerate(demo_clouds):
        arr = np.asarray(cloud)
        if arr.ndim != 2 or arr.shape[-1] != 3:
            raise InvalidInputError(f"demo cloud {a} must have shape (n, 3), got {arr.shape}")
        try:
            cleaned.append(clean_cloud(arr, f"demo cloud {a}", params.max_points))
            reasons.append("")
        except InvalidInputError as exc:
            cleaned.append(None)
            reasons.append(str(exc))
    if not cleaned:
        raise InvalidInputError("the demo library is empty")
    return _build_side(cleaned, reasons, params)


# ----------------------------------------------------------------------------- the RPM core


@dataclass(frozen=True, eq=False)
class _ChunkOut:
    e_f: np.ndarray  # (b, k, 3)
    e_g: np.ndarray  # (b, k_y, 3)
    costs_bc: np.ndarray
    corr_bnm: np.ndarray | None
    failed: dict[int, str]


def _solve_weighted(
    g_bnk: np.ndarray, mu_bk: np.ndarray, h_bk3: np.ndarray, target_bn3, w_bn, lam: float
) -> tuple[np.ndarray, dict[int, str]]:
    """Batched (I + lambda diag mu - G^T diag(1-w) G) e = G^T diag(w) y^ + h."""
    k = g_bnk.shape[-1]
    lhs = np.eye(k) + lam * mu_bk[:, :, None] * np.eye(k)
    gw = g_bnk * (1.0 - w_bn)[:, :, None]
    lhs = lhs - np.swapaxes(g_bnk, 1, 2) @ gw
    rhs = np.swapaxes(g_bnk, 1, 2) @ (w_bn[:, :, None] * target_bn3) + h_bk3
    failed: dict[int, str] = {}
    try:
        return np.linalg.solve(lhs, rhs), failed
    except np.linalg.LinAlgError:
        out = np.zeros_like(rhs)
        for b in range(lhs.shape[0]):
            try:
                out[b] = np.linalg.solve(lhs[b], rhs[b])
            except np.linalg.LinAlgError:
                failed[b] = "weighted TPS system singular (no inlier mass?)"
        return out, failed


class _PhaseClock:
    """Accumulates wall time per phase into a dict when one is given (for the benchmark)."""

    def __init__(self, timings: dict[str, float] | None) -> None:
        self.timings = timings
        self.last = time.perf_counter() if timings is not None else 0.0

    def tick(self, phase: str) -> None:
        if self.timings is not None:
            now = time.perf_counter()
            self.timings[phase] = self.timings.get(phase, 0.0) + now - self.last
            self.last = now


# ----------------------------------------------------------------------------- numba kernels
#
# One fused kernel, `rpm_kernel`, runs the whole annealing loop for a chunk of demos, one demo
# at a time (its correspondence matrix, 90 kB at 150 x 150 float32, stays in L1/L2 for all
# iterations). It is compiled without fastmath (strict IEEE; results do not depend on
# reassociation) and without numba's own threading (`parallel=False`): the one level of
# parallelism is `LibraryRegistrar`'s worker threads over chunks, which the kernel allows by
# releasing the GIL (`nogil=True`); numba's threading layer is never started. Two idioms keep
# the inner loops SIMD-vectorisable under strict IEEE:
#   * p is kept in both layouts (p and p^T, one copy per iteration) so every Sinkhorn, target
#     and TPS product is an axpy along contiguous memory; a dot-product reduction is not
#     vectorised without reassociation. Each such product is `_add_weighted_rows`, which adds
#     four rows per pass over its output in the same order as one at a time (bit-identical);
#     where several outputs share one matrix (targets: 4, TPS fit and apply: 3) its 3- and
#     4-output forms read the matrix once for all of them, each output summed as alone;
#   * the affinity's distances are a function of their own (`_distance_row`): inlined in the
#     large kernel, LLVM left that loop scalar;
#   * exp(-s) is `_exp_neg_row`: Cody-Waite range reduction s = k ln2 - r, a degree-10 Taylor
#     polynomial (relative truncation error < 3e-13) and 2^-k assembled from its IEEE bits;
#     LLVM's exp is a scalar libm call when SVML is absent. Measured error vs np.exp: < 1e-7
#     relative in float32 (about 1 ulp), < 1e-12 in float64 (tests/test_registration.py).
# The ten costs are computed in the kernel too, in float64, at the end of each demo over that
# demo's own points (`_match_costs`, `_spline_costs`): in NumPy over a chunk's padded arrays
# they took ~6 % of a scan, and the padding could change a cost's last bit with the chunking.
# Chunks therefore only schedule work: every output is the same whatever the chunk (tested).


@dataclass(frozen=True, eq=False)
class KernelInputs:
    """What every chunk of one scan hands the kernel: scene arrays, schedule and constants.

    Built before the scene's basis is factorised (`first_iteration_inputs`), the basis arrays
    are zeros: only the first iteration's affinity, Sinkhorn and targets may run on them.
    """

    dtype: np.dtype
    y_m3: np.ndarray
    g_y: np.ndarray
    gt_y: np.ndarray
    mu_y: np.ndarray
    h_y: np.ndarray
    mu_y64: np.ndarray  # float64, for the costs
    theta_y64: np.ndarray
    lams: np.ndarray
    inv2t: np.ndarray
    cst: np.ndarray
    e_bias: np.floating
    e_shift: np.floating


def _schedule_inputs(dt: np.dtype, params: RegistrationParams) -> dict:
    """The kernel inputs that do not depend on the scene: schedule and constants."""
    lams, temps = params.normalised_schedule()
    e_bias, e_shift = exp_bits_constants(dt)
    return dict(
        dtype=dt,
        lams=lams.astype(dt),
        inv2t=(0.5 / temps).astype(dt),
        cst=kernel_constants(dt, params),
        e_bias=e_bias,
        e_shift=e_shift,
    )


def kernel_inputs(scene: CloudSide, params: RegistrationParams) -> KernelInputs:
    """The scan-wide kernel inputs, built once per scan rather than once per chunk."""
    dt = np.dtype(params.dtype)
    m = int(scene.n_a[0])
    ky = m + 4
    scene_cast = scene.cast(dt)
    return KernelInputs(
        y_m3=np.ascontiguousarray(scene_cast["x_an3"][0, :m]),
        # rows padded as the kernel's (zeros beyond ky and m)
        g_y=np.ascontiguousarray(scene_cast["g_ank"][0, :m, : padded_length(ky)]),
        gt_y=np.ascontiguousarray(scene_cast["gt_akn"][0, :ky, : padded_length(m)]),
        mu_y=np.ascontiguousarray(scene_cast["mu_ak"][0, :ky]),
        h_y=np.ascontiguousarray(scene_cast["h_ak3"][0, :ky]),
        mu_y64=scene.mu_ak[0],
        theta_y64=scene.theta_apk[0],
        **_schedule_inputs(dt, params),
    )


def first_iteration_inputs(y_m3: np.ndarray, params: RegistrationParams) -> KernelInputs:
    """Kernel inputs for the first iteration's first phases, from the normalised scene alone."""
    dt = np.dtype(params.dtype)
    m = len(y_m3)
    ky = m + 4
    return KernelInputs(
        y_m3=np.ascontiguousarray(y_m3, dtype=dt),  # the values scene.cast gives: one rounding
        g_y=np.zeros((m, padded_length(ky)), dt),
        gt_y=np.zeros((ky, padded_length(m)), dt),
        mu_y=np.zeros(ky, dt),
        h_y=np.zeros((ky, 3), dt),
        mu_y64=np.zeros(ky),
        theta_y64=np.zeros((4 + m, ky)),
        **_schedule_inputs(dt, params),
    )


@dataclass(frozen=True, eq=False)
class FirstIteration:
    """First-iteration targets and inlier masses per demo, kept by a `first_only` kernel run.

    done[a] says which demos have them; a scan resumes those demos from here (bit-identical
    to running them whole). Arrays in the RPM dtype, over all demos of the library.
    """

    xhat_a3n: np.ndarray
    yhat_a3m: np.ndarray
    wf_an: np.ndarray
    wg_am: np.ndarray
    done_a: np.ndarray

    @staticmethod
    def allocate(n_demos: int, n_max: int, m: int, dt: np.dtype) -> FirstIteration:
        """Room for every demo of a library, none done."""
        return FirstIteration(
            np.zeros((n_demos, 3, n_max), dt),
            np.zeros((n_demos, 3, m), dt),
            np.zeros((n_demos, n_max), dt),
            np.zeros((n_demos, m), dt),
            np.zeros(n_demos, np.bool_),
        )

    @staticmethod
    def none(dt: np.dtype) -> FirstIteration:
        """No demo done (what a scan without an early start passes the kernel)."""
        return FirstIteration.allocate(0, 0, 0, dt)


def can_start_early(params: RegistrationParams, keep_corr: bool) -> bool:
    """Whether a scan may run the first iteration before the scene basis exists.

    A resumed demo does not keep the first iteration's match, so the final costs must come from
    a later iteration (n_iter >= 2) and no correspondence may be asked for.
    """
    return params.n_iter >= 2 and not keep_corr


def rpm_batch(
    demo: CloudSide,
    idx: np.ndarray,
    scene: CloudSide,
    params: RegistrationParams,
    keep_corr: bool,
    timings: dict[str, float] | None = None,
    stop_after: int = len(PHASES) - 1,
    inputs: KernelInputs | None = None,
    first: FirstIteration | None = None,
) -> _ChunkOut:
    """Run bidirectional TPS-RPM for demos idx against the scene (one cloud) in one batch.

    `first`: demos with first.done_a resume from their kept first-iteration targets.
    """
    clock = _PhaseClock(timings)
    if inputs is None:
        inputs = kernel_inputs(scene, params)
    dt = inputs.dtype
    if first is None:
        first = FirstIteration.none(dt)
    elif first.done_a[idx].any() and (
        not can_start_early(params, keep_corr) or stop_after < len(PHASES) - 1
    ):
        raise InvalidInputError(
            "a resumed first iteration needs n_iter >= 2, all phases and no correspondence"
        )
    n = max(int(demo.n_a[idx].max()), 1)
    m = inputs.y_m3.shape[0]
    nb = len(idx)
    e_f = np.zeros((nb, n + 4, 3), dt)
    e_g = np.zeros((nb, m + 4, 3), dt)
    costs = np.zeros((nb, len(COST_NAMES)))
    corr = np.zeros((nb, n, m) if keep_corr else (0, 0, 0), dt)
    bad = np.zeros(nb, np.bool_)
    clock.tick("setup")
    _run_kernel(demo, idx, inputs, params, stop_after, (e_f, e_g, costs, corr, bad), False, first)
    clock.tick("rpm kernel")
    failed = {int(b): "weighted TPS system singular (no inlier mass?)" for b in np.flatnonzero(bad)}

    e_f64, e_g64 = e_f.astype(float), e_g.astype(float)
    return _ChunkOut(e_f64, e_g64, costs, corr.astype(float) if keep_corr else None, failed)


def first_iteration_batch(
    demo: CloudSide,
    idx: np.ndarray,
    inputs: KernelInputs,
    params: RegistrationParams,
    first: FirstIteration,
) -> None:
    """The first iteration's affinity, Sinkhorn and targets for demos idx, kept in `first`.

    Needs only `first_iteration_inputs` (no scene basis), so it can run while that is factorised.
    """
    dt = inputs.dtype
    no_outputs = (
        np.zeros((0, 0, 3), dt),
        np.zeros((0, 0, 3), dt),
        np.zeros((0, len(COST_NAMES))),
        np.zeros((0, 0, 0), dt),
        np.zeros(0, np.bool_),
    )
    _run_kernel(demo, idx, inputs, params, len(PHASES) - 1, no_outputs, True, first)


def _run_kernel(
    demo: CloudSide,
    idx: np.ndarray,
    inputs: KernelInputs,
    params: RegistrationParams,
    stop_after: int,
    outputs: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray],
    first_only: bool,
    first: FirstIteration,
) -> None:
    """Call `rpm_kernel` for demos idx: the per-chunk arguments around the scan-wide inputs."""
    dt = inputs.dtype
    weighted = params.target_rule == "weighted"
    n_valid = demo.n_a[idx]
    cast = demo.cast(dt)
    m = inputs.y_m3.shape[0]
    frac = params.outlier_frac
    corner_coef = frac if not weighted else params.outlier_prior
    # scratch, one per call, as long as the kernel's padded affinity rows
    bits = np.empty(padded_length(m), np.int32 if dt == np.float32 else np.int64)
    e_f, e_g, costs, corr, bad = outputs
    rpm_kernel(
        np.ascontiguousarray(idx, dtype=np.int64),
        cast["x_an3"],
        demo.n_a,
        cast["g_ank"],
        cast["gt_akn"],
        cast["mu_ak"],
        cast["h_ak3"],
        inputs.y_m3,
        inputs.g_y,
        inputs.gt_y,
        inputs.mu_y,
        inputs.h_y,
        inputs.lams,
        inputs.inv2t,
        inputs.cst,
        bits,
        bits.view(dt),
        inputs.e_bias,
        inputs.e_shift,
        np.array(m * frac, dt),
        (n_valid * frac).astype(dt),
        (corner_coef * np.sqrt(n_valid * m)).astype(dt),
        TARGET_RULES[params.target_rule],
        params.sinkhorn_iters,
        stop_after,
        demo.mu_ak,
        demo.theta_apk,
        inputs.mu_y64,
        inputs.theta_y64,
        float(params.scale_m),
        e_f,
        e_g,
        costs,
        corr,
        bad,
        first_only,
        first.xhat_a3n,
        first.yhat_a3m,
        first.wf_an,
        first.wg_am,
        first.done_a,
    )


# ----------------------------------------------------------------------------- results


@dataclass(frozen=True, eq=False)
class Registration:
    """One bidirectional registration: f (demo -> scene), g (scene -> demo), world coordinates."""

    f: ThinPlateSpline
    g: ThinPlateSpline
    costs: RegistrationCosts
    ok: bool
    reason: str
    corr_nm: np.ndarray | None  # row-normalised soft correspondence (demo point i, scene point j)

    @property
    def nn_cost(self) -> float:
        """Nearest-neighbour cost (paper-era GPU batch), +inf when not ok."""
        return self.costs.nn_cost if self.ok else float("inf")


@dataclass(frozen=True, eq=False)
class ScanResult:
    """Registrations of one scene against every demo a; arrays over demos."""

    params: RegistrationParams
    costs_ac: np.ndarray  # columns COST_NAMES; +inf rows where not ok
    ok_a: np.ndarray
    reason_a: tuple[str, ...]
    e_f_ak3: np.ndarray
    e_g_ak3: np.ndarray
    corr_anm: np.ndarray | None
    _demo: CloudSide
    _scene: CloudSide

    @property
    def nn_cost_a(self) -> np.ndarray:
        """map_fwd + map_bwd + bend_f + bend_g per demo (+inf where not ok); lower is better."""
        return self.costs_ac[:, :4].sum(axis=1)

    def cost(self, name: str) -> np.ndarray:
        """One cost column by name (see COST_NAMES)."""
        return self.costs_ac[:, COST_NAMES.index(name)]

    def costs(self, a: int) -> RegistrationCosts:
        """Cost record of demo a."""
        return RegistrationCosts(*(float(v) for v in self.costs_ac[a]))

    def f(self, a: int) -> ThinPlateSpline:
        """f_a: demo a's cloud -> scene, world coordinates."""
        s = self.params.scale_m
        basis = self._demo.basis(a)
        spline = basis.spline(self.e_f_ak3[a, : basis.n_coef])
        return spline.compose_affine(s, self._demo.centre_a3[a], self._scene.centre_a3[0])

    def g(self, a: int) -> ThinPlateSpline:
        """g_a: scene -> demo a's cloud, world coordinates."""
        s = self.params.scale_m
        basis = self._scene.basis(0)
        spline = basis.spline(self.e_g_ak3[a, : basis.n_coef])
        return spline.compose_affine(s, self._scene.centre_a3[0], self._demo.centre_a3[a])

    def registration(self, a: int) -> Registration:
        """Everything about demo a as a Registration record."""
        corr = None if self.corr_anm is None else self.corr_anm[a, : self._demo.n_a[a]]
        return Registration(
            self.f(a), self.g(a), self.costs(a), bool(self.ok_a[a]), self.reason_a[a], corr
        )


def chunk_plan(n_items: int, chunk_size: int, n_workers: int) -> list[tuple[int, int]]:
    """[start, stop) ranges of at most chunk_size items that shrink toward the end.

    Guided scheduling: with several workers each chunk is at most 1 / (2 workers) of what is
    left, so the last chunks are small and the workers, taking chunks as they free up, finish
    close together (148 demos in chunks of 16 on 2 workers left one worker idle for up to 16
    demos). A chunk's results do not depend on the chunk it is in (tested), only speed does.
    """
    plan: list[tuple[int, int]] = []
    start = 0
    while start < n_items:
        left = n_items - start
        size = min(chunk_size, left if n_workers <= 1 else -(-left // (2 * n_workers)))
        plan.append((start, start + size))
        start += size
    return plan


def run_chunks(
    demo: CloudSide,
    scene: CloudSide,
    params: RegistrationParams,
    *,
    chunk_size: int,
    n_workers: int,
    keep_corr: bool,
    timings: dict[str, float] | None = None,
    pool: Executor | None = None,
    first: FirstIteration | None = None,
) -> ScanResult:
    """Registers the scene against every demo, in chunks (independent batches) over workers.

    `pool`: an executor with n_workers threads to reuse (LibraryRegistrar keeps one); without
    it a pool is started and stopped for this call (~0.7 ms). `first`: demos whose first
    iteration ran early (`first_iteration_batch`) resume from it.
    """
    n_demos = len(demo)
    demo.cast(np.dtype(params.dtype))  # convert once, before any worker thread reads it
    inputs = kernel_inputs(scene, params)
    good = np.flatnonzero(demo.ok_a)
    chunks = [good[a:b] for a, b in chunk_plan(len(good), chunk_size, n_workers)]

    def work(idx: np.ndarray) -> _ChunkOut:
        # A demo whose fit overflows is detected below and reported; no warning spam for it.
        with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
            return rpm_batch(
                demo, idx, scene, params, keep_corr, timings, inputs=inputs, first=first
            )

    if n_workers > 1 and len(chunks) > 1:
        # The kernel releases the GIL, so threads share one copy of the library.
        if pool is not None:
            outs = list(pool.map(work, chunks))
        else:
            with ThreadPoolExecutor(n_workers) as own_pool:
                outs = list(own_pool.map(work, chunks))
    else:
        outs = [work(idx) for idx in chunks]
    n_max = demo.x_an3.shape[1]
    m = int(scene.n_a[0])
    costs = np.full((n_demos, len(COST_NAMES)), np.inf)
    e_f = np.zeros((n_demos, n_max + 4, 3))
    e_g = np.zeros((n_demos, m + 4, 3))
    corr = np.zeros((n_demos, n_max, m)) if keep_corr else None
    ok = demo.ok_a.copy()
    reason = list(demo.reason_a)
    with np.errstate(invalid="ignore"):
        for idx, out in zip(chunks, outs, strict=True):
            k = out.e_f.shape[1]
            costs[idx] = out.costs_bc
            e_f[idx, :k] = out.e_f
            e_g[idx] = out.e_g
            if corr is not None and out.corr_bnm is not None:
                corr[idx, : out.corr_bnm.shape[1]] = out.corr_bnm
            for b, why in out.failed.items():
                ok[idx[b]] = False
                reason[idx[b]] = why
    finite = np.all(np.isfinite(costs), axis=1) & np.all(np.isfinite(e_f), axis=(1, 2))
    finite &= np.all(np.isfinite(e_g), axis=(1, 2))
    for a in np.flatnonzero(ok & ~finite):
        ok[a] = False
        reason[a] = "registration produced non-finite values"
    costs[~ok] = np.inf
    return ScanResult(params, costs, ok, tuple(reason), e_f, e_g, corr, demo, scene)


def scene_side(
    scene_cloud: np.ndarray, params: RegistrationParams, *, cleaned: bool = False
) -> CloudSide:
    """Scene side: a bad scene cloud raises (it concerns every demo).

    cleaned: the cloud already went through `clean_cloud` (it is not cleaned twice).
    """
    cloud = scene_cloud if cleaned else clean_cloud(scene_cloud, "scene cloud", params.max_points)
    side = _build_side([cloud], [""], params)
    if not side.ok_a[0]:
        raise SolverError(f"scene cloud: {side.reason_a[0]}")
    return side


def register(
    demo_cloud: np.ndarray, scene_cloud: np.ndarray, params: RegistrationParams = EXACT
) -> Registration:
    """Bidirectional TPS-RPM of one demo cloud onto one scene cloud (a batch of one)."""
    demo = one_demo_side(demo_cloud, params)
    return register_sides(demo, scene_side(scene_cloud, params), params)


def one_demo_side(demo_cloud: np.ndarray, params: RegistrationParams) -> CloudSide:
    """The factorised side of one demo cloud (what `register` builds); raises if unusable."""
    demo = demo_side([clean_cloud(demo_cloud, "demo cloud", params.max_points)], params)
    if not demo.ok_a[0]:
        raise SolverError(f"demo cloud: {demo.reason_a[0]}")
    return demo


def register_sides(demo: CloudSide, scene: CloudSide, params: RegistrationParams) -> Registration:
    """`register` on sides already factorised (`one_demo_side`, `scene_side`): same result."""
    result = run_chunks(demo, scene, params, chunk_size=1, n_workers=1, keep_corr=True)
    return result.registration(0)


# ----------------------------------------------------------------------------- library scans
