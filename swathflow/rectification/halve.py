"""One overview level of a block: the 2 x 2 reduction of the COG writer (:mod:`.writing`),
compiled (numba, ``cache=True``). :func:`halve` chooses the kernel: integer pixels of at
most 4 bytes averaged in integers (:func:`_halve_int`: on the demo's uint16 tiles 3x
faster), anything else in floats (:func:`_halve_any`); the same values."""
from __future__ import annotations

import math

import numpy as np
from numba import njit


def halve(src, nodata: float, use_nodata: bool, average: bool, is_int: bool, out,
          r0: int = 0, c0: int = 0) -> None:
    """``out[b, r0 + i, c0 + j]`` from the 2 x 2 pixels ``src[b, 2i:2i+2, 2j:2j+2]``
    (fewer at the right and bottom edges; as far as ``out`` reaches). ``average``: the
    mean of the valid ones (not NaN, not ``nodata`` when ``use_nodata``), rounded half up
    for integer output, ``nodata`` (or NaN) where none is valid; else nearest: the pixel
    at (2i + 1, 2j + 1), clamped to the block. (At the edges a pixel taken twice leaves
    the mean unchanged.) The kernels take the whole ``out`` and the offsets, not a view
    of it: a view is another array type to numba, whose compiled code each forked worker
    would load again (5-7 ms)."""
    if average and is_int and src.dtype.kind in "ui" and src.dtype.itemsize <= 4:
        # no integer of 4 bytes equals a nodata value with a fraction, nor NO_VALUE
        whole = use_nodata and float(nodata).is_integer() and abs(nodata) < 2 ** 53
        _halve_int(src, int(nodata) if whole else NO_VALUE, out, r0, c0)
        return
    _halve_any(src, nodata, use_nodata, average, is_int, out, r0, c0)


#: the nodata value :func:`_halve_int` compares with when there is none (beyond 4 bytes)
NO_VALUE = 1 << 40


@njit(cache=True, nogil=True, inline="always")
def _mean_int(a0, a1, a2, a3, nodata):
    """``floor(s / n + 0.5)`` of the ``n`` values (int64) that are not ``nodata``, whose
    sum is ``s``, without a branch for the common cases: ``(s + k) >> k`` with
    ``k = n >> 1`` for n = 1, 2, 4; ``(2 s + 3) // 6`` for 3; ``nodata`` for none."""
    m0, m1, m2, m3 = a0 != nodata, a1 != nodata, a2 != nodata, a3 != nodata
    n = np.int64(m0) + np.int64(m1) + np.int64(m2) + np.int64(m3)
    s = a0 * m0 + a1 * m1 + a2 * m2 + a3 * m3
    k = n >> 1
    r = (s + k) >> k
    if n == 3:
        r = (2 * s + 3) // 6
    if n == 0:
        r = nodata
    return r


@njit(cache=True, nogil=True)
def _halve_int(src, nodata, out, r0, c0):
    """:func:`halve`'s average of integer pixels (at most 4 bytes: their sums are exact
    in float64 too, so the values are :func:`_halve_any`'s) in int64 (:func:`_mean_int`),
    the columns with two pixels each in a loop of their own (3x faster than
    :func:`_halve_any` on the demo's uint16 tiles)."""
    nb, h, w = src.shape
    oh, ow = min(-(-h // 2), out.shape[1] - r0), min(-(-w // 2), out.shape[2] - c0)
    full = min(ow, w // 2)
    for b in range(nb):
        for i in range(oh):
            r1 = min(2 * i + 1, h - 1)
            s0, s1, o = src[b, 2 * i], src[b, r1], out[b, r0 + i, c0:]
            for j in range(full):
                c = 2 * j
                o[j] = _mean_int(np.int64(s0[c]), np.int64(s0[c + 1]), np.int64(s1[c]),
                                 np.int64(s1[c + 1]), nodata)
            for j in range(full, ow):
                c, c1 = 2 * j, min(2 * j + 1, w - 1)
                o[j] = _mean_int(np.int64(s0[c]), np.int64(s0[c1]), np.int64(s1[c]),
                                 np.int64(s1[c1]), nodata)


@njit(cache=True, nogil=True)
def _halve_any(src, nodata, use_nodata, average, is_int, out, oi, oj):
    """:func:`halve` for any pixel type, in float64 (``oi, oj``: the offsets in ``out``)."""
    nb, h, w = src.shape
    oh, ow = min(-(-h // 2), out.shape[1] - oi), min(-(-w // 2), out.shape[2] - oj)
    for b in range(nb):
        for i in range(oh):
            r0 = 2 * i
            r1 = min(r0 + 1, h - 1)
            for j in range(ow):
                c0 = 2 * j
                c1 = min(c0 + 1, w - 1)
                if not average:
                    out[b, oi + i, oj + j] = src[b, r1, c1]
                    continue
                s = 0.0
                n = 0
                for v in (src[b, r0, c0], src[b, r0, c1], src[b, r1, c0], src[b, r1, c1]):
                    if v == v and not (use_nodata and v == nodata):
                        s += v
                        n += 1
                if n == 0:
                    out[b, oi + i, oj + j] = nodata
                elif is_int:
                    out[b, oi + i, oj + j] = math.floor(s / n + 0.5)
                else:
                    out[b, oi + i, oj + j] = s / n
