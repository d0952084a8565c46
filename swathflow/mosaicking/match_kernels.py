"""Compiled kernels of the overlap matching (numba, ``nogil``, ``cache=True``): the paper's
minimum-mean-grey-difference cost over all integer shifts and the least-squares polish, so
the overlaps match on every core through threads (the numpy version held the GIL in its
per-shift partitions). A block's noise and texture checks are in
swathflow.mosaicking.block_kernels."""
from __future__ import annotations

import numpy as np

from numba import njit
from swathflow.mosaicking.kernels import _b3  # the cubic B-spline, written once

__all__ = ["mmgd_costs", "shift_block", "gauss_newton", "polish"]


@njit(cache=True, nogil=True)
def _select(a, lo, hi, k):
    """Move the ``k``-th smallest of ``a[lo:hi + 1]`` to ``a[k]``, smaller ones before it
    and larger ones after (quickselect in place: median-of-three pivot, a branch-free
    Lomuto partition: 6 against 15 us for 1152 random values with Hoare's, whose
    comparisons the processor mispredicts half the time)."""
    while hi > lo:
        mid = (lo + hi) // 2
        if a[mid] < a[lo]:
            a[mid], a[lo] = a[lo], a[mid]
        if a[hi] < a[lo]:
            a[hi], a[lo] = a[lo], a[hi]
        if a[mid] < a[hi]:
            a[hi], a[mid] = a[mid], a[hi]
        pivot = a[hi]                     # the median of the three
        store = lo
        for i in range(lo, hi):
            v = a[i]
            w = a[store]
            c = v < pivot
            a[i] = w if c else v
            a[store] = v if c else w
            store += 1 if c else 0
        a[store], a[hi] = a[hi], a[store]
        if k == store:
            return
        if k < store:
            hi = store - 1
        elif store > lo:
            lo = store + 1
        else:
            # the pivot is the smallest value left: its copies to the front in one more
            # pass (many equal values, e.g. a flat area of integer data, would otherwise
            # shrink the range by one a pass)
            e = lo + 1
            for i in range(lo + 1, hi + 1):
                v = a[i]
                w = a[e]
                c = v <= pivot
                a[i] = w if c else v
                a[e] = v if c else w
                e += 1 if c else 0
            if k < e:
                return
            lo = e


@njit(cache=True, nogil=True)
def _median(a, n):
    """The median of ``a[:n]`` as np.median takes it (mean of the two middle values for
    even ``n``); reorders ``a[:n]``."""
    k = n // 2
    _select(a, 0, n - 1, k)
    if n % 2:
        return a[k]
    lo = a[0]
    for q in range(1, k):
        if a[q] > lo:
            lo = a[q]
    return 0.5 * (lo + a[k])


@njit(cache=True, nogil=True)
def mmgd_costs(ref, ref_ok, mov, mov_ok, S, min_pixels, stride=1):
    """``cost[S + dr, S + dc]``: mean ``|d - median(d)|`` of ``d = ref[x] - mov[x + s]`` over
    the pixels valid in both, for every shift ``s = (dr, dc)`` with ``|dr|, |dc| <= S``
    (``mov`` is read with a margin of ``S``); ``inf`` where fewer than ``min_pixels``.
    ``stride > 1``: over the pixels of every ``stride``-th row and column of ``ref`` only
    (the shifts stay whole pixels)."""
    h, w = ref.shape
    n_s = 2 * S + 1
    cost = np.full((n_s, n_s), np.inf)
    buf = np.empty(h * w)
    # the valid pixels of ref (every stride-th row and column), in row order, once: their
    # values and their places in mov at shift (0, 0); each shift then reads mov at those
    # places plus one offset, without a branch (the same differences in the same order)
    w_m = mov.shape[1]
    m_flat = mov.ravel()
    ok_flat = mov_ok.ravel()
    r_val = np.empty(h * w)
    r_at = np.empty(h * w, np.int64)
    n_ref = 0
    for r in range(0, h, stride):
        for c in range(0, w, stride):
            if ref_ok[r, c]:
                r_val[n_ref] = ref[r, c]
                r_at[n_ref] = r * w_m + c
                n_ref += 1
    for i in range(n_s):
        for j in range(n_s):
            off = i * w_m + j
            n = 0
            for q in range(n_ref):
                at = r_at[q] + off
                buf[n] = r_val[q] - m_flat[at]
                n += 1 if ok_flat[at] else 0
            if n < min_pixels or n == 0:
                continue
            med = _median(buf, n)
            s = 0.0
            for k in range(n):
                s += abs(buf[k] - med)
            cost[i, j] = s / n
    return cost


