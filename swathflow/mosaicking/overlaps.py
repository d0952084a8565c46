"""Overlaps between swings and their matching (coarse to fine, on the active Dask cluster's
workers when there is one), then the network solution: :func:`plan`."""
from __future__ import annotations

import contextlib
import math
import os

import numpy as np

from swathflow.errors import SwathflowError
from swathflow.mosaicking.inputs import Layout, _Handles, read_window
from swathflow.mosaicking.matching import OverlapMatch, combine_blocks
from swathflow.mosaicking.network import solve_network

__all__ = ["find_overlaps", "match_pair", "plan"]


def _bbox_pairs(ext):
    """Pairs ``i < j`` of boxes ``(r0, c0, r1, c1)`` that intersect, by a sweep over the
    rows (cost grows with the number of boxes times the boxes met per row band, not with
    the number of boxes squared)."""
    order = np.argsort(ext[:, 0], kind="stable")
    r0s = ext[order, 0]
    out = []
    for a, i in enumerate(order):
        js = order[a + 1:np.searchsorted(r0s, ext[i, 2], side="left")]
        js = js[(ext[js, 1] < ext[i, 3]) & (ext[js, 3] > ext[i, 1]) & (ext[js, 2] > ext[i, 0])]
        out += [(int(min(i, j)), int(max(i, j))) for j in js]
    return sorted(out)


