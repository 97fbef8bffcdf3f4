"""The compiled TPS-RPM annealing kernel (numba) and its scalar constants.

See `knotlab.core.registration.rpm` for the algorithm; this module holds only the machine
code and what it reads.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from knotlab.core.registration.params import MAX_EXPONENT, RegistrationParams
from knotlab.core.registration.simd import BLOCK, transpose_block

# Compilation: `cache=True` writes the machine code next to this file (core/__pycache__/*.nbi,
# *.nbc); numba falls back to NUMBA_CACHE_DIR or ~/.cache when that is not writable. A cold
# compile of both dtypes takes tens of seconds; a warm start loads in about a second.
# Every array a kernel reads is in the RPM dtype (float32 for SCAN, float64 for EXACT), and so
# are the constants (`kernel_constants`), so float32 arithmetic never silently widens to float64.

_EXP_TAYLOR = tuple(1.0 / math.factorial(q) for q in range(11))


def kernel_constants(dt: np.dtype, params: RegistrationParams) -> np.ndarray:
    """The kernel's scalars in the RPM dtype; see `_K_*` for the slots."""
    ln2 = math.log(2.0)
    ln2_hi = 0.693359375  # 355/512: k * ln2_hi is exact in float32 for the k < 128 used
    c = [1.0 / ln2, 0.5, ln2_hi, ln2 - ln2_hi, MAX_EXPONENT, *_EXP_TAYLOR]
    c += [params.outlier_prior, params.outlier_frac, params.outlier_cutoff, 1.0, 0.0, 1e-30]
    return np.array(c, dtype=dt)


def exp_bits_constants(dt: np.dtype) -> tuple[np.floating, np.floating]:
    """(exponent bias, 2^mantissa bits) in the RPM dtype: what `_exp_neg_row` builds 2^-k from."""
    dt = np.dtype(dt)
    if dt == np.float32:
        return np.float32(127.0), np.float32(2.0**23)
    return np.float64(1023.0), np.float64(2.0**52)


_K_PRIOR, _K_FRAC, _K_CUTOFF, _K_ONE, _K_ZERO, _K_TINY = range(16, 22)
TARGET_RULES = {"batch": 0, "gpu": 1, "weighted": 2}
# stop_after: run the phases up to this one in every iteration (the benchmark's phase split)
PHASES = ("affinity", "sinkhorn", "targets", "tps fit", "costs")
N_COSTS = 10  # the columns of params.COST_NAMES, in that order
# Vector loops over the affinity's rows and columns run over lengths rounded up to a multiple of
# this: LLVM vectorises an axpy 32 lanes a pass (two AVX-512 registers) and finishes with 4-lane
# and scalar remainder loops, which at 150 points did ~45 % of the instructions of each pass.
# The padded entries are finite, never feed a real output, and every real output element is the
# same sum in the same order (bit-identical).
VECTOR_PAD = 32
assert VECTOR_PAD % BLOCK == 0, "the padded rows must hold whole transposed blocks"


