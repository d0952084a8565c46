"""Prefect's temporary server, imported while the mission is checked.

Importing the server's code is almost all of its start (about 3.2 CPU-s of 3.4, Prefect
3.8), and ``swathflow run`` checks the mission first (about 4 CPU-s on the survey) so that
bad input is told before any server or cluster starts. :func:`start` spawns, as the check
begins, a process that only imports the server's code and builds its app, on the core the
check leaves idle; it binds no port until :func:`claim` hands it one once the check has
passed (flows/mission.py ``_launch_server``), and it is ended unused when the check fails
(:func:`discard`) or the caller exits. Meanwhile a new Prefect home gets its database, a
copy of a migrated one (:mod:`swathflow.flows.prefectdb`).

No Prefect here: the check's process must not import it before the check.
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
#: returns the cached app), give a new Prefect home its database (flows/prefectdb.py),
#: then wait for ``{"port", "settings"}`` on stdin and serve as ``python -m uvicorn ...``
#: (Prefect's own command, flows/mission.py ``_server_command``) would, unless the caller's
#: Prefect settings differ from the ones seen here
_CODE = r"""
import json, os, sys
import prefect
import prefect.server.api.server as server
from prefect.settings import get_current_settings
server.create_app()
from swathflow.flows import prefectdb
prefectdb.seed()    # a new Prefect home's database: a copy of a migrated one, kept
line = sys.stdin.readline()
if not line:
    sys.exit(0)
go = json.loads(line)
if go["settings"] != get_current_settings().to_environment_variables(exclude_unset=True):
    sys.exit(%d)
import uvicorn.main
sys.argv = ["uvicorn", "--app-dir", str(prefect.__module_path__.parent), "--factory",
            "prefect.server.api.server:create_app", "--host", "127.0.0.1", "--port",
            str(go["port"]), "--log-level", "error", "--lifespan", "on"]
uvicorn.main.main()
""" % STALE

#: environment of Prefect's temporary server besides the caller's settings (as Prefect's
#: ``SubprocessASGIServer`` sets it)
SERVER_ENV = {"PREFECT_UI_ENABLED": "0", "PREFECT__SERVER_EPHEMERAL": "1",
              "PREFECT__SERVER_FINAL": "1"}

_STANDBY: dict = {}


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
