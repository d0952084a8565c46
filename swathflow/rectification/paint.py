"""Compiled painting of the lattice's rectangular leaves (numba, ``cache=True``).

A leaf ``(r, c, sr, sc)`` covers the ``sr + 1`` x ``sc + 1`` output pixels from ``(r, c)``;
their raw (line, element) is the bilinear interpolation of its four corner values at
(r, c), (r, c + sc), (r + sr, c), (r + sr, c + sc). Leaves are painted in order, later
(finer) ones overwriting the edges they share with coarser ones.
"""
from __future__ import annotations

import math

import numpy as np

from numba import njit
from swathflow.rectification.kernel import _bil  # one bilinear rule for both painters


@njit(cache=True, nogil=True)
def paint_window(cells, corners, h, w, l0, e0, nl, ne):
    """Window-relative raw coordinates ``(2, h, w)`` float32 of a tile's pixels: NaN where
    the coordinate is NaN or off the raw image (``nl`` x ``ne``) by more than half a
    pixel, else minus the window origin ``(l0, e0)``.

    A leaf with four finite corners is painted row by row as a linear function of the
    column (the bilinear form's left and right ends interpolated down the leaf, then
    ``a + j * b`` across it: no division or branch per pixel, so the row vectorises; the
    same values to a few ulp); a leaf with a NaN corner through :func:`_bil` pixel by
    pixel (terms of zero weight left out)."""
    out = np.full((2, h, w), np.nan, np.float32)
    lo_l, hi_l = -0.5 - l0, nl - 0.5 - l0           # the raw image, window-relative
    lo_e, hi_e = -0.5 - e0, ne - 0.5 - e0
    nan = np.float32(np.nan)
    for k in range(cells.shape[0]):
        r, c, sr, sc = cells[k, 0], cells[k, 1], cells[k, 2], cells[k, 3]
        nr, nc = min(sr + 1, h - r), min(sc + 1, w - c)
        q00l, q01l, q10l, q11l = (corners[k, 0, 0], corners[k, 1, 0], corners[k, 2, 0],
                                  corners[k, 3, 0])
        q00e, q01e, q10e, q11e = (corners[k, 0, 1], corners[k, 1, 1], corners[k, 2, 1],
                                  corners[k, 3, 1])
        if math.isnan(q00l + q01l + q10l + q11l + q00e + q01e + q10e + q11e):
            _paint_nan_leaf(out, k, r, c, sr, sc, nr, nc, corners, l0, e0, nl, ne)
            continue
        for i in range(nr):
            wr = i / sr
            left_l = q00l + wr * (q10l - q00l)
            left_e = q00e + wr * (q10e - q00e)
            b_l = (q01l + wr * (q11l - q01l) - left_l) / sc
            b_e = (q01e + wr * (q11e - q01e) - left_e) / sc
            a_l = left_l - l0
            a_e = left_e - e0
            o0 = out[0, r + i, c:c + nc]
            o1 = out[1, r + i, c:c + nc]
            for j in range(nc):
                li = a_l + j * b_l
                ei = a_e + j * b_e
                ok = (li >= lo_l) & (li <= hi_l) & (ei >= lo_e) & (ei <= hi_e)
                o0[j] = np.float32(li) if ok else nan
                o1[j] = np.float32(ei) if ok else nan
    return out


@njit(cache=True, nogil=True)
def _paint_nan_leaf(out, k, r, c, sr, sc, nr, nc, corners, l0, e0, nl, ne):
    """One leaf with a NaN corner, pixel by pixel through :func:`_bil`."""
    for i in range(nr):
        wr = i / sr
        rr = r + i
        for j in range(nc):
            wc = j / sc
            li = _bil(wr, wc, corners[k, 0, 0], corners[k, 1, 0], corners[k, 2, 0],
                      corners[k, 3, 0])
            ei = _bil(wr, wc, corners[k, 0, 1], corners[k, 1, 1], corners[k, 2, 1],
                      corners[k, 3, 1])
            if (li >= -0.5) and (li <= nl - 0.5) and (ei >= -0.5) and (ei <= ne - 0.5):
                out[0, rr, c + j] = li - l0
                out[1, rr, c + j] = ei - e0
            else:
                out[0, rr, c + j] = np.nan
                out[1, rr, c + j] = np.nan


