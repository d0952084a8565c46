"""The Dask cluster the parallel stages run on: an existing scheduler, or a local one."""
from __future__ import annotations

import contextlib
import os


@contextlib.contextmanager
def dask_client(address: str | None = None, n_workers: int | None = None):
    """A Dask distributed client: on ``address``, or on a local cluster sized to the
    machine (one single-threaded worker process per core, at most 4), closed on exit."""
    from distributed import Client, LocalCluster
    if address:
        with Client(address) as client:
            yield client
        return
    n = n_workers or max(1, min(os.cpu_count() or 1, 4))
    with LocalCluster(n_workers=n, threads_per_worker=1, processes=True,
                      # CRITICAL: a worker that outlives the scheduler by a heartbeat at
                      # shutdown logs a CommClosedError traceback after a successful run
                      # (task failures still reach the client as exceptions)
                      dashboard_address=None, silence_logs=50) as cluster, \
            Client(cluster) as client:
        yield client
