"""Compiled checks of one matched block (numba, ``nogil``, ``cache=True``): its noise and
texture figures (scipy.ndimage's Gaussian filter and binary erosion written out, same
values to 1e-12), and the overview's block means, so a block's checks are one call that
releases the GIL (the numpy/scipy versions held it between their many small calls)."""
from __future__ import annotations

import numpy as np

from numba import njit
from swathflow.mosaicking.match_kernels import _grad, _median

__all__ = ["gaussian", "erode", "weakest_gradient", "noise_texture", "block_mean"]


@njit(cache=True, nogil=True)
def _reflect(i, n):
    """Index ``i`` folded into ``0..n-1`` the way scipy.ndimage's ``mode="reflect"`` extends
    a line (``d c b a | a b c d | d c b a``)."""
    if n == 1:
        return 0
    p = 2 * n
    i = i % p
    return i if i < n else p - 1 - i


@njit(cache=True, nogil=True)
def _smooth_axis(a, wts, axis):
    """scipy.ndimage.correlate1d of ``a`` (float64) with the symmetric ``wts`` along
    ``axis``, ``mode="reflect"`` (scipy's summation order: the centre, then the pairs from
    the farthest in)."""
    h, w = a.shape
    r = (wts.shape[0] - 1) // 2
    out = np.empty((h, w))
    n = h if axis == 0 else w
    line = np.empty(n + 2 * r)
    for k in range(w if axis == 0 else h):
        for q in range(-r, n + r):       # the fold (a division) only at the ends
            p = q if 0 <= q < n else _reflect(q, n)
            line[q + r] = a[p, k] if axis == 0 else a[k, p]
        # four outputs at a time: four independent chains of additions (each output's
        # terms still added in the same order, so the same values)
        wc = wts[r]
        q = 0
        while q + 4 <= n:
            s0 = line[q + r] * wc
            s1 = line[q + r + 1] * wc
            s2 = line[q + r + 2] * wc
            s3 = line[q + r + 3] * wc
            for j in range(-r, 0):
                wj = wts[r + j]
                b, e = q + r + j, q + r - j
                s0 += (line[b] + line[e]) * wj
                s1 += (line[b + 1] + line[e + 1]) * wj
                s2 += (line[b + 2] + line[e + 2]) * wj
                s3 += (line[b + 3] + line[e + 3]) * wj
            if axis == 0:
                out[q, k], out[q + 1, k], out[q + 2, k], out[q + 3, k] = s0, s1, s2, s3
            else:
                out[k, q], out[k, q + 1], out[k, q + 2], out[k, q + 3] = s0, s1, s2, s3
            q += 4
        for t in range(q, n):
            s = line[t + r] * wc
            for j in range(-r, 0):
                s += (line[t + r + j] + line[t + r - j]) * wts[r + j]
            if axis == 0:
                out[t, k] = s
            else:
                out[k, t] = s
    return out


@njit(cache=True, nogil=True)
def gaussian(a, sigma):
    """``scipy.ndimage.gaussian_filter(a, sigma)`` of a 2-D float64 array (``mode="reflect"``,
    ``truncate=4``; rows first, then columns, as scipy)."""
    r = int(4.0 * sigma + 0.5)
    wts = np.empty(2 * r + 1)
    for q in range(-r, r + 1):
        wts[q + r] = np.exp(-0.5 / (sigma * sigma) * q * q)
    wts /= wts.sum()
    return _smooth_axis(_smooth_axis(a, wts, 0), wts, 1)


@njit(cache=True, nogil=True)
def erode(mask, iterations):
    """``scipy.ndimage.binary_erosion(mask, iterations=iterations)`` (the cross structure,
    the frame outside the array counts as False)."""
    h, w = mask.shape
    cur = mask.copy()
    nxt = np.empty((h, w), np.bool_)
    for _ in range(iterations):
        for i in range(h):
            for j in range(w):
                nxt[i, j] = (cur[i, j] and i > 0 and cur[i - 1, j] and i < h - 1
                             and cur[i + 1, j] and j > 0 and cur[i, j - 1] and j < w - 1
                             and cur[i, j + 1])
        cur, nxt = nxt, cur
    return cur


