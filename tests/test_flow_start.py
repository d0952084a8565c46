"""The flow's services, as a user meets them: ``swathflow run`` is a Prefect flow run on
Prefect's own temporary server (each swing a task run, the run's logs stored), the Dask
workers are Dask's own processes, unreachable services are told in one line, importing
the flow changes no setting, and what a run killed by SIGKILL left serving is gone once
the next run has started."""
import json
import os
import signal
import socket
import subprocess
import sys
import time

import pytest

_SCRIPT = """
import asyncio, json, sys
from swathflow.flows.cli import main
code = main(["run", sys.argv[1], "--out", sys.argv[2], "--calibration", sys.argv[3]])
from prefect import get_client
from prefect.client.schemas.filters import LogFilter, LogFilterFlowRunId
from prefect.server.api.server import SubprocessASGIServer
import psutil

async def recorded():
    async with get_client() as client:      # the same temporary server as the run's
        flows = await client.read_flow_runs()
        tasks = await client.read_task_runs()
        names = {f.id: (await client.read_flow(f.flow_id)).name for f in flows}
        logs = await client.read_logs(LogFilter(flow_run_id=LogFilterFlowRunId(
            any_=[f.id for f in flows])))
        return ([(names[f.id], f.state.type.value) for f in flows],
                [(t.name, t.state.type.value) for t in tasks], [l.message for l in logs])

flows, tasks, logs = asyncio.run(recorded())
kids = [p.pid for p in psutil.Process().children(recursive=True)]
print("RESULT " + json.dumps({"code": code, "flows": flows, "tasks": tasks, "logs": logs,
                              "children": kids}))
"""


def _fresh_env(tmp_path, **extra):
    env = {**os.environ, "PREFECT_HOME": str(tmp_path / "prefect-home"), **extra}
    for k in ("PREFECT_API_URL", "DASK_LOGGING__DISTRIBUTED", "PREFECT_LOGGING_LEVEL"):
        env.pop(k, None)        # as in a user's shell (conftest sets some of them)
    return env


