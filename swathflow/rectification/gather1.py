"""Compiled gather of ONE band, bilinear, in one pass a pixel (numba, ``cache=True``): the
single-band swings' hot path, without the row buffers of taps of :mod:`.gather`'s
multi-band kernels (the same taps, weights and rounding: :func:`.taps.pixel_taps`).
:func:`.gather.gather` chooses them."""
from __future__ import annotations

import math

import numpy as np
from numba import njit
from swathflow.rectification.taps import pixel_taps, step_off


@njit(cache=True, nogil=True, inline="always")
def _tap_v(v, wgt):
    """:func:`.taps.checked_tap` of a loaded value (``check`` on, no nodata value)."""
    if wgt == 0.0:
        return 0.0
    if v != v:
        return np.nan
    return wgt * v


@njit(cache=True, nogil=True)
def gather_one(flat, sl, se, nl, ne, coords, out, out_nodata, valid):
    """:func:`.gather.gather_bands` for one band, bilinear, float output, without a
    nodata value (NaN the only nodata of a float raw type), in one pass per pixel, no row
    buffers (12-15 % less time than the row form; the same arithmetic, so the same
    values). A NaN sum is redone with each tap tested (:func:`.taps.checked_tap`): nodata where
    a tap of non-zero weight is NaN. (Integer output: :func:`gather_int_one`.)"""
    _, h, w = coords.shape
    dl = sl if nl > 1 else 0
    de = se if ne > 1 else 0
    o = out[0]
    for r in range(h):
        for c in range(w):
            li = coords[0, r, c]
            ei = coords[1, r, c]
            if math.isnan(li) or math.isnan(ei):
                valid[r, c] = 0
                o[r, c] = out_nodata
                continue
            k, w0, w1, w2, w3 = pixel_taps(li, ei, nl, ne, sl, se, False)
            v0 = flat[k]
            v1 = flat[k + de]
            v2 = flat[k + dl]
            v3 = flat[k + dl + de]
            acc = w0 * v0 + w1 * v1 + w2 * v2 + w3 * v3
            if acc != acc:
                acc = _tap_v(v0, w0) + _tap_v(v1, w1) + _tap_v(v2, w2) + _tap_v(v3, w3)
                if acc != acc:
                    valid[r, c] = 0
                    o[r, c] = out_nodata
                    continue
            valid[r, c] = 255
            o[r, c] = acc
    return out


@njit(cache=True, nogil=True)
def gather_int_one(flat, sl, se, nl, ne, coords, out, out_nodata, nd_cmp, valid):
    """:func:`.gather.gather_int` for one band (the single-band swings'): bilinear,
    integer raw data without a nodata value into an integer type at least as wide, in one
    pass per pixel, no row buffers of taps (on the demo's uint16 swings at 0.05 m 4.9
    against 6.4 ns a pixel for the row form of :func:`.gather.gather_bands`, which an
    earlier measurement had found as fast; the same arithmetic, so the same values).
    Pixels without a coordinate get ``out_nodata``; a value landing on ``nd_cmp`` moves
    up by one (NaN: no nodata value to avoid)."""
    _, h, w = coords.shape
    dl = sl if nl > 1 else 0
    de = se if ne > 1 else 0
    o = out[0]
    for r in range(h):
        for c in range(w):
            li = coords[0, r, c]
            ei = coords[1, r, c]
            if math.isnan(li) or math.isnan(ei):
                valid[r, c] = 0
                o[r, c] = out_nodata
                continue
            k, w0, w1, w2, w3 = pixel_taps(li, ei, nl, ne, sl, se, False)
            acc = (w0 * flat[k] + w1 * flat[k + de] + w2 * flat[k + dl]
                   + w3 * flat[k + dl + de])
            valid[r, c] = 255
            o[r, c] = step_off(math.floor(acc + 0.5), nd_cmp)
    return out
