"""Compiled kernels of the feathered blend (numba, ``nogil``, ``cache=True``).

* :func:`fill_rows`: invalid pixels take the nearest valid value of their row (the spline
  prefilter then sees no jump at the footprint's edges).
* :func:`sample_clip`: one pass per swing over the cubic B-spline coefficients: the
  separable 4 x 4 tap sum at a fractional shift ``f`` (the same weights at every pixel),
  clipped to the values of the pixel's 4 x 4 support (no ringing at steps), the validity of
  the shifted pixel (every pixel the interpolation leans on valid along each shifted axis)
  and the radiometric offset removed; float32 out.
* :func:`capped_distance`: the exact Euclidean distance of every valid pixel to the nearest
  invalid one (the frame outside the array counts as invalid), capped at ``cap``: one pass
  along the columns (two sweeps), one lower envelope of parabolas per row
  (Felzenszwalb & Huttenlocher 2012). Capping the column distances at ``cap`` does not
  change any result below ``cap``. Same values as scipy's ``distance_transform_edt`` on
  the mask padded by one invalid pixel, at a fraction of its cost (no feature transform).
* :func:`accumulate`: ``acc += w * v``, ``wsum += w`` of one corrected swing into a tile,
  float32.

All release the GIL, so the tiles of a mosaic render on every core through threads.
``fill_rows``, ``sample_clip``, ``capped_distance`` and ``prefilter`` each have an
``*_into`` variant that writes into arrays it is given (the swing cache's reused buffers,
:class:`swathflow.mosaicking.blend.Scratch`) and that the function itself calls.
"""
from __future__ import annotations

import numpy as np
from numba import njit

__all__ = ["fill_rows", "sample_clip", "capped_distance", "accumulate", "fill_rows_into",
           "sample_clip_into", "capped_distance_into", "prefilter_into"]


@njit(cache=True, nogil=True)
def fill_rows(val, ok):
    """A copy of ``val`` (float64) where each invalid pixel takes the previous valid value
    of its row, else the next; rows without a valid pixel take the nearest such row."""
    out = np.empty(val.shape)
    fill_rows_into(val, ok, out)
    return out


@njit(cache=True, nogil=True)
def _copy_row(out, src, dst):
    """Row ``src`` of ``out`` into row ``dst``, element by element (a row assigned to a
    slice compiles numba's shape-mismatch message: ~5 s a process on a cold cache)."""
    for j in range(out.shape[1]):
        out[dst, j] = out[src, j]


@njit(cache=True, nogil=True)
def fill_rows_into(val, ok, out):
    """:func:`fill_rows` into ``out`` (float64, the shape of ``val``)."""
    h, w = val.shape
    has = np.zeros(h, np.bool_)
    for i in range(h):
        last = -1
        for j in range(w):
            if ok[i, j]:
                last = j
                out[i, j] = val[i, j]
            elif last >= 0:
                out[i, j] = val[i, last]
            else:
                out[i, j] = np.nan
        if last < 0:
            continue
        has[i] = True
        nxt = -1
        for j in range(w - 1, -1, -1):          # leading invalid pixels: the next valid
            if ok[i, j]:
                nxt = j
            elif np.isnan(out[i, j]):
                out[i, j] = val[i, nxt]
    if h == 0:
        return
    # rows with no valid pixel: the previous filled row, else the next
    prev = -1
    for i in range(h):
        if has[i]:
            prev = i
        elif prev >= 0:
            _copy_row(out, prev, i)
    nxt = -1
    for i in range(h - 1, -1, -1):
        if has[i]:
            nxt = i
        elif not np.isnan(out[i, 0]) or nxt < 0:
            continue
        else:
            _copy_row(out, nxt, i)
    if nxt < 0 and prev < 0:
        out[:, :] = 0.0


@njit(cache=True, nogil=True)
def _b3(x):
    x = abs(x)
    if x < 1.0:
        return 2.0 / 3.0 - x * x + x * x * x / 2.0
    if x < 2.0:
        return (2.0 - x) ** 3 / 6.0
    return 0.0


