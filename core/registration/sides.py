"""Cloud sides: the demo and scene clouds of a registration, normalised and factorised once.

A side holds one or more cleaned clouds, each translated by its median and divided by the shared
length `scale_m` (`normalise_cloud`), with its TPS basis (`tps.tps_basis`), all zero-padded to a
common size so that a batch of demos is one set of arrays. A bad demo cloud is reported on its
side (not ok + reason); a bad scene cloud raises, as it concerns every demo.
Shape suffixes: a clouds, n points (padded), k TPS basis coefficients, p rows of theta, 3 xyz.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from knotlab.core.errors import InvalidInputError, SolverError
from knotlab.core.registration.kernel import padded_length
from knotlab.core.registration.params import RegistrationParams, clean_cloud
from knotlab.core.registration.tps import TpsBasis, tps_basis


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

    def rows(self, indices: Sequence[int]) -> CloudSide:
        """The side of these clouds alone, in this order: the arrays `demo_side` would build
        from them (the same values, padded to their own largest cloud), without factorising
        any cloud again."""
        idx = np.asarray(indices, dtype=int)
        n_max = max([len(self.clouds[a]) for a in idx] + [5])
        k_max = n_max + 4
        return CloudSide(
            clouds=tuple(self.clouds[a] for a in idx),
            centre_a3=self.centre_a3[idx],
            x_an3=self.x_an3[idx, :n_max],
            mask_an=self.mask_an[idx, :n_max],
            g_ank=self.g_ank[idx, :n_max, :k_max],
            mu_ak=self.mu_ak[idx, :k_max],
            h_ak3=self.h_ak3[idx, :k_max],
            theta_apk=self.theta_apk[idx, : 4 + n_max, :k_max],
            n_a=self.n_a[idx],
            ok_a=self.ok_a[idx],
            reason_a=tuple(self.reason_a[a] for a in idx),
        )

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


def one_demo_side(demo_cloud: np.ndarray, params: RegistrationParams) -> CloudSide:
    """The factorised side of one demo cloud (what `register` builds); raises if unusable."""
    demo = demo_side([clean_cloud(demo_cloud, "demo cloud", params.max_points)], params)
    if not demo.ok_a[0]:
        raise SolverError(f"demo cloud: {demo.reason_a[0]}")
    return demo
