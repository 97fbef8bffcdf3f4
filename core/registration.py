"""Bidirectional TPS-RPM (deterministic annealing) for one pair or a whole demo library at once.

One implementation, `_rpm_batch`, registers a batch of demo clouds X_a against one scene cloud Y;
a single pair is a batch of one. For each demo a it fits f_a: X_a -> Y and g_a: Y -> X_a
(`core.tps` conventions) by alternating, for iteration i with bending lambda_i and temperature T_i
(both geometric from init to final, as lfd's `loglinspace`):

  1. affinity   p_ij = exp(-(||f(x_i) - y_j|| + ||x_i - g(y_j)||) / (2 T_i))  (not squared)
  2. an outlier row and column (prior 0.1, marginals n*frac and m*frac) and `sinkhorn_iters`
     Sinkhorn sweeps, rows first, giving row- and column-normalised matches M^r, M^c;
  3. targets x^_i = sum_j M^r_ij y_j (and y^_j = sum_i M^c_ij x_i) and a TPS fit for f and g.

Target rules (`RegistrationParams.target_rule`), all through the same kernel:
  * "batch"    targets x^_i = sum_j M^r_ij y_j / w_i (divided by the inlier mass w_i); a point
               whose inlier mass is below `outlier_cutoff` keeps its current warped position as
               target; the fit is unweighted, so with the spectral basis of `core.tps.TpsBasis`
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

The annealing loop itself is one numba kernel (`_rpm_kernel`, see the comment above it); the
single-pair `register` runs it as a batch of one, so a scan and a pair use the same code.

Shape suffixes: a demos, b demos in a chunk, n demo points (padded), m scene points, k TPS
basis coefficients, 3 xyz.
"""

from __future__ import annotations

import hashlib
import math
import os
import time
import warnings
from collections import OrderedDict
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import astuple, dataclass, field, fields
from pathlib import Path
from typing import Literal

import numpy as np
from numba import njit

from core.errors import InvalidInputError, SolverError
from core.tps import ThinPlateSpline, TpsBasis, tps_basis

_CACHE_VERSION = 2
_MAX_EXPONENT = 80.0


@dataclass(frozen=True)
class RegistrationParams:
    """Settings of bidirectional TPS-RPM, every length-dependent one in WORLD units (metres).

    The fit in world coordinates minimises
        sum ||y - f(x)||^2 [m^2] + lambda tr(W^T K W) [lambda in m] + tr((B-I)^T R (B-I)) [R in m^2]
    and the affinity is exp(-d / (2 T)) with d and T in metres. The kernel works in coordinates
    divided by `scale_m`; `normalised_schedule` and `normalised_rot_coef` convert once (lambda / s,
    T / s, R / s^2), so changing `scale_m` leaves the world-space fit unchanged (tested). Stating
    R in the internal units made it 1 / s^2 = 4x weaker than meant (issue 12's bug A).
    Defaults: the paper-era rll/lfd schedule as this project ran it (lambda 0.1 -> 0.001 and
    T 0.1 -> 0.005 in units of 0.5 m) and the identity pull (1e-3, 1e-3, 0.1) that made transfer
    work in the rope-world prototype (transfer_notes.md).
    """

    n_iter: int = 10
    bend_init: float = 0.05
    bend_final: float = 0.0005
    temp_init: float = 0.05
    temp_final: float = 0.0025
    rot_coef: tuple[float, float, float] = (1e-3, 1e-3, 0.1)
    outlier_prior: float = 0.1
    outlier_frac: float = 0.01
    outlier_cutoff: float = 0.01
    sinkhorn_iters: int = 10
    max_points: int = 150
    scale_m: float = 0.5
    target_rule: Literal["batch", "gpu", "weighted"] = "batch"
    dtype: Literal["float32", "float64"] = "float32"

    def __post_init__(self) -> None:
        if self.n_iter < 1 or self.sinkhorn_iters < 1 or self.max_points < 5:
            raise InvalidInputError("n_iter, sinkhorn_iters must be >= 1 and max_points >= 5")
        positive = (self.bend_init, self.bend_final, self.temp_init, self.temp_final, self.scale_m)
        if min(positive) <= 0 or min(self.outlier_prior, self.outlier_frac) <= 0:
            raise InvalidInputError("bend, temperature, scale and outlier settings must be > 0")
        if self.target_rule not in ("batch", "gpu", "weighted") or self.dtype not in (
            "float32",
            "float64",
        ):
            raise InvalidInputError(f"unknown target_rule/dtype {self.target_rule}/{self.dtype}")

    def schedule(self) -> tuple[np.ndarray, np.ndarray]:
        """(lambda_i, T_i) in world units: geometric from init to final over n_iter iterations."""
        return (
            np.geomspace(self.bend_init, self.bend_final, self.n_iter),
            np.geomspace(self.temp_init, self.temp_final, self.n_iter),
        )

    def normalised_schedule(self) -> tuple[np.ndarray, np.ndarray]:
        """(lambda_i / s, T_i / s): the schedule in the kernel's coordinates (x / scale_m)."""
        lams, temps = self.schedule()
        return lams / self.scale_m, temps / self.scale_m

    @property
    def normalised_rot_coef(self) -> tuple[float, float, float]:
        """R / s^2: the identity pull in the kernel's coordinates (residuals scale by 1 / s^2)."""
        s2 = self.scale_m**2
        return (self.rot_coef[0] / s2, self.rot_coef[1] / s2, self.rot_coef[2] / s2)