@njit(cache=True, nogil=True)
def shift_block(coef, pad, h, w, d0, d1, out, tmp):
    """``out[x] = img[x - d]`` (h, w) from ``coef``, the cubic B-spline coefficients of
    ``img`` padded by ``pad`` edge pixels: the separable 4-tap sum (the recipe of
    swathflow.mosaicking.matching._Shifter). False (``out`` untouched) when the shift
    reaches past the padding."""
    f0, f1 = -d0, -d1
    a0, a1 = int(np.floor(f0)), int(np.floor(f1))
    if abs(a0) > pad - 3 or abs(a1) > pad - 3:
        return False
    k0 = np.empty(4)
    k1 = np.empty(4)
    for j in range(4):
        k0[j] = _b3(f0 - a0 - (j - 1))
        k1[j] = _b3(f1 - a1 - (j - 1))
    r0, c0 = pad + a0 - 1, pad + a1 - 1
    for r in range(h + 3):
        for c in range(w):
            s = 0.0
            for j in range(4):
                s += k1[j] * coef[r0 + r, c0 + c + j]
            tmp[r, c] = s
    for r in range(h):
        for c in range(w):
            s = 0.0
            for j in range(4):
                s += k0[j] * tmp[r + j, c]
            out[r, c] = s
    return True


@njit(cache=True, nogil=True)
def _grad(a, r, c, axis):
    """np.gradient of ``a`` at (r, c) along ``axis`` (central, one-sided at the edges)."""
    n = a.shape[axis]
    i = r if axis == 0 else c
    if n < 2:
        return 0.0
    if i == 0:
        return a[1, c] - a[0, c] if axis == 0 else a[r, 1] - a[r, 0]
    if i == n - 1:
        return a[n - 1, c] - a[n - 2, c] if axis == 0 else a[r, n - 1] - a[r, n - 2]
    return (0.5 * (a[r + 1, c] - a[r - 1, c]) if axis == 0 else
            0.5 * (a[r, c + 1] - a[r, c - 1]))


@njit(cache=True, nogil=True)
def _inverse(n):
    """Inverse of a small symmetric matrix by Gauss-Jordan with partial pivoting; a
    matrix of NaN when it is singular."""
    k = n.shape[0]
    a = n.copy()
    inv = np.eye(k)
    for col in range(k):
        p = col
        for r in range(col + 1, k):
            if abs(a[r, col]) > abs(a[p, col]):
                p = r
        if not abs(a[p, col]) > 1e-300:
            return np.full((k, k), np.nan)
        if p != col:
            for j in range(k):
                a[col, j], a[p, j] = a[p, j], a[col, j]
                inv[col, j], inv[p, j] = inv[p, j], inv[col, j]
        piv = a[col, col]
        for j in range(k):
            a[col, j] /= piv
            inv[col, j] /= piv
        for r in range(k):
            if r != col and a[r, col] != 0.0:
                f = a[r, col]
                for j in range(k):
                    a[r, j] -= f * a[col, j]
                    inv[r, j] -= f * inv[col, j]
    return inv