@njit(cache=True, nogil=True)
def _gradients(sm, r, c):
    return _grad(sm, r, c, 0), _grad(sm, r, c, 1)


@njit(cache=True, nogil=True)
def weakest_gradient(img, mask):
    """The smallest eigenvalue of the structure tensor (mean of ``grad grad^T`` of the
    sigma = 1 smoothed ``img`` over ``mask`` eroded twice when it has more than 100
    pixels), NaN when fewer than 16 pixels are left: the texture check of
    swathflow.mosaicking.matching.texture_measure."""
    sm = gaussian(img, 1.0)
    h, w = mask.shape
    n_mask = 0
    for i in range(h):
        for j in range(w):
            n_mask += mask[i, j]
    m = erode(mask, 2) if n_mask > 100 else mask
    n = 0
    srr = src = scc = 0.0
    for i in range(h):
        for j in range(w):
            if m[i, j]:
                gr, gc = _gradients(sm, i, j)
                srr += gr * gr
                src += gr * gc
                scc += gc * gc
                n += 1
    if n < 16:
        return np.nan
    a, b, d = srr / n, src / n, scc / n
    # the smaller root of the 2 x 2 symmetric matrix's characteristic polynomial
    return 0.5 * (a + d) - np.sqrt(0.25 * (a - d) ** 2 + b * b)


@njit(cache=True, nogil=True)
def noise_texture(fill_r, fill_m, aligned, g, inner, joint):
    """The noise and texture figures of one aligned block (swathflow.mosaicking.matching
    .match_block): ``(noise, weakest)``. ``noise``: the robust noise (1.4826 MAD / sqrt 2) of
    the difference ``fill_m - g * aligned`` high-passed by subtracting its sigma = 3 Gaussian
    (invalid pixels set to its median over ``inner`` first), over ``inner``; ``weakest``:
    :func:`weakest_gradient` of ``fill_r`` over ``joint``."""
    h, w = fill_r.shape
    diff = np.empty((h, w))
    buf = np.empty(h * w)
    n = 0
    for i in range(h):
        for j in range(w):
            diff[i, j] = fill_m[i, j] - g * aligned[i, j]
            if inner[i, j]:
                buf[n] = diff[i, j]
                n += 1
    noise = np.inf
    if n > 0:
        med = _median(buf, n)
        z = np.empty((h, w))
        for i in range(h):
            for j in range(w):
                z[i, j] = diff[i, j] if inner[i, j] else med
        sm = gaussian(z, 3.0)
        n = 0
        for i in range(h):
            for j in range(w):
                if inner[i, j]:
                    buf[n] = diff[i, j] - sm[i, j]
                    n += 1
        m1 = _median(buf, n)
        for k in range(n):
            buf[k] = abs(buf[k] - m1)
        noise = 1.4826 * _median(buf, n) / np.sqrt(2.0)
    return noise, weakest_gradient(fill_r, joint)


@njit(cache=True, nogil=True)
def block_mean(val, ok, f, need):
    """Mean of the valid pixels of ``val`` over each ``f x f`` cell (the trailing partial
    row and column of cells dropped) and the cells with at least ``need`` valid pixels
    (0 elsewhere): swathflow.mosaicking.coarse.decimate in one pass."""
    h, w = val.shape[0] // f, val.shape[1] // f
    out = np.zeros((h, w))
    good = np.zeros((h, w), np.bool_)
    for i in range(h):
        for j in range(w):
            s = 0.0
            n = 0
            for a in range(i * f, i * f + f):
                for b in range(j * f, j * f + f):
                    if ok[a, b]:
                        s += val[a, b]
                        n += 1
            if n >= need:
                good[i, j] = True
                out[i, j] = s / max(n, 1)
    return out, good
