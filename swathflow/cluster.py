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


#: the HTTP routes of a local cluster's scheduler and of forked workers: none. Dask starts
#: an HTTP server even with ``dashboard_address=None`` (Prometheus metrics, JSON state,
#: health, on 127.0.0.1:8787 for the scheduler); no dashboard is shown, so it serves
#: nothing, on a free loopback port
NO_HTTP = {"distributed.scheduler.http.routes": [], "distributed.worker.http.routes": []}


@contextlib.contextmanager
def local_cluster(n_workers: int | None = None, preload: tuple[str, ...] = (),
                  fork_setup=None, worker_setup=None):
    """A local Dask cluster sized to the machine (``n_workers`` single-threaded worker
    processes; default one per core, at most 4), closed on exit. ``preload``: modules
    whose ``dask_setup(worker)`` each worker runs as it starts (Dask's worker preload).

    ``fork_setup``: when given, and this process runs only its main thread on a platform
    with ``fork``, ``fork_setup()`` runs here and the workers are then forked from this
    process (:func:`forked_workers`): they start with its imports and memory (e.g. a
    loaded mission) instead of importing everything again (about 1.5 CPU-s each), and
    ``preload`` is not run; each then runs ``worker_setup()`` (when given) on a thread
    while it joins the scheduler (its first task may run meanwhile). Otherwise Dask's
    nannies spawn them."""
    import dask
    from distributed import LocalCluster
    n = n_workers or max(1, min(os.cpu_count() or 1, 4))
    with contextlib.ExitStack() as stack:
        forked = None
        if fork_setup is not None and can_fork():
            fork_setup()
            forked = stack.enter_context(forked_workers(n, worker_setup))
        extra = {"preload": list(preload)} if preload and forked is None else {}
        with dask.config.set(NO_HTTP):
            local = stack.enter_context(LocalCluster(
                n_workers=0 if forked else n, threads_per_worker=1, processes=True, **extra,
                # CRITICAL: a worker that outlives the scheduler by a heartbeat at shutdown
                # logs a CommClosedError traceback after a successful run (task failures
                # still reach the client as exceptions)
                dashboard_address=None, silence_logs=50,
                scheduler_kwargs={"dashboard_address": "127.0.0.1:0"}))
        if forked is not None:
            forked.start(local)
        yield local


def can_fork() -> bool:
    """Forking this process is safe: ``fork`` exists and only the main thread runs (a
    thread holding a lock at the fork, e.g. a logging handler's, would leave it held in
    the child forever)."""
    import multiprocessing
    import threading
    return "fork" in multiprocessing.get_all_start_methods() and threading.active_count() == 1


class _Forked:
    """Worker processes forked by :func:`forked_workers`, waiting for the scheduler."""

    def __init__(self, pids: list[int], pipes: list[int]):
        self.pids, self.pipes = pids, pipes

    def start(self, cluster, timeout: float = 60.0) -> None:
        """Tell the workers ``cluster``'s scheduler address; wait until all registered."""
        import time
        address = cluster.scheduler_address.encode()
        for fd in self.pipes:
            os.write(fd, address)
            os.close(fd)
        self.pipes = []
        limit = time.monotonic() + timeout
        while len(cluster.scheduler.workers) < len(self.pids):
            for pid in self.pids:
                if os.waitpid(pid, os.WNOHANG)[0]:
                    raise RuntimeError(f"a forked Dask worker (process {pid}) ended before "
                                       f"it joined the scheduler")
            if time.monotonic() > limit:
                raise RuntimeError(f"timed out waiting for {len(self.pids)} forked Dask "
                                   f"workers to join the scheduler")
            time.sleep(0.01)


