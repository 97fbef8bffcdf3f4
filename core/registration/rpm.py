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
This module drives that kernel (its inputs, the early first iteration, `rpm_batch`) and registers
one pair; the normalised clouds are `sides`, a scan's chunks over workers `chunks`, and what comes
back `results`.

Shape suffixes: a demos, b demos in a chunk, n demo points (padded), m scene points, k TPS
basis coefficients, 3 xyz.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from knotlab.core.errors import InvalidInputError
from knotlab.core.registration.chunks import _ChunkOut, run_chunks
from knotlab.core.registration.kernel import (
    PHASES,
    TARGET_RULES,
    exp_bits_constants,
    kernel_constants,
    padded_length,
    rpm_kernel,
)
from knotlab.core.registration.params import COST_NAMES, EXACT, RegistrationParams
from knotlab.core.registration.results import Registration
from knotlab.core.registration.sides import CloudSide, one_demo_side, scene_side

# ----------------------------------------------------------------------------- the RPM core


def _solve_weighted(
    g_bnk: np.ndarray,
    mu_bk: np.ndarray,
    h_bk3: np.ndarray,
    target_bn3: np.ndarray,
    w_bn: np.ndarray,
    lam: float,
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


# ----------------------------------------------------------------------------- one pair


def register(
    demo_cloud: np.ndarray, scene_cloud: np.ndarray, params: RegistrationParams = EXACT
) -> Registration:
    """Bidirectional TPS-RPM of one demo cloud onto one scene cloud (a batch of one)."""
    demo = one_demo_side(demo_cloud, params)
    return register_sides(demo, scene_side(scene_cloud, params), params)


def register_sides(demo: CloudSide, scene: CloudSide, params: RegistrationParams) -> Registration:
    """`register` on sides already factorised (`one_demo_side`, `scene_side`): same result."""
    result = run_chunks(demo, scene, params, chunk_size=1, n_workers=1, keep_corr=True)
    return result.registration(0)