EXACT = RegistrationParams(n_iter=50, bend_init=5.0, target_rule="weighted", dtype="float64")
SCAN = RegistrationParams()

COST_NAMES: tuple[str, ...] = (
    "map_fwd",
    "map_bwd",
    "bend_f",
    "bend_g",
    "inlier_frac_fwd",
    "inlier_frac_bwd",
    "affine_dev_f",
    "affine_dev_g",
    "residual_fwd_m",
    "residual_bwd_m",
)


@dataclass(frozen=True)
class RegistrationCosts:
    """Cost parts of one bidirectional registration (normalised coordinates unless _m)."""

    map_fwd: float  # sum_i w_i ||f(x_i) - x^_i||^2 (w = 1 for the batch rule)
    map_bwd: float  # sum_j w_j ||g(y_j) - y^_j||^2
    bend_f: float  # tr(W_f^T K_X W_f)
    bend_g: float  # tr(W_g^T K_Y W_g)
    inlier_frac_fwd: float  # mean inlier mass of demo points
    inlier_frac_bwd: float  # mean inlier mass of scene points
    affine_dev_f: float  # ||B_f - I||_F
    affine_dev_g: float  # ||B_g - I||_F
    residual_fwd_m: float  # inlier-weighted mean ||f(x_i) - matched scene point||, metres
    residual_bwd_m: float  # same for g and demo points

    @property
    def nn_cost(self) -> float:
        """Paper-era GPU batch cost: map_fwd + map_bwd + bend_f + bend_g (bend coefficient 1)."""
        return self.map_fwd + self.map_bwd + self.bend_f + self.bend_g

    def as_array(self) -> np.ndarray:
        """The fields in COST_NAMES order."""
        return np.array(astuple(self), dtype=float)


# ----------------------------------------------------------------------------- input clouds


def clean_cloud(cloud: np.ndarray, name: str, max_points: int) -> np.ndarray:
    """Validated float64 (n, 3) cloud: NaN rows and duplicates dropped, capped at max_points."""
    arr = np.asarray(cloud, dtype=float)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise InvalidInputError(f"{name} must have shape (n, 3), got {arr.shape}")
    if arr.shape[0] == 0:
        raise InvalidInputError(f"{name} is empty")
    finite = np.all(np.isfinite(arr), axis=1)
    if not finite.any():
        raise InvalidInputError(f"{name} has no finite points ({arr.shape[0]} rows, all NaN/inf)")
    if not finite.all():
        warnings.warn(
            f"{name}: dropped {int((~finite).sum())} non-finite rows", RuntimeWarning, stacklevel=3
        )
        arr = arr[finite]
    _, first = np.unique(arr, axis=0, return_index=True)
    if first.shape[0] < arr.shape[0]:
        # Coincident points make the TPS system singular (two equal kernel rows).
        warnings.warn(
            f"{name}: dropped {arr.shape[0] - first.shape[0]} duplicate points",
            RuntimeWarning,
            stacklevel=3,
        )
        arr = arr[np.sort(first)]
    if arr.shape[0] > max_points:
        warnings.warn(
            f"{name}: {arr.shape[0]} points exceed the cap of {max_points}; "
            "subsampled deterministically (seed 0)",
            RuntimeWarning,
            stacklevel=3,
        )
        keep = np.sort(np.random.default_rng(0).choice(arr.shape[0], max_points, replace=False))
        arr = arr[keep]
    if arr.shape[0] < 5:
        raise InvalidInputError(f"{name} needs at least 5 distinct finite points, got {len(arr)}")
    return arr


@dataclass(frozen=True, eq=False)
class _Side:
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
                "g_ank": self.g_ank.astype(dtype),
                "gt_akn": np.ascontiguousarray(np.swapaxes(self.g_ank, 1, 2), dtype=dtype),
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


def _build_side(
    clouds: Sequence[np.ndarray | None], reasons: Sequence[str], params: RegistrationParams
) -> _Side:
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
        centre = np.median(cloud, axis=0)
        x = (cloud - centre) / params.scale_m
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
    return _Side(clouds=tuple(kept), ok_a=ok, reason_a=tuple(reason), **side)