@njit(cache=True, nogil=True)
def paint_pixels(pixels, l0, e0, nl, ne):
    """:func:`paint_window` for a tile evaluated exactly at every pixel: ``pixels``
    ``(h, w, 2)`` float64 absolute raw coordinates."""
    h, w = pixels.shape[0], pixels.shape[1]
    out = np.full((2, h, w), np.nan, np.float32)
    for i in range(h):
        for j in range(w):
            li, ei = pixels[i, j, 0], pixels[i, j, 1]
            if (li >= -0.5) and (li <= nl - 0.5) and (ei >= -0.5) and (ei <= ne - 0.5):
                out[0, i, j] = li - l0
                out[1, i, j] = ei - e0
    return out


def paint_leaves(lv, l0, e0, nl, ne):
    """Window-relative raw coordinates ``(2, h, w)`` float32 of a tile's
    :class:`~.lattice.Leaves` (:func:`paint_window`, or :func:`paint_pixels` for a tile
    evaluated at every pixel)."""
    if lv.pixels is not None:
        return paint_pixels(lv.pixels, l0, e0, nl, ne)
    return paint_window(lv.cells, lv.corners, lv.shape[0], lv.shape[1], l0, e0, nl, ne)


@njit(cache=True, nogil=True)
def paint_f64(cells, corners, h, w):
    """Absolute raw coordinates ``(h, w, 2)`` float64 of the leaves (no masking)."""
    out = np.full((h, w, 2), np.nan)
    for k in range(cells.shape[0]):
        r, c, sr, sc = cells[k, 0], cells[k, 1], cells[k, 2], cells[k, 3]
        for i in range(min(sr + 1, h - r)):
            wr = i / sr
            for j in range(min(sc + 1, w - c)):
                wc = j / sc
                for q in range(2):
                    out[r + i, c + j, q] = _bil(wr, wc, corners[k, 0, q], corners[k, 1, q],
                                                corners[k, 2, q], corners[k, 3, q])
    return out


@njit(cache=True, nogil=True)
def _by_row(cells):
    """The order of ``cells`` ``(m, 4)`` by first row, stable (a counting sort over
    their rows' range, a tile's at most): what ``np.argsort(kind="mergesort")`` gives,
    without compiling numba's merge sort (3 CPU-s a process on a cold cache)."""
    m = cells.shape[0]
    lo = hi = cells[0, 0] if m else 0
    for t in range(m):
        lo, hi = min(lo, cells[t, 0]), max(hi, cells[t, 0])
    start = np.zeros(hi - lo + 2, np.int64)
    for t in range(m):
        start[cells[t, 0] - lo + 1] += 1
    for r in range(1, hi - lo + 2):
        start[r] += start[r - 1]
    order = np.empty(m, np.int64)
    for t in range(m):
        b = cells[t, 0] - lo
        order[start[b]] = t
        start[b] += 1
    return order


@njit(cache=True, nogil=True)
def _bisect(a, x, right):
    """``np.searchsorted(a, x, side="right" if right else "left")`` of a sorted int64
    vector (numba's compiles for 1-2 CPU-s a process on a cold cache)."""
    lo, hi = 0, a.shape[0]
    while lo < hi:
        mid = (lo + hi) // 2
        if a[mid] < x or (right and a[mid] == x):
            lo = mid + 1
        else:
            hi = mid
    return lo


@njit(cache=True, nogil=True)
def touching(cells, marked, H, W):
    """For each cell ``(r, c, sr, sc)`` (``(n, 4)``), whether its closed rectangle shares a
    pixel of the ``H`` x ``W`` tile with the closed rectangle of a ``marked`` cell
    (``(m, 4)``). Rectangle against rectangle (their row and column ranges overlap inside
    the tile), the marked cells sorted by first row so each cell meets only those that
    can reach it: no tile-sized mask to clear and paint (0.69 -> 0.21 ms on the 1x
    kernel benchmark's calls)."""
    n, m = cells.shape[0], marked.shape[0]
    out = np.zeros(n, np.bool_)
    if m == 0:
        return out
    order = _by_row(marked)
    first = np.empty(m, np.int64)
    span = 0
    for t in range(m):
        first[t] = marked[order[t], 0]
        span = max(span, marked[order[t], 2])
    for k in range(n):
        r, c = cells[k, 0], cells[k, 1]
        r1, c1 = min(r + cells[k, 2], H - 1), min(c + cells[k, 3], W - 1)
        lo, hi = _bisect(first, r - span, False), _bisect(first, r1, True)
        for t in range(lo, hi):
            j = order[t]
            rb, cb = marked[j, 0], marked[j, 1]
            if (max(r, rb) <= min(r1, rb + marked[j, 2])
                    and max(c, cb) <= min(c1, cb + marked[j, 3])):
                out[k] = True
                break
    return out