@njit(cache=True, nogil=True)
def _row_bounds(filled, a, lo_r, hi_r):
    """The min and max of ``filled`` over columns ``j - 1 .. j + 2`` of row ``a`` (edge
    extended) into ``lo_r``, ``hi_r``: :func:`sample_clip` takes its 4 x 4 bounds over 4 rows
    of these (the same values as over the 16 pixels, at half the reads)."""
    w = filled.shape[1]
    for j in range(w):
        lo, hi = np.inf, -np.inf
        for b in range(j - 1, j + 3):
            x = filled[a, min(max(b, 0), w - 1)]
            lo = min(lo, x)
            hi = max(hi, x)
        lo_r[j] = lo
        hi_r[j] = hi


@njit(cache=True, nogil=True)
def sample_clip(coef, filled, ok, pad, fr, fc, radiometric):
    """Shifted values ``out[x] = image(x + f) - radiometric`` (``0 <= f < 1`` per axis) and
    their validity, from ``coef`` (B-spline coefficients of ``filled`` padded by ``pad``
    edge pixels), clipped to the min/max of ``filled`` over the 4 x 4 support (rows and
    columns ``x - 1 .. x + 2``, edge-extended). Returns ``(values float32 (0 where
    invalid), valid)``."""
    h, w = filled.shape
    out = np.empty((h, w), np.float32)
    valid = np.empty((h, w), np.bool_)
    sample_clip_into(coef, filled, ok, pad, fr, fc, radiometric, out, valid)
    return out, valid


@njit(cache=True, nogil=True)
def sample_clip_into(coef, filled, ok, pad, fr, fc, radiometric, out, valid):
    """:func:`sample_clip` into ``out`` (float32) and ``valid`` (bool), the shape of
    ``filled``."""
    h, w = filled.shape
    wr = np.empty(4)
    wc = np.empty(4)
    for k in range(4):
        wr[k] = _b3(fr - (k - 1))
        wc[k] = _b3(fc - (k - 1))
    sr, sc = fr >= 1e-6, fc >= 1e-6
    tmp = np.empty(w + 3)
    # the row bounds of the 4 rows around row i, in a ring of 4 rows (row a in a % 4)
    # made as the rows come (not a whole image's worth of them: less memory traffic)
    lo_r = np.empty((4, w))
    hi_r = np.empty((4, w))
    have = -1
    for i in range(h):
        while have < min(i + 2, h - 1):
            have += 1
            _row_bounds(filled, have, lo_r[have % 4], hi_r[have % 4])
        empty = True
        for j in range(w):
            m = ok[i, j]
            if m and sc:
                m = j + 1 < w and ok[i, j + 1]
            if m and sr:
                m = i + 1 < h and ok[i + 1, j] and (not sc or ok[i + 1, j + 1])
            valid[i, j] = m
            empty = empty and not m
        if empty:
            out[i, :] = 0.0
            continue
        # rows of the spline sum first (4 taps), then columns
        for jj in range(w + 3):
            s = 0.0
            for k in range(4):
                s += wr[k] * coef[pad + i + k - 1, pad + jj - 1]
            tmp[jj] = s
        # the ring's slots of rows i - 1 .. i + 2 (edge-extended)
        a0, a1 = max(i - 1, 0) % 4, i % 4
        a2, a3 = min(i + 1, h - 1) % 4, min(i + 2, h - 1) % 4
        for j in range(w):
            if not valid[i, j]:
                out[i, j] = 0.0
                continue
            v = wc[0] * tmp[j] + wc[1] * tmp[j + 1] + wc[2] * tmp[j + 2] + wc[3] * tmp[j + 3]
            lo = min(min(min(min(np.inf, lo_r[a0, j]), lo_r[a1, j]), lo_r[a2, j]), lo_r[a3, j])
            hi = max(max(max(max(-np.inf, hi_r[a0, j]), hi_r[a1, j]), hi_r[a2, j]),
                     hi_r[a3, j])
            v = min(max(v, lo), hi)
            out[i, j] = v - radiometric