def _demo_side(demo_clouds: Sequence[np.ndarray], params: RegistrationParams) -> _Side:
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
# One fused kernel, `_rpm_kernel`, runs the whole annealing loop for a chunk of demos, one demo
# at a time (its correspondence matrix, 90 kB at 150 x 150 float32, stays in L1/L2 for all
# iterations). It is compiled without fastmath (strict IEEE; results do not depend on
# reassociation) and without numba's own threading (`parallel=False`): the one level of
# parallelism is `LibraryRegistrar`'s worker threads over chunks, which the kernel allows by
# releasing the GIL (`nogil=True`); numba's threading layer is never started. Two idioms keep
# the inner loops SIMD-vectorisable under strict IEEE:
#   * p is kept in both layouts (p and p^T, one copy per iteration) so every Sinkhorn and
#     target product is an axpy along contiguous memory; a dot-product reduction is not
#     vectorised without reassociation;
#   * exp(-s) is `_exp_neg_row`: Cody-Waite range reduction s = k ln2 - r, a degree-10 Taylor
#     polynomial (relative truncation error < 3e-13) and 2^-k assembled from its IEEE bits;
#     LLVM's exp is a scalar libm call when SVML is absent. Measured error vs np.exp: < 1e-7
#     relative in float32 (about 1 ulp), < 1e-12 in float64 (tests/test_registration.py).
# Compilation: `cache=True` writes the machine code next to this file (core/__pycache__/*.nbi,
# *.nbc); numba falls back to NUMBA_CACHE_DIR or ~/.cache when that is not writable. A cold
# compile of both dtypes takes tens of seconds; a warm start loads in about a second.
# Every array a kernel reads is in the RPM dtype (float32 for SCAN, float64 for EXACT), and so
# are the constants (`_consts`), so float32 arithmetic never silently widens to float64.

_EXP_TAYLOR = tuple(1.0 / math.factorial(q) for q in range(11))


def _consts(dt: np.dtype, params: RegistrationParams) -> np.ndarray:
    """The kernel's scalars in the RPM dtype; see `_K_*` for the slots."""
    ln2 = math.log(2.0)
    ln2_hi = 0.693359375  # 355/512: k * ln2_hi is exact in float32 for the k < 128 used
    c = [1.0 / ln2, 0.5, ln2_hi, ln2 - ln2_hi, _MAX_EXPONENT, *_EXP_TAYLOR]
    c += [params.outlier_prior, params.outlier_frac, params.outlier_cutoff, 1.0, 0.0, 1e-30]
    return np.array(c, dtype=dt)


_K_PRIOR, _K_FRAC, _K_CUTOFF, _K_ONE, _K_ZERO, _K_TINY = range(16, 22)
_RULES = {"batch": 0, "gpu": 1, "weighted": 2}
# stop_after: run the phases up to this one in every iteration (the benchmark's phase split)
_PHASES = ("affinity", "sinkhorn", "targets", "tps fit")


@njit(cache=True, nogil=True, fastmath=False)
def _exp_neg_row(s, p, i, bits, bits_f, e_bias, e_shift, cst, m):  # pragma: no cover - compiled
    """p[i, j] = exp(-min(s[j], cap)) for j < m, s >= 0; 2^-k built in `bits` (a view: bits_f)."""
    log2e, half, ln2_hi, ln2_lo, cap = cst[0], cst[1], cst[2], cst[3], cst[4]
    c0, c1, c2, c3, c4, c5 = cst[5], cst[6], cst[7], cst[8], cst[9], cst[10]
    c6, c7, c8, c9, c10 = cst[11], cst[12], cst[13], cst[14], cst[15]
    for j in range(m):
        v = min(s[j], cap)
        kf = np.floor(v * log2e + half)
        r = kf * ln2_lo - (v - kf * ln2_hi)  # -v = -k ln2 + r, |r| <= ln2 / 2
        poly = c10
        poly = poly * r + c9
        poly = poly * r + c8
        poly = poly * r + c7
        poly = poly * r + c6
        poly = poly * r + c5
        poly = poly * r + c4
        poly = poly * r + c3
        poly = poly * r + c2
        poly = poly * r + c1
        poly = poly * r + c0
        s[j] = poly
        bits[j] = (e_bias - int(kf)) << e_shift  # the IEEE bit pattern of 2^-k
    for j in range(m):
        p[i, j] = s[j] * bits_f[j]


