"""Solve for the continuous scan line at which ground points cross a line scanner's
viewing surface: vectorised bisection over integer lines, then secant steps on the exact
condition at fractional lines. Shared by every line-scanner sensor model.
"""
from __future__ import annotations

from typing import Callable

import numpy as np


def bracket_lines(f_at: Callable[[np.ndarray, np.ndarray], np.ndarray], n_points: int,
                  n_lines: int, lo=None, hi=None, flo=None, fhi=None
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Find for each point an integer ``j`` with a sign change of ``f`` between ``j, j+1``.

    ``f_at(point_index, line_index)`` evaluates the crossing condition at integer lines.
    ``lo``/``hi`` optionally narrow the starting bracket per point (with ``flo``/``fhi``,
    the condition's values there, when already known). Returns
    ``(j, f_j, f_j1, found)``; ``found`` is False where the end lines do not differ in sign
    (the point is not swept by the image).
    """
    idx = np.arange(n_points)
    lo = np.zeros(n_points, dtype=np.intp) if lo is None else np.asarray(lo, np.intp).copy()
    hi = (np.full(n_points, n_lines - 1, dtype=np.intp) if hi is None
          else np.asarray(hi, np.intp).copy())
    flo = f_at(idx, lo) if flo is None else np.asarray(flo, float).copy()
    fhi = f_at(idx, hi) if fhi is None else np.asarray(fhi, float).copy()
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


def plane_brackets(points: np.ndarray, planes: np.ndarray, nodes: int = 8,
                   chunk: int = 65536) -> tuple[np.ndarray, ...]:
    """Narrow brackets from a coarse pass over evenly spaced lines, then one chord step.

    ``planes`` ``(n_lines, 4)`` holds each line's viewing plane as ``(normal, offset)`` with
    the condition ``normal . X + offset``; evaluating ``nodes`` lines for all points is one
    matrix product per chunk. Inside the coarse bracket the root's line is guessed from the
    chord and checked at the two integer lines around the guess; where the root is not
    between them, the secant through those two lines guesses again (at most six times),
    which settles nearly every point without bisection. Returns per-point
    ``(lo, hi, f_lo, f_hi)``; the full range where there is no sign change, so the caller
    reports "not found".
    """
    n_lines = planes.shape[0]
    n = points.shape[0]
    grid = np.unique(np.linspace(0, n_lines - 1, min(nodes, n_lines)).round().astype(np.intp))
    lo = np.zeros(n, dtype=np.intp)
    hi = np.full(n, n_lines - 1, dtype=np.intp)
    flo = np.empty(n)
    fhi = np.empty(n)
    p = planes[grid]
    rows = np.arange(min(chunk, n))
    for s in range(0, n, chunk):
        f = points[s:s + chunk] @ p[:, :3].T + p[:, 3]
        m = f.shape[0]
        sg = np.signbit(f)
        change = sg[:, 1:] != sg[:, :-1]
        has = change.any(axis=1)
        first = np.argmax(change, axis=1)
        lo[s:s + m] = np.where(has, grid[first], 0)
        hi[s:s + m] = np.where(has, grid[first + 1], n_lines - 1)
        flo[s:s + m] = np.where(has, f[rows[:m], first], f[:, 0])
        fhi[s:s + m] = np.where(has, f[rows[:m], first + 1], f[:, -1])

    def f_at(i, j):
        pl = planes[j]
        q = points[i]
        return pl[:, 0] * q[:, 0] + pl[:, 1] * q[:, 1] + pl[:, 2] * q[:, 2] + pl[:, 3]

    k = np.flatnonzero((hi - lo > 1) & (np.signbit(flo) != np.signbit(fhi)))
    # secant steps: first the chord of the coarse bracket, then the local secant through
    # the two lines just evaluated (nearly exact: the condition is smooth over a line)
    a, fa, b, fb = lo[k], flo[k], hi[k], fhi[k]
    for _ in range(6):
        if not k.size:
            break
        with np.errstate(invalid="ignore", divide="ignore"):
            guess = a + fa / (fa - fb) * (b - a)
        j = np.clip(np.floor(np.nan_to_num(guess)).astype(np.intp), lo[k], hi[k] - 1)
        fj, fj1 = f_at(k, j), f_at(k, j + 1)
        left = np.signbit(fj) == np.signbit(flo[k])          # root right of j
        right1 = np.signbit(fj1) == np.signbit(flo[k])       # root right of j + 1
        new_lo = np.where(left, np.where(right1, j + 1, j), lo[k])
        new_flo = np.where(left, np.where(right1, fj1, fj), flo[k])
        new_hi = np.where(left & ~right1, j + 1, np.where(left, hi[k], j))
        new_fhi = np.where(left & ~right1, fj1, np.where(left, fhi[k], fj))
        lo[k], flo[k], hi[k], fhi[k] = new_lo, new_flo, new_hi, new_fhi
        still = hi[k] - lo[k] > 1
        k, a, fa, b, fb = k[still], j[still], fj[still], j[still] + 1, fj1[still]
    return lo, hi, flo, fhi


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
