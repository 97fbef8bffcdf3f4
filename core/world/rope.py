"""Rope geometry on node polylines: length, resampling, xy self-intersection, perturbation.

Shape suffixes: k = rope nodes (polyline vertices), m = segments, 2/3 = xy/xyz.
All functions are pure; every random choice takes a seed (numpy Generator).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import brentq

from knotlab.core.arrays import points_n3
from knotlab.core.errors import InvalidInputError

# |cross| below this (m^2) counts as parallel: such pairs cannot cross transversally.
_PARALLEL_EPS = 1e-18


def as_nodes(nodes_k3: np.ndarray, name: str = "rope nodes", min_nodes: int = 2) -> np.ndarray:
    """Validate a (K, 3) finite float array of rope nodes and return it as float64."""
    return points_n3(name, nodes_k3, min_nodes, unit="nodes")


def rope_length(nodes_k3: np.ndarray) -> float:
    """Polyline length sum_i |p_{i+1} - p_i| in metres."""
    nodes = as_nodes(nodes_k3)
    return float(np.linalg.norm(np.diff(nodes, axis=0), axis=1).sum())


def arc_lengths(nodes_k3: np.ndarray) -> np.ndarray:
    """Arc length from the first node at every node (k,)."""
    return np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(nodes_k3, axis=0), axis=1))])


def points_at_arc(nodes_k3: np.ndarray, at_n: np.ndarray) -> np.ndarray:
    """The chain's points at arc lengths ``at_n`` from its first node (N, 3), continued
    straight along its end links past either end."""
    nodes = np.asarray(nodes_k3, dtype=float)
    at = np.asarray(at_n, dtype=float)
    arc_k = arc_lengths(nodes)
    out = np.stack([np.interp(at, arc_k, nodes[:, d]) for d in range(3)], axis=1)
    for outside, end, inner, edge in ((at < 0.0, 0, 1, 0.0), (at > arc_k[-1], -1, -2, arc_k[-1])):
        if outside.any():
            step = nodes[end] - nodes[inner]
            step = step / max(float(np.linalg.norm(step)), 1e-12)
            out[outside] = nodes[end] + np.outer(np.abs(at[outside] - edge), step)
    return out


def slide_along(nodes_k3: np.ndarray, by: float) -> np.ndarray:
    """The chain with every node moved ``by`` m along its own curve (positive: towards the last
    node; past an end, straight on): a tracker's error along the rope."""
    nodes = np.asarray(nodes_k3, dtype=float)
    return points_at_arc(nodes, arc_lengths(nodes) + by)