@njit(cache=True, nogil=True, fastmath=False)
def _rpm_kernel(
    idx,
    x_an3,
    n_a,
    g_ank,
    gt_akn,
    mu_ak,
    h_ak3,
    y_m3,
    g_y,
    gt_y,
    mu_y,
    h_y,
    lam_i,
    inv2t_i,
    cst,
    bits,
    bits_f,
    e_bias,
    e_shift,
    a_out,
    b_out_b,
    corner_b,
    rule,
    sinkhorn_iters,
    stop_after,
    e_f,
    e_g,
    fx_out,
    gy_out,
    xhat_out,
    yhat_out,
    wf_out,
    wg_out,
    mf_out,
    mg_out,
    corr,
    failed,
):  # pragma: no cover - compiled
    """Bidirectional TPS-RPM for every demo b of a chunk against the scene (see `_rpm_batch`)."""
    dt_one = cst[_K_ONE]
    zero = cst[_K_ZERO]
    prior, cutoff, tiny = cst[_K_PRIOR], cst[_K_CUTOFF], cst[_K_TINY]
    m = y_m3.shape[0]
    ky = gt_y.shape[0]
    nb = idx.shape[0]
    n_max = x_an3.shape[1]
    ys = np.empty((4, m), cst.dtype)  # scene SoA, row 3 = 1
    for j in range(m):
        for d in range(3):
            ys[d, j] = y_m3[j, d]
        ys[3, j] = dt_one
    # per-demo scratch, sized for the largest demo
    xs = np.empty((3, n_max), cst.dtype)
    fx = np.empty((3, n_max), cst.dtype)
    gy = np.empty((3, m), cst.dtype)
    p = np.empty((n_max, m), cst.dtype)
    pt = np.empty((m, n_max), cst.dtype)
    srow = np.empty(m, cst.dtype)
    rd = np.empty(n_max, cst.dtype)
    r = np.empty(n_max, cst.dtype)
    c = np.empty(m, cst.dtype)
    c_prev = np.empty(m, cst.dtype)
    col = np.empty(m, cst.dtype)
    cy = np.empty((4, m), cst.dtype)
    fwd = np.empty((4, n_max), cst.dtype)
    bwd = np.empty((4, m), cst.dtype)
    xhat = np.empty((3, n_max), cst.dtype)
    yhat = np.empty((3, m), cst.dtype)
    wf = np.empty(n_max, cst.dtype)
    wg = np.empty(m, cst.dtype)
    ef = np.empty((3, n_max + 4), cst.dtype)
    eg = np.empty((3, ky), cst.dtype)
    for b in range(nb):
        a = idx[b]
        n = n_a[a]
        k = n + 4
        b_out = b_out_b[b]
        corner = corner_b[b]
        for i in range(n):
            for d in range(3):
                xs[d, i] = x_an3[a, i, d]
                fx[d, i] = x_an3[a, i, d]
        for j in range(m):
            for d in range(3):
                gy[d, j] = y_m3[j, d]
        ef[:, :k] = zero
        eg[:, :] = zero
        ok = True
        for it in range(lam_i.shape[0]):
            inv2t = inv2t_i[it]
            # 1. affinity p_ij = exp(-(|f(x_i) - y_j| + |x_i - g(y_j)|) / 2T), exponent capped
            for i in range(n):
                f0, f1, f2 = fx[0, i], fx[1, i], fx[2, i]
                x0, x1, x2 = xs[0, i], xs[1, i], xs[2, i]
                for j in range(m):
                    a0 = f0 - ys[0, j]
                    a1 = f1 - ys[1, j]
                    a2 = f2 - ys[2, j]
                    b0 = x0 - gy[0, j]
                    b1 = x1 - gy[1, j]
                    b2 = x2 - gy[2, j]
                    srow[j] = (
                        np.sqrt(a0 * a0 + a1 * a1 + a2 * a2) + np.sqrt(b0 * b0 + b1 * b1 + b2 * b2)
                    ) * inv2t
                _exp_neg_row(srow, p, i, bits, bits_f, e_bias, e_shift, cst, m)
            # p^T too: with both layouts every product below is an axpy along contiguous
            # memory, which vectorises under strict IEEE (a dot-product reduction does not)
            for i in range(n):
                for j in range(m):
                    pt[j, i] = p[i, j]
            if stop_after == 0:
                continue
            # 2. Sinkhorn with an outlier row and column, rows first (GPU order); one pass
            #    over p per sweep: row i's scale r_i, then its share of the column sums
            c[:] = dt_one
            c_out = dt_one
            r_out = zero
            for _ in range(sinkhorn_iters):
                csum = zero
                for j in range(m):
                    csum += c[j]
                r_out = a_out / (prior * csum + corner * c_out)
                rd[:n] = zero
                for j in range(m):
                    cj = c[j]
                    for i in range(n):
                        rd[i] += pt[j, i] * cj
                col[:] = zero
                for i in range(n):
                    ri = dt_one / (rd[i] + prior * c_out)
                    r[i] = ri
                    for j in range(m):
                        col[j] += p[i, j] * ri
                rsum = zero
                for i in range(n):
                    rsum += r[i]
                for j in range(m):
                    c_prev[j] = c[j]
                    c[j] = dt_one / (col[j] + prior * r_out)
                c_out = b_out / (prior * rsum + corner * r_out)
            if stop_after == 1:
                continue
            # 3. targets: forward from the row-normalised match r p c_prev, backward from the
            #    column-normalised one r p c
            for j in range(m):
                for d in range(4):
                    cy[d, j] = ys[d, j] * c_prev[j]
            fwd[:, :n] = zero
            for j in range(m):
                cy0, cy1, cy2, cy3 = cy[0, j], cy[1, j], cy[2, j], cy[3, j]
                for i in range(n):
                    pji = pt[j, i]
                    fwd[0, i] += pji * cy0
                    fwd[1, i] += pji * cy1
                    fwd[2, i] += pji * cy2
                    fwd[3, i] += pji * cy3
            bwd[:, :] = zero
            for i in range(n):
                ri = r[i]
                rx0, rx1, rx2 = ri * xs[0, i], ri * xs[1, i], ri * xs[2, i]
                for j in range(m):
                    pij = p[i, j]
                    bwd[0, j] += pij * rx0
                    bwd[1, j] += pij * rx1
                    bwd[2, j] += pij * rx2
                    bwd[3, j] += pij * ri
            for i in range(n):
                wf[i] = r[i] * fwd[3, i]
                inlier = wf[i] >= cutoff or rule == 2
                for d in range(3):
                    val = r[i] * fwd[d, i] if rule == 1 else fwd[d, i] / max(fwd[3, i], tiny)
                    xhat[d, i] = val if inlier else fx[d, i]
            for j in range(m):
                wg[j] = c[j] * bwd[3, j]
                inlier = wg[j] >= cutoff or rule == 2
                for d in range(3):
                    val = c[j] * bwd[d, j] if rule == 1 else bwd[d, j] / max(bwd[3, j], tiny)
                    yhat[d, j] = val if inlier else gy[d, j]
            if stop_after == 2:
                continue
            # 4. TPS fits of f and g
            lam = lam_i[it]
            if rule == 2:
                ok = _fit_weighted(g_ank[a, :n, :k], mu_ak[a, :k], h_ak3[a, :k], xhat, wf, lam, ef)
                ok = ok and _fit_weighted(g_y, mu_y, h_y, yhat, wg, lam, eg)
                if not ok:
                    break
            else:
                _fit_unweighted(g_ank[a], mu_ak[a], h_ak3[a], xhat, lam, dt_one, ef, n, k)
                _fit_unweighted(g_y, mu_y, h_y, yhat, lam, dt_one, eg, m, ky)
            _apply(gt_akn[a], ef, fx, n, k)
            _apply(gt_y, eg, gy, m, ky)
        failed[b] = not ok
        for i in range(n):
            wf_out[b, i] = wf[i]
            for d in range(3):
                fx_out[b, i, d] = fx[d, i]
                xhat_out[b, i, d] = xhat[d, i]
                mf_out[b, i, d] = fwd[d, i] / max(fwd[3, i], tiny)
        for j in range(m):
            wg_out[b, j] = wg[j]
            for d in range(3):
                gy_out[b, j, d] = gy[d, j]
                yhat_out[b, j, d] = yhat[d, j]
                mg_out[b, j, d] = bwd[d, j] / max(bwd[3, j], tiny)
        for q in range(k):
            for d in range(3):
                e_f[b, q, d] = ef[d, q]
        for q in range(ky):
            for d in range(3):
                e_g[b, q, d] = eg[d, q]
        if corr.shape[0] > 0:
            for i in range(n):
                for j in range(m):
                    corr[b, i, j] = r[i] * p[i, j] * c_prev[j]


