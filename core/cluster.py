"""The Dask cluster the parallel stages run on: an existing scheduler, a local one, or
workers submitted as SLURM jobs (dask-jobqueue)."""
from __future__ import annotations

import contextlib
import os

from swathflow.errors import SwathflowError

CLUSTERS = ("local", "slurm")


def slurm_options() -> dict:
    """SLURMCluster keyword arguments: Dask's ``jobqueue.slurm`` configuration (e.g.
    deploy/dask/jobqueue.yaml through ``DASK_CONFIG``) wins; where it leaves a size unset,
    one single-threaded 2 GB worker process per job."""
    import dask
    cfg = dask.config.get("jobqueue.slurm", default={}) or {}
    kw = {}
    for key, default in (("cores", 1), ("processes", 1), ("memory", "2GB")):
        if cfg.get(key) is None:
            kw[key] = default
    return kw


@contextlib.contextmanager
def dask_client(address: str | None = None, n_workers: int | None = None,
                cluster: str = "local", jobs: int | None = None,
                timeout: float = 600.0):
    """A Dask distributed client, closed on exit (with the cluster it started): on
    ``address``; or, for ``cluster="slurm"``, on ``jobs`` worker jobs submitted through
    SLURM (waits up to ``timeout`` s for the first worker); or on a local cluster sized to
    the machine (one single-threaded worker process per core, at most 4)."""
    from distributed import Client
    if address:
        with Client(address) as client:
            yield client
        return
    if cluster == "slurm":
        try:
            from dask_jobqueue import SLURMCluster
        except ImportError:  # pragma: no cover - a main dependency
            raise SwathflowError("--cluster slurm needs dask-jobqueue: pip install "
                                 "dask-jobqueue") from None
        with SLURMCluster(**slurm_options()) as slurm, Client(slurm) as client:
            slurm.scale(jobs=jobs or 1)
            try:
                client.wait_for_workers(1, timeout=timeout)
            except TimeoutError:
                raise SwathflowError(
                    f"no SLURM worker job started within {timeout:.0f} s: check `squeue` "
                    f"and the jobqueue.slurm settings (queue, account, walltime)") from None
            yield client
        return
    if cluster != "local":
        raise SwathflowError(f"unknown cluster {cluster!r}: use one of {', '.join(CLUSTERS)}")
    with local_cluster(n_workers) as local, Client(local) as client:
        yield client


@contextlib.contextmanager
def local_cluster(n_workers: int | None = None, preload: tuple[str, ...] = ()):
    """A local Dask cluster sized to the machine (``n_workers`` single-threaded worker
    processes; default one per core, at most 4), closed on exit. ``preload``: modules
    whose ``dask_setup(worker)`` each worker runs as it starts (Dask's worker preload)."""
    from distributed import LocalCluster
    n = n_workers or max(1, min(os.cpu_count() or 1, 4))
    extra = {"preload": list(preload)} if preload else {}
    with LocalCluster(n_workers=n, threads_per_worker=1, processes=True, **extra,
                      # CRITICAL: a worker that outlives the scheduler by a heartbeat at
                      # shutdown logs a CommClosedError traceback after a successful run
                      # (task failures still reach the client as exceptions)
                      dashboard_address=None, silence_logs=50) as local:
        yield local
