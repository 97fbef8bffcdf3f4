"""Is the rope tied in an overhand knot? Decided by a knot invariant, not a pattern match.

Method (docs/reference/knot_and_stages.md, "Knot test"):
1. Close the open rope far above (and, separately, far below) everything: from each end straight
   up to height h, joined by a straight chord at height h. Everything at height h passes over (or
   under) the whole rope, so any such path gives the same knot; a chord is the simplest one.
2. Project to the plane and find every crossing of non-adjacent segments (vectorised numpy),
   with which strand is on top and the crossing's sign.
3. Build the Alexander (Fox) matrix of the diagram: for crossing c with over-arc k and under-arcs
   i (incoming) and j (outgoing), row c has 1 - t at k and (t, -1) at (i, j) for one crossing sign,
   (-1, t) for the other. Delete one row and column: the minor's determinant is +-t^m Delta(t).
   |Delta(-1)| is the knot determinant (1 unknot, 3 trefoil; docs/tasks.md) and Delta(2) with
   powers of two divided out is 3 for the trefoil (Delta = t^2 - t + 1).
4. It is an overhand knot only if BOTH closures give the trefoil, so the answer does not depend
   on how the open ends are closed.

Degenerate projections (a vertex exactly on another segment, collinear overlaps) are avoided by
projecting along a fixed, slightly tilted direction (1.7e-7, 3.1e-7, 1) instead of straight
down: symbolic perturbation with no randomness.
Shape suffixes: k = rope nodes, m = segments of the closed curve, c = crossings.
"""

from __future__ import annotations

from dataclasses import dataclass
from fractions import Fraction

import numpy as np

from knotlab.core.world.rope import as_nodes, segment_crossings_xy

_TILT_2 = np.array([1.7e-7, 3.1e-7])  # xy shift per metre of height in the projection
_CLOSURE_HEIGHT = 10.0  # closure height above the rope, in multiples of the rope's extent


@dataclass(frozen=True)
class Crossings:
    """Crossings of one closed curve, as positions along it (segment index + parameter)."""

    over_pos_c: np.ndarray
    under_pos_c: np.ndarray
    sign_c: np.ndarray  # +1 / -1
    over_seg_c: np.ndarray
    under_seg_c: np.ndarray


@dataclass(frozen=True)
class KnotAnalysis:
    """Invariants of the rope under the two closures, and its crossing code for display."""

    is_overhand: bool
    determinants: tuple[int, int]  # |Delta(-1)| for the (over, under) closures
    alexander_values: tuple[int, int]  # |Delta(2)| with powers of 2 removed, (over, under)
    gauss_code: str  # crossings of the open rope in order along it, e.g. "U0 O1 U2 O0 U1 O2"
    n_crossings: int  # crossings of the open rope's projection


def _crossings(points_m3: np.ndarray, cyclic: bool) -> Crossings:
    """Crossings of the polyline through `points_m3` (closed if cyclic) in the tilted projection."""
    pts = points_m3 if not cyclic else np.vstack([points_m3, points_m3[:1]])
    proj = pts[:, :2] - pts[:, 2:3] * _TILT_2
    i, j, t, s = segment_crossings_xy(proj[:-1], proj[1:], cyclic=cyclic)
    z = pts[:, 2]
    z_i = z[i] + t * (z[i + 1] - z[i])
    z_j = z[j] + s * (z[j + 1] - z[j])
    i_over = z_i >= z_j  # equal heights mean the rope passes through itself: pick one, no crash
    over_seg = np.where(i_over, i, j)
    under_seg = np.where(i_over, j, i)
    pos_i, pos_j = i + t, j + s
    d = proj[1:] - proj[:-1]
    d_over, d_under = d[over_seg], d[under_seg]
    cross = d_over[:, 0] * d_under[:, 1] - d_over[:, 1] * d_under[:, 0]
    return Crossings(
        over_pos_c=np.where(i_over, pos_i, pos_j),
        under_pos_c=np.where(i_over, pos_j, pos_i),
        sign_c=np.where(cross > 0, 1, -1),
        over_seg_c=over_seg,
        under_seg_c=under_seg,
    )


