"""The Dask cluster the parallel work runs on: an existing scheduler, a local one, or
workers submitted as SLURM jobs (dask-jobqueue). Every worker is started by Dask itself
(``distributed.LocalCluster``'s nannies, ``dask worker``, dask-jobqueue's jobs)."""
from __future__ import annotations

import contextlib
import logging

from swathflow.errors import SwathflowError

CLUSTERS = ("local", "slurm")

#: seconds to wait for a named scheduler (``--dask-address``) to answer
CONNECT_TIMEOUT = 10.0


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


def default_workers() -> int:
    """One worker per core this process may use (Dask's own count: CPU affinity and
    cgroup limits included)."""
    from dask.system import CPU_COUNT
    return max(1, int(CPU_COUNT))


def connect(address: str, timeout: float = CONNECT_TIMEOUT):
    """A Dask client of the scheduler at ``address``; a :class:`SwathflowError` naming
    the address when none answers within ``timeout`` s (or the address is malformed)."""
    from distributed import Client
    try:
        return Client(address, timeout=timeout)
    except Exception as exc:  # noqa: BLE001 - whatever failed, no scheduler to use
        cause = " ".join(str(exc).split())[:300] or type(exc).__name__
        raise SwathflowError(
            f"--dask-address {address}: no Dask scheduler answered within {timeout:.0f} s "
            f"({cause}); check the address (tcp://HOST:PORT) and that the scheduler "
            f"runs, or leave --dask-address out for a local cluster") from None


@contextlib.contextmanager
def dask_client(address: str | None = None, n_workers: int | None = None,
                cluster: str = "local", jobs: int | None = None,
                timeout: float = 600.0, preload: tuple[str, ...] = ()):
    """A Dask distributed client, closed on exit (with the cluster it started): on
    ``address`` (:func:`connect`); or, for ``cluster="slurm"``, on ``jobs`` worker jobs
    submitted through SLURM (waits up to ``timeout`` s for the first worker); or on a
    local cluster (:func:`local_cluster`: ``n_workers`` processes, ``preload``)."""
    from distributed import Client
    if address:
        with connect(address) as client:
            yield client
        return
    if cluster == "slurm":
        try:
            from dask_jobqueue import SLURMCluster
        except ImportError:  # pragma: no cover - a main dependency
            raise SwathflowError("--cluster slurm needs dask-jobqueue: pip install "
                                 "dask-jobqueue") from None
        import shutil
        if shutil.which("sbatch") is None:
            raise SwathflowError("--cluster slurm: SLURM's sbatch is not on PATH here; run "
                                 "on a SLURM login node (or load its module), or use "
                                 "--cluster local")
        with SLURMCluster(**slurm_options()) as slurm, Client(slurm) as client:
            slurm.scale(jobs=jobs or 1)
            first_worker(client, timeout)
            yield client
        return
    if cluster != "local":
        raise SwathflowError(f"unknown cluster {cluster!r}: use one of {', '.join(CLUSTERS)}")
    with local_cluster(n_workers, preload) as local, Client(local) as client:
        yield client


def first_worker(client, timeout: float) -> None:
    """Wait until a worker has joined ``client``'s scheduler, polled (Dask's own
    ``wait_for_workers`` on a SLURMCluster ignored its timeout: a job that never started
    kept the run waiting for good); a :class:`SwathflowError` after ``timeout`` s."""
    import time
    deadline = time.monotonic() + timeout
    while not client.scheduler_info().get("workers"):
        if time.monotonic() > deadline:
            raise SwathflowError(
                f"no SLURM worker job started within {timeout:.0f} s: check `squeue` "
                f"and the jobqueue.slurm settings (queue, account, walltime)")
        time.sleep(0.5)


def leave_quickly() -> None:
    """This process's objects left out of the garbage collector's passes from now on
    (``gc.freeze``): for a process that is about to end, e.g. a Dask worker being
    closed (Dask's ``dask_teardown`` preload hook). The collector's last passes over
    the engine's objects as the interpreter ends took 1.4-2.4 s of a worker's close
    (0.3 s without them), and Dask's nanny kills a worker that takes over 4 s."""
    import gc
    gc.disable()
    gc.freeze()


#: the HTTP routes of a local cluster's scheduler and workers: none. Dask starts an HTTP
#: server even with ``dashboard_address=None`` (Prometheus metrics, JSON state, health,
#: on 127.0.0.1:8787 for the scheduler); no dashboard is shown, so it serves nothing, on
#: a free loopback port (Dask's configuration ``distributed.*.http.routes``)
NO_HTTP = {"distributed.scheduler.http.routes": [], "distributed.worker.http.routes": []}


def dask_setup(worker=None) -> None:
    """Dask's worker preload hook of every worker of :func:`local_cluster`: Ctrl-C ends a
    worker the way it ends any program, silently. A terminal sends SIGINT to every process
    of its foreground job, the local workers too: Python's KeyboardInterrupt then printed
    a traceback from each, on that terminal, while the run was stopping anyway. (Ignoring
    SIGINT instead kept the workers alive and Prefect's report of the interrupted run
    waiting on its server, which the same Ctrl-C stops: minutes of retries.)"""
    import signal
    import threading
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGINT, signal.SIG_DFL)


def local_cluster(n_workers: int | None = None, preload: tuple[str, ...] = ()):
    """A ``distributed.LocalCluster`` on this machine: ``n_workers`` single-threaded worker
    processes (default :func:`default_workers`) started by Dask's nannies, the scheduler
    on loopback; ``preload``: modules whose ``dask_setup(worker)`` each worker runs as it
    starts (Dask's worker preload), after this module's (:func:`dask_setup`). Use it as a
    context manager (closed on exit)."""
    import dask
    from distributed import LocalCluster
    if n_workers is not None and n_workers < 1:
        raise SwathflowError(f"workers must be at least 1, not {n_workers}")
    n = n_workers or default_workers()
    extra = {"preload": [__name__, *preload]}
    with dask.config.set(NO_HTTP):
        return LocalCluster(n_workers=n, threads_per_worker=1, processes=True,
                            host="127.0.0.1", dashboard_address=None, **extra,
                            scheduler_kwargs={"dashboard_address": "127.0.0.1:0"},
                            # CRITICAL: a worker that outlives the scheduler by a
                            # heartbeat at the close logs a CommClosedError traceback
                            # (task failures still reach the client as exceptions)
                            silence_logs=logging.CRITICAL)
