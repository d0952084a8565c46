"""Prefect's temporary server of this process, its code imported while the mission is checked.

Importing the server's code is almost all of its start (about 3.2 CPU-s of 3.4, Prefect
3.8), and ``swathflow run`` checks the mission first (about 4 CPU-s on the survey) so that
bad input is told before any server or cluster starts. :func:`start` spawns, as the check
begins, a process that only imports the server's code and builds its app, on the core the
check leaves idle; it binds no port until :func:`claim` hands it one once the check has
passed (:func:`launch`), and it is ended unused when the check fails
(:func:`discard`) or the caller exits. Meanwhile a new Prefect home gets its database, a
copy of a migrated one (:mod:`swathflow.flows.prefectdb`).

No Prefect at import (its functions that serve import it): the check's process must not
import it before the check.
"""
from __future__ import annotations

import atexit
import json
import os
import subprocess
import sys

#: the environment defaults of a run (flows/mission.py sets them before importing Prefect)
QUIET_PREFECT = {
    "PREFECT_SERVER_ANALYTICS_ENABLED": "false",
    "PREFECT_SERVER_UI_ENABLED": "false",
    "PREFECT_LOGGING_LEVEL": "CRITICAL",  # failures are reported once, by the CLI
    "PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS": "60",
    "DASK_LOGGING__DISTRIBUTED": "warning",
    "DO_NOT_TRACK": "1",   # Prefect's client telemetry and its first-run notice: off
}

#: exit code of a standby whose Prefect settings differ from the caller's: start afresh
STALE = 4

#: the standby: import the server's code and build its app (Prefect's uvicorn factory
#: returns the cached app), build its routes' request handling (:func:`warm_routes`), all
#: without the garbage collector's passes (``collector.uncollected``: the objects made then
#: live as long as the server; 0.1-1.5 of 3.5-6 CPU-s, in each of six alternated pairs),
#: give a new Prefect home its database (flows/prefectdb.py), then wait for ``{"port",
#: "settings"}`` on stdin and serve that app as ``python -m uvicorn ...`` (Prefect's own
#: command, :func:`server_command`) would, unless the caller's Prefect
#: settings differ from the ones seen here; the migration on start is left out when the
#: database is at the revision of this Prefect's migrated template (flows/prefectdb.py)
_CODE = r"""
import json, os, sys
from swathflow.collector import uncollected
with uncollected():     # no collector passes over the server's code and app as they are made
    import prefect
    import prefect.server.api.server as server
    from prefect.settings import get_current_settings
    app = server.create_app()
    from swathflow.flows import prefectdb, standby
    standby.warm_routes(app)
prefectdb.seed()    # a new Prefect home's database: a copy of a migrated one, kept
line = sys.stdin.readline()
if not line:
    sys.exit(0)
go = json.loads(line)
if go["settings"] != get_current_settings().to_environment_variables(exclude_unset=True):
    sys.exit(%d)
import uvicorn
from prefect.settings import PREFECT_API_DATABASE_MIGRATE_ON_START, temporary_settings
skip = {PREFECT_API_DATABASE_MIGRATE_ON_START: False} if prefectdb.at_head() else {}
with temporary_settings(skip):
    uvicorn.run(app, host="127.0.0.1", port=go["port"], log_level="error", lifespan="on")
""" % STALE

#: environment of Prefect's temporary server besides the caller's settings (as Prefect's
#: ``SubprocessASGIServer`` sets it)
SERVER_ENV = {"PREFECT_UI_ENABLED": "0", "PREFECT__SERVER_EPHEMERAL": "1",
              "PREFECT__SERVER_FINAL": "1"}

_STANDBY: dict = {}


