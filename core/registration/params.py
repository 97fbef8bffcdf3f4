"""Settings of bidirectional TPS-RPM (world units), the two presets, costs, cloud cleaning."""

from __future__ import annotations

import warnings
from dataclasses import astuple, dataclass
from typing import Literal

import numpy as np

from knotlab.core.errors import InvalidInputError

CACHE_VERSION = 2
MAX_EXPONENT = 80.0


@dataclass(frozen=True)
class RegistrationParams:
    """Settings of bidirectional TPS-RPM, every length-dependent one in WORLD units (metres).

    The fit in world coordinates minimises
        sum ||y - f(x)||^2 [m^2] + lambda tr(W^T K W) [lambda in m] + tr((B-I)^T R (B-I)) [R in m^2]
    and the affinity is exp(-d / (2 T)) with d and T in metres. The kernel works in coordinates
    divided by `scale_m`; `normalised_schedule` and `normalised_rot_coef` convert once (lambda / s,
    T / s, R / s^2), so changing `scale_m` leaves the world-space fit unchanged (tested). Stating
    R in the internal units made it 1 / s^2 = 4x weaker than meant ("bug A").
    Defaults: the paper-era rll/lfd schedule as this project ran it (lambda 0.1 -> 0.001 and
    T 0.1 -> 0.005 in units of 0.5 m) and the identity pull (1e-3, 1e-3, 0.1) that made transfer
    work in the rope-world prototype (docs/reference/registration.md, "The identity pull").
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