@njit(cache=True, nogil=True)
def _normal_planar(rw, rows, cols, y, rad, g, o):
    """The upper triangle of the normal matrix and the right-hand side of one Gauss-Newton
    step of :func:`gauss_newton` with a planar radiometric term (6 unknowns), each sum in
    scalars (the same terms in the same order as the general loop, so the same values)."""
    n00 = n01 = n02 = n03 = n04 = n05 = 0.0
    n11 = n12 = n13 = n14 = n15 = 0.0
    n22 = n23 = n24 = n25 = 0.0
    n33 = n34 = n35 = n44 = n45 = n55 = 0.0
    b0 = b1 = b2 = b3 = b4 = b5 = 0.0
    o0, o1, o2 = o[0], o[1], o[2]
    for q in range(rows.shape[0]):
        r, c = rows[q], cols[q]
        v = rw[r, c]
        a0 = -g * _grad(rw, r, c, 0)
        a1 = -g * _grad(rw, r, c, 1)
        a2 = v
        a3, a4, a5 = rad[q, 0], rad[q, 1], rad[q, 2]
        model = g * v
        model += a3 * o0
        model += a4 * o1
        model += a5 * o2
        res = y[q] - model
        b0 += a0 * res
        n00 += a0 * a0
        n01 += a0 * a1
        n02 += a0 * a2
        n03 += a0 * a3
        n04 += a0 * a4
        n05 += a0 * a5
        b1 += a1 * res
        n11 += a1 * a1
        n12 += a1 * a2
        n13 += a1 * a3
        n14 += a1 * a4
        n15 += a1 * a5
        b2 += a2 * res
        n22 += a2 * a2
        n23 += a2 * a3
        n24 += a2 * a4
        n25 += a2 * a5
        b3 += a3 * res
        n33 += a3 * a3
        n34 += a3 * a4
        n35 += a3 * a5
        b4 += a4 * res
        n44 += a4 * a4
        n45 += a4 * a5
        b5 += a5 * res
        n55 += a5 * a5
    nm = np.zeros((6, 6))
    nm[0, 0], nm[0, 1], nm[0, 2], nm[0, 3], nm[0, 4], nm[0, 5] = n00, n01, n02, n03, n04, n05
    nm[1, 1], nm[1, 2], nm[1, 3], nm[1, 4], nm[1, 5] = n11, n12, n13, n14, n15
    nm[2, 2], nm[2, 3], nm[2, 4], nm[2, 5] = n22, n23, n24, n25
    nm[3, 3], nm[3, 4], nm[3, 5] = n33, n34, n35
    nm[4, 4], nm[4, 5] = n44, n45
    nm[5, 5] = n55
    b = np.empty(6)
    b[0], b[1], b[2], b[3], b[4], b[5] = b0, b1, b2, b3, b4, b5
    return nm, b


@njit(cache=True, nogil=True)
def gauss_newton(coef, pad, h, w, rows, cols, y, rad, d_start, iterations, tol):
    """The least-squares polish of swathflow.mosaicking.matching.gradient_refine: fit
    ``y = g * ref[x - d] + rad @ o`` at the pixels (rows, cols) by Gauss-Newton from
    ``d_start``, ``ref`` given by its spline coefficients ``coef`` (padded by ``pad``).
    Returns (status, d, g, o, cov, rms, shifted): status 0 done, 1 singular normal
    matrix, 2 the shift left the padding (the caller falls back); ``shifted`` is
    ``ref[x - d]`` at the final ``d``."""
    m = rows.shape[0]
    p = rad.shape[1]
    k = 3 + p
    d = d_start.copy()
    g = 1.0
    o = np.zeros(p)
    cov = np.full((k, k), np.nan)
    rw = np.empty((h, w))
    tmp = np.empty((h + 3, w))
    a = np.empty(k)
    for _ in range(iterations):
        if not shift_block(coef, pad, h, w, d[0], d[1], rw, tmp):
            return 2, d, g, o, cov, np.inf, rw
        if p == 3:
            nm, b = _normal_planar(rw, rows, cols, y, rad, g, o)
        else:
            nm = np.zeros((k, k))
            b = np.zeros(k)
            for q in range(m):
                r, c = rows[q], cols[q]
                v = rw[r, c]
                a[0] = -g * _grad(rw, r, c, 0)
                a[1] = -g * _grad(rw, r, c, 1)
                a[2] = v
                model = g * v
                for j in range(p):
                    a[3 + j] = rad[q, j]
                    model += rad[q, j] * o[j]
                res = y[q] - model
                for i in range(k):
                    b[i] += a[i] * res
                    for j in range(i, k):
                        nm[i, j] += a[i] * a[j]
        for i in range(k):
            for j in range(i):
                nm[i, j] = nm[j, i]
        cov = _inverse(nm)
        if np.isnan(cov[0, 0]):
            return 1, d, g, o, cov, np.inf, rw
        dx = np.zeros(k)
        for i in range(k):
            for j in range(k):
                dx[i] += cov[i, j] * b[j]
        d[0] += dx[0]
        d[1] += dx[1]
        g += dx[2]
        for j in range(p):
            o[j] += dx[3 + j]
        if abs(dx[0]) < tol and abs(dx[1]) < tol:
            break
    if not shift_block(coef, pad, h, w, d[0], d[1], rw, tmp):
        return 2, d, g, o, cov, np.inf, rw
    ss = 0.0
    for q in range(m):
        model = g * rw[rows[q], cols[q]]
        for j in range(p):
            model += rad[q, j] * o[j]
        ss += (y[q] - model) ** 2
    rms = np.sqrt(ss / max(m - k, 1))
    return 0, d, g, o, cov, rms, rw