class _Footprints:
    """Valid masks of the swings decimated by ``step`` on the grid lattice (one read per
    swing, at most ``keep`` kept)."""

    def __init__(self, layout: Layout, handles, step: int, keep: int = 256):
        from collections import OrderedDict
        self.layout, self.handles, self.step, self.keep = layout, handles, step, keep
        self._m: OrderedDict = OrderedDict()

    def __call__(self, k):
        if k in self._m:
            self._m.move_to_end(k)
            return self._m[k]
        s, st = self.layout.swings[k], self.step
        r0, c0 = (s.row // st) * st, (s.col // st) * st
        r1, c1 = -(-(s.row + s.height) // st) * st, -(-(s.col + s.width) // st) * st
        _, ok = read_window(self.handles, s, r0, c0, r1, c1, step=st)
        self._m[k] = (r0, c0, ok)
        while len(self._m) > self.keep:
            self._m.popitem(last=False)
        return self._m[k]

    def common(self, i, j, win) -> int:
        """Pixels valid in both swings inside grid window ``win`` (decimated count)."""
        st = self.step
        (ri, ci, oi), (rj, cj, oj) = self(i), self(j)
        r0, c0 = (win[0] // st) * st, (win[1] // st) * st
        r1, c1 = -(-win[2] // st) * st, -(-win[3] // st) * st
        a = oi[(r0 - ri) // st:(r1 - ri) // st, (c0 - ci) // st:(c1 - ci) // st]
        b = oj[(r0 - rj) // st:(r1 - rj) // st, (c0 - cj) // st:(c1 - cj) // st]
        return int((a & b).sum()) * st * st


def find_overlaps(layout: Layout, groups=None, min_pixels: int = 256, handles=None,
                  max_cells: int = 256):
    """Pairs ``(i, j, window, n_common)`` of swings whose valid footprints overlap by at least
    ``min_pixels`` pixels (counted on each swing's valid mask decimated to about
    ``max_cells`` cells a side, read once per swing). ``groups``: optional node key per
    swing; pairs within one group are left out."""
    sw = layout.swings
    ext = np.array([s.extent for s in sw]).reshape(-1, 4)
    g = None if groups is None else list(groups)
    side = float(np.median(np.maximum(ext[:, 2] - ext[:, 0], ext[:, 3] - ext[:, 1])))
    step = max(1, min(int(math.ceil(side / max_cells)), int(math.sqrt(min_pixels)) // 2))
    own = handles is None
    handles = handles or _Handles()
    fp = _Footprints(layout, handles, step)
    pairs = []
    try:
        for i, j in _bbox_pairs(ext):
            if g is not None and g[i] == g[j]:
                continue
            win = (int(max(ext[i, 0], ext[j, 0])), int(max(ext[i, 1], ext[j, 1])),
                   int(min(ext[i, 2], ext[j, 2])), int(min(ext[i, 3], ext[j, 3])))
            n = fp.common(i, j, win)
            if n >= min_pixels:
                pairs.append((int(i), int(j), win, n))
    finally:
        if own:
            handles.close()
    return pairs


def match_pair(layout: Layout, i: int, j: int, win, handles=None, max_shift: int = 12,
               block: int = 128, max_blocks: int = 16, min_texture: float = 1.0,
               min_pixels: int = 256, coarse: int = 3) -> OverlapMatch:
    """Offset of swing ``j`` relative to swing ``i`` over their overlap ``win``, coarse to
    fine (swathflow.coarse: the integer offset on a ``coarse``-times decimated overview,
    then at most ``max_blocks`` well-textured blocks refined in a small window)."""
    from swathflow.mosaicking.coarse import match_overlap
    own = handles is None
    handles = handles or _Handles()
    a, b = layout.swings[i], layout.swings[j]
    S = int(max_shift)
    M = S + int(coarse) // 2 + 2
    r0, c0, r1, c1 = win
    try:
        ref, rok = read_window(handles, a, r0, c0, r1, c1)
        mov, mok = read_window(handles, b, r0 - M, c0 - M, r1 + M, c1 + M)
    finally:
        if own:
            handles.close()
    blocks, _ = match_overlap(ref, rok, mov, mok, M, S, block, max_blocks, min_texture,
                              min_pixels, factor=max(int(coarse), 1))
    for m in blocks:
        m.centre = (m.centre[0] + r0, m.centre[1] + c0)
    return combine_blocks(blocks)


def _node_keys(layout: Layout, per_image: bool):
    if per_image:
        return [s.image_id for s in layout.swings]
    return [s.strip for s in layout.swings]


def _resolve_anchors(layout, keys, nodes, anchors):
    out = set()
    by_id = {s.image_id: k for k, s in enumerate(layout.swings)}
    strips = {str(s.strip) for s in layout.swings}
    for a in anchors or ():
        a = str(a)
        if a in by_id:
            out.add(nodes.index(keys[by_id[a]]))
        elif a.removeprefix("strip:") in strips:
            sn = int(a.removeprefix("strip:"))
            for k, s in enumerate(layout.swings):
                if s.strip == sn:
                    out.add(nodes.index(keys[k]))
        else:
            raise SwathflowError(f"anchor {a!r} is neither an image id nor a strip number of "
                                 f"the inputs (image ids: {sorted(by_id)[:5]}...)")
    return sorted(out)


def _active_client():
    """The Dask distributed client of this context (the mission flow's cluster), if any.
    Without ``distributed`` imported there is none (importing it costs half a second)."""
    import sys
    if "distributed" not in sys.modules:
        return None
    try:
        from distributed import get_client
        return get_client()
    except (ImportError, ValueError):
        return None


def _match_batch(layout: Layout, batch, max_shift, block, min_texture, handles=None,
                 limit: bool = True):
    """Match a list of overlaps ``(i, j, win)`` with one set of open files (``handles``,
    else its own) and, with ``limit``, one BLAS thread (BLAS threads on top of the
    matching's own parallelism cost 5x on 2 cores; the local threads of :func:`match_all`
    are limited once around all of them instead: a limit entered and left per batch on
    concurrent threads restores the BLAS threads of one batch while another still runs)."""
    from threadpoolctl import threadpool_limits
    own = handles is None
    handles = handles or _Handles()
    try:
        with threadpool_limits(1) if limit else contextlib.nullcontext():
            return [match_pair(layout, i, j, win, handles, max_shift, block, 16, min_texture)
                    for i, j, win in batch]
    finally:
        if own:
            handles.close()


def match_all(layout: Layout, pairs, max_shift: int = 12, block: int = 128,
              min_texture: float = 1.0, workers: int | None = None, handles=None) -> list:
    """:func:`match_pair` for every overlap, in batches: on the active Dask distributed
    client's worker processes when there is one (the matching holds the GIL), else on
    ``workers`` local threads sharing ``handles`` (:class:`_Handles`; its own if None).

    With the swings kept decoded in ``handles`` (:meth:`_Handles.keep_if_fits`) the local
    threads slice them, and a cluster is used only when it has more threads than this
    machine has cores: its workers would decode every overlap's windows again. The survey
    flow's 644 overlaps on its 2 local workers took 7.6-7.8 CPU-s (workers and this
    process) and 17-19 s, on this process's 2 threads 3.3-3.5 CPU-s and 4.2-5.2 s (load 7-8,
    the same offsets)."""
    from concurrent.futures import ThreadPoolExecutor
    jobs = [(i, j, win) for i, j, win, *_ in pairs]
    client = _active_client()
    if client is not None and handles is not None and handles.keep_bytes > 0 and \
            sum(client.nthreads().values()) <= (os.cpu_count() or 1):
        client = None
    n = max(1, sum(client.nthreads().values())) if client is not None else \
        max(1, workers or os.cpu_count() or 1)
    # batches for the cluster's workers (a task has its overheads); one overlap at a time
    # on local threads, so none is left alone with the last batch
    size = max(1, math.ceil(len(jobs) / (4 * n))) if client is not None else 1
    batches = [jobs[k:k + size] for k in range(0, len(jobs), size)]
    if client is not None:
        lay = client.scatter(layout, broadcast=True)
        futures = [client.submit(_match_batch, lay, b, max_shift, block, min_texture,
                                 pure=False) for b in batches]
        done = client.gather(futures)
    else:
        from threadpoolctl import threadpool_limits
        with threadpool_limits(1), ThreadPoolExecutor(n) as ex:
            done = list(ex.map(lambda b: _match_batch(layout, b, max_shift, block,
                                                      min_texture, handles, False), batches))
    return [m for part in done for m in part]


def plan(layout: Layout, per_image: bool = False, anchors=(), max_shift: int = 12,
         block: int = 128, min_texture: float = 1.0, workers: int | None = None,
         log=None, control: dict | None = None, handles=None):
    """Match every overlap (:func:`match_all`) and solve the network. ``control``: image id
    -> ``(offset (drow, dcol), sigma (row, col))``, the image's absolute offset from its
    control points, which ties the network to the ground. ``handles``: the
    :class:`_Handles` to read through (e.g. keeping decoded swings for the blend; its own
    if None). Returns (network, pairs, matches, keys)."""
    keys = _node_keys(layout, per_image)
    nodes = list(dict.fromkeys(keys))
    node_of = {k: q for q, k in enumerate(nodes)}
    pairs = find_overlaps(layout, groups=keys, handles=handles)
    if log:
        log(f"{len(layout.swings)} swings, {len(nodes)} nodes, {len(pairs)} overlaps")
    matches = match_all(layout, pairs, max_shift, block, min_texture, workers, handles)
    obs = [(node_of[keys[i]], node_of[keys[j]], m) for (i, j, _, _), m in zip(pairs, matches)]
    by_id = {s.image_id: k for k, s in enumerate(layout.swings)}
    absolute = [(node_of[keys[by_id[iid]]], off, sig) for iid, (off, sig) in
                sorted((control or {}).items()) if iid in by_id]
    net = solve_network(nodes, obs, _resolve_anchors(layout, keys, nodes, anchors),
                        absolute=absolute)
    return net, pairs, matches, keys
