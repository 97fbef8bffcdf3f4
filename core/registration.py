"""Bidirectional TPS-RPM (deterministic annealing) for one pair or a whole demo library at once.

One implementation, `_rpm_batch`, registers a batch of demo clouds X_a against one scene cloud Y;
a single pair is a batch of one. For each demo a it fits f_a: X_a -> Y and g_a: Y -> X_a
(`core.tps` conventions) by alternating, for iteration i with bending lambda_i and temperature T_i
(both geometric from init to final, as lfd's `loglinspace`):

  1. affinity   p_ij = exp(-(||f(x_i) - y_j|| + ||x_i - g(y_j)||) / (2 T_i))  (not squared)
  2. an outlier row and column (prior 0.1, marginals n*frac and m*frac) and `sinkhorn_iters`
     Sinkhorn sweeps, rows first, giving row- and column-normalised matches M^r, M^c;
  3. targets x^_i = sum_j M^r_ij y_j (and y^_j = sum_i M^c_ij x_i) and a TPS fit for f and g.

Target rules (`RegistrationParams.target_rule`), both through the same code:
  * "batch"    the paper-era GPU rule: targets NOT divided by the inlier mass w_i; a point whose
               inlier mass is below `outlier_cutoff` keeps its current warped position as target;
               the fit is unweighted, so with the spectral basis of `core.tps.TpsBasis` each fit is
               e = (G^T x^ + h) / (1 + lambda mu): matrix products only, precomputed per cloud.
               Used by `SCAN` (features, nearest-neighbour cost). Outlier corner frac*sqrt(nm).
  * "weighted" the paper-era CPU rule: x^_i = sum_j M^r_ij y_j / w_i and a fit weighted by w_i
               (one k x k solve per demo per iteration). Used by `EXACT` (transfer).
               Outlier corner prior*sqrt(nm).

Normalisation: every cloud is translated by its own median (so the identity start is lfd's
median-translation initialisation) and divided by ONE fixed isotropic length `scale_m` shared by
all clouds. Not a per-cloud bounding box: per-axis boxes blow up on straight ropes, and because
the kernel -r is 1-homogeneous, scaling a pair by s is the same as dividing lambda by s, so a
pair-dependent scale would make the per-demo precomputation scene-dependent. Costs are in these
normalised ("unit-box") coordinates; f and g are returned in world coordinates.

Shape suffixes: a demos, b demos in a chunk, n demo points (padded), m scene points, k TPS
basis coefficients, 3 xyz.
"""

from __future__ import annotations

import hashlib
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

from core.errors import InvalidInputError, SolverError
from core.tps import ThinPlateSpline, TpsBasis, tps_basis

_CACHE_VERSION = 1
_MAX_EXPONENT = 80.0


@dataclass(frozen=True)
class RegistrationParams:
    """Settings of bidirectional TPS-RPM (paper-era rll/lfd values by default)."""

    n_iter: int = 10
    bend_init: float = 0.1
    bend_final: float = 0.001
    temp_init: float = 0.1
    temp_final: float = 0.005
    rot_coef: tuple[float, float, float] = (1e-4, 1e-4, 0.1)
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
        """(lambda_i, T_i): geometric from init to final over n_iter iterations."""
        return (
            np.geomspace(self.bend_init, self.bend_final, self.n_iter),
            np.geomspace(self.temp_init, self.temp_final, self.n_iter),
        )


EXACT = RegistrationParams(n_iter=50, bend_init=10.0, target_rule="weighted", dtype="float64")
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
            basis = tps_basis(x, params.rot_coef)
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


def _left_aug(a_bn3: np.ndarray, padded_bn: np.ndarray, scale2) -> np.ndarray:
    """Rows [s2 a, s2 |a|^2, s2]: with `_right_aug` rows, left . right = s2 |a - b|^2."""
    out = np.empty((*a_bn3.shape[:-1], 5), a_bn3.dtype)
    out[..., :3] = a_bn3 * scale2
    out[..., 3] = np.einsum("...d,...d->...", a_bn3, a_bn3) * scale2
    out[..., 4] = scale2
    # A padded point is 'far from everything': distance sqrt(1e6) -> affinity exactly 0.
    out[padded_bn] = (0.0, 0.0, 0.0, 1e6, 0.0)
    return out


def _right_aug(b_m3: np.ndarray) -> np.ndarray:
    """Columns [-2 b; 1; |b|^2] (5, m), or (batch, 5, m) for a batch of clouds."""
    out = np.empty((*b_m3.shape[:-2], 5, b_m3.shape[-2]), b_m3.dtype)
    out[..., :3, :] = -2.0 * np.swapaxes(b_m3, -1, -2)
    out[..., 3, :] = 1.0
    out[..., 4, :] = np.einsum("...d,...d->...", b_m3, b_m3)
    return out