def padded_length(length: int) -> int:
    """length rounded up to a multiple of VECTOR_PAD: how long the kernel's padded rows are."""
    return -(-length // VECTOR_PAD) * VECTOR_PAD


_padded = njit(cache=True, nogil=True)(padded_length)  # the same rule inside the kernel


@njit(cache=True, nogil=True, fastmath=False)
def _exp_neg_row(  # pragma: no cover - compiled
    s: np.ndarray,
    p: np.ndarray,
    i: int,
    bits: np.ndarray,
    bits_f: np.ndarray,
    e_bias: np.floating,
    e_shift: np.floating,
    cst: np.ndarray,
    m: int,
) -> None:
    """p[i, j] = exp(-min(s[j], cap)) for j < m, s >= 0; 2^-k built in `bits` (a view: bits_f).

    e_bias and e_shift are the exponent bias and 2^(mantissa bits), both in the RPM dtype.
    """
    log2e, half, ln2_hi, ln2_lo, cap = cst[0], cst[1], cst[2], cst[3], cst[4]
    c0, c1, c2, c3, c4, c5 = cst[5], cst[6], cst[7], cst[8], cst[9], cst[10]
    c6, c7, c8, c9, c10 = cst[11], cst[12], cst[13], cst[14], cst[15]
    # Two independent chains a pass, element j and element j + h: the polynomial is a chain of
    # 20 dependent operations, and a CPU whose scheduler holds one chain at a time (AVX2 EPYC,
    # 128-bit units) waited on its latency. Each element gets the same operations in the same
    # order as one chain a pass (bit-identical): 2.70 -> 2.10 ns an element there.
    h = m // 2
    for j in range(h):
        v = min(s[j], cap)
        w = min(s[j + h], cap)
        kv = np.floor(v * log2e + half)
        kw = np.floor(w * log2e + half)
        rv = kv * ln2_lo - (v - kv * ln2_hi)  # -v = -k ln2 + r, |r| <= ln2 / 2
        rw = kw * ln2_lo - (w - kw * ln2_hi)
        pv = c10
        pw = c10
        pv = pv * rv + c9
        pw = pw * rw + c9
        pv = pv * rv + c8
        pw = pw * rw + c8
        pv = pv * rv + c7
        pw = pw * rw + c7
        pv = pv * rv + c6
        pw = pw * rw + c6
        pv = pv * rv + c5
        pw = pw * rw + c5
        pv = pv * rv + c4
        pw = pw * rw + c4
        pv = pv * rv + c3
        pw = pw * rw + c3
        pv = pv * rv + c2
        pw = pw * rw + c2
        pv = pv * rv + c1
        pw = pw * rw + c1
        pv = pv * rv + c0
        pw = pw * rw + c0
        s[j] = pv
        s[j + h] = pw
        # The IEEE bit pattern of 2^-k, (bias - k) << shift, formed as a float product (exact:
        # a small integer times a power of two) and converted to the bits' integer type on
        # store. `int(kf)` would go through int64, which AVX2 cannot convert from float32 in
        # SIMD registers, and the whole loop ran scalar (2.4 ns a point instead of ~0.3).
        bits[j] = (e_bias - kv) * e_shift
        bits[j + h] = (e_bias - kw) * e_shift
    for j in range(2 * h, m):  # an odd m's last element (the kernel's padded rows are even)
        v = min(s[j], cap)
        kv = np.floor(v * log2e + half)
        rv = kv * ln2_lo - (v - kv * ln2_hi)
        pv = c10
        for c in (c9, c8, c7, c6, c5, c4, c3, c2, c1, c0):
            pv = pv * rv + c
        s[j] = pv
        bits[j] = (e_bias - kv) * e_shift
    for j in range(m):
        p[i, j] = s[j] * bits_f[j]


@njit(cache=True, nogil=True, fastmath=False)
def _distance_row(  # pragma: no cover - compiled
    fx: np.ndarray,
    xs: np.ndarray,
    ys: np.ndarray,
    gy: np.ndarray,
    srow: np.ndarray,
    i: int,
    m: int,
    inv2t: np.floating,
) -> None:
    """srow[j] = (|f(x_i) - y_j| + |x_i - g(y_j)|) / 2T for j < m (the affinity's exponent).

    A function of its own so that LLVM vectorises it: inside the large kernel the same loop was
    left scalar (one vsqrtss a pair instead of vsqrtps on eight), measured from the assembly.
    """
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


@njit(cache=True, nogil=True, fastmath=False)
def _add_weighted_rows(  # pragma: no cover - compiled
    mat: np.ndarray, w: np.ndarray, out: np.ndarray, rows: int, length: int
) -> None:
    """out[x] += mat[r, x] * w[r] for r = 0 .. rows-1 in that order, x < length.

    Four rows per pass over `out`, each written as (((out + a) + b) + c) + d: the same sums in
    the same order as one row at a time (bit-identical under strict IEEE), but `out` is loaded
    and stored a quarter as often, which is what bounds these axpys (they are load/store bound).
    """
    r = 0
    while r + 4 <= rows:
        m0, m1, m2, m3 = mat[r], mat[r + 1], mat[r + 2], mat[r + 3]
        w0, w1, w2, w3 = w[r], w[r + 1], w[r + 2], w[r + 3]
        for x in range(length):
            out[x] = out[x] + m0[x] * w0 + m1[x] * w1 + m2[x] * w2 + m3[x] * w3
        r += 4
    while r < rows:
        m0, w0 = mat[r], w[r]
        for x in range(length):
            out[x] = out[x] + m0[x] * w0
        r += 1


@njit(cache=True, nogil=True, fastmath=False)
def _add_weighted_rows3(  # pragma: no cover
    mat: np.ndarray,
    w0v: np.ndarray,
    w1v: np.ndarray,
    w2v: np.ndarray,
    o0: np.ndarray,
    o1: np.ndarray,
    o2: np.ndarray,
    rows: int,
    length: int,
) -> None:
    """`_add_weighted_rows` for three (weights, out) pairs in one pass over `mat`.

    Each out gets exactly the sums, in exactly the order, of its own `_add_weighted_rows`
    call (bit-identical); `mat` is read once instead of three times.
    """
    r = 0
    while r + 4 <= rows:
        m0, m1, m2, m3 = mat[r], mat[r + 1], mat[r + 2], mat[r + 3]
        a0, a1, a2, a3 = w0v[r], w0v[r + 1], w0v[r + 2], w0v[r + 3]
        b0, b1, b2, b3 = w1v[r], w1v[r + 1], w1v[r + 2], w1v[r + 3]
        c0, c1, c2, c3 = w2v[r], w2v[r + 1], w2v[r + 2], w2v[r + 3]
        for x in range(length):
            v0, v1, v2, v3 = m0[x], m1[x], m2[x], m3[x]
            o0[x] = o0[x] + v0 * a0 + v1 * a1 + v2 * a2 + v3 * a3
            o1[x] = o1[x] + v0 * b0 + v1 * b1 + v2 * b2 + v3 * b3
            o2[x] = o2[x] + v0 * c0 + v1 * c1 + v2 * c2 + v3 * c3
        r += 4
    while r < rows:
        m0 = mat[r]
        a0, b0, c0 = w0v[r], w1v[r], w2v[r]
        for x in range(length):
            v0 = m0[x]
            o0[x] = o0[x] + v0 * a0
            o1[x] = o1[x] + v0 * b0
            o2[x] = o2[x] + v0 * c0
        r += 1


@njit(cache=True, nogil=True, fastmath=False)
def _add_weighted_rows4(  # pragma: no cover
    mat: np.ndarray,
    w0v: np.ndarray,
    w1v: np.ndarray,
    w2v: np.ndarray,
    w3v: np.ndarray,
    o0: np.ndarray,
    o1: np.ndarray,
    o2: np.ndarray,
    o3: np.ndarray,
    rows: int,
    length: int,
) -> None:
    """`_add_weighted_rows3` for four (weights, out) pairs (bit-identical to four calls).

    Written out again rather than looping over outputs: with the outputs unrolled LLVM
    vectorises the x loop; a loop over a runtime number of outputs would be the inner one.
    """
    r = 0
    while r + 4 <= rows:
        m0, m1, m2, m3 = mat[r], mat[r + 1], mat[r + 2], mat[r + 3]
        a0, a1, a2, a3 = w0v[r], w0v[r + 1], w0v[r + 2], w0v[r + 3]
        b0, b1, b2, b3 = w1v[r], w1v[r + 1], w1v[r + 2], w1v[r + 3]
        c0, c1, c2, c3 = w2v[r], w2v[r + 1], w2v[r + 2], w2v[r + 3]
        d0, d1, d2, d3 = w3v[r], w3v[r + 1], w3v[r + 2], w3v[r + 3]
        for x in range(length):
            v0, v1, v2, v3 = m0[x], m1[x], m2[x], m3[x]
            o0[x] = o0[x] + v0 * a0 + v1 * a1 + v2 * a2 + v3 * a3
            o1[x] = o1[x] + v0 * b0 + v1 * b1 + v2 * b2 + v3 * b3
            o2[x] = o2[x] + v0 * c0 + v1 * c1 + v2 * c2 + v3 * c3
            o3[x] = o3[x] + v0 * d0 + v1 * d1 + v2 * d2 + v3 * d3
        r += 4
    while r < rows:
        m0 = mat[r]
        a0, b0, c0, d0 = w0v[r], w1v[r], w2v[r], w3v[r]
        for x in range(length):
            v0 = m0[x]
            o0[x] = o0[x] + v0 * a0
            o1[x] = o1[x] + v0 * b0
            o2[x] = o2[x] + v0 * c0
            o3[x] = o3[x] + v0 * d0
        r += 1


@njit(cache=True, nogil=True, fastmath=False)
def rpm_kernel(
    idx: np.ndarray,
    x_an3: np.ndarray,
    n_a: np.ndarray,
    g_ank: np.ndarray,
    gt_akn: np.ndarray,
    mu_ak: np.ndarray,
    h_ak3: np.ndarray,
    y_m3: np.ndarray,
    g_y: np.ndarray,
    gt_y: np.ndarray,
    mu_y: np.ndarray,
    h_y: np.ndarray,
    lam_i: np.ndarray,
    inv2t_i: np.ndarray,
    cst: np.ndarray,
    bits: np.ndarray,
    bits_f: np.ndarray,
    e_bias: np.floating,
    e_shift: np.floating,
    a_out: np.ndarray,
    b_out_b: np.ndarray,
    corner_b: np.ndarray,
    rule: int,
    sinkhorn_iters: int,
    stop_after: int,
    mu_a64: np.ndarray,
    theta_a64: np.ndarray,
    mu_y64: np.ndarray,
    theta_y64: np.ndarray,
    scale: float,
    e_f: np.ndarray,
    e_g: np.ndarray,
    costs: np.ndarray,
    corr: np.ndarray,
    failed: np.ndarray,
    first_only: bool,
    pre_xhat: np.ndarray,
    pre_yhat: np.ndarray,
    pre_wf: np.ndarray,
    pre_wg: np.ndarray,
    pre_done: np.ndarray,
) -> None:  # pragma: no cover - compiled
    """Bidirectional TPS-RPM for every demo b of a chunk against the scene (see `rpm_batch`).

    The first iteration's affinity, Sinkhorn and targets do not read the scene's TPS basis, so
    they can run while it is being factorised: with `first_only` the kernel stops each demo a
    there and keeps its targets and inlier masses in pre_*[a], setting pre_done[a]; a later
    call (first_only False) resumes a demo with pre_done[a] from them, with the same values in
    the same order as an uninterrupted run (bit-identical, tested). pre_* may be empty (0 rows).
    """
    dt_one = cst[_K_ONE]
    zero = cst[_K_ZERO]
    prior, cutoff, tiny = cst[_K_PRIOR], cst[_K_CUTOFF], cst[_K_TINY]
    m = y_m3.shape[0]
    ky = gt_y.shape[0]
    nb = idx.shape[0]
    n_max = x_an3.shape[1]
    m_pad = _padded(m)
    # numba does not check bounds: inputs not padded as `rpm` pads them would be overrun
    if bits.shape[0] < m_pad or g_y.shape[1] < _padded(ky) or gt_y.shape[1] < m_pad:
        raise ValueError("rpm_kernel: scene inputs or scratch not padded (padded_length)")
    if g_ank.shape[2] < _padded(n_max + 4) or gt_akn.shape[2] < _padded(n_max):
        raise ValueError("rpm_kernel: demo TPS bases not padded (padded_length)")
    ys = np.zeros((4, m_pad), cst.dtype)  # scene SoA, row 3 = 1
    for j in range(m):
        for d in range(3):
            ys[d, j] = y_m3[j, d]
        ys[3, j] = dt_one
    # per-demo scratch, sized for the largest demo
    xs = np.empty((3, n_max), cst.dtype)
    fx = np.zeros((3, _padded(n_max)), cst.dtype)
    gy = np.zeros((3, m_pad), cst.dtype)
    # p, pt and the sums over them have VECTOR_PAD-padded rows, zeroed once: the padding only
    # ever holds zeros, earlier real values or the affinity of the zero-padded scene points
    # (finite), and lands only in padded sums
    # (rows too: p^T is copied in BLOCK x BLOCK blocks, which may cover up to BLOCK - 1 rows of
    # p beyond n and of p^T beyond m; VECTOR_PAD is a multiple of BLOCK)
    p = np.zeros((_padded(n_max), m_pad), cst.dtype)
    pt = np.zeros((m_pad, _padded(n_max)), cst.dtype)
    srow = np.empty(m_pad, cst.dtype)
    rd = np.zeros(_padded(n_max), cst.dtype)
    r = np.empty(n_max, cst.dtype)
    c = np.empty(m, cst.dtype)
    c_prev = np.empty(m, cst.dtype)
    col = np.zeros(m_pad, cst.dtype)
    cy = np.empty((4, m), cst.dtype)
    fwd = np.zeros((4, _padded(n_max)), cst.dtype)
    bwd = np.zeros((4, m_pad), cst.dtype)
    rx = np.empty((4, n_max), cst.dtype)  # r_i x_i and r_i: the backward weights
    xhat = np.empty((3, n_max), cst.dtype)
    yhat = np.empty((3, m), cst.dtype)
    wf = np.empty(n_max, cst.dtype)
    wg = np.empty(m, cst.dtype)
    ef = np.zeros((3, _padded(n_max + 4)), cst.dtype)
    eg = np.zeros((3, _padded(ky)), cst.dtype)
    for b in range(nb):
        a = idx[b]
        n = n_a[a]
        k = n + 4
        n_pad = _padded(n)
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
        resume = pre_done.shape[0] > 0 and pre_done[a] and not first_only
        for it in range(lam_i.shape[0]):
            if it == 0 and resume:
                for i in range(n):
                    wf[i] = pre_wf[a, i]
                    for d in range(3):
                        xhat[d, i] = pre_xhat[a, d, i]
                for j in range(m):
                    wg[j] = pre_wg[a, j]
                    for d in range(3):
                        yhat[d, j] = pre_yhat[a, d, j]
            else:
                inv2t = inv2t_i[it]
                # 1. affinity p_ij = exp(-(|f(x_i) - y_j| + |x_i - g(y_j)|) / 2T), exponent capped
                for i in range(n):
                    _distance_row(fx, xs, ys, gy, srow, i, m_pad, inv2t)
                    _exp_neg_row(srow, p, i, bits, bits_f, e_bias, e_shift, cst, m_pad)
                # p^T too: with both layouts every product below is an axpy along contiguous
                # memory, which vectorises under strict IEEE (a dot-product reduction does not)
                for i0 in range(0, n, BLOCK):
                    for j0 in range(0, m, BLOCK):
                        transpose_block(p, i0, j0, pt)
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
                    rd[:n_pad] = zero
                    _add_weighted_rows(pt, c, rd, m, n_pad)
                    for i in range(n):
                        r[i] = dt_one / (rd[i] + prior * c_out)
                    col[:] = zero
                    _add_weighted_rows(p, r, col, n, m_pad)
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
                fwd[:, :n_pad] = zero
                bwd[:, :] = zero
                for i in range(n):
                    for d in range(3):
                        rx[d, i] = r[i] * xs[d, i]
                    rx[3, i] = r[i]
                _add_weighted_rows4(
                    pt, cy[0], cy[1], cy[2], cy[3], fwd[0], fwd[1], fwd[2], fwd[3], m, n_pad
                )
                _add_weighted_rows4(
                    p, rx[0], rx[1], rx[2], rx[3], bwd[0], bwd[1], bwd[2], bwd[3], n, m_pad
                )
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
                if first_only:
                    for i in range(n):
                        pre_wf[a, i] = wf[i]
                        for d in range(3):
                            pre_xhat[a, d, i] = xhat[d, i]
                    for j in range(m):
                        pre_wg[a, j] = wg[j]
                        for d in range(3):
                            pre_yhat[a, d, j] = yhat[d, j]
                    pre_done[a] = True
                    break
                if stop_after == 2:
                    continue
            # 4. TPS fits of f and g
            lam = lam_i[it]
            if rule == 2:
                ok = _fit_weighted(g_ank[a, :n, :k], mu_ak[a, :k], h_ak3[a, :k], xhat, wf, lam, ef)
                ok = ok and _fit_weighted(g_y[:, :ky], mu_y, h_y, yhat, wg, lam, eg)
                if not ok:
                    break
            else:
                _fit_unweighted(g_ank[a], mu_ak[a], h_ak3[a], xhat, lam, dt_one, ef, n, k)
                _fit_unweighted(g_y, mu_y, h_y, yhat, lam, dt_one, eg, m, ky)
            _apply(gt_akn[a], ef, fx, n_pad, k)
            _apply(gt_y, eg, gy, m_pad, ky)
        if first_only:
            continue
        failed[b] = not ok
        if stop_after >= 4:
            weighted = rule == 2
            map_f, inl_f, res_f = _match_costs(fx, xhat, fwd, wf, weighted, tiny, n)
            map_g, inl_g, res_g = _match_costs(gy, yhat, bwd, wg, weighted, tiny, m)
            bend_f, aff_f = _spline_costs(mu_a64[a], theta_a64[a], ef, k)
            bend_g, aff_g = _spline_costs(mu_y64, theta_y64, eg, ky)
            row = (map_f, map_g, bend_f, bend_g, inl_f / max(n, 1), inl_g / m, aff_f, aff_g)
            for q in range(8):
                costs[b, q] = row[q]
            costs[b, 8] = res_f * scale
            costs[b, 9] = res_g * scale
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
def _match_costs(  # pragma: no cover - compiled
    w3: np.ndarray,
    hat3: np.ndarray,
    sums4: np.ndarray,
    w: np.ndarray,
    weighted: bool,
    tiny: np.floating,
    n: int,
) -> tuple[float, float, float]:
    """(mapping cost, inlier mass, mean residual) of one direction, in float64.

    w3: warped points, hat3: their targets, sums4: the weighted sums behind the targets (row 3 the
    inlier mass), w: inlier masses (3, n) / (n,) in the RPM dtype. Mapping cost: sum over points
    of |w(x) - x^|^2 weighted by w when `weighted` (else 1); residual: the w-weighted mean
    distance from w(x) to the match centroid sums4[:3] / sums4[3].
    """
    mapping = 0.0
    mass = 0.0
    residual = 0.0
    for i in range(n):
        wi = np.float64(w[i])
        sq = 0.0
        res_sq = 0.0
        denom = max(sums4[3, i], tiny)
        for d in range(3):
            x = np.float64(w3[d, i])
            diff = x - np.float64(hat3[d, i])
            sq += diff * diff
            centroid = np.float64(sums4[d, i] / denom)  # in the RPM dtype, as the targets are
            res_sq += (x - centroid) * (x - centroid)
        mapping += wi * sq if weighted else sq
        mass += wi
        residual += wi * math.sqrt(res_sq)
    return mapping, mass, residual / max(mass, 1e-30)


@njit(cache=True, nogil=True, fastmath=False)
def _spline_costs(  # pragma: no cover - compiled
    mu_k: np.ndarray, theta_pk: np.ndarray, e_3k: np.ndarray, k: int
) -> tuple[float, float]:
    """(bending energy sum mu_q |e_q|^2, |B - I|_F) of one spline, in float64."""
    bend = 0.0
    for q in range(k):
        for d in range(3):
            e = np.float64(e_3k[d, q])
            bend += mu_k[q] * (e * e)
    aff = 0.0
    for row in range(3):
        for d in range(3):
            b = 0.0
            for q in range(k):
                b += theta_pk[1 + row, q] * np.float64(e_3k[d, q])
            dev = b - (1.0 if row == d else 0.0)
            aff += dev * dev
    return bend, math.sqrt(aff)


@njit(cache=True, nogil=True, fastmath=False)
def _fit_unweighted(  # pragma: no cover
    g_nk: np.ndarray,
    mu_k: np.ndarray,
    h_k3: np.ndarray,
    target_3n: np.ndarray,
    lam: np.floating,
    one: np.floating,
    e_3k: np.ndarray,
    n: int,
    k: int,
) -> None:
    """e = (G^T x^ + h) / (1 + lambda mu), e stored (3, k); vectorised over k.

    G's rows and e are VECTOR_PAD-padded (zeros beyond k in G): the padding of e stays zero.
    """
    for d in range(3):
        for q in range(k):
            e_3k[d, q] = h_k3[q, d]
    # e[d, q] += sum_i G[i, q] x^[d, i], i ascending
    t = target_3n
    _add_weighted_rows3(g_nk, t[0], t[1], t[2], e_3k[0], e_3k[1], e_3k[2], n, _padded(k))
    for q in range(k):
        s = one / (one + lam * mu_k[q])
        for d in range(3):
            e_3k[d, q] *= s


@njit(cache=True, nogil=True, fastmath=False)
def _apply(  # pragma: no cover - compiled
    gt_kn: np.ndarray, e_3k: np.ndarray, out_3n: np.ndarray, n: int, k: int
) -> None:
    """out = G e, out stored (3, n); vectorised over n (a padded length: G^T's rows are)."""
    out_3n[:, :n] = 0
    # out[d, i] = sum_q G[i, q] e[d, q], q ascending
    e = e_3k
    _add_weighted_rows3(gt_kn, e[0], e[1], e[2], out_3n[0], out_3n[1], out_3n[2], k, n)


@njit(cache=True, nogil=True, fastmath=False)
def _fit_weighted(  # pragma: no cover
    g_nk: np.ndarray,
    mu_k: np.ndarray,
    h_k3: np.ndarray,
    target_3n: np.ndarray,
    w_n: np.ndarray,
    lam: np.floating,
    e_3k: np.ndarray,
) -> bool:
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
