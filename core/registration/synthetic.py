"""Seeded synthetic rope clouds and known smooth warps, for registration tests and benchmarks.

A rope is a smooth random 1 m curve lying on the table (z = radius), its tube surface (radius
1 cm) sampled densely and voxel-downsampled to about the requested number of points, like the
simulator's observation. Shape suffixes: n points, 3 xyz.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from knotlab.core.voxels import voxel_groups

ROPE_LENGTH_M = 1.0
ROPE_RADIUS_M = 0.01


def rope_centreline(rng: np.random.Generator, n_nodes: int = 200, bend: float = 1.0) -> np.ndarray:
    """A smooth random 1 m planar curve: heading(s) = a0 + sum_k a_k sin(k pi s + phase_k)."""
    s = np.linspace(0.0, 1.0, n_nodes)
    heading = rng.uniform(0, 2 * np.pi) + np.zeros_like(s)
    for k in range(1, 4):
        heading += bend * rng.normal(0, 1.2 / k) * np.sin(k * np.pi * s + rng.uniform(0, 2 * np.pi))
    step = ROPE_LENGTH_M / (n_nodes - 1)
    xy = np.cumsum(np.stack([np.cos(heading), np.sin(heading)], axis=1) * step, axis=0)
    xy -= xy.mean(axis=0)
    xy += rng.uniform(-0.1, 0.1, size=2)
    return np.column_stack([xy, np.full(n_nodes, ROPE_RADIUS_M)])


def _voxel_downsample(points_n3: np.ndarray, voxel: float) -> np.ndarray:
    """One point per occupied voxel: the mean of the points in it (like a PCL voxel grid)."""
    return voxel_groups(points_n3, voxel)[2]


def rope_cloud(rng: np.random.Generator, n_points: int = 120, bend: float = 1.0) -> np.ndarray:
    """A rope-like cloud of exactly n_points: tube surface voxel-downsampled, then subsampled."""
    centre = rope_centreline(rng, bend=bend)
    tangent = np.gradient(centre, axis=0)
    tangent /= np.linalg.norm(tangent, axis=1, keepdims=True)
    normal = np.column_stack([-tangent[:, 1], tangent[:, 0], np.zeros(len(centre))])
    phi = rng.uniform(0, 2 * np.pi, size=(len(centre), 12))
    up = np.array([0.0, 0.0, 1.0])
    surface = (
        centre[:, None, :]
        + ROPE_RADIUS_M * np.cos(phi)[..., None] * normal[:, None, :]
        + ROPE_RADIUS_M * np.sin(phi)[..., None] * up
    ).reshape(-1, 3)
    surface = surface[surface[:, 2] >= 0.002]  # the camera does not see the underside
    voxel = 0.03
    cloud = _voxel_downsample(surface, voxel)
    while cloud.shape[0] < n_points and voxel > 1e-3:
        voxel *= 0.85
        cloud = _voxel_downsample(surface, voxel)
    keep = np.sort(rng.choice(cloud.shape[0], size=n_points, replace=False))
    return cloud[keep]


@dataclass(frozen=True)
class SmoothWarp:
    """x -> x R + t + sum_k a_k sin(omega_k . x + phase_k): a known smooth warp (in-plane bumps)."""

    rot_33: np.ndarray
    t_3: np.ndarray
    amp_k3: np.ndarray
    omega_k3: np.ndarray
    phase_k: np.ndarray

    def __call__(self, x_n3: np.ndarray) -> np.ndarray:
        """Apply the warp to rows of x_n3."""
        x = np.asarray(x_n3, dtype=float)
        centre = np.array([0.0, 0.0, ROPE_RADIUS_M])
        lin = (x - centre) @ self.rot_33 + centre + self.t_3
        return lin + np.sin(x @ self.omega_k3.T + self.phase_k) @ self.amp_k3


def smooth_warp(
    rng: np.random.Generator, magnitude_m: float = 0.03, angle_rad: float = 0.1
) -> SmoothWarp:
    """A random warp: rotation about z up to angle_rad, a shift, and bumps of size magnitude_m."""
    ang = rng.uniform(-angle_rad, angle_rad)
    c, s = np.cos(ang), np.sin(ang)
    rot = np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])
    n_k = 3
    amp = np.zeros((n_k, 3))
    amp[:, :2] = rng.normal(0, magnitude_m / np.sqrt(n_k), size=(n_k, 2))
    omega = np.zeros((n_k, 3))
    omega[:, :2] = rng.normal(0, 4.0, size=(n_k, 2))  # wavelengths around 1-2 m / 2 pi
    return SmoothWarp(
        rot, rng.uniform(-0.05, 0.05, 3) * [1, 1, 0], amp, omega, rng.uniform(0, 2 * np.pi, n_k)
    )


def corrupt(
    rng: np.random.Generator,
    cloud_n3: np.ndarray,
    noise_m: float = 0.002,
    outlier_frac: float = 0.05,
) -> np.ndarray:
    """Add Gaussian noise and replace a fraction of points by uniform outliers near the cloud."""
    out = cloud_n3 + rng.normal(0, noise_m, size=cloud_n3.shape)
    n_out = round(outlier_frac * len(out))
    if n_out:
        lo = cloud_n3.min(axis=0) - [0.05, 0.05, 0.0]
        hi = cloud_n3.max(axis=0) + np.array([0.05, 0.05, 0.05])
        idx = rng.choice(len(out), size=n_out, replace=False)
        out[idx] = rng.uniform(lo, hi, size=(n_out, 3))
    return out


def library(rng: np.random.Generator, n_demos: int, n_points: int = 120) -> list[np.ndarray]:
    """n_demos independent rope clouds of n_points each."""
    return [rope_cloud(rng, n_points) for _ in range(n_demos)]


WarpFn = Callable[[np.ndarray], np.ndarray]