def segment_feet(
    points_n3: np.ndarray,
    path_k3: np.ndarray,
    *,
    xy_only: bool = False,
    low_m: np.ndarray | float = 0.0,
    high_m: np.ndarray | float = 1.0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each point's nearest place on each segment of a polyline: the fraction along the
    segment (N, M), clipped to [low, high] per segment (-inf / inf continue a segment past its
    ends), the foot there (N, M, 3) and its distance (N, M), in the table's plane where
    ``xy_only``."""
    points = np.asarray(points_n3, dtype=float)
    path = np.asarray(path_k3, dtype=float)
    dims = 2 if xy_only else 3
    start_m3 = path[:-1]
    step_m3 = np.diff(path, axis=0)
    len2_m = np.maximum(np.einsum("mi,mi->m", step_m3[:, :dims], step_m3[:, :dims]), 1e-18)
    rel_nm = points[:, None, :dims] - start_m3[None, :, :dims]
    t_nm = np.clip(np.einsum("nmi,mi->nm", rel_nm, step_m3[:, :dims]) / len2_m, low_m, high_m)
    foot_nm3 = start_m3[None] + t_nm[:, :, None] * step_m3[None]
    dist_nm = np.linalg.norm(foot_nm3[:, :, :dims] - points[:, None, :dims], axis=2)
    return t_nm, foot_nm3, dist_nm


def resample_by_arc_length(nodes_k3: np.ndarray, n: int) -> np.ndarray:
    """n nodes evenly spaced by arc length along the polyline (ends kept exactly)."""
    nodes = as_nodes(nodes_k3)
    if int(n) != n or n < 2:
        raise InvalidInputError(f"resample count must be an integer >= 2, got {n}")
    seg_m = np.linalg.norm(np.diff(nodes, axis=0), axis=1)
    arc_k = arc_lengths(nodes)
    if arc_k[-1] <= 0.0:
        raise InvalidInputError("rope nodes have zero length: cannot resample")
    # Drop repeated nodes so np.interp sees a strictly increasing abscissa.
    keep = np.concatenate([[True], seg_m > 0.0])
    arc_k, nodes = arc_k[keep], nodes[keep]
    targets = np.linspace(0.0, arc_k[-1], int(n))
    out = np.stack([np.interp(targets, arc_k, nodes[:, d]) for d in range(3)], axis=1)
    out[0], out[-1] = nodes[0], nodes[-1]
    return out


def segment_crossings_xy(
    starts_m2: np.ndarray,
    ends_m2: np.ndarray,
    cyclic: bool,
    closed_intervals: bool = False,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """All crossings of non-adjacent 2-D segments: (i, j, t_i, s_j) with i < j, vectorised.

    Segment i runs a_i + t d_i. Parameters are half-open, t, s in [0, 1), so a crossing exactly
    at a shared vertex is counted once; with ``closed_intervals`` both ends count (touching
    counts as intersecting). Parallel pairs never cross. Adjacent segments (|i - j| == 1, and the
    first/last pair when ``cyclic``) are skipped because they always meet at their shared vertex.
    """
    a = np.asarray(starts_m2, dtype=float)
    d = np.asarray(ends_m2, dtype=float) - a
    m = a.shape[0]
    ii, jj = np.triu_indices(m, k=2)
    if cyclic and m > 2:
        keep = ~((ii == 0) & (jj == m - 1))
        ii, jj = ii[keep], jj[keep]
    di, dj = d[ii], d[jj]
    denom = di[:, 0] * dj[:, 1] - di[:, 1] * dj[:, 0]
    w = a[jj] - a[ii]
    ok = np.abs(denom) > _PARALLEL_EPS
    safe = np.where(ok, denom, 1.0)
    t = (w[:, 0] * dj[:, 1] - w[:, 1] * dj[:, 0]) / safe
    s = (w[:, 0] * di[:, 1] - w[:, 1] * di[:, 0]) / safe
    if closed_intervals:
        hit = ok & (t >= 0.0) & (t <= 1.0) & (s >= 0.0) & (s <= 1.0)
    else:
        hit = ok & (t >= 0.0) & (t < 1.0) & (s >= 0.0) & (s < 1.0)
    return ii[hit], jj[hit], t[hit], s[hit]


def has_xy_self_intersection(nodes_k3: np.ndarray) -> bool:
    """True if the xy projection of the open polyline crosses or touches itself."""
    nodes = as_nodes(nodes_k3)
    if nodes.shape[0] < 4:
        return False
    xy = nodes[:, :2]
    i, _, _, _ = segment_crossings_xy(xy[:-1], xy[1:], cyclic=False, closed_intervals=True)
    return bool(i.size)


def tent_displacements(
    n_nodes: int, rho: float, n_centres: int, rng: np.random.Generator
) -> np.ndarray:
    """One round of xy tent displacements (n_nodes, 2): peak rho at k centres, random directions.

    Centres sit evenly along the node index, ends included; each tent falls linearly to zero at
    +-bandwidth = floor(n_nodes / (k - 1)) nodes, as in the original task generator.
    """
    if n_centres < 2:
        raise InvalidInputError(f"n_centres must be >= 2, got {n_centres}")
    centres_c = np.round(np.linspace(0, n_nodes - 1, n_centres))
    bandwidth = max(1, n_nodes // (n_centres - 1))
    theta_c = rng.uniform(0.0, 2.0 * np.pi, size=n_centres)
    dir_c2 = np.stack([np.cos(theta_c), np.sin(theta_c)], axis=1)
    idx_k = np.arange(n_nodes, dtype=float)
    weight_kc = np.clip(1.0 - np.abs(idx_k[:, None] - centres_c[None, :]) / bandwidth, 0.0, None)
    return rho * weight_kc @ dir_c2


@dataclass(frozen=True)
class Perturbation:
    """A perturbed rope and how it was drawn."""

    nodes_k3: np.ndarray
    n_tries: int  # draws needed (1 = first draw was valid)
    peak_tent: float  # max |xy tent displacement| of the accepted draw, before the length fix


def scale_xy_to_length(nodes_k3: np.ndarray, target: float) -> np.ndarray:
    """Scale xy about the xy centroid so the 3-D polyline length equals target (z untouched)."""
    centre = nodes_k3[:, :2].mean(axis=0)

    def scaled(s: float) -> np.ndarray:
        out = nodes_k3.copy()
        out[:, :2] = centre + s * (nodes_k3[:, :2] - centre)
        return out

    def excess(s: float) -> float:
        return float(np.linalg.norm(np.diff(scaled(s), axis=0), axis=1).sum()) - target

    if excess(0.0) >= 0.0:
        return nodes_k3  # z alone is already as long as the target; nothing to scale
    hi = 2.0
    while excess(hi) < 0.0 and hi < 1e3:
        hi *= 2.0
    return scaled(brentq(excess, 0.0, hi, xtol=1e-14, rtol=1e-14))


def perturb_rope_with_info(
    nodes_k3: np.ndarray,
    rho: float,
    n_centres: int = 7,
    seed: int | np.random.Generator | None = 0,
    max_tries: int = 20,
) -> Perturbation:
    """Tent-perturb the rope in xy keeping its length and node count; resample; no xy crossings.

    Every retry draws a fresh perturbation of the ORIGINAL rope: the original generator stacked
    retries on top of each other, which made the displacement grow with every failed draw.
    """
    nodes = as_nodes(nodes_k3, min_nodes=3)
    if not np.isfinite(rho) or rho < 0:
        raise InvalidInputError(f"rho must be a finite non-negative distance, got {rho}")
    if max_tries < 1:
        raise InvalidInputError(f"max_tries must be >= 1, got {max_tries}")
    rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
    k = nodes.shape[0]
    target = rope_length(nodes)
    for attempt in range(1, max_tries + 1):
        disp_k2 = tent_displacements(k, rho, n_centres, rng)
        cand = nodes.copy()
        cand[:, :2] += disp_k2
        # Resample first (even spacing), then scale: scaling keeps the spacing even.
        cand = scale_xy_to_length(resample_by_arc_length(cand, k), target)
        if not has_xy_self_intersection(cand):
            peak = float(np.linalg.norm(disp_k2, axis=1).max())
            return Perturbation(nodes_k3=cand, n_tries=attempt, peak_tent=peak)
    raise InvalidInputError(
        f"perturb_rope: no self-intersection-free perturbation with rho={rho} in {max_tries} "
        "tries (is the original rope itself crossing in xy, or rho too large for it?)"
    )


def perturb_rope(
    nodes_k3: np.ndarray,
    rho: float,
    n_centres: int = 7,
    seed: int | np.random.Generator | None = 0,
    max_tries: int = 20,
) -> np.ndarray:
    """Perturbed copy of the rope (same length and node count, no xy self-intersection)."""
    return perturb_rope_with_info(nodes_k3, rho, n_centres, seed, max_tries).nodes_k3


def straight_rope(n_nodes: int = 41, length: float = 1.0, height: float = 0.01) -> np.ndarray:
    """A straight rope along x centred at the origin, resting at z = height (n_nodes, 3)."""
    if n_nodes < 2 or length <= 0:
        raise InvalidInputError(f"need n_nodes >= 2 and length > 0, got {n_nodes}, {length}")
    nodes = np.zeros((n_nodes, 3))
    nodes[:, 0] = np.linspace(-length / 2, length / 2, n_nodes)
    nodes[:, 2] = height
    return nodes