@njit(cache=True, nogil=True)
def _envelope(f, n, d, v, z):
    """Squared distance transform of one line ``f`` (length ``n``) into ``d``."""
    k = 0
    v[0] = 0
    z[0] = -np.inf
    z[1] = np.inf
    for q in range(1, n):
        s = ((f[q] + q * q) - (f[v[k]] + v[k] * v[k])) / (2.0 * (q - v[k]))
        while s <= z[k]:
            k -= 1
            s = ((f[q] + q * q) - (f[v[k]] + v[k] * v[k])) / (2.0 * (q - v[k]))
        k += 1
        v[k] = q
        z[k] = s
        z[k + 1] = np.inf
    k = 0
    for q in range(n):
        while z[k + 1] < q:
            k += 1
        d[q] = (q - v[k]) ** 2 + f[v[k]]


@njit(cache=True, nogil=True)
def capped_distance(ok, cap):
    """``min(edt, cap)`` as float32: the distance of each valid pixel of ``ok`` to the
    nearest invalid pixel (outside the array: invalid); 0 where invalid."""
    out = np.empty(ok.shape, np.float32)
    capped_distance_into(ok, cap, out, np.empty(ok.shape))
    return out


@njit(cache=True, nogil=True)
def capped_distance_into(ok, cap, out, g):
    """:func:`capped_distance` into ``out`` (float32), with ``g`` (float64) for its
    column pass; both the shape of ``ok``."""
    h, w = ok.shape
    c = float(cap)
    # the column pass row by row (the arrays' order): each column's run down, then up
    run = np.zeros(w)
    for i in range(h):
        for j in range(w):
            run[j] = min(run[j] + 1.0, c) if ok[i, j] else 0.0
            g[i, j] = run[j]
    run[:] = 0.0
    for i in range(h - 1, -1, -1):
        for j in range(w):
            run[j] = min(run[j] + 1.0, c) if ok[i, j] else 0.0
            g[i, j] = min(g[i, j], run[j])
    f = np.empty(w)
    d = np.empty(w)
    v = np.empty(w, np.int64)
    z = np.empty(w + 1)
    for i in range(h):
        for j in range(w):
            f[j] = g[i, j] * g[i, j]
        _envelope(f, w, d, v, z)
        for j in range(w):
            if not ok[i, j]:
                out[i, j] = 0.0
                continue
            e = min(d[j], float(j + 1) ** 2, float(w - j) ** 2)
            out[i, j] = min(np.sqrt(e), c)


@njit(cache=True, nogil=True)
def accumulate(acc, wsum, values, weight, ta, tb, sa, sb, hh, ww):
    """``acc[ta:ta+hh, tb:tb+ww] += weight * values`` and ``wsum += weight`` over the
    swing's window starting at ``(sa, sb)``."""
    for i in range(hh):
        for j in range(ww):
            wt = weight[sa + i, sb + j]
            if wt > 0:
                acc[ta + i, tb + j] += wt * values[sa + i, sb + j]
                wsum[ta + i, tb + j] += wt


@njit(cache=True, nogil=True)
def normalise(acc, wsum):
    """``acc / wsum`` where ``wsum > 0``, NaN elsewhere (float32, in place in ``acc``)."""
    h, w = acc.shape
    for i in range(h):
        for j in range(w):
            acc[i, j] = acc[i, j] / wsum[i, j] if wsum[i, j] > 0 else np.nan
    return acc


_Z = np.sqrt(3.0) - 2.0          # the pole of the cubic B-spline


@njit(cache=True, nogil=True)
def _first_mirror(c, n, axis, k):
    """The causal filter's first value of line ``k`` (scipy's mirror initialisation; the
    sum stops where the pole's powers fall below 1e-18)."""
    z = _Z
    zn1 = z ** (n - 1)
    a = (c[0, k] + zn1 * c[n - 1, k]) if axis == 0 else (c[k, 0] + zn1 * c[k, n - 1])
    zi = z
    for i in range(1, n - 1):
        if abs(zi) < 1e-18:
            break
        if axis == 0:
            a += zi * (c[i, k] + zn1 * c[n - 1 - i, k])
        else:
            a += zi * (c[k, i] + zn1 * c[k, n - 1 - i])
        zi *= z
    return a / (1.0 - zn1 * zn1)