def _exact_det(rows: list[list[int]]) -> int:
    """Exact integer determinant by fraction-free Gaussian elimination (Bareiss)."""
    a = [[Fraction(x) for x in row] for row in rows]
    n, sign, prev = len(a), 1, Fraction(1)
    for k in range(n - 1):
        if a[k][k] == 0:
            swap = next((r for r in range(k + 1, n) if a[r][k] != 0), None)
            if swap is None:
                return 0
            a[k], a[swap] = a[swap], a[k]
            sign = -sign
        for r in range(k + 1, n):
            for c in range(k + 1, n):
                a[r][c] = (a[r][c] * a[k][k] - a[r][k] * a[k][c]) / prev
        prev = a[k][k]
    return int(sign * a[n - 1][n - 1]) if n else 1


def _alexander_minor(cr: Crossings, t: int) -> int:
    """Determinant of the Alexander matrix minor at integer t (exact)."""
    n = cr.sign_c.size
    if n <= 1:
        return 1
    order = np.argsort(cr.under_pos_c, kind="stable")
    sorted_under = cr.under_pos_c[order]
    rank = np.empty(n, dtype=int)
    rank[order] = np.arange(n)
    # Arc r runs from the r-th under-pass (in curve order) to the next one.
    out_arc = rank
    in_arc = (rank - 1) % n
    over_arc = (np.searchsorted(sorted_under, cr.over_pos_c, side="right") - 1) % n
    mat = np.zeros((n, n), dtype=np.int64)
    rows = np.arange(n)
    np.add.at(mat, (rows, over_arc), 1 - t)
    pos = cr.sign_c > 0
    np.add.at(mat, (rows, in_arc), np.where(pos, t, -1))
    np.add.at(mat, (rows, out_arc), np.where(pos, -1, t))
    minor = mat[:-1, :-1]
    value = np.linalg.det(minor.astype(float))
    if abs(value) < 2.0**50:
        return round(value)
    return _exact_det(minor.tolist())


def _odd_part(v: int) -> int:
    v = abs(v)
    while v and v % 2 == 0:
        v //= 2
    return v


def _closed(nodes_k3: np.ndarray, above: bool) -> np.ndarray:
    extent = max(float(np.ptp(nodes_k3, axis=0).max()), 1e-9)
    if above:
        h = nodes_k3[:, 2].max() + _CLOSURE_HEIGHT * extent
    else:
        h = nodes_k3[:, 2].min() - _CLOSURE_HEIGHT * extent
    end, start = nodes_k3[-1].copy(), nodes_k3[0].copy()
    end[2] = start[2] = h
    return np.vstack([nodes_k3, end, start])


def gauss_code(nodes_k3: np.ndarray) -> tuple[str, int]:
    """Over/under code of the open rope's projection, crossings numbered by first visit."""
    nodes = as_nodes(nodes_k3, min_nodes=2)
    cr = _crossings(nodes, cyclic=False)
    n = cr.sign_c.size
    passes = sorted(
        [(float(cr.over_pos_c[c]), "O", c) for c in range(n)]
        + [(float(cr.under_pos_c[c]), "U", c) for c in range(n)]
    )
    label: dict[int, int] = {}
    parts = []
    for _, kind, c in passes:
        label.setdefault(c, len(label))
        parts.append(f"{kind}{label[c]}")
    return " ".join(parts), n


def _relabel(tokens: list[str]) -> str:
    labels: dict[str, int] = {}
    out = []
    for tok in tokens:
        labels.setdefault(tok[1:], len(labels))
        out.append(f"{tok[0]}{labels[tok[1:]]}")
    return " ".join(out)


def canonical_code(code: str) -> str:
    """Direction-free form of a crossing code: the smaller of the code and its reversal, each
    with crossings renumbered by first visit (a rope's code read from either end)."""
    tokens = code.split()
    if not tokens:
        return ""
    return min(_relabel(tokens), _relabel(tokens[::-1]))


