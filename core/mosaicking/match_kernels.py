"""Compiled kernel of the overlap matching (numba, ``nogil``, ``cache=True``): the paper's
minimum-mean-grey-difference cost over all integer shifts, so the overlaps match on every
core through threads (the numpy version held the GIL in its per-shift partitions)."""
from __future__ import annotations

import numpy as np
from numba import njit

__all__ = ["mmgd_costs"]


@njit(cache=True, nogil=True)
def mmgd_costs(ref, ref_ok, mov, mov_ok, S, min_pixels):
    """``cost[S + dr, S + dc]``: mean ``|d - median(d)|`` of ``d = ref[x] - mov[x + s]`` over
    the pixels valid in both, for every shift ``s = (dr, dc)`` with ``|dr|, |dc| <= S``
    (``mov`` is read with a margin of ``S``); ``inf`` where fewer than ``min_pixels``."""
    h, w = ref.shape
    n_s = 2 * S + 1
    cost = np.full((n_s, n_s), np.inf)
    buf = np.empty(h * w)
    for i in range(n_s):
        for j in range(n_s):
            n = 0
            for r in range(h):
                for c in range(w):
                    if ref_ok[r, c] and mov_ok[r + i, c + j]:
                        buf[n] = ref[r, c] - mov[r + i, c + j]
                        n += 1
            if n < min_pixels or n == 0:
                continue
            med = np.median(buf[:n])
            s = 0.0
            for k in range(n):
                s += abs(buf[k] - med)
            cost[i, j] = s / n
    return cost
