"""The blocks of dask arrays computed on the active scheduler and written in THIS process
(:func:`store_here`): the COG writer's loop (:mod:`.writing`), whose targets are open
files that must never travel to a worker. Dask's public API only: ``dask.array.store``
on a local scheduler, a ``distributed.Client``'s ``compute`` and ``as_completed`` on a
cluster."""
from __future__ import annotations

import itertools
import sys

import numpy as np

#: bound on the finished blocks gathered from a cluster before they are written (bytes)
BATCH_BYTES = 256 * 2 ** 20


def store_here(sources, targets, scheduler=None) -> None:
    """Compute the dask arrays ``sources`` and write each block into its ``targets``
    (``target[slices] = block``) in THIS process, memory bounded by the blocks in flight.
    On a local scheduler (``scheduler``, else the one dask's configuration names, else
    its threads) this is :func:`dask.array.store` with a lock (one graph: blocks the
    arrays share are computed once). With a ``distributed.Client`` (``scheduler`` itself,
    or the active one when none is given or configured) the blocks are computed on the
    cluster in batches of about :data:`BATCH_BYTES` and written here as they arrive."""
    import threading

    import dask.array as da
    client = _client(scheduler)
    if client is None:
        # a lock of our own: with lock=True dask imports distributed to look for a
        # cluster's lock (0.2-0.4 CPU-s), and no cluster is active here
        da.store(sources, targets, lock=threading.Lock(), scheduler=scheduler)
        return
    from distributed import as_completed
    items = [(blk, slc, tgt) for arr, tgt in zip(sources, targets)
             for blk, slc in zip(arr.to_delayed().ravel(), block_slices(arr.chunks))]
    biggest = max((int(np.prod([max(c) for c in a.chunks])) * a.dtype.itemsize
                   for a in sources), default=1)
    n = 4 * max(1, sum(client.nthreads().values()))
    n = max(2, min(n, BATCH_BYTES // max(biggest, 1)))
    for i in range(0, len(items), n):
        chunk = items[i:i + n]
        futures = client.compute([blk for blk, _, _ in chunk])
        index = {f.key: k for k, f in enumerate(futures)}
        for fut, value in as_completed(futures, with_results=True):
            _, slc, tgt = chunk[index[fut.key]]
            tgt[slc] = value


def block_slices(chunks) -> list[tuple[slice, ...]]:
    """The slices of every block of an array with dask ``chunks``, in row-major order
    (the order of ``to_delayed().ravel()``)."""
    edges = []
    for c in chunks:
        stops = list(itertools.accumulate(c))
        edges.append([slice(b - n, b) for b, n in zip(stops, c)])
    return list(itertools.product(*edges))


def _client(scheduler):
    """The ``distributed.Client`` that computes the blocks: ``scheduler`` if it is one;
    when ``scheduler`` is None and dask's configuration names no local scheduler, the
    active Client if ``distributed`` is in use; else None (a local scheduler)."""
    if scheduler is not None:
        return scheduler if hasattr(scheduler, "nthreads") else None
    import dask
    named = dask.config.get("scheduler", None)
    if named is not None and not (isinstance(named, str) and named.lower() in
                                  ("distributed", "dask.distributed")):
        return None
    if "distributed" not in sys.modules:        # no Client can be active
        return None
    from distributed import default_client
    try:
        return default_client()
    except ValueError:
        return None
