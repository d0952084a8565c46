"""Solve for the continuous scan line at which ground points cross a line scanner's
viewing surface: vectorised bisection over integer lines, then secant steps on the exact
condition at fractional lines. Shared by every line-scanner sensor model.
"""
from __future__ import annotations

from typing import Callable

import numpy as np


def bracket_lines(f_at: Callable[[np.ndarray, np.ndarray], np.ndarray], n_points: int,
                  n_lines: int, lo=None, hi=None
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Find for each point an integer ``j`` with a sign change of ``f`` between ``j, j+1``.

    ``f_at(point_index, line_index)`` evaluates the crossing condition at integer lines.
    ``lo``/``hi`` optionally narrow the starting bracket per point. Returns
    ``(j, f_j, f_j1, found)``; ``found`` is False where the end lines do not differ in sign
    (the point is not swept by the image).
    """
    idx = np.arange(n_points)
    lo = np.zeros(n_points, dtype=np.intp) if lo is None else np.asarray(lo, np.intp).copy()
    hi = (np.full(n_points, n_lines - 1, dtype=np.intp) if hi is None
          else np.asarray(hi, np.intp).copy())
    flo = f_at(idx, lo)
    fhi = f_at(idx, hi)
    found = (np.sign(flo) != np.sign(fhi)) & np.isfinite(flo) & np.isfinite(fhi)
    slo = np.sign(flo)
    while True:
        open_ = found & (hi - lo > 1)
        if not open_.any():
            break
        k = np.flatnonzero(open_)
        mid = (lo[k] + hi[k]) // 2
        fm = f_at(k, mid)
        left = np.sign(fm) == slo[k]
        lo[k] = np.where(left, mid, lo[k])
        flo[k] = np.where(left, fm, flo[k])
        hi[k] = np.where(left, hi[k], mid)
        fhi[k] = np.where(left, fhi[k], fm)
    return lo, flo, fhi, found


def plane_brackets(points: np.ndarray, planes: np.ndarray, nodes: int = 64,
                   chunk: int = 65536) -> tuple[np.ndarray, np.ndarray]:
    """Narrow brackets from a coarse pass over evenly spaced lines.

    ``planes`` ``(n_lines, 4)`` holds each line's viewing plane as ``(normal, offset)`` with
    the condition ``normal . X + offset``; evaluating ``nodes`` lines for all points is one
    matrix product per chunk. Returns per-point ``(lo, hi)`` line indices around the first
    sign change (the full range where there is none, so the caller reports "not found").
    """
    n_lines = planes.shape[0]
    n = points.shape[0]
    grid = np.unique(np.linspace(0, n_lines - 1, min(nodes, n_lines)).round().astype(np.intp))
    lo = np.zeros(n, dtype=np.intp)
    hi = np.full(n, n_lines - 1, dtype=np.intp)
    p = planes[grid]
    for s in range(0, n, chunk):
        f = points[s:s + chunk] @ p[:, :3].T + p[:, 3]
        sg = np.signbit(f)
        change = sg[:, 1:] != sg[:, :-1]
        has = change.any(axis=1)
        first = np.argmax(change, axis=1)
        lo[s:s + chunk] = np.where(has, grid[first], 0)
        hi[s:s + chunk] = np.where(has, grid[first + 1], n_lines - 1)
    return lo, hi


def secant_lines(f_exact: Callable[[np.ndarray, np.ndarray], np.ndarray], j, fj, fj1,
                 tol: float = 1e-9, max_iter: int = 8) -> np.ndarray:
    """Refine fractional lines inside ``[j, j+1]`` with secant steps on the exact condition.

    ``f_exact(point_index, line)`` evaluates at fractional lines. Starts from the chord of
    the bracket; converges quadratically (the condition is smooth within a line).
    """
    n = len(j)
    idx = np.arange(n)
    l0 = j.astype(float)
    f0 = fj.astype(float)
    with np.errstate(invalid="ignore", divide="ignore"):
        l1 = j + fj / (fj - fj1)
    l1 = np.where(np.isfinite(l1), l1, j + 0.5)
    active = idx
    for _ in range(max_iter):
        if active.size == 0:
            break
        f1 = f_exact(active, l1[active])
        with np.errstate(invalid="ignore", divide="ignore"):
            step = f1 * (l1[active] - l0[active]) / (f1 - f0[active])
        step = np.where(np.isfinite(step), step, 0.0)
        l0[active] = l1[active]
        f0[active] = f1
        l1[active] = l1[active] - step
        active = active[np.abs(step) > tol]
    return l1