def warm_routes(app) -> int:
    """Build the request handling of every route of ``app`` (a FastAPI app, its mounted
    apps and included routers) now rather than at its first request: FastAPI 0.150 builds
    an included router's routes (their dependencies and body models) when a request first
    reaches it, which made the first requests of a flow run wait on the new server (0.3-0.9 s
    the first ``/admin/version``, 0.3-0.7 s the first ``POST /flows/``). Uses FastAPI's
    private ``effective_candidates``: where a FastAPI has none, nothing is done (the routes
    are then built as before, at their first request). The number of routes visited."""
    seen: set = set()
    todo = list(getattr(getattr(app, "router", None), "routes", ()))
    while todo:
        route = todo.pop()
        if id(route) in seen:
            continue
        seen.add(id(route))
        for name in ("effective_candidates", "effective_low_priority_routes"):
            build = getattr(route, name, None)
            if callable(build):
                try:
                    todo.extend(build())
                except Exception:  # noqa: BLE001 - left to the first request, as before
                    pass
        sub = getattr(getattr(route, "app", None), "router", None)   # a mounted app
        todo.extend(getattr(sub, "routes", ()))
    return len(seen)


def start() -> None:
    """Spawn the standby (once), unless a Prefect server is named (``PREFECT_API_URL``)."""
    proc = _STANDBY.get("process")
    if os.environ.get("PREFECT_API_URL") or (proc is not None and proc.poll() is None):
        return
    env = {**QUIET_PREFECT, **os.environ,
           **SERVER_ENV}
    _STANDBY["process"] = spawn([sys.executable, "-c", _CODE], env, stdin=subprocess.PIPE)
    _STANDBY["env"] = env
    if not _STANDBY.get("atexit"):
        atexit.register(discard)
        _STANDBY["atexit"] = True


def spawn(args: list[str], env: dict, **kw) -> subprocess.Popen:
    """Start the server's process with its output in an anonymous file (``proc.output``),
    not on the caller's terminal: what uvicorn or Prefect's services print when the
    server is stopped (e.g. an event flush cancelled when a run is ended by SIGTERM) is
    not the user's concern; :func:`output_tail` gives it when the server fails to start."""
    import tempfile
    output = tempfile.TemporaryFile()
    proc = subprocess.Popen(args, env=env, stdout=output, stderr=subprocess.STDOUT, **kw)
    proc.output = output     # type: ignore[attr-defined]
    return proc


def output_tail(proc, chars: int = 2000) -> str:
    """The last ``chars`` characters the server's process printed ('' if none)."""
    output = getattr(proc, "output", None)
    if output is None:
        return ""
    output.seek(0, os.SEEK_END)
    output.seek(max(0, output.tell() - chars))
    return output.read().decode(errors="replace").strip()


def claim(port: int, settings: dict, env: dict):
    """The standby process, told to serve on ``port`` (None when there is none, it has
    ended, or it was spawned with other Prefect variables than ``env``, the environment
    the server would now be started with). It exits with :data:`STALE` when ``settings`` (the
    caller's Prefect settings, ``to_environment_variables(exclude_unset=True)``) are not
    the ones it sees."""
    proc = _STANDBY.pop("process", None)
    spawned = _STANDBY.pop("env", None)
    if proc is None or proc.poll() is not None:
        return None
    if _prefect(spawned, settings) != _prefect(env, settings):
        _end(proc)
        return None
    try:
        proc.stdin.write(json.dumps({"port": port, "settings": settings}).encode() + b"\n")
        proc.stdin.close()
    except OSError:
        _end(proc)
        return None
    return proc


def _prefect(env: dict, settings: dict) -> dict:
    """Prefect's variables of ``env`` other than its settings (which the standby compares
    itself: a profile may set them); other variables, e.g. the ones rasterio sets when it
    is imported, do not concern the server."""
    return {k: v for k, v in env.items() if k.startswith("PREFECT") and k not in settings}


def discard() -> None:
    """End the standby unused (the check failed, or the caller exits)."""
    proc = _STANDBY.pop("process", None)
    _STANDBY.pop("env", None)
    if proc is not None:
        _end(proc)


def _end(proc) -> None:
    if proc.poll() is None:
        proc.kill()
    proc.wait()


#: this process's temporary Prefect server: {"process": Popen, "url": API url}
SERVER: dict = {}