@njit(cache=True, nogil=True, fastmath=False)
def _fit_unweighted(g_nk, mu_k, h_k3, target_3n, lam, one, e_3k, n, k):  # pragma: no cover
    """e = (G^T x^ + h) / (1 + lambda mu), e stored (3, k); vectorised over k."""
    for d in range(3):
        for q in range(k):
            e_3k[d, q] = h_k3[q, d]
    for d in range(3):  # one output row at a time: a plain axpy the vectoriser accepts
        e_d = e_3k[d]
        for i in range(n):
            t = target_3n[d, i]
            for q in range(k):
                e_d[q] += g_nk[i, q] * t
    for q in range(k):
        s = one / (one + lam * mu_k[q])
        for d in range(3):
            e_3k[d, q] *= s


@njit(cache=True, nogil=True, fastmath=False)
def _apply(gt_kn, e_3k, out_3n, n, k):  # pragma: no cover - compiled
    """out = G e, out stored (3, n); vectorised over n."""
    out_3n[:, :n] = 0
    for d in range(3):
        out_d = out_3n[d]
        for q in range(k):
            e = e_3k[d, q]
            for i in range(n):
                out_d[i] += gt_kn[q, i] * e


@njit(cache=True, nogil=True, fastmath=False)
def _fit_weighted(g_nk, mu_k, h_k3, target_3n, w_n, lam, e_3k):  # pragma: no cover
    """Solve (I + lambda diag mu - G^T diag(1-w) G) e = G^T diag(w) x^ + h; False if singular."""
    n, k = g_nk.shape
    g = np.ascontiguousarray(g_nk)
    gw = np.empty((n, k), g.dtype)
    rhs_n = np.empty((n, 3), g.dtype)
    for i in range(n):
        for q in range(k):
            gw[i, q] = g[i, q] * (1 - w_n[i])
        for d in range(3):
            rhs_n[i, d] = w_n[i] * target_3n[d, i]
    gt = np.ascontiguousarray(g.T)
    lhs = -(gt @ gw)
    for q in range(k):
        lhs[q, q] += 1 + lam * mu_k[q]
    rhs = gt @ rhs_n + h_k3
    try:
        e = np.linalg.solve(lhs, rhs)
    except Exception:  # numba raises LinAlgError for a singular system
        return False
    for q in range(k):
        for d in range(3):
            if not np.isfinite(e[q, d]):
                return False
            e_3k[d, q] = e[q, d]
    return True


