"""The arithmetic of one output pixel shared by the compiled gather kernels
(:mod:`.gather`'s multi-band kernels, :mod:`.gather1`'s single-band ones): where its
taps are in the raw window, their weights, a tap tested for nodata, and the rounding of
the sum into the output type (numba, ``cache=True``, inlined into the kernels).

The same taps, weights and rounding as :func:`.kernel.resample_bands`: bilinear taps
``i`` and ``i + 1`` clamped to the image, nearest one tap, integer output rounded half up
and stepped off the output's nodata value.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit


@njit(cache=True, nogil=True, inline="always")
def taps_1d(x, n, nearest):
    """(index of the first tap, weight of the second tap) along one axis: bilinear taps
    are ``i`` and ``i + 1`` with ``i`` in ``[0, n - 2]`` and the weight clamped to
    ``[0, 1]`` (the same values as clamping each tap to the image); nearest: one tap."""
    if nearest:
        i = math.floor(x + 0.5)
        return min(max(i, 0), n - 1), 0.0
    i = math.floor(x)
    i = min(max(i, 0), max(n - 2, 0))
    f = x - i
    if f < 0.0:
        f = 0.0
    elif f > 1.0 or n == 1:
        f = 1.0 if n > 1 else 0.0
    return i, f


@njit(cache=True, nogil=True, inline="always")
def checked_tap(flat, k, wgt, check, has_nodata, nodata):
    """One weighted tap; NaN when ``check`` and the tap is nodata (NaN or ``nodata``)."""
    v = flat[k]
    if check:
        if wgt == 0.0:
            return 0.0
        if v != v or (has_nodata and v == nodata):
            return np.nan
    return wgt * v


@njit(cache=True, nogil=True, inline="always")
def pixel_taps(li, ei, nl, ne, sl, se, nearest):
    """Taps of one pixel: (flat offset of its first tap, the four weights). Inside the
    image (NaN is not) bilinear taps truncate and need no clamp: :func:`taps_1d`'s values,
    30 % faster (gather_one, gather_bands' rows; in gather_int's loop nest it measured 8 %
    slower on the cube)."""
    if not nearest and li >= 0 and li < nl - 1 and ei >= 0 and ei < ne - 1:
        i, j = int(li), int(ei)
        p, q = li - i, ei - j
    else:
        i, p = taps_1d(li, nl, nearest)
        j, q = taps_1d(ei, ne, nearest)
    return i * sl + j * se, (1 - p) * (1 - q), (1 - p) * q, p * (1 - q), p * q


@njit(cache=True, nogil=True, inline="always")
def finish(acc, is_int, clamp, lo, hi, avoid, out_nodata):
    """Round half up (integer output), clamp when the output type is narrower than the
    raw one, and step off the nodata value (as :func:`.kernel._to_int`)."""
    if is_int:
        acc = math.floor(acc + 0.5)
        if clamp:
            acc = min(max(acc, lo), hi)
        if avoid and acc == out_nodata:
            acc = acc + 1 if acc < hi else acc - 1
    return acc


@njit(cache=True, nogil=True, inline="always")
def step_off(acc, nd_cmp):
    """A value landing on ``nd_cmp`` moves up by one."""
    if acc == nd_cmp:
        return acc + 1
    return acc