def analyse_knot(rope_nodes_k3: np.ndarray) -> KnotAnalysis:
    """Knot invariants of the rope closed above and below, plus its crossing code."""
    nodes = as_nodes(rope_nodes_k3, min_nodes=2)
    dets, values = [], []
    for above in (True, False):
        cr = _crossings(_closed(nodes, above), cyclic=True)
        dets.append(abs(_alexander_minor(cr, -1)))
        values.append(_odd_part(_alexander_minor(cr, 2)))
    code, n_open = gauss_code(nodes)
    trefoil = all(d == 3 for d in dets) and all(v == 3 for v in values)
    return KnotAnalysis(
        is_overhand=trefoil,
        determinants=(dets[0], dets[1]),
        alexander_values=(values[0], values[1]),
        gauss_code=code,
        n_crossings=n_open,
    )


def _alexander_minor_exact(cr: Crossings, t: int) -> int:
    """The Alexander matrix minor's determinant at integer t, in exact integer arithmetic."""
    n = cr.sign_c.size
    if n <= 1:
        return 1
    order = np.argsort(cr.under_pos_c, kind="stable")
    rank = np.empty(n, dtype=int)
    rank[order] = np.arange(n)
    over_arc = (np.searchsorted(cr.under_pos_c[order], cr.over_pos_c, side="right") - 1) % n
    rows = [[0] * n for _ in range(n)]
    for c in range(n):
        i, j, k = (int(rank[c]) - 1) % n, int(rank[c]), int(over_arc[c])
        rows[c][k] += 1 - t
        rows[c][i] += t if cr.sign_c[c] > 0 else -1
        rows[c][j] += -1 if cr.sign_c[c] > 0 else t
    return _exact_det([row[:-1] for row in rows[:-1]])


def alexander_polynomial(rope_nodes_k3: np.ndarray, above: bool = True) -> tuple[int, ...]:
    """Alexander polynomial of the rope closed far above (or below): integer coefficients,
    lowest power first, normalised (no factor t or -1: the lowest coefficient is positive).

    The minor's determinant is a polynomial of degree below the crossing count n; it is
    evaluated exactly at n integers near 0 and interpolated (exact rationals). Unknot (1,),
    trefoil (1, -1, 1); the tasks' own goals are in their folders (docs/tasks.md).
    """
    nodes = as_nodes(rope_nodes_k3, min_nodes=2)
    cr = _crossings(_closed(nodes, above), cyclic=True)
    n = max(cr.sign_c.size, 1)
    ts = [(k + 1) // 2 * (1 if k % 2 else -1) for k in range(n)]  # 0, 1, -1, 2, -2, ...
    values = [Fraction(_alexander_minor_exact(cr, t)) for t in ts]
    coeffs = [Fraction(0)] * n
    for a, (t_a, v_a) in enumerate(zip(ts, values, strict=True)):
        # Lagrange basis polynomial of t_a, built coefficient by coefficient.
        basis = [Fraction(1)]
        denom = Fraction(1)
        for b, t_b in enumerate(ts):
            if b == a:
                continue
            basis = [Fraction(0), *basis]
            for d in range(len(basis) - 1):
                basis[d] -= t_b * basis[d + 1]
            denom *= t_a - t_b
        for d, c in enumerate(basis):
            coeffs[d] += v_a * c / denom
    ints = [int(c) for c in coeffs]
    while len(ints) > 1 and ints[-1] == 0:
        ints.pop()
    while len(ints) > 1 and ints[0] == 0:
        ints.pop(0)
    if ints[0] < 0:
        ints = [-c for c in ints]
    return tuple(ints)


def is_overhand_knot(rope_nodes_k3: np.ndarray) -> bool:
    """True if the open rope, closed far above and far below, is a trefoil both ways."""
    return analyse_knot(rope_nodes_k3).is_overhand
