"""The checks of one matched block: its noise and texture figures (scipy.ndimage's
Gaussian filter and binary erosion, which release the GIL, around a compiled structure
tensor), and the overview's block means (compiled, ``nogil``, ``cache=True``)."""
from __future__ import annotations

import numpy as np
from scipy import ndimage

from numba import njit
from swathflow.mosaicking.match_kernels import _grad

__all__ = ["weakest_gradient", "noise_texture", "block_mean"]


@njit(cache=True, nogil=True)
def _gradients(sm, r, c):
    return _grad(sm, r, c, 0), _grad(sm, r, c, 1)


@njit(cache=True, nogil=True)
def _weakest(sm, m):
    """The smallest eigenvalue of the mean of ``grad grad^T`` of ``sm`` over ``m``; NaN
    when fewer than 16 pixels."""
    h, w = m.shape
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


def weakest_gradient(img, mask) -> float:
    """The smallest eigenvalue of the structure tensor (mean of ``grad grad^T`` of the
    sigma = 1 smoothed ``img`` over ``mask`` eroded twice when it has more than 100
    pixels), NaN when fewer than 16 pixels are left: the texture check of
    swathflow.mosaicking.matching.texture_measure."""
    img = np.asarray(img, float)
    mask = np.asarray(mask, bool)
    sm = ndimage.gaussian_filter(img, 1.0)
    m = ndimage.binary_erosion(mask, iterations=2) if mask.sum() > 100 else mask
    return float(_weakest(np.ascontiguousarray(sm), np.ascontiguousarray(m)))


def noise_texture(fill_r, fill_m, aligned, g, inner, joint):
    """The noise and texture figures of one aligned block (swathflow.mosaicking.matching
    .match_block): ``(noise, weakest)``. ``noise``: the robust noise (1.4826 MAD / sqrt 2) of
    the difference ``fill_m - g * aligned`` high-passed by subtracting its sigma = 3 Gaussian
    (invalid pixels set to its median over ``inner`` first), over ``inner``; ``weakest``:
    :func:`weakest_gradient` of ``fill_r`` over ``joint``."""
    diff = np.asarray(fill_m, float) - g * np.asarray(aligned, float)
    noise = np.inf
    if inner.any():
        z = np.where(inner, diff, np.median(diff[inner]))
        v = (diff - ndimage.gaussian_filter(z, 3.0))[inner]
        noise = 1.4826 * float(np.median(np.abs(v - np.median(v)))) / np.sqrt(2.0)
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
