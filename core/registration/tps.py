"""Thin-plate splines in 3-D: fit, evaluate, Jacobian, bending energy.

Convention (row vectors, as in rll/lfd): a point is a row x (1x3) and

    f(x) = x B + t + sum_i w_i phi(||x - c_i||),   phi(r) = -r   (the 3-D TPS kernel)

with centres c_i (n x 3), W = [w_i] (n x 3), B (3 x 3, multiplies row vectors from the right, so
row a of B is the image of input axis a) and t (3,).

The fit minimises, over theta = [t; B; W],

    J = sum_i omega_i ||y_i - f(x_i)||^2 + lambda tr(W^T K W) + tr((B - I)^T R (B - I))
    subject to [1 X]^T W = 0                    (W carries no affine part)

where K_ik = phi(||x_i - x_k||), lambda is the bending coefficient and R = diag(rot_coef)
penalises the rows of B (the input axes), pulling B toward the identity.

Implementation: `TpsBasis` factorises the problem once per centre set. With N a basis of the
constraint's null space (theta = N z), Q = [1 X K] and R~ = R on the B block, let
A0 = N^T (Q^T Q + R~) N and A1 = N^T K~ N. The generalised eigenvectors V (V^T A0 V = I,
V^T A1 V = diag(mu)) turn every fit into a k x k problem in coefficients e (z = V e):

    (I + lambda diag(mu) - G^T diag(1 - omega) G) e = G^T diag(omega) y + h,
    G = Q N V (warped centres f(X) = G e),  h = V^T N^T [0; R; 0],
    tr(W^T K W) = sum_k mu_k |e_k|^2.

With unit weights this is diagonal: e = (G^T y + h) / (1 + lambda mu), which is what lets the
registration scan a whole library with matrix products only. Shape suffixes: n points,
k basis coefficients, p = 4 + n parameters, 3 xyz.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from knotlab.core.arrays import points_n3
from knotlab.core.errors import InvalidInputError, SolverError

DEFAULT_ROT_COEF: tuple[float, float, float] = (1e-4, 1e-4, 0.1)


def tps_kernel(a_n3: np.ndarray, b_m3: np.ndarray) -> np.ndarray:
    """K_ij = phi(||a_i - b_j||) = -||a_i - b_j||, the 3-D TPS kernel."""
    diff = a_n3[:, None, :] - b_m3[None, :, :]
    return -np.sqrt(np.einsum("nmd,nmd->nm", diff, diff))


def _as_cloud(name: str, arr: np.ndarray, min_points: int = 1) -> np.ndarray:
    return points_n3(name, arr, min_points)


@dataclass(frozen=True, eq=False)
class ThinPlateSpline:
    """f(x) = x B + t + sum_i w_i (-||x - c_i||): a 3-D TPS in the row-vector convention."""

    centres_n3: np.ndarray
    w_n3: np.ndarray
    b_33: np.ndarray  # row a = image of input axis a (row vectors multiply from the left)
    t_3: np.ndarray

    @staticmethod
    def identity() -> ThinPlateSpline:
        """The identity map f(x) = x (no centres)."""
        return ThinPlateSpline(np.zeros((0, 3)), np.zeros((0, 3)), np.eye(3), np.zeros(3))

    def evaluate(self, x_m3: np.ndarray) -> np.ndarray:
        """f(x) = x B + t + K(x, C) W for each row x."""
        x = _as_cloud("x_m3", x_m3, min_points=0)
        return x @ self.b_33 + self.t_3 + tps_kernel(x, self.centres_n3) @ self.w_n3

    __call__ = evaluate

    def jacobian(self, x_m3: np.ndarray) -> np.ndarray:
        """J[m, g, a] = df_g/dx_a = B[a, g] - sum_i W[i, g] (x_a - c_ia) / ||x - c_i||."""
        x = _as_cloud("x_m3", x_m3, min_points=0)
        diff = x[:, None, :] - self.centres_n3[None, :, :]
        dist = np.sqrt(np.einsum("mnd,mnd->mn", diff, diff))
        # The kernel -r is not differentiable at a centre; lfd sets that term to zero (nan2zero).
        safe = np.where(dist > 0, dist, 1.0)
        unit = np.where(dist[..., None] > 0, diff / safe[..., None], 0.0)
        return self.b_33.T[None] - np.einsum("mna,ng->mga", unit, self.w_n3)

    def bending_energy(self) -> float:
        """tr(W^T K W) with K the kernel on the centres (no lambda)."""
        k_nn = tps_kernel(self.centres_n3, self.centres_n3)
        return float(np.einsum("ng,nk,kg->", self.w_n3, k_nn, self.w_n3))

    def compose_affine(
        self, scale: float, offset_in_3: np.ndarray, offset_out_3: np.ndarray
    ) -> ThinPlateSpline:
        """x -> scale f((x - off_in) / scale) + off_out; W unchanged as phi is 1-homogeneous."""
        off_in = np.asarray(offset_in_3, dtype=float)
        off_out = np.asarray(offset_out_3, dtype=float)
        return ThinPlateSpline(
            centres_n3=self.centres_n3 * scale + off_in,
            w_n3=self.w_n3.copy(),
            b_33=self.b_33.copy(),
            t_3=scale * self.t_3 + off_out - off_in @ self.b_33,
        )


@dataclass(frozen=True, eq=False)
class TpsBasis:
    """Spectral factorisation of the TPS fit on fixed centres (see module docstring)."""

    centres_n3: np.ndarray
    rot_coef_3: np.ndarray
    g_nk: np.ndarray  # f(X) = G e
    mu_k: np.ndarray  # bending energy per coefficient: tr(W^T K W) = sum_k mu_k |e_k|^2
    h_k3: np.ndarray  # V^T N^T [0; R; 0]: the identity pull on B
    theta_pk: np.ndarray  # theta = [t; B; W] = N V e

    @property
    def n_coef(self) -> int:
        """Number of basis coefficients k (n + 4 - rank[1 X])."""
        return int(self.mu_k.shape[0])

    def solve(
        self, y_n3: np.ndarray, bend_coef: float, weights_n: np.ndarray | None = None
    ) -> np.ndarray:
        """e solving (I + lambda diag(mu) - G^T diag(1-omega) G) e = G^T omega y + h."""
        if weights_n is None:
            return (self.g_nk.T @ y_n3 + self.h_k3) / (1.0 + bend_coef * self.mu_k)[:, None]
        lhs = np.eye(self.n_coef) + np.diag(bend_coef * self.mu_k)
        lhs -= self.g_nk.T @ ((1.0 - weights_n)[:, None] * self.g_nk)
        rhs = self.g_nk.T @ (weights_n[:, None] * y_n3) + self.h_k3
        try:
            e = np.linalg.solve(lhs, rhs)
        except np.linalg.LinAlgError as exc:
            raise SolverError(f"weighted TPS system is singular: {exc}") from exc
        if not np.all(np.isfinite(e)):
            raise SolverError("weighted TPS solve produced non-finite coefficients")
        return e

    def spline(self, e_k3: np.ndarray) -> ThinPlateSpline:
        """The ThinPlateSpline with parameters theta = N V e."""
        theta = self.theta_pk @ e_k3
        return ThinPlateSpline(self.centres_n3.copy(), theta[4:], theta[1:4], theta[0])


def tps_basis(x_n3: np.ndarray, rot_coef: Sequence[float] = DEFAULT_ROT_COEF) -> TpsBasis:
    """Factorise A0 = N^T(Q^T Q + R~)N, A1 = N^T K~ N into V^T A0 V = I, V^T A1 V = diag(mu)."""
    x = _as_cloud("x_n3", x_n3, min_points=1)
    rot = np.asarray(rot_coef, dtype=float)
    if rot.shape != (3,) or np.any(rot < 0) or not np.all(np.isfinite(rot)):
        raise InvalidInputError(f"rot_coef must be 3 non-negative numbers, got {rot_coef!r}")
    n = x.shape[0]
    ones_x = np.hstack([np.ones((n, 1)), x])
    # Null space of [1 X]^T from a full SVD: rank-deficient (planar) clouds simply get a larger one.
    u, s, _ = np.linalg.svd(ones_x, full_matrices=True)
    rank = int(np.sum(s > s[0] * 1e-10))
    null_w = u[:, rank:]
    k_nn = tps_kernel(x, x)
    # theta = N z with N = blockdiag(I_4, null_w): the affine parameters stay free.
    qn = np.hstack([ones_x, k_nn @ null_w])
    n_coef = qn.shape[1]
    a0 = qn.T @ qn
    a0[1:4, 1:4] += np.diag(rot)
    a1 = np.zeros((n_coef, n_coef))
    a1[4:, 4:] = null_w.T @ k_nn @ null_w
    try:
        chol = np.linalg.cholesky(a0)
    except np.linalg.LinAlgError as exc:
        raise SolverError(
            f"TPS normal matrix is singular for this cloud ({n} points, rank[1 X] = {rank}): "
            "duplicate or too few points"
        ) from exc
    lin = np.linalg.inv(chol)
    c = lin @ a1 @ lin.T
    mu, u_c = np.linalg.eigh(0.5 * (c + c.T))
    v = lin.T @ u_c
    mu = np.clip(mu, 0.0, None)  # A1 is PSD; tiny negative eigenvalues are rounding
    theta = np.zeros((4 + n, n_coef))
    theta[:4] = v[:4]
    theta[4:] = null_w @ v[4:]
    g = qn @ v
    f_offset = np.zeros((n_coef, 3))
    f_offset[1:4] = np.diag(rot)
    h = v.T @ f_offset
    if not (np.all(np.isfinite(g)) and np.all(np.isfinite(v))):
        raise SolverError("TPS basis is not finite (ill-conditioned cloud)")
    return TpsBasis(x, rot, g, mu, h, theta)


def fit_tps(
    x_n3: np.ndarray,
    y_n3: np.ndarray,
    bend_coef: float,
    rot_coef: Sequence[float] = DEFAULT_ROT_COEF,
    weights_n: np.ndarray | None = None,
) -> ThinPlateSpline:
    """argmin sum w_i|y_i - f(x_i)|^2 + lambda tr(W^T K W) + tr((B-I)^T R (B-I)); [1 X]^T W = 0."""
    x = _as_cloud("x_n3", x_n3)
    y = _as_cloud("y_n3", y_n3)
    if y.shape != x.shape:
        raise InvalidInputError(f"y_n3 must have the shape of x_n3 {x.shape}, got {y.shape}")
    if not (np.isfinite(bend_coef) and bend_coef >= 0):
        raise InvalidInputError(f"bend_coef must be finite and >= 0, got {bend_coef}")
    w = None
    if weights_n is not None:
        w = np.asarray(weights_n, dtype=float)
        if w.shape != (x.shape[0],) or np.any(w < 0) or not np.all(np.isfinite(w)):
            raise InvalidInputError(f"weights_n must be {x.shape[0]} finite values >= 0")
    basis = tps_basis(x, rot_coef)
    return basis.spline(basis.solve(y, bend_coef, w))


def bending_energy(f: ThinPlateSpline) -> float:
    """tr(W^T K W), K the kernel on f's centres."""
    return f.bending_energy()