@njit(cache=True, nogil=True)
def polish(coef, pad, mov, mask, planar, d_start, iterations, tol):
    """:func:`gauss_newton` over the pixels of ``mask`` (row order): ``y = mov`` there,
    the radiometric columns 1 and, with ``planar``, the rows and columns about their mean
    over the block's height and width (the values numpy gives: integer sums are exact)."""
    h, w = mask.shape
    m = 0
    sr = sc = 0
    for r in range(h):
        for c in range(w):
            if mask[r, c]:
                m += 1
                sr += r
                sc += c
    rows = np.empty(m, np.int64)
    cols = np.empty(m, np.int64)
    y = np.empty(m)
    rad = np.empty((m, 3 if planar else 1))
    mr = sr / m if m else 0.0
    mc = sc / m if m else 0.0
    q = 0
    for r in range(h):
        for c in range(w):
            if mask[r, c]:
                rows[q], cols[q], y[q] = r, c, mov[r, c]
                rad[q, 0] = 1.0
                if planar:
                    rad[q, 1] = (r - mr) / max(h, 1)
                    rad[q, 2] = (c - mc) / max(w, 1)
                q += 1
    return gauss_newton(coef, pad, h, w, rows, cols, y, rad, d_start, iterations, tol)


@njit(cache=True, nogil=True)
def _row_invalid(m, k, c0, c1):
    """1 - the valid fraction of row ``k`` of ``m[:, c0:c1]`` (the bounds as variables:
    a literal argument would compile a specialisation of its own)."""
    n = 0
    for c in range(c0, c1):
        n += m[k, c]
    return 1.0 - n / (c1 - c0)


@njit(cache=True, nogil=True)
def _column_invalid(m, k, r0, r1):
    """1 - the valid fraction of column ``k`` of ``m[r0:r1]``."""
    n = 0
    for r in range(r0, r1):
        n += m[r, k]
    return 1.0 - n / (r1 - r0)


@njit(cache=True, nogil=True)
def valid_rectangle_bounds(m):
    """(r0, r1, c0, c1) of swathflow.mosaicking.matching.valid_rectangle (greedy: drop the
    border row or column with the largest invalid fraction until none is left);
    r1 == r0 when nothing is left."""
    r0, r1, c0, c1 = 0, m.shape[0], 0, m.shape[1]
    bad = np.empty(4)
    while r1 > r0 and c1 > c0:
        bad[0] = _row_invalid(m, r0, c0, c1)
        bad[1] = _row_invalid(m, r1 - 1, c0, c1)
        bad[2] = _column_invalid(m, c0, r0, r1)
        bad[3] = _column_invalid(m, c1 - 1, r0, r1)
        k = 0
        for q in range(1, 4):
            if bad[q] > bad[k]:
                k = q
        if bad[k] == 0.0:
            return r0, r1, c0, c1
        if k == 0:
            r0 += 1
        elif k == 1:
            r1 -= 1
        elif k == 2:
            c0 += 1
        else:
            c1 -= 1
    return r0, r0, c0, c0