def _rpm_batch(
    demo: _Side,
    idx: np.ndarray,
    scene: _Side,
    params: RegistrationParams,
    keep_corr: bool,
    timings: dict[str, float] | None = None,
    stop_after: int = len(_PHASES) - 1,
) -> _ChunkOut:
    """Run bidirectional TPS-RPM for demos idx against the scene (one cloud) in one batch."""
    clock = _PhaseClock(timings)
    dt = np.dtype(params.dtype)
    weighted = params.target_rule == "weighted"
    n_valid = demo.n_a[idx]
    n = max(int(n_valid.max()), 1)
    k = n + 4
    cast = demo.cast(dt)
    m = int(scene.n_a[0])
    ky = m + 4
    scene_cast = scene.cast(dt)
    y = np.ascontiguousarray(scene_cast["x_an3"][0, :m])
    g_y = np.ascontiguousarray(scene_cast["g_ank"][0, :m, :ky])
    gt_y = np.ascontiguousarray(scene_cast["gt_akn"][0, :ky, :m])
    mu_y = np.ascontiguousarray(scene_cast["mu_ak"][0, :ky])
    h_y = np.ascontiguousarray(scene_cast["h_ak3"][0, :ky])
    nb = len(idx)
    frac = params.outlier_frac
    corner_coef = frac if not weighted else params.outlier_prior
    a_out = np.array(m * frac, dt)
    b_out = (n_valid * frac).astype(dt)
    corner = (corner_coef * np.sqrt(n_valid * m)).astype(dt)
    lams, temps = params.normalised_schedule()
    cst = _consts(dt, params)
    bits = np.empty(m, np.int32 if dt == np.float32 else np.int64)
    e_bias, e_shift = (127, 23) if dt == np.float32 else (1023, 52)

    e_f = np.zeros((nb, k, 3), dt)
    e_g = np.zeros((nb, ky, 3), dt)
    fx, xhat, mf = (np.zeros((nb, n, 3), dt) for _ in range(3))
    gy, yhat, mg = (np.zeros((nb, m, 3), dt) for _ in range(3))
    w_f = np.zeros((nb, n), dt)
    w_g = np.zeros((nb, m), dt)
    corr = np.zeros((nb, n, m) if keep_corr else (0, 0, 0), dt)
    bad = np.zeros(nb, np.bool_)
    clock.tick("setup")
    _rpm_kernel(
        np.ascontiguousarray(idx, dtype=np.int64),
        cast["x_an3"],
        demo.n_a,
        cast["g_ank"],
        cast["gt_akn"],
        cast["mu_ak"],
        cast["h_ak3"],
        y,
        g_y,
        gt_y,
        mu_y,
        h_y,
        lams.astype(dt),
        (0.5 / temps).astype(dt),
        cst,
        bits,
        bits.view(dt),
        e_bias,
        e_shift,
        a_out,
        b_out,
        corner,
        _RULES[params.target_rule],
        params.sinkhorn_iters,
        stop_after,
        e_f,
        e_g,
        fx,
        gy,
        xhat,
        yhat,
        w_f,
        w_g,
        mf,
        mg,
        corr,
        bad,
    )
    clock.tick("rpm kernel")
    failed = {int(b): "weighted TPS system singular (no inlier mass?)" for b in np.flatnonzero(bad)}

    # costs, in normalised coordinates, float64
    fx64, gy64 = fx.astype(float), gy.astype(float)
    xhat64, yhat64 = xhat.astype(float), yhat.astype(float)
    w_f64, w_g64 = w_f.astype(float), w_g.astype(float)
    wf = w_f64 if weighted else demo.mask_an[idx, :n].astype(float)
    wg = w_g64 if weighted else np.ones((nb, m))
    map_fwd = np.einsum("bn,bn->b", wf, ((fx64 - xhat64) ** 2).sum(axis=2))
    map_bwd = np.einsum("bm,bm->b", wg, ((gy64 - yhat64) ** 2).sum(axis=2))
    e_f64, e_g64 = e_f.astype(float), e_g.astype(float)
    bend_f = np.einsum("bk,bkd->b", demo.mu_ak[idx, :k], e_f64**2)
    bend_g = np.einsum("k,bkd->b", scene.mu_ak[0, :ky], e_g64**2)
    inl_f = w_f64.sum(axis=1) / np.maximum(n_valid, 1)
    inl_g = w_g64.mean(axis=1)
    b_f = np.einsum("bpk,bkd->bpd", demo.theta_apk[idx, 1:4, :k], e_f64)
    b_g = np.einsum("pk,bkd->bpd", scene.theta_apk[0, 1:4, :ky], e_g64)
    aff_f = np.linalg.norm(b_f - np.eye(3), axis=(1, 2))
    aff_g = np.linalg.norm(b_g - np.eye(3), axis=(1, 2))
    res_f = np.linalg.norm(fx64 - mf, axis=2)
    res_g = np.linalg.norm(gy64 - mg, axis=2)
    res_f = (w_f64 * res_f).sum(1) / np.maximum(w_f64.sum(1), 1e-30) * params.scale_m
    res_g = (w_g64 * res_g).sum(1) / np.maximum(w_g64.sum(1), 1e-30) * params.scale_m
    costs = np.stack(
        [map_fwd, map_bwd, bend_f, bend_g, inl_f, inl_g, aff_f, aff_g, res_f, res_g], axis=1
    )
    clock.tick("costs")
    return _ChunkOut(e_f64, e_g64, costs, corr.astype(float) if keep_corr else None, failed)


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
    _demo: _Side
    _scene: _Side

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