@contextlib.contextmanager
def forked_workers(n: int, setup=None):
    """``n`` processes forked from this one (see :func:`can_fork`), each to become a
    single-threaded Dask worker once ``start(cluster)`` tells it the scheduler's address
    (``setup()``, when given, run in each on a thread beside the worker's start: its
    failure is printed, the worker serves);
    on exit the ones still running (the scheduler's close ends them) are waited for, then
    ended. Python's objects are frozen across the fork (no collector passes copy their
    pages into the workers), as the rectify command does before it forks."""
    import gc
    import sys

    import distributed.worker  # noqa: F401  (imported once, here, for every worker)
    pids, pipes, parent = [], [], os.getpid()
    for stream in (sys.stdout, sys.stderr):
        stream.flush()      # not written again by the children
    gc.freeze()
    try:
        for k in range(n):
            r, w = os.pipe()
            pid = os.fork()
            if pid == 0:    # pragma: no cover - the child never returns
                os.close(w)
                for fd in pipes:
                    os.close(fd)
                _worker(r, k, parent, setup)
            os.close(r)
            pids.append(pid)
            pipes.append(w)
    finally:
        gc.unfreeze()
    forked = _Forked(pids, pipes)
    try:
        yield forked
    finally:
        for fd in forked.pipes:     # never started: the children read no address and end
            os.close(fd)
        _reap(pids)


def _reap(pids: list[int], timeout: float = 10.0) -> None:
    """Wait for the child processes ``pids`` to end; after ``timeout`` s, kill the rest."""
    import signal
    import time
    limit, left = time.monotonic() + timeout, set(pids)
    while left:
        for pid in list(left):
            with contextlib.suppress(ChildProcessError):
                if not os.waitpid(pid, os.WNOHANG)[0]:
                    continue
            left.discard(pid)
        if left and time.monotonic() > limit:
            for pid in left:
                with contextlib.suppress(ProcessLookupError):
                    os.kill(pid, signal.SIGKILL)
            for pid in left:
                with contextlib.suppress(ChildProcessError):
                    os.waitpid(pid, 0)
            return
        if left:
            time.sleep(0.01)


def _worker(fd: int, name: int, parent: int,
            setup=None) -> None:  # pragma: no cover - runs in a forked child
    """A forked child: ``setup()`` started on a thread of its own, then the scheduler's
    address read from ``fd``, served as a Dask worker (one thread) until the scheduler
    closes it, then ended without the interpreter's teardown (the parent's exit handlers
    are not the child's)."""
    import signal
    import sys
    code = 1
    try:
        signal.signal(signal.SIGTERM, signal.SIG_DFL)   # the parent's handler is not ours
        signal.signal(signal.SIGINT, signal.SIG_IGN)    # Ctrl-C: the parent closes us
        _end_with_parent(parent)
        if setup is not None:   # beside the worker's start: the scheduler waits for none
            import threading
            threading.Thread(target=_setup, args=(setup,), daemon=True).start()
        address = b""
        while chunk := os.read(fd, 4096):
            address += chunk
        os.close(fd)
        if address:
            import asyncio
            import logging

            import dask
            from distributed import Worker

            # as LocalCluster's silence_logs=50 quiets a spawned worker (its handlers at
            # CRITICAL, set in this process after the fork): a heartbeat in flight as the
            # scheduler closes printed a CommClosedError traceback after a successful run
            logging.getLogger("distributed").setLevel(logging.CRITICAL)

            async def serve():
                async with Worker(address.decode(), nthreads=1, name=name,
                                  death_timeout=60) as worker:
                    await worker.finished()

            with dask.config.set(NO_HTTP):
                asyncio.run(serve())
        code = 0
    except BaseException:   # noqa: BLE001 - told on stderr, the parent sees the exit
        import traceback
        traceback.print_exc()
    finally:
        for stream in (sys.stdout, sys.stderr):
            with contextlib.suppress(Exception):
                stream.flush()
        os._exit(code)


def _setup(setup) -> None:  # pragma: no cover - in a forked child
    try:
        setup()
    except Exception:   # noqa: BLE001 - told on stderr; the worker serves anyway
        import traceback
        traceback.print_exc()


def _end_with_parent(parent: int) -> None:  # pragma: no cover - in a forked child
    """Linux: this process is sent SIGTERM when its parent ``parent`` ends (even by
    SIGKILL); ended at once if it already has."""
    import ctypes
    import signal
    with contextlib.suppress(Exception):
        ctypes.CDLL(None, use_errno=True).prctl(1, int(signal.SIGTERM))  # PR_SET_PDEATHSIG
        if os.getppid() != parent:
            os._exit(1)