def _rpm_batch(
    demo: _Side,
    idx: np.ndarray,
    scene: _Side,
    params: RegistrationParams,
    keep_corr: bool,
    timings: dict[str, float] | None = None,
) -> _ChunkOut:
    """Run bidirectional TPS-RPM for demos idx against the scene (one cloud) in one batch."""
    clock = _PhaseClock(timings)
    dt = np.dtype(params.dtype)
    weighted = params.target_rule == "weighted"
    n_valid = demo.n_a[idx]
    n = max(int(n_valid.max()), 1)
    k = n + 4
    cast = demo.cast(dt)
    x = cast["x_an3"][idx, :n]
    rowmask = demo.mask_an[idx, :n].astype(dt)
    g_x = cast["g_ank"][idx, :n, :k]
    gt_x = cast["gt_akn"][idx, :k, :n]
    mu_x = cast["mu_ak"][idx, :k]
    h_x = cast["h_ak3"][idx, :k]
    m = int(scene.n_a[0])
    ky = m + 4
    y = scene.x_an3[0, :m].astype(dt)
    g_y = scene.g_ank[0, :m, :ky].astype(dt)
    gt_y = np.ascontiguousarray(g_y.T)
    mu_y = scene.mu_ak[0, :ky].astype(dt)
    h_y = scene.h_ak3[0, :ky].astype(dt)
    nb = len(idx)
    prior, frac, cutoff = params.outlier_prior, params.outlier_frac, params.outlier_cutoff
    a_out = m * frac
    b_out = (n_valid * frac).astype(dt)
    corner = ((frac if not weighted else prior) * np.sqrt(n_valid * m)).astype(dt)

    lams, temps = params.schedule()
    fx = x.copy()  # identity start in median-centred coordinates
    gy = np.broadcast_to(y, (nb, m, 3)).copy()
    e_f = np.zeros((nb, k, 3), dt)
    e_g = np.zeros((nb, ky, 3), dt)
    padded = ~demo.mask_an[idx, :n]
    left_x = _left_aug(x, padded, dt.type(1.0))
    d_f = np.empty((nb, n, m), dt)
    d_g = np.empty((nb, n, m), dt)
    failed: dict[int, str] = {}
    clock.tick("setup")
    for lam, temp in zip(lams, temps, strict=True):
        # 1. affinities exp(-(|f(x_i) - y_j| + |x_i - g(y_j)|) / 2T); padded rows: exp(-1e3) = 0.
        #    Squared distances come from one K=5 product of augmented points, pre-scaled by
        #    1/(2T)^2, so the only full-size passes are abs, sqrt, add, negate and exp.
        inv2t_sq = dt.type((0.5 / temp) ** 2)
        np.matmul(
            _left_aug(fx, padded, inv2t_sq).reshape(nb * n, 5),
            _right_aug(y),
            out=d_f.reshape(nb * n, m),
        )
        np.matmul(left_x * inv2t_sq, _right_aug(gy), out=d_g)
        # abs, not max(., 0): rounding makes tiny negatives, and abs is the cheaper pass.
        np.sqrt(np.abs(d_f, out=d_f), out=d_f)
        np.sqrt(np.abs(d_g, out=d_g), out=d_g)
        d_f += d_g
        # Cap the exponent at 80: exp(-80) is still a normal float32, whereas smaller values
        # become subnormals that slow every later product over p by an order of magnitude.
        np.minimum(d_f, _MAX_EXPONENT, out=d_f)
        p = np.exp(np.negative(d_f, out=d_f), out=d_f)
        p_t = np.swapaxes(p, 1, 2)
        clock.tick("affinity")
        # 2. Sinkhorn with an outlier row and column, rows first (GPU order)
        c = np.ones((nb, m), dt)
        c_out = np.ones(nb, dt)
        for _ in range(params.sinkhorn_iters):
            r = rowmask / ((p @ c[:, :, None])[:, :, 0] + prior * c_out[:, None])
            r_out = a_out / (prior * c.sum(axis=1) + corner * c_out)
            col = (p_t @ r[:, :, None])[:, :, 0] + prior * r_out[:, None]
            c_prev = c
            c = 1.0 / col
            c_out = b_out / (prior * r.sum(axis=1) + corner * r_out)
        clock.tick("sinkhorn")
        # 3. targets: forward from the row-normalised, backward from the column-normalised match
        fwd = p @ np.concatenate([c_prev[:, :, None] * y, c_prev[:, :, None]], axis=2)
        w_f = r * fwd[:, :, 3]
        bwd = p_t @ np.concatenate([r[:, :, None] * x, r[:, :, None]], axis=2)
        w_g = c * bwd[:, :, 3]
        clock.tick("targets")
        if weighted:
            xhat = fwd[:, :, :3] / np.maximum(fwd[:, :, 3:], 1e-30)
            yhat = bwd[:, :, :3] / np.maximum(bwd[:, :, 3:], 1e-30)
            e_f, bad_f = _solve_weighted(g_x, mu_x, h_x, xhat, w_f, lam)
            e_g, bad_g = _solve_weighted(
                np.broadcast_to(g_y, (nb, m, ky)),
                np.broadcast_to(mu_y, (nb, ky)),
                np.broadcast_to(h_y, (nb, ky, 3)),
                yhat,
                w_g,
                lam,
            )
            failed.update(bad_f)
            failed.update(bad_g)
        else:
            if params.target_rule == "gpu":
                xhat_in = r[:, :, None] * fwd[:, :, :3]
                yhat_in = c[:, :, None] * bwd[:, :, :3]
            else:
                xhat_in = fwd[:, :, :3] / np.maximum(fwd[:, :, 3:], 1e-30)
                yhat_in = bwd[:, :, :3] / np.maximum(bwd[:, :, 3:], 1e-30)
            xhat = np.where((w_f >= cutoff)[:, :, None], xhat_in, fx)
            yhat = np.where((w_g >= cutoff)[:, :, None], yhat_in, gy)
            e_f = gt_x @ xhat
            e_f += h_x
            e_f /= (1 + dt.type(lam) * mu_x)[:, :, None]
            # The scene basis is shared: one GEMM over all demos' targets at once.
            e_g = (gt_y @ yhat.transpose(1, 0, 2).reshape(m, nb * 3)).reshape(ky, nb, 3)
            e_g = e_g.transpose(1, 0, 2) + h_y
            e_g /= (1 + dt.type(lam) * mu_y)[None, :, None]
        fx = g_x @ e_f
        gy = (g_y @ e_g.transpose(1, 0, 2).reshape(ky, nb * 3)).reshape(m, nb, 3)
        gy = gy.transpose(1, 0, 2)
        clock.tick("tps fit")

    # costs, in normalised coordinates, float64
    fx64, gy64 = fx.astype(float), gy.astype(float)
    wf = w_f.astype(float) if weighted else rowmask.astype(float)
    wg = w_g.astype(float) if weighted else np.ones((nb, m))
    map_fwd = np.einsum("bn,bn->b", wf, ((fx64 - xhat) ** 2).sum(axis=2))
    map_bwd = np.einsum("bm,bm->b", wg, ((gy64 - yhat) ** 2).sum(axis=2))
    e_f64, e_g64 = e_f.astype(float), e_g.astype(float)
    bend_f = np.einsum("bk,bkd->b", demo.mu_ak[idx, :k], e_f64**2)
    bend_g = np.einsum("k,bkd->b", scene.mu_ak[0, :ky], e_g64**2)
    w_f64, w_g64 = w_f.astype(float), w_g.astype(float)
    inl_f = w_f64.sum(axis=1) / np.maximum(n_valid, 1)
    inl_g = w_g64.mean(axis=1)
    b_f = np.einsum("bpk,bkd->bpd", demo.theta_apk[idx, 1:4, :k], e_f64)
    b_g = np.einsum("pk,bkd->bpd", scene.theta_apk[0, 1:4, :ky], e_g64)
    aff_f = np.linalg.norm(b_f - np.eye(3), axis=(1, 2))
    aff_g = np.linalg.norm(b_g - np.eye(3), axis=(1, 2))
    matched_f = fwd[:, :, :3].astype(float) / np.maximum(fwd[:, :, 3:].astype(float), 1e-30)
    matched_g = bwd[:, :, :3].astype(float) / np.maximum(bwd[:, :, 3:].astype(float), 1e-30)
    res_f = np.linalg.norm(fx64 - matched_f, axis=2)
    res_g = np.linalg.norm(gy64 - matched_g, axis=2)
    res_f = (w_f64 * res_f).sum(1) / np.maximum(w_f64.sum(1), 1e-30) * params.scale_m
    res_g = (w_g64 * res_g).sum(1) / np.maximum(w_g64.sum(1), 1e-30) * params.scale_m
    costs = np.stack(
        [map_fwd, map_bwd, bend_f, bend_g, inl_f, inl_g, aff_f, aff_g, res_f, res_g], axis=1
    )
    corr = None
    if keep_corr:
        corr = (r[:, :, None] * p * c_prev[:, None, :]).astype(float)
    clock.tick("costs")
    return _ChunkOut(e_f64, e_g64, costs, corr, failed)


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