def _run(
    demo: _Side,
    scene: _Side,
    params: RegistrationParams,
    *,
    chunk_size: int,
    n_workers: int,
    keep_corr: bool,
    timings: dict[str, float] | None = None,
) -> ScanResult:
    """Registers the scene against every demo, in chunks (independent batches) over workers."""
    n_demos = len(demo)
    demo.cast(np.dtype(params.dtype))  # convert once, before any worker thread reads it
    good = np.flatnonzero(demo.ok_a)
    chunks = [good[i : i + chunk_size] for i in range(0, len(good), chunk_size)]

    def work(idx: np.ndarray) -> _ChunkOut:
        # A demo whose fit overflows is detected below and reported; no warning spam for it.
        with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
            return _rpm_batch(demo, idx, scene, params, keep_corr, timings)

    if n_workers > 1 and len(chunks) > 1:
        # NumPy releases the GIL in its kernels, so threads share one copy of the library.
        with ThreadPoolExecutor(n_workers) as pool:
            outs = list(pool.map(work, chunks))
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


def _scene_side(scene_cloud: np.ndarray, params: RegistrationParams) -> _Side:
    """Scene side: a bad scene cloud raises (it concerns every demo)."""
    cloud = clean_cloud(scene_cloud, "scene cloud", params.max_points)
    side = _build_side([cloud], [""], params)
    if not side.ok_a[0]:
        raise SolverError(f"scene cloud: {side.reason_a[0]}")
    return side


def register(
    demo_cloud: np.ndarray, scene_cloud: np.ndarray, params: RegistrationParams = EXACT
) -> Registration:
    """Bidirectional TPS-RPM of one demo cloud onto one scene cloud (a batch of one)."""
    demo_arr = clean_cloud(demo_cloud, "demo cloud", params.max_points)
    demo = _demo_side([demo_arr], params)
    if not demo.ok_a[0]:
        raise SolverError(f"demo cloud: {demo.reason_a[0]}")
    scene = _scene_side(scene_cloud, params)
    result = _run(demo, scene, params, chunk_size=1, n_workers=1, keep_corr=True)
    return result.registration(0)


# ----------------------------------------------------------------------------- library scans


def library_digest(demo_clouds: Sequence[np.ndarray]) -> str:
    """sha1 over the demo clouds' float64 bytes and shapes (a cache key when none is given)."""
    digest = hashlib.sha1()
    for cloud in demo_clouds:
        arr = np.ascontiguousarray(np.asarray(cloud, dtype=float))
        digest.update(str(arr.shape).encode())
        digest.update(arr.tobytes())
    return digest.hexdigest()


def _params_key(params: RegistrationParams) -> str:
    """The settings the demo-side precomputation depends on."""
    return f"rot{params.rot_coef}_scale{params.scale_m}_cap{params.max_points}"


