"""The blocks of dask arrays computed and written in THIS process, as they arrive
(:func:`store_here`): the COG writer's loop (:mod:`.writing`), whose targets are open
files that must never travel to a worker."""
from __future__ import annotations

import numpy as np

#: bound on the finished blocks held before they are written (bytes)
BATCH_BYTES = 256 * 2 ** 20


def store_here(sources, targets, scheduler=None, batch: int | None = None) -> None:
    """Compute the arrays' blocks on the active scheduler (threads, or a distributed
    cluster) and write each block in THIS process as it arrives. The targets are open
    files, which must never travel to a worker; memory stays bounded by one batch of
    blocks. Blocks of one batch share their graph, so common tiles are computed once.
    On the synchronous scheduler (the command's forked workers) the blocks are computed
    one by one here (:func:`_blocks_in_order`), also when dask's configuration names it
    (the flow's Dask workers set ``scheduler="sync"`` around their swings)."""
    import dask
    from dask.array.core import slices_from_chunks
    scheduler = _configured(scheduler)
    if _synchronous(scheduler):
        for arr, tgt in zip(sources, targets):
            for slc, value in _blocks_in_order(arr):
                tgt[slc] = value
        return
    items = []
    for arr, tgt in zip(sources, targets):
        for blk, slc in zip(arr.to_delayed().ravel(), slices_from_chunks(arr.chunks)):
            items.append((blk, slc, tgt))
    client = None
    if scheduler is None:
        try:
            from distributed import default_client
            client = default_client()
        except (ImportError, ValueError):
            client = None
    n = batch or (4 * max(1, sum(client.nthreads().values())) if client else 16)
    # multi-band tiles are large: at most about BATCH_BYTES of finished blocks at a time
    biggest = max((int(np.prod([max(c) for c in a.chunks])) * a.dtype.itemsize
                   for a in sources), default=1)
    n = max(2, min(n, BATCH_BYTES // max(biggest, 1)))
    for i in range(0, len(items), n):
        chunk = items[i:i + n]
        if client is not None:
            from distributed import as_completed
            futures = client.compute([blk for blk, _, _ in chunk])
            index = {f.key: k for k, f in enumerate(futures)}
            for fut, value in as_completed(futures, with_results=True):
                _, slc, tgt = chunk[index[fut.key]]
                tgt[slc] = value
        else:
            values = dask.compute(*[blk for blk, _, _ in chunk], scheduler=scheduler)
            for (_, slc, tgt), value in zip(chunk, values):
                tgt[slc] = value


def _configured(scheduler):
    """``scheduler``, or when None the one dask's configuration names (dask's own order:
    the configured scheduler before a Client), None for a Client's."""
    import dask
    if scheduler is None:
        scheduler = dask.config.get("scheduler", None)
        if isinstance(scheduler, str) and scheduler.lower() in ("distributed",
                                                                "dask.distributed"):
            return None
    return scheduler


def _synchronous(scheduler) -> bool:
    """Whether ``scheduler`` (as :func:`store_here` gets it: None is the active one) is
    dask's synchronous one: the blocks are then computed here by :func:`_blocks_in_order`,
    one at a time."""
    from dask.callbacks import Callback
    if Callback.active:             # diagnostics or a progress bar watch dask's tasks
        return False
    try:                            # dask's task objects (2024.12 on)
        from dask._task_spec import convert_legacy_graph, cull  # noqa: F401
    except ImportError:
        return False
    if isinstance(scheduler, str):
        return scheduler.lower() in ("sync", "synchronous", "single-threaded")
    from dask.local import get_sync
    return scheduler is get_sync


def _blocks_in_order(arr):
    """``(slices, block)`` of every block of a dask array, computed in this process one
    block at a time (row-major), each task run once and its result dropped when its last
    dependent has run: what :func:`dask.compute` on the synchronous scheduler gives for
    each batch of blocks, without the graph's conversion, culling and ordering per batch
    nor the fused tasks' subgraphs (0.27 of 6.5 CPU-s over the 468 tiles of the demo at
    0.05 m). The graph is run as built, culled to the blocks (fusing its tasks only adds
    work here)."""
    from dask._task_spec import convert_legacy_graph, cull
    from dask.array.core import slices_from_chunks
    from dask.core import flatten
    keys = list(flatten(arr.__dask_keys__()))
    dsk = cull(convert_legacy_graph(dict(arr.__dask_graph__())), keys)
    left: dict = {}                     # dependents not yet run, of every task
    for node in dsk.values():
        for d in node.dependencies:
            left[d] = left.get(d, 0) + 1
    cache: dict = {}

    def run(key):
        if key in cache:
            return cache[key]
        node = dsk[key]
        for d in node.dependencies:
            run(d)
        value = node(cache)
        for d in node.dependencies:
            left[d] -= 1
            if not left[d]:
                del cache[d]
        if left.get(key):
            cache[key] = value
        return value

    for key, slc in zip(keys, slices_from_chunks(arr.chunks)):
        yield slc, run(key)