@njit(cache=True, nogil=True)
def _along_columns(c):
    """The cubic B-spline's causal and anti-causal recursions down every column of ``c``
    (in place), row by row; every column's mirror initialisation (:func:`_first_mirror`)
    at once, read along the rows (the same sums in the same order)."""
    H, W = c.shape
    z = _Z
    zn1 = z ** (H - 1)
    first = np.empty(W)
    for k in range(W):
        first[k] = c[0, k] + zn1 * c[H - 1, k]
    zi = z
    for i in range(1, H - 1):
        if abs(zi) < 1e-18:
            break
        for k in range(W):
            first[k] += zi * (c[i, k] + zn1 * c[H - 1 - i, k])
        zi *= z
    for k in range(W):
        c[0, k] = first[k] / (1.0 - zn1 * zn1)
    for i in range(1, H):
        for k in range(W):
            c[i, k] += z * c[i - 1, k]
    for k in range(W):
        c[H - 1, k] = (z * c[H - 2, k] + c[H - 1, k]) * z / (z * z - 1.0)
    for i in range(H - 2, -1, -1):
        for k in range(W):
            c[i, k] = z * (c[i + 1, k] - c[i, k])


@njit(cache=True, nogil=True)
def _along_rows(c):
    """The same recursions along every row of ``c`` (in place), four rows at a time: four
    independent recursions side by side (each row's operations unchanged, so the same
    values, at less wait on each addition)."""
    H, W = c.shape
    z = _Z
    i = 0
    while i + 4 <= H:
        for a in range(i, i + 4):
            c[a, 0] = _first_mirror(c, W, 1, a)
        for j in range(1, W):
            c[i, j] += z * c[i, j - 1]
            c[i + 1, j] += z * c[i + 1, j - 1]
            c[i + 2, j] += z * c[i + 2, j - 1]
            c[i + 3, j] += z * c[i + 3, j - 1]
        for a in range(i, i + 4):
            c[a, W - 1] = (z * c[a, W - 2] + c[a, W - 1]) * z / (z * z - 1.0)
        for j in range(W - 2, -1, -1):
            c[i, j] = z * (c[i, j + 1] - c[i, j])
            c[i + 1, j] = z * (c[i + 1, j + 1] - c[i + 1, j])
            c[i + 2, j] = z * (c[i + 2, j + 1] - c[i + 2, j])
            c[i + 3, j] = z * (c[i + 3, j + 1] - c[i + 3, j])
        i += 4
    for a in range(i, H):
        c[a, 0] = _first_mirror(c, W, 1, a)
        for j in range(1, W):
            c[a, j] += z * c[a, j - 1]
        c[a, W - 1] = (z * c[a, W - 2] + c[a, W - 1]) * z / (z * z - 1.0)
        for j in range(W - 2, -1, -1):
            c[a, j] = z * (c[a, j + 1] - c[a, j])


@njit(cache=True, nogil=True)
def prefilter(val, pad):
    """Cubic B-spline coefficients of ``val`` padded by ``pad`` edge pixels on each side:
    ``ndimage.spline_filter(np.pad(val, pad, mode="edge"), order=3, mode="mirror")`` (the
    same recursions and mirror initialisation, in one compiled pass per axis; equal to
    scipy's to about 1e-12 relative)."""
    h, w = val.shape
    c = np.empty((h + 2 * pad, w + 2 * pad))
    prefilter_into(val, pad, c)
    return c


@njit(cache=True, nogil=True)
def prefilter_into(val, pad, c):
    """:func:`prefilter` into ``c`` (float64, the shape of ``val`` plus ``2 * pad``)."""
    h, w = val.shape
    H, W = h + 2 * pad, w + 2 * pad
    for i in range(H):
        r = min(max(i - pad, 0), h - 1)
        for j in range(W):
            c[i, j] = 6.0 * 6.0 * val[r, min(max(j - pad, 0), w - 1)]   # both axes' gain
    if H > 1:
        _along_columns(c)
    else:
        for k in range(W):
            c[0, k] /= 6.0
    if W > 1:
        _along_rows(c)
    else:
        for i in range(H):
            c[i, 0] /= 6.0
