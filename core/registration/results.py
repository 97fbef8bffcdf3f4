"""Registration results: one pair (`Registration`) and one scene against a library (`ScanResult`).

Splines come back in world coordinates; costs are in the normalised coordinates of `rpm`.
Shape suffixes: a demos, c costs (`COST_NAMES`), k TPS basis coefficients, n demo points,
m scene points, 3 xyz.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from knotlab.core.registration.params import COST_NAMES, RegistrationCosts, RegistrationParams
from knotlab.core.registration.sides import CloudSide
from knotlab.core.registration.tps import ThinPlateSpline, tps_kernel


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

    def f_points(self, a: int, x_m3: np.ndarray) -> np.ndarray:
        """f_a(x) for world points x (m, 3): `f(a).evaluate(x)` bit for bit, without building
        and checking the spline (the features warp a few points through every demo's f_a)."""
        s = self.params.scale_m
        side = self._demo
        n = int(side.n_a[a])
        k = n + 4
        # the same arithmetic, in the same order, as TpsBasis.spline, compose_affine, evaluate
        theta = side.theta_apk[a, : 4 + n, :k] @ self.e_f_ak3[a, :k]
        b_33, w_n3 = theta[1:4].copy(), theta[4:].copy()
        off_in = side.centre_a3[a]
        centres = side.x_an3[a, :n] * s + off_in
        t_3 = s * theta[0] + self._scene.centre_a3[0] - off_in @ b_33
        return x_m3 @ b_33 + t_3 + tps_kernel(x_m3, centres) @ w_n3

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