def quiet_defaults() -> None:
    """:data:`QUIET_PREFECT` as this process's environment defaults (a variable set by the
    user is kept), before Prefect is imported: it reads them then."""
    for k, v in QUIET_PREFECT.items():
        os.environ.setdefault(k, v)


def serve() -> bool:
    """Prefect's temporary server for this process launched (:func:`launch`), unless a
    server is named (``PREFECT_API_URL``, e.g. by a profile) or the ephemeral one is
    disabled: the standby is then ended unused. Whether this process has its own server.
    ``swathflow run`` calls it as soon as the mission is checked, so the server starts
    while the flow's modules are imported; the flow's start calls it again (no-op)."""
    quiet_defaults()
    from prefect.settings import PREFECT_API_URL, PREFECT_SERVER_EPHEMERAL_ENABLED
    if PREFECT_API_URL.value() or not PREFECT_SERVER_EPHEMERAL_ENABLED.value():
        discard()
        return False
    launch()
    return True


def server_command(port: int) -> list[str]:
    """The command line Prefect's own ``SubprocessASGIServer`` runs its temporary server
    with (prefect 3.8), for ``port``."""
    import prefect
    return [sys.executable, "-m", "uvicorn", "--app-dir", str(prefect.__module_path__.parent),
            "--factory", "prefect.server.api.server:create_app", "--host", "127.0.0.1",
            "--port", str(port), "--log-level", "error", "--lifespan", "on"]


def _free_port() -> int:
    import socket
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def launch() -> None:
    """Start Prefect's temporary server as Prefect's ``SubprocessASGIServer`` does (same
    command, same environment), without importing the server's code in this process
    (about 3 CPU-s that the flow never uses); stopped when this process exits, like
    Prefect's. The standby (its code imported while the mission was checked) serves, when
    there is one. Returns at once; :func:`ready` waits for it."""
    from prefect.settings import get_current_settings
    proc = SERVER.get("process")
    if proc is not None and proc.poll() is None:
        return
    port = _free_port()
    settings = get_current_settings().to_environment_variables(exclude_unset=True)
    env = {**os.environ, **SERVER_ENV, **settings}
    proc = claim(port, settings, env)   # its code imported during the check
    if proc is None:
        proc = spawn(server_command(port), env)
    SERVER.update(process=proc, url=f"http://127.0.0.1:{port}/api", env=env, ready=False)
    if not SERVER.get("atexit"):
        atexit.register(stop)
        SERVER["atexit"] = True


def ready() -> str:
    """Wait until the temporary server answers its health check (a port taken meanwhile:
    started again on another, as Prefect does); its API url."""
    import time
    import urllib.error
    import urllib.request

    from prefect.settings import PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS
    limit = time.monotonic() + float(PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS.value())
    while not SERVER.get("ready"):
        proc = SERVER["process"]
        if proc.poll() in (3, STALE):   # uvicorn: the port is taken; or a standby
            # spawned with other Prefect settings than the ones in force now
            port = _free_port()
            SERVER.update(process=spawn(server_command(port), SERVER["env"]),
                          url=f"http://127.0.0.1:{port}/api")
            continue
        if proc.poll() is not None:
            tail = output_tail(proc)
            raise RuntimeError(f"Prefect's temporary server exited with code "
                               f"{proc.returncode} before it was ready"
                               + (f"; it printed:\n{tail}" if tail else ""))
        if time.monotonic() > limit:
            raise RuntimeError("timed out while waiting for Prefect's temporary server")
        try:
            with urllib.request.urlopen(SERVER["url"] + "/health", timeout=2) as r:
                SERVER["ready"] = r.status == 200
        except (OSError, urllib.error.URLError):
            pass
        if not SERVER.get("ready"):
            time.sleep(0.05)
    return SERVER["url"]


def stop() -> None:
    """Stop this process's temporary server (SIGTERM, then SIGKILL after 5 s)."""
    proc = SERVER.pop("process", None)
    SERVER["ready"] = False
    if proc is None or proc.poll() is not None:
        return
    proc.terminate()
    try:
        proc.wait(timeout=5)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()
