"""Compiled bracketing of ground points between the viewing planes of two integer scan
lines: the numba form of ``linesolve.plane_brackets`` followed by ``linesolve.bracket_lines``
(same steps, same results), one point at a time so no temporaries leave the cache.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _plane(planes, j, x, y, z):
    return planes[j, 0] * x + planes[j, 1] * y + planes[j, 2] * z + planes[j, 3]


@njit(cache=True, nogil=True, error_model="numpy")
def _sgn(v):
    return (v > 0.0) - (v < 0.0)


@njit(cache=True, nogil=True, error_model="numpy")
def _coarse(planes, grid, x, y, z):
    """First sign change over the coarse lines ``grid``: (lo, hi, f_lo, f_hi)."""
    n_lines = planes.shape[0]
    f_prev = _plane(planes, grid[0], x, y, z)
    f_first = f_prev
    for g in range(1, grid.shape[0]):
        f = _plane(planes, grid[g], x, y, z)
        if math.copysign(1.0, f) != math.copysign(1.0, f_prev):
            return grid[g - 1], grid[g], f_prev, f
        f_prev = f
    return 0, n_lines - 1, f_first, f_prev


@njit(cache=True, nogil=True, error_model="numpy")
def _chord_steps(planes, x, y, z, lo, hi, flo, fhi):
    """Up to six secant guesses of the root's line, each checked at two integer lines."""
    a, fa, b, fb = float(lo), flo, float(hi), fhi
    for _ in range(6):
        if hi - lo <= 1:
            break
        guess = a + fa / (fa - fb) * (b - a)
        if math.isnan(guess):
            guess = 0.0
        j = int(math.floor(guess)) if abs(guess) < 9e18 else -(2 ** 62)
        j = min(max(j, lo), hi - 1)
        fj = _plane(planes, j, x, y, z)
        fj1 = _plane(planes, j + 1, x, y, z)
        s_lo = math.copysign(1.0, flo)
        left = math.copysign(1.0, fj) == s_lo
        right1 = math.copysign(1.0, fj1) == s_lo
        if left and right1:
            lo, flo = j + 1, fj1
        elif left:
            lo, flo, hi, fhi = j, fj, j + 1, fj1
        else:
            hi, fhi = j, fj
        a, fa, b, fb = float(j), fj, float(j + 1), fj1
    return lo, hi, flo, fhi


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def bracket_one(planes, grid, x, y, z):
    """The line ``j`` with a sign change of point (x, y, z)'s plane condition between
    ``j`` and ``j + 1``: ``(j, f_j, f_j+1, found)`` (found False where the image's end
    lines agree in sign)."""
    lo, hi, flo, fhi = _coarse(planes, grid, x, y, z)
    if math.copysign(1.0, flo) != math.copysign(1.0, fhi):
        lo, hi, flo, fhi = _chord_steps(planes, x, y, z, lo, hi, flo, fhi)
    slo = _sgn(flo)
    found = (slo != _sgn(fhi)) and math.isfinite(flo) and math.isfinite(fhi)
    while found and hi - lo > 1:
        mid = (lo + hi) // 2
        fm = _plane(planes, mid, x, y, z)
        if _sgn(fm) == slo:
            lo, flo = mid, fm
        else:
            hi, fhi = mid, fm
    return lo, flo, fhi, found


def coarse_grid(n_lines: int, nodes: int = 8) -> np.ndarray:
    """The evenly spaced lines of the coarse pass (as ``linesolve.plane_brackets``)."""
    return np.unique(np.linspace(0, n_lines - 1, min(nodes, n_lines)).round().astype(np.intp))