def _alive(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as f:
            return not f.read().split(") ", 1)[1].startswith("Z")
    except (FileNotFoundError, ProcessLookupError):
        return False


def test_run_is_a_prefect_flow_run_on_its_own_temporary_server(tiny_mission, tmp_path):
    """`swathflow run` without PREFECT_API_URL: Prefect starts its own temporary server
    (its ephemeral mode), which records the flow run, one task run per stage and per
    swing, and the run's logs; the terminal shows no Prefect or Dask log lines; the
    server and the Dask workers end with the process."""
    cal = str(tiny_mission / "truth" / "calibration.json")
    r = subprocess.run([sys.executable, "-c", _SCRIPT, str(tiny_mission), str(tmp_path / "out"),
                        cal], capture_output=True, text=True, env=_fresh_env(tmp_path),
                       timeout=900)
    assert r.returncode == 0, r.stderr[-3000:]
    # Dask's and Prefect's informational lines (the cluster's start and close, the flow
    # run's states) only with --verbose
    assert "INFO" not in r.stderr and "distributed.scheduler" not in r.stderr, r.stderr[-3000:]
    doc = json.loads(r.stdout.split("RESULT ", 1)[1])
    assert doc["code"] == 0
    assert doc["flows"] == [["swathflow-mission", "COMPLETED"]]
    names = {name for name, _ in doc["tasks"]}
    stages = {name.rsplit("-", 1)[0] for name in names}
    assert {"ingest", "calibrate", "interpolate-pos", "mosaic", "catalog"} <= stages, stages
    assert {"rectify-L1", "rectify-R1"} <= names, names     # each swing a task run
    assert {state for _, state in doc["tasks"]} == {"COMPLETED"}
    assert any("Finished in state Completed" in m for m in doc["logs"]), doc["logs"][:20]
    assert (tmp_path / "out" / "mosaic.tif").exists()
    # the temporary server and the workers ended with the process that started them
    left = [pid for pid in doc["children"] if _alive(pid)]
    assert not left, f"processes of the run outlived it: {left}"


_WORKERS = """
import json, os, sys, urllib.error, urllib.request
from distributed import Client
from swathflow.cluster import local_cluster

def engine():
    return "swathflow.rectification.kernel" in sys.modules

def main():
    with local_cluster(2, preload=("swathflow.tasks.swings",)) as c, Client(c) as client:
        pids = list(client.run(os.getpid).values())
        preloaded = list(client.run(engine).values())
        total = client.submit(sum, range(10)).result()
        ports = sorted(s.getsockname()[1] for s in c.scheduler.http_server._sockets.values())
        codes = []
        for route in ("health", "metrics", "json/counts.json"):
            try:
                urllib.request.urlopen(f"http://127.0.0.1:{ports[0]}/{route}", timeout=10)
                codes.append(200)
            except urllib.error.HTTPError as e:
                codes.append(e.code)
    left = []
    for pid in pids:
        try:
            with open(f"/proc/{pid}/stat") as f:
                left += [pid] if not f.read().split(") ", 1)[1].startswith("Z") else []
        except FileNotFoundError:
            pass
    print("RESULT " + json.dumps({"parent": os.getpid(), "pids": pids, "total": total,
                                 "preloaded": preloaded, "ports": ports, "codes": codes,
                                 "left": left}))

if __name__ == "__main__":
    main()
"""


def test_local_workers_are_dasks_own_processes(tmp_path):
    """The local cluster's workers are processes Dask's nannies start (not this
    process, nor forks of it): each ran the preload (the engine imported), they run
    tasks, and none is left once the cluster is closed; the scheduler's HTTP server
    serves nothing, and not on Dask's dashboard port 8787."""
    script = tmp_path / "workers.py"
    script.write_text(_WORKERS)
    r = subprocess.run([sys.executable, str(script)], capture_output=True, text=True,
                       timeout=300, cwd=tmp_path)
    assert r.returncode == 0, r.stderr[-3000:]
    doc = json.loads(r.stdout.split("RESULT ", 1)[1])
    assert len(set(doc["pids"])) == 2 and doc["parent"] not in doc["pids"]
    assert doc["preloaded"] == [True, True]
    assert doc["total"] == 45
    assert doc["left"] == [], "a worker process outlived its cluster"
    assert 8787 not in doc["ports"]
    assert doc["codes"] == [404, 404, 404]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.mark.parametrize("service", ["dask", "prefect"])
def test_unreachable_service_is_one_clear_error(tiny_mission, tmp_path, service):
    """An unreachable --dask-address or PREFECT_API_URL ends `swathflow run` with one
    line naming it and what to do (exit 2), not a traceback; nothing is written."""
    port = _free_port()         # nothing listens there
    env = _fresh_env(tmp_path)
    args = []
    if service == "dask":
        args = ["--dask-address", f"tcp://127.0.0.1:{port}"]
    else:
        env["PREFECT_API_URL"] = f"http://127.0.0.1:{port}/api"
    r = subprocess.run([sys.executable, "-m", "swathflow.flows.cli", "run", str(tiny_mission),
                        "--out", str(tmp_path / "out"), *args], capture_output=True,
                       text=True, env=env, timeout=300)
    assert r.returncode == 2, r.stdout + r.stderr
    assert "Traceback" not in r.stderr, r.stderr
    line = r.stderr.strip().splitlines()[-1]
    if service == "dask":
        assert line.startswith(f"swathflow run: error: --dask-address tcp://127.0.0.1:{port}: "
                               f"no Dask scheduler answered"), line
    else:
        assert line.startswith(f"swathflow run: error: PREFECT_API_URL=http://127.0.0.1:{port}"
                               f"/api: the Prefect server did not answer"), line
        assert "unset PREFECT_API_URL" in line
    assert not (tmp_path / "out" / "rectified").exists()


def test_no_server_allowed_is_one_clear_error(tiny_mission, tmp_path):
    """No PREFECT_API_URL and Prefect's temporary server switched off: one line."""
    env = _fresh_env(tmp_path, PREFECT_SERVER_ALLOW_EPHEMERAL_MODE="false")
    r = subprocess.run([sys.executable, "-m", "swathflow.flows.cli", "run", str(tiny_mission),
                        "--out", str(tmp_path / "out")], capture_output=True, text=True,
                       env=env, timeout=300)
    assert r.returncode == 2, r.stdout + r.stderr
    assert "Traceback" not in r.stderr, r.stderr
    assert "PREFECT_API_URL is not set" in r.stderr and \
        "PREFECT_SERVER_ALLOW_EPHEMERAL_MODE" in r.stderr, r.stderr


_IMPORT = """
import json, logging, os, warnings
def state():
    import dask
    from prefect.settings import get_current_settings
    return {"prefect": get_current_settings().to_environment_variables(exclude_unset=True),
            "dask": json.dumps(dask.config.config, sort_keys=True, default=str),
            "env": dict(os.environ),
            "levels": {n: logging.getLogger(n).level for n in
                       ("", "prefect", "distributed", "prefect.flow_runs")},
            "filters": len(warnings.filters)}
# the libraries themselves first: what importing them, or defining a Prefect task
# (Prefect sets up its logging then), does is theirs
import prefect, prefect.flows, prefect.tasks, distributed, dask.array, rasterio, xarray  # noqa
prefect.task(json.dumps)
before = state()
import swathflow.flows.mission, swathflow.flows.inbox, swathflow.tasks.stages  # noqa: F401
after = state()
print("RESULT " + json.dumps({k: before[k] == after[k] for k in before}))
"""


def test_importing_the_flow_changes_no_setting(tmp_path):
    """Importing the flow modules leaves Prefect's settings, Dask's configuration, the
    environment, the loggers' levels and the warning filters as the libraries left them
    (a served or deployed flow run logs as its Prefect settings say)."""
    r = subprocess.run([sys.executable, "-c", _IMPORT], capture_output=True, text=True,
                       env=_fresh_env(tmp_path, DO_NOT_TRACK="1"), timeout=300)
    assert r.returncode == 0, r.stderr[-3000:]
    assert json.loads(r.stdout.split("RESULT ", 1)[1]) == {
        "prefect": True, "dask": True, "env": True, "levels": True, "filters": True}


def _cmdline(proc) -> str:
    import psutil
    try:
        return " ".join(proc.cmdline())
    except psutil.Error:
        return ""


def test_killed_run_leaves_nothing_serving_once_the_next_has_started(tiny_mission, tmp_path):
    """`kill -9` of `swathflow run` (its process alone, as a crash or the OOM killer
    would): Prefect's temporary server and the Dask workers it started may go on
    running, re-parented; once the next run has started, none of them is left."""
    import psutil
    cal = str(tiny_mission / "truth" / "calibration.json")
    env = _fresh_env(tmp_path)
    cmd = [sys.executable, "-m", "swathflow.flows.cli", "run", str(tiny_mission),
           "--calibration", cal]
    log = open(tmp_path / "first.log", "w")
    first = subprocess.Popen(cmd + ["--out", str(tmp_path / "a")], env=env, stdout=log,
                             stderr=subprocess.STDOUT)
    started: list = []
    try:
        deadline = time.time() + 600
        while time.time() < deadline and first.poll() is None:
            try:
                kids = psutil.Process(first.pid).children(recursive=True)
            except psutil.NoSuchProcess:
                break
            # Prefect's temporary server and the Dask workers (processes of their own) up
            if len(kids) >= 3 and any("prefect.server" in _cmdline(k) for k in kids):
                time.sleep(2)
                started = [k.pid for k in psutil.Process(first.pid).children(recursive=True)]
                break
            time.sleep(0.05)
        assert started, ("the run ended before its services were up: "
                         + (tmp_path / "first.log").read_text()[-3000:])
        os.kill(first.pid, signal.SIGKILL)
        first.wait()
        time.sleep(1)
        orphans = [pid for pid in started if _alive(pid)]
        second = subprocess.run(cmd + ["--out", str(tmp_path / "b")], env=env,
                                capture_output=True, text=True, timeout=900)
        assert second.returncode == 0, second.stderr[-3000:]
        left = [pid for pid in started if _alive(pid)]
        assert not left, f"left serving after the next run: {left} (orphans: {orphans})"
    finally:
        for pid in started:
            if _alive(pid):
                os.kill(pid, signal.SIGKILL)


def test_rectify_on_an_unreachable_scheduler_is_one_clear_error(tiny_mission, tmp_path):
    """`swathflow rectify --dask-address` naming no scheduler: one line, exit 2."""
    port = _free_port()
    r = subprocess.run([sys.executable, "-m", "swathflow.flows.cli", "rectify",
                        str(tiny_mission), "--out", str(tmp_path / "out"), "--dask-address",
                        f"tcp://127.0.0.1:{port}"], capture_output=True, text=True,
                       env=_fresh_env(tmp_path), timeout=300)
    assert r.returncode == 2, r.stdout + r.stderr
    assert "Traceback" not in r.stderr, r.stderr
    assert r.stderr.strip().splitlines()[-1].startswith(
        f"swathflow rectify: error: --dask-address tcp://127.0.0.1:{port}: no Dask scheduler "
        f"answered"), r.stderr
