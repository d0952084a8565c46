"""The compiled steps of the lattice's cells (:mod:`.lattice`, numba): which of their
points are not yet known, their tests (the bilinear interpolation's miss at their edge
midpoints and centre), whether they lie off the raw image, and their children.

A cell is ``(r, c, sr, sc)``: a rectangle of output pixels from row ``r``, column ``c``,
``sr`` rows and ``sc`` columns across (power-of-two sides), corners at (r, c), (r, c + sc),
(r + sr, c), (r + sr, c + sc).
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

#: least distance (raw pixels) beyond the raw image's edge of a cell left unrefined
OFF_MARGIN_PX = 4.0

@njit(cache=True, nogil=True)
def _unknown(r, c, known):
    """The points of ``r, c`` not yet ``known``, each once; marks them known (the caller
    evaluates them at once)."""
    rr = np.empty(r.shape[0], np.int64)
    cc = np.empty(r.shape[0], np.int64)
    k = 0
    for i in range(r.shape[0]):
        if not known[r[i], c[i]]:
            known[r[i], c[i]] = True
            rr[k], cc[k] = r[i], c[i]
            k += 1
    return rr[:k], cc[:k]


@njit(cache=True, nogil=True)
def _store(values, r, c, x):
    """``values[r, c] = x`` for points ``r, c`` and their values ``x`` ``(n, 2)`` (numpy's
    indexed assignment costs ~20 us a call: a level's whole model call costs ~100)."""
    for i in range(r.shape[0]):
        values[r[i], c[i], 0] = x[i, 0]
        values[r[i], c[i], 1] = x[i, 1]


@njit(cache=True, nogil=True)
def _cell_unknown(cells, known, tests):
    """:func:`_unknown` of the corners of ``cells`` ``(n, 4)`` and, with ``tests``, of
    their test points (edge midpoints across a side of 2 or more, centre)."""
    n = cells.shape[0]
    r = np.empty(9 * n, np.int64)
    c = np.empty(9 * n, np.int64)
    k = 0
    for i in range(n):
        r0, c0, sr, sc = cells[i, 0], cells[i, 1], cells[i, 2], cells[i, 3]
        hr, hc = sr // 2, sc // 2
        # scalar stores: a tuple assigned to a slice made a view (and its reference
        # counting) and an array of the tuple per cell
        r[k], r[k + 1], r[k + 2], r[k + 3] = r0, r0, r0 + sr, r0 + sr
        c[k], c[k + 1], c[k + 2], c[k + 3] = c0, c0 + sc, c0, c0 + sc
        k += 4
        if tests and sc >= 2:
            r[k], c[k], r[k + 1], c[k + 1] = r0, c0 + hc, r0 + sr, c0 + hc
            k += 2
        if tests and sr >= 2:
            r[k], c[k], r[k + 1], c[k + 1] = r0 + hr, c0, r0 + hr, c0 + sc
            k += 2
        if tests and sr >= 2 and sc >= 2:
            r[k], c[k] = r0 + hr, c0 + hc
            k += 1
    return _unknown(r[:k], c[:k], known)


@njit(cache=True, nogil=True, inline="always")
def _miss(e0, e1, a0, a1):
    """The interpolation's miss at a point of exact value ``(e0, e1)`` against the
    interpolated ``(a0, a1)``: the larger of line and element; inf where NaN. Scalars
    only: an inlined helper taking arrays counts references to each at every call."""
    d0, d1 = abs(e0 - a0), abs(e1 - a1)
    if math.isnan(d0) or math.isnan(d1):
        return math.inf
    return max(d0, d1)


@njit(cache=True, nogil=True)
def _cell_tests(cells, v):
    """Test the cells ``(n, 4)`` (r, c, sr, sc) at their edge midpoints and centre (all
    known in ``v``): the error of interpolation across columns (top and bottom
    midpoints), across rows (left and right midpoints) and both (centre), NaN as inf, 0
    where a size is 1; the points' values ``(n, 9, 2)``: the corners (r, c), (r, c + sc),
    (r + sr, c), (r + sr, c + sc), then the test points (NaN where a test does not
    exist). Written with scalars (no row views of ``pts``, no arrays passed to helpers):
    numba counts references to every array view and argument at every cell."""
    n = cells.shape[0]
    err_c, err_r, err_m = np.zeros(n), np.zeros(n), np.zeros(n)
    pts = np.full((n, 9, 2), np.nan)
    for i in range(n):
        r, c, sr, sc = cells[i, 0], cells[i, 1], cells[i, 2], cells[i, 3]
        hr, hc = sr // 2, sc // 2
        a0, a1 = v[r, c, 0], v[r, c, 1]                       # the corners
        b0, b1 = v[r, c + sc, 0], v[r, c + sc, 1]
        c0, c1 = v[r + sr, c, 0], v[r + sr, c, 1]
        d0, d1 = v[r + sr, c + sc, 0], v[r + sr, c + sc, 1]
        pts[i, 0, 0], pts[i, 0, 1], pts[i, 1, 0], pts[i, 1, 1] = a0, a1, b0, b1
        pts[i, 2, 0], pts[i, 2, 1], pts[i, 3, 0], pts[i, 3, 1] = c0, c1, d0, d1
        if sc >= 2:
            t0, t1 = v[r, c + hc, 0], v[r, c + hc, 1]
            u0, u1 = v[r + sr, c + hc, 0], v[r + sr, c + hc, 1]
            pts[i, 4, 0], pts[i, 4, 1], pts[i, 5, 0], pts[i, 5, 1] = t0, t1, u0, u1
            err_c[i] = max(_miss(t0, t1, (a0 + b0) / 2, (a1 + b1) / 2),
                           _miss(u0, u1, (c0 + d0) / 2, (c1 + d1) / 2))
        if sr >= 2:
            t0, t1 = v[r + hr, c, 0], v[r + hr, c, 1]
            u0, u1 = v[r + hr, c + sc, 0], v[r + hr, c + sc, 1]
            pts[i, 6, 0], pts[i, 6, 1], pts[i, 7, 0], pts[i, 7, 1] = t0, t1, u0, u1
            err_r[i] = max(_miss(t0, t1, (a0 + c0) / 2, (a1 + c1) / 2),
                           _miss(u0, u1, (b0 + d0) / 2, (b1 + d1) / 2))
        if sr >= 2 and sc >= 2:
            t0, t1 = v[r + hr, c + hc, 0], v[r + hr, c + hc, 1]
            pts[i, 8, 0], pts[i, 8, 1] = t0, t1
            err_m[i] = _miss(t0, t1, (a0 + b0 + c0 + d0) / 4, (a1 + b1 + c1 + d1) / 4)
    return err_c, err_r, err_m, pts


@njit(cache=True, nogil=True)
def _off_image(points, err, nl, ne):
    """Cells whose test points and corners ``points`` ``(k, 9, 2)`` all lie beyond one
    edge of the raw image (``nl`` lines x ``ne`` elements) by more than ``OFF_MARGIN_PX``
    plus twice the cell's interpolation error there: every pixel of such a cell is off
    the image (NaN), however its coordinates are interpolated. A NaN point (or a test
    that does not exist) never qualifies on its coordinate."""
    k = points.shape[0]
    out = np.zeros(k, np.bool_)
    for i in range(k):
        m = OFF_MARGIN_PX + 2 * err[i] if math.isfinite(err[i]) else math.inf
        off = False
        for q in range(2):
            lo, hi = math.inf, -math.inf
            nan = False
            for p in range(points.shape[1]):
                x = points[i, p, q]
                if math.isnan(x):
                    nan = True
                    break
                lo, hi = min(lo, x), max(hi, x)
            edge = (nl if q == 0 else ne) - 0.5
            if not nan and (lo > edge + m or hi < -0.5 - m):
                off = True
        out[i] = off
    return out


@njit(cache=True, nogil=True)
def _children(cells, split_r, split_c):
    """The halves (or quarters) of cells split across rows and / or columns (the
    cells with neither flag are kept whole): first every cell's top-left part, then the
    lower, right and lower-right parts, each in the cells' order."""
    n = cells.shape[0]
    m = n
    for i in range(n):
        m += int(split_r[i]) + int(split_c[i]) + int(split_r[i] and split_c[i])
    out = np.empty((m, 4), np.int64)
    k = 0
    for part in range(4):
        for i in range(n):
            if part == 1 and not split_r[i] or part == 2 and not split_c[i] or (
                    part == 3 and not (split_r[i] and split_c[i])):
                continue
            nsr = cells[i, 2] // 2 if split_r[i] else cells[i, 2]
            nsc = cells[i, 3] // 2 if split_c[i] else cells[i, 3]
            out[k, 0] = cells[i, 0] + (nsr if part == 1 or part == 3 else 0)
            out[k, 1] = cells[i, 1] + (nsc if part >= 2 else 0)
            out[k, 2], out[k, 3] = nsr, nsc
            k += 1
    return out


@njit(cache=True, nogil=True)
def _inside(cells, h, w):
    """The cells that start inside the tile's ``h`` x ``w`` pixels (the others cover none
    of its pixels)."""
    keep = np.empty(cells.shape[0], np.bool_)
    every = True
    for i in range(cells.shape[0]):
        keep[i] = cells[i, 0] <= h - 1 and cells[i, 1] <= w - 1
        every = every and keep[i]
    return cells if every else _rows(cells, keep)


@njit(cache=True, nogil=True)
def _rows(a, keep):
    """``a[keep]`` of an ``(n, 4)`` int64 array, row by row."""
    m = 0
    for i in range(keep.shape[0]):
        m += keep[i]
    out = np.empty((m, 4), np.int64)
    t = 0
    for i in range(keep.shape[0]):
        if keep[i]:
            for q in range(4):
                out[t, q] = a[i, q]
            t += 1
    return out


@njit(cache=True, nogil=True)
def _items(a, keep):
    """``a[keep]`` of a boolean vector."""
    m = 0
    for i in range(keep.shape[0]):
        m += keep[i]
    out = np.empty(m, np.bool_)
    t = 0
    for i in range(keep.shape[0]):
        if keep[i]:
            out[t] = a[i]
            t += 1
    return out


@njit(cache=True, nogil=True)
def corner_bounds(corners, nl, ne):
    """``(lmin, lmax, emin, emax)`` of the corners ``(n, 4, 2)`` of the leaves whose
    corners' box (NaN corners left out) meets the raw image (``nl`` x ``ne``, edges at
    -0.5 and n - 0.5); NaN where no leaf does."""
    lmin = emin = math.inf
    lmax = emax = -math.inf
    for k in range(corners.shape[0]):
        lo_l = lo_e = math.inf
        hi_l = hi_e = -math.inf
        for p in range(4):
            a, b = corners[k, p, 0], corners[k, p, 1]
            if not math.isnan(a):
                lo_l, hi_l = min(lo_l, a), max(hi_l, a)
            if not math.isnan(b):
                lo_e, hi_e = min(lo_e, b), max(hi_e, b)
        if hi_l >= -0.5 and lo_l <= nl - 0.5 and hi_e >= -0.5 and lo_e <= ne - 0.5:
            lmin, lmax = min(lmin, lo_l), max(lmax, hi_l)
            emin, emax = min(emin, lo_e), max(emax, hi_e)
    if lmin > lmax:
        return math.nan, math.nan, math.nan, math.nan
    return lmin, lmax, emin, emax