class LibraryRegistrar:
    """Scans scene clouds against demo libraries; demo-side factorisations cached by library key.

    The cache is per instance: an LRU dict in memory and, when `cache_dir` is given, one `.npz`
    per library under `cache_dir/.cache/`. A library is identified by the caller's key (the
    library's content hash) or, without one, by `library_digest` of the clouds.
    """

    def __init__(
        self,
        params: RegistrationParams = SCAN,
        *,
        cache_dir: str | os.PathLike[str] | None = None,
        max_cached: int = 4,
        chunk_size: int = 8,
        n_workers: int = 1,
    ) -> None:
        if chunk_size < 1 or n_workers < 1 or max_cached < 1:
            raise InvalidInputError("chunk_size, n_workers and max_cached must be >= 1")
        self.params = params
        self.cache_dir = None if cache_dir is None else Path(cache_dir) / ".cache"
        self.max_cached = max_cached
        self.chunk_size = chunk_size
        self.n_workers = n_workers
        self._cache: OrderedDict[str, _Side] = OrderedDict()

    def prepare(
        self, demo_clouds: Sequence[np.ndarray], key: str | None = None, params=None
    ) -> _Side:
        """Demo-side precomputation (normalise, factorise, pad), from cache when possible."""
        params = params or self.params
        full_key = f"{key or library_digest(demo_clouds)}_{_params_key(params)}"
        if full_key in self._cache:
            self._cache.move_to_end(full_key)
            return self._cache[full_key]
        side = self._load(full_key, len(demo_clouds))
        if side is None:
            side = _demo_side(demo_clouds, params)
            self._save(full_key, side)
        self._cache[full_key] = side
        while len(self._cache) > self.max_cached:
            self._cache.popitem(last=False)
        return side

    def scan(
        self,
        scene_cloud: np.ndarray,
        demo_clouds: Sequence[np.ndarray],
        key: str | None = None,
        *,
        params: RegistrationParams | None = None,
        keep_correspondence: bool = False,
        timings: dict[str, float] | None = None,
    ) -> ScanResult:
        """Register the scene against every demo (bad demos: ok False, cost +inf; never raises)."""
        params = params or self.params
        demo = self.prepare(demo_clouds, key, params)
        scene = _scene_side(scene_cloud, params)
        return _run(
            demo,
            scene,
            params,
            chunk_size=self.chunk_size,
            n_workers=self.n_workers,
            keep_corr=keep_correspondence,
            timings=timings,
        )

    def _path(self, full_key: str) -> Path | None:
        if self.cache_dir is None:
            return None
        safe = hashlib.sha1(full_key.encode()).hexdigest()
        return self.cache_dir / f"registration_v{_CACHE_VERSION}_{safe}.npz"

    def _save(self, full_key: str, side: _Side) -> None:
        path = self._path(full_key)
        if path is None:
            return
        path.parent.mkdir(parents=True, exist_ok=True)
        arrays = {f.name: getattr(side, f.name) for f in fields(side) if f.name != "_casts"}
        clouds = arrays.pop("clouds")
        reasons = arrays.pop("reason_a")
        tmp = path.with_suffix(".tmp.npz")
        np.savez(
            tmp,
            key=np.array(full_key),
            reason_a=np.array(reasons, dtype=str),
            clouds_n=np.array([len(c) for c in clouds]),
            clouds=np.concatenate(clouds) if clouds else np.zeros((0, 3)),
            **arrays,
        )
        os.replace(tmp, path)  # atomic: a concurrent reader never sees half a file

    def _load(self, full_key: str, n_demos: int) -> _Side | None:
        path = self._path(full_key)
        if path is None or not path.exists():
            return None
        with np.load(path, allow_pickle=False) as data:
            if str(data["key"]) != full_key or len(data["n_a"]) != n_demos:
                return None
            names = [
                f.name for f in fields(_Side) if f.name not in ("clouds", "reason_a", "_casts")
            ]
            arrays = {name: data[name] for name in names}
            split = np.cumsum(data["clouds_n"])[:-1]
            clouds = tuple(np.split(data["clouds"], split))
            reasons = tuple(str(s) for s in data["reason_a"])
        return _Side(clouds=clouds, reason_a=reasons, **arrays)


def scan_library(
    scene_cloud: np.ndarray,
    demo_clouds: Sequence[np.ndarray],
    params: RegistrationParams = SCAN,
    **kwargs,
) -> ScanResult:
    """One-off scan without a cache (see LibraryRegistrar for repeated queries)."""
    return LibraryRegistrar(params).scan(scene_cloud, demo_clouds, **kwargs)


__all__ = [
    "COST_NAMES",
    "EXACT",
    "SCAN",
    "LibraryRegistrar",
    "Registration",
    "RegistrationCosts",
    "RegistrationParams",
    "ScanResult",
    "clean_cloud",
    "library_digest",
    "register",
    "scan_library",
]
