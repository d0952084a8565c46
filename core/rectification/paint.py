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

from swathflow.rectification.gather import _finish, _tap, _taps_1d
from swathflow.rectification.kernel import _bil  # one bilinear rule for both painters


@njit(cache=True, nogil=True)
def paint_window(cells, corners, h, w, l0, e0, nl, ne):
    """Window-relative raw coordinates ``(2, h, w)`` float32 of a tile's pixels: NaN where
    the coordinate is NaN or off the raw image (``nl`` x ``ne``) by more than half a
    pixel, else minus the window origin ``(l0, e0)``."""
    out = np.full((2, h, w), np.nan, np.float32)
    for k in range(cells.shape[0]):
        r, c, sr, sc = cells[k, 0], cells[k, 1], cells[k, 2], cells[k, 3]
        for i in range(min(sr + 1, h - r)):
            wr = i / sr
            rr = r + i
            for j in range(min(sc + 1, w - c)):
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
    return out


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
def touching(cells, marked, H, W):
    """For each cell ``(r, c, sr, sc)`` (``(n, 4)``), whether its closed rectangle shares a
    pixel with the closed rectangle of a ``marked`` cell (``(m, 4)``)."""
    mask = np.zeros((H, W), np.bool_)
    for k in range(marked.shape[0]):
        r, c, sr, sc = marked[k, 0], marked[k, 1], marked[k, 2], marked[k, 3]
        for i in range(r, min(r + sr + 1, H)):
            for j in range(c, min(c + sc + 1, W)):
                mask[i, j] = True
    out = np.zeros(cells.shape[0], np.bool_)
    for k in range(cells.shape[0]):
        r, c, sr, sc = cells[k, 0], cells[k, 1], cells[k, 2], cells[k, 3]
        hit = False
        for i in range(r, min(r + sr + 1, H)):
            for j in range(c, min(c + sc + 1, W)):
                if mask[i, j]:
                    hit = True
                    break
            if hit:
                break
        out[k] = hit
    return out


@njit(cache=True, nogil=True, inline="always")
def _lerp(a, b, t):
    """``(1 - t) a + t b``, the term of zero weight left out (as :func:`.kernel._bil`)."""
    if t == 0.0:
        return a
    if t == 1.0:
        return b
    return (1.0 - t) * a + t * b


@njit(cache=True, nogil=True, inline="always")
def _bands_at(flat, t, sb, nb, de, dl, p, q, plain, nearest, check, has_nodata, nodata, out,
              rr, cc, out_nodata, lo, hi, is_int, clamp, avoid):
    """Every band of one output pixel from the taps at flat offset ``t`` (weights of the
    second line and element ``p``, ``q``); returns 255, or 0 where a band is nodata.
    ``plain``: one band, bilinear, every tap data, no clamp (the common case, no tests)."""
    w0 = (1 - p) * (1 - q)
    w1 = (1 - p) * q
    w2 = p * (1 - q)
    w3 = p * q
    if plain:
        acc = w0 * flat[t] + w1 * flat[t + de] + w2 * flat[t + dl] + w3 * flat[t + dl + de]
        out[0, rr, cc] = _finish(acc, is_int, False, lo, hi, avoid, out_nodata)
        return 255
    ok = 255
    for b in range(nb):
        base = b * sb + t
        if nearest:
            acc = _tap(flat, base, 1.0, check, has_nodata, nodata)
        elif check:
            acc = (_tap(flat, base, w0, True, has_nodata, nodata)
                   + _tap(flat, base + de, w1, True, has_nodata, nodata)
                   + _tap(flat, base + dl, w2, True, has_nodata, nodata)
                   + _tap(flat, base + dl + de, w3, True, has_nodata, nodata))
        else:
            acc = (w0 * flat[base] + w1 * flat[base + de] + w2 * flat[base + dl]
                   + w3 * flat[base + dl + de])
        if check and math.isnan(acc):
            ok = 0
            out[b, rr, cc] = out_nodata
            continue
        out[b, rr, cc] = _finish(acc, is_int, clamp, lo, hi, avoid, out_nodata)
    return ok


@njit(cache=True, nogil=True)
def paint_gather(cells, corners, l0, e0, nl, ne, flat, sb, sl, se, nb, wl, we, nearest,
                 check, has_nodata, nodata, out, out_nodata, lo, hi, is_int, clamp, avoid,
                 valid):
    """:func:`paint_window` and :func:`.gather.gather_bands` in one pass, without the
    coordinate array: each leaf pixel's raw (line, element) is interpolated from its
    leaf's corners (down the leaf's left and right edges, then across: the bilinear
    interpolation of :func:`_bil`, zero-weight terms left out alike) and the ``nb``
    bands of the raw window (``flat`` with element strides ``sb, sl, se``, ``wl`` x
    ``we`` pixels from ``(l0, e0)``) are resampled there at once (nearest or bilinear,
    the taps and rules of :mod:`.gather`) into ``out`` ``(nb, h, w)``; ``valid`` gets
    255 where every band is valid. Leaves are painted in order, later ones overwriting
    shared edges; pixels off the raw image (``nl`` x ``ne``) by more than half a pixel,
    or of no leaf, get ``out_nodata``."""
    h, w = out.shape[1], out.shape[2]
    for b in range(nb):
        for r in range(h):
            for c in range(w):
                out[b, r, c] = out_nodata
    for r in range(h):
        for c in range(w):
            valid[r, c] = 0
    dl = sl if wl > 1 else 0
    de = se if we > 1 else 0
    plain = nb == 1 and not nearest and not check and not clamp
    for k in range(cells.shape[0]):
        r, c, sr, sc = cells[k, 0], cells[k, 1], cells[k, 2], cells[k, 3]
        for i in range(min(sr + 1, h - r)):
            wr = i / sr
            rr = r + i
            la = _lerp(corners[k, 0, 0], corners[k, 2, 0], wr)
            lb = _lerp(corners[k, 1, 0], corners[k, 3, 0], wr)
            ea = _lerp(corners[k, 0, 1], corners[k, 2, 1], wr)
            eb = _lerp(corners[k, 1, 1], corners[k, 3, 1], wr)
            inv = 1.0 / sc
            for j in range(min(sc + 1, w - c)):
                wc = 1.0 if j == sc else j * inv
                cc = c + j
                li = _lerp(la, lb, wc)
                ei = _lerp(ea, eb, wc)
                if not ((li >= -0.5) and (li <= nl - 0.5) and (ei >= -0.5)
                        and (ei <= ne - 0.5)):
                    valid[rr, cc] = 0
                    for b in range(nb):
                        out[b, rr, cc] = out_nodata
                    continue
                ti, p = _taps_1d(li - l0, wl, nearest)
                tj, q = _taps_1d(ei - e0, we, nearest)
                valid[rr, cc] = _bands_at(flat, ti * sl + tj * se, sb, nb, de, dl, p, q,
                                          plain, nearest, check, has_nodata, nodata, out,
                                          rr, cc, out_nodata, lo, hi, is_int, clamp, avoid)
    return out
