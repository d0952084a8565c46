"""The services a run uses, reached through their public APIs: Prefect's API (the server
named by ``PREFECT_API_URL`` or Prefect's own temporary server) checked with a timeout, a
run interrupted without waiting on a Prefect server the same Ctrl-C stopped, and the
processes of a run killed by SIGKILL found and ended by the next run."""
from __future__ import annotations

import contextlib
import os

from swathflow.errors import SwathflowError


#: seconds to wait for the Prefect server named by ``PREFECT_API_URL`` to answer
PREFECT_TIMEOUT = 10.0


def prefect_ready(timeout: float = PREFECT_TIMEOUT) -> None:
    """Prefect's API answers, through Prefect's public client (``get_client``): the
    server named by ``PREFECT_API_URL`` within ``timeout`` s (no retries), or else
    Prefect's own temporary server, which the client starts (Prefect's ephemeral mode;
    its start waits up to ``PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS``). A
    :class:`SwathflowError` saying what to do otherwise. After :func:`start_prefect`,
    waits for its thread instead."""
    thread = _STARTING.pop("thread", None)
    if thread is not None:
        thread.join()
        error = _STARTING.pop("error", None)
        if error is not None:
            raise error
        return
    _healthy(timeout)


#: the thread of :func:`start_prefect` and its failure
_STARTING: dict = {}


def start_prefect(timeout: float = PREFECT_TIMEOUT) -> None:
    """:func:`prefect_ready` begun on a thread of its own: Prefect's temporary server
    starts (its process imports the server's code, about 3 CPU-s) while this process
    does other work, e.g. checks the mission; :func:`prefect_ready` then waits for it.
    Prefect stops its temporary server when this process exits, as always."""
    import threading
    if "thread" in _STARTING:
        return

    def start():
        try:
            _healthy(timeout)
        except BaseException as exc:  # noqa: BLE001 - raised by prefect_ready
            _STARTING["error"] = exc
    _STARTING["thread"] = threading.Thread(target=start, name="prefect-start", daemon=True)
    _STARTING["thread"].start()


def _healthy(timeout: float) -> None:
    from prefect import get_client
    from prefect.settings import (PREFECT_API_URL, PREFECT_CLIENT_MAX_RETRIES,
                                  PREFECT_SERVER_EPHEMERAL_ENABLED, temporary_settings)
    url = PREFECT_API_URL.value()
    if not url and not PREFECT_SERVER_EPHEMERAL_ENABLED.value():
        raise SwathflowError("no Prefect server to record the run: PREFECT_API_URL is not "
                             "set and Prefect's temporary server is switched off "
                             "(PREFECT_SERVER_ALLOW_EPHEMERAL_MODE=false): set either")
    error: BaseException | None
    try:
        with temporary_settings({PREFECT_CLIENT_MAX_RETRIES: 0}), \
                get_client(sync_client=True, httpx_settings={"timeout": timeout}) as client:
            error = client.api_healthcheck()
    except Exception as exc:  # noqa: BLE001 - told below, with what to do
        error = exc
    if error is None:
        return
    cause = " ".join(f"{type(error).__name__}: {error}".split())[:400]
    if url:
        raise SwathflowError(f"PREFECT_API_URL={url}: the Prefect server did not answer "
                             f"within {timeout:.0f} s ({cause}); start it (prefect server "
                             f"start), or unset PREFECT_API_URL to let Prefect start a "
                             f"temporary server for the run")
    raise SwathflowError(f"Prefect's temporary server did not start ({cause}); a first run "
                         f"in a new Prefect home builds its database: raise "
                         f"PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS, or run "
                         f"`prefect server start` and set PREFECT_API_URL")


#: environment variable that marks every process a ``swathflow run`` starts (inherited by
#: Prefect's temporary server and the Dask workers): "<pid>:<start time>" of the run
RUN_MARK = "SWATHFLOW_RUN"


def mark_run() -> None:
    """Mark this process's children as a run's (:data:`RUN_MARK`, in this process's
    environment, which the processes it starts inherit): :func:`end_orphans` of a later
    run finds them if this one is killed before it could stop them."""
    import psutil
    me = psutil.Process()
    os.environ[RUN_MARK] = f"{me.pid}:{me.create_time():.3f}"


def end_orphans(timeout: float = 5.0) -> list[int]:
    """End the processes of this user that an earlier run started (marked by
    :func:`mark_run`) and left behind when it was killed (``kill -9``: its temporary
    Prefect server and Dask workers go on serving, re-parented): those whose run is no
    longer alive. SIGTERM, then SIGKILL after ``timeout`` s. Their process ids."""
    import psutil
    me = os.getpid()
    uid = os.getuid()
    found = []
    for proc in psutil.process_iter(["pid", "uids"]):
        try:
            if proc.info["pid"] == me or proc.info["uids"] is None \
                    or proc.info["uids"].real != uid:
                continue
            owner = proc.environ().get(RUN_MARK)
        except (psutil.Error, OSError):
            continue
        if owner and not _alive(owner):
            found.append(proc)
    for proc in found:
        with contextlib.suppress(psutil.Error):
            proc.terminate()
    _, left = psutil.wait_procs(found, timeout=timeout)
    for proc in left:
        with contextlib.suppress(psutil.Error):
            proc.kill()
    psutil.wait_procs(left, timeout=timeout)
    return [p.pid for p in found]


def _alive(owner: str) -> bool:
    """Whether the run ``"<pid>:<start time>"`` (:data:`RUN_MARK`) is still running."""
    import psutil
    try:
        pid, start = owner.split(":")
        return abs(psutil.Process(int(pid)).create_time() - float(start)) < 0.01
    except (ValueError, psutil.Error):
        return False


@contextlib.contextmanager
def interrupt_quickly():
    """Ctrl-C inside the block: Prefect's client stops retrying for the rest of the block,
    then KeyboardInterrupt as usual. A terminal's Ctrl-C reaches every process of the
    job, Prefect's temporary server too: Prefect's report of the interrupted flow run
    retried each call to the stopped server with growing waits (minutes before the
    prompt came back). Prefect's public ``temporary_settings`` say no retries (this
    thread's; see :func:`leave_if_prefect_stopped` for the queues drained at exit)."""
    import signal
    import threading
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    entered = []

    def interrupted(signum, frame):
        from prefect.settings import PREFECT_CLIENT_MAX_RETRIES, temporary_settings
        settings = temporary_settings({PREFECT_CLIENT_MAX_RETRIES: 0})
        settings.__enter__()
        entered.append(settings)
        raise KeyboardInterrupt
    previous = signal.signal(signal.SIGINT, interrupted)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)
        for settings in reversed(entered):
            with contextlib.suppress(Exception):   # entered inside a context now left
                settings.__exit__(None, None, None)


def leave_if_prefect_stopped(code: int, timeout: float = 2.0) -> None:
    """After an interrupted run: when Prefect's API no longer answers (its temporary
    server stopped by the same Ctrl-C), end the process now with ``code``, stdout and
    stderr flushed: Prefect's log and event queues, drained as the process ends, could
    only retry the stopped server for minutes (the Dask cluster is closed by then). With
    the server answering, nothing happens: the usual way out records the queued logs."""
    import sys
    try:
        _healthy(timeout)
        return
    except SwathflowError:
        pass
    for f in (sys.stdout, sys.stderr):
        with contextlib.suppress(OSError, ValueError):
            f.flush()
    os._exit(code)
