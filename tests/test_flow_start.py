"""The flow's start-up: ``run()`` starts Prefect's temporary server itself (Prefect's own
command, without importing the server's code in the calling process), the flow is a real
Prefect flow run recorded by that server, and the server ends with the process."""
import json
import os
import subprocess
import sys

_SCRIPT = """
import asyncio, json, sys
from swathflow.flows.guard import check_run_inputs
check_run_inputs(sys.argv[1])     # as `swathflow run` does, before the flow's module
from swathflow.flows import mission as fm, standby
result = fm.run(sys.argv[1], sys.argv[2], calibration=sys.argv[3], workers=1)
server_code = "prefect.server.api.server" in sys.modules
from prefect.client.orchestration import get_client
from prefect.settings import PREFECT_API_URL, temporary_settings

async def recorded():
    async with get_client() as client:
        flows = await client.read_flow_runs()
        tasks = await client.read_task_runs()
        names = {f.id: (await client.read_flow(f.flow_id)).name for f in flows}
        return ([(names[f.id], f.state.type.value) for f in flows],
                [(t.name, t.state.type.value) for t in tasks])

with temporary_settings({PREFECT_API_URL: standby.SERVER["url"]}):
    flows, tasks = asyncio.run(recorded())
print("RESULT " + json.dumps({"server_code": server_code, "flows": flows, "tasks": tasks,
                              "pid": standby.SERVER["process"].pid,
                              "mosaic": result["mosaic"]}))
"""


def test_run_is_a_prefect_flow_run_on_its_own_temporary_server(tiny_mission, tmp_path):
    env = {**os.environ, "PREFECT_HOME": str(tmp_path / "prefect-home")}
    env.pop("PREFECT_API_URL", None)
    env.pop("DASK_LOGGING__DISTRIBUTED", None)      # as in a user's shell (conftest sets it)
    cal = str(tiny_mission / "truth" / "calibration.json")
    r = subprocess.run([sys.executable, "-c", _SCRIPT, str(tiny_mission), str(tmp_path / "out"),
                        cal], capture_output=True, text=True, env=env, timeout=600)
    assert r.returncode == 0, r.stderr[-3000:]
    # Dask's informational lines (the cluster's start and close) only with --verbose
    assert "INFO" not in r.stderr and "distributed.scheduler" not in r.stderr, r.stderr[-3000:]
    doc = json.loads(r.stdout.split("RESULT ", 1)[1])
    assert not doc["server_code"], "the calling process imported Prefect's server code"
    assert doc["flows"] == [["swathflow-mission", "COMPLETED"]]
    stages = {name.rsplit("-", 1)[0] for name, _ in doc["tasks"]}
    assert {"ingest", "calibrate", "interpolate-pos", "mosaic", "catalog"} <= stages, stages
    assert {state for _, state in doc["tasks"]} == {"COMPLETED"}
    assert os.path.exists(doc["mosaic"])
    # the temporary server ended with the process that started it
    try:
        os.kill(doc["pid"], 0)
    except ProcessLookupError:
        pass
    else:
        with open(f"/proc/{doc['pid']}/stat") as f:       # only a zombie may remain
            assert f.read().split(") ", 1)[1].startswith("Z"), "the server outlived its run"


_STANDBY = """
import json, os, sys, urllib.request
from swathflow.errors import SwathflowError
from swathflow.flows import standby
from swathflow.flows.guard import check_run_inputs
mission, bad = sys.argv[1], sys.argv[2]
raised = False
try:
    check_run_inputs(bad)
except SwathflowError:
    raised = True
print("BAD", json.dumps({"raised": raised, "left": standby._STANDBY.get("process") is not None}))
check_run_inputs(mission)
spawned = standby._STANDBY["process"].pid
standby.launch()
url = standby.ready()
with urllib.request.urlopen(url + "/health", timeout=10) as r:
    health = r.status
print("GOOD", json.dumps({"spawned": spawned, "serving": standby.SERVER["process"].pid,
                          "health": health}))
"""


def test_server_code_imported_while_the_mission_is_checked(tiny_mission, tmp_path):
    """`swathflow run`'s check spawns a standby that imports Prefect's server code: on bad
    input it is ended unused (the process that spawned it never started a server); after
    a good check it is the process that serves the flow's temporary server."""
    import shutil
    bad = tmp_path / "bad"
    shutil.copytree(tiny_mission, bad)
    toml = bad / "mission.toml"
    toml.write_text(toml.read_text().replace("gsd = 0.4", "gsd = -1"))
    env = {**os.environ, "PREFECT_HOME": str(tmp_path / "prefect-home")}
    env.pop("PREFECT_API_URL", None)
    r = subprocess.run([sys.executable, "-c", _STANDBY, str(tiny_mission), str(bad)],
                       capture_output=True, text=True, env=env, timeout=600)
    assert r.returncode == 0, r.stderr[-3000:]
    assert json.loads(r.stdout.split("BAD ", 1)[1].splitlines()[0]) == {"raised": True,
                                                                          "left": False}
    good = json.loads(r.stdout.split("GOOD ", 1)[1].splitlines()[0])
    assert good["health"] == 200
    assert good["serving"] == good["spawned"], "the standby did not serve"


_FORKED = """
import json, os, sys, threading, urllib.error, urllib.request
from distributed import Client
from swathflow.cluster import local_cluster

def setup():      # left in a module of this process: a forked worker has it, a spawned not
    json.SET_UP = os.getpid()

def child():      # run in each forked worker, on a thread beside its start
    json.CHILD = os.getpid()

def own_child():  # in a worker: child() ran there (waited for: it runs on a thread)
    import time
    mod, limit = sys.modules["json"], time.monotonic() + 60
    while getattr(mod, "CHILD", None) is None and time.monotonic() < limit:
        time.sleep(0.01)
    return getattr(mod, "CHILD", None) == os.getpid()

def noise():      # what a worker's heartbeat logs when the scheduler closes first
    import logging
    logging.getLogger("distributed.worker").error("WORKER-NOISE %d", os.getpid())

def cluster(forks=True):
    with local_cluster(2, fork_setup=setup, worker_setup=child) as c, Client(c) as client:
        seen = client.run(lambda: getattr(sys.modules["json"], "SET_UP", None))
        own = client.run(own_child) if forks else {}
        pids = list(client.run(os.getpid).values())
        client.run(noise)
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
    return {"seen": list(seen.values()), "own": list(own.values()), "total": total,
            "ports": ports,
            "codes": codes, "left": left}

forked = cluster()
stop = threading.Event()
t = threading.Thread(target=stop.wait)       # another thread runs: no fork
t.start()
try:
    spawned = cluster(forks=False)
finally:
    stop.set()
print("RESULT " + json.dumps({"parent": os.getpid(), "forked": forked, "spawned": spawned,
                             "in_parent": getattr(json, "CHILD", None)}))
"""


def test_local_workers_forked_from_a_one_thread_process(tmp_path):
    """The flow's local Dask workers are forked from its process while only its main thread
    runs (they share what ``fork_setup`` prepared, e.g. the checked mission, and import
    nothing again; each ran ``worker_setup`` itself), spawned by Dask's nannies otherwise;
    either way real workers that run tasks, whose processes are gone once the cluster is
    closed and whose Dask log lines are not printed (LocalCluster's ``silence_logs``: an
    error logged on each is not seen); and the scheduler's HTTP server serves nothing, and
    not on Dask's dashboard port 8787."""
    r = subprocess.run([sys.executable, "-c", _FORKED], capture_output=True, text=True,
                       timeout=300, cwd=tmp_path)
    assert r.returncode == 0, r.stderr[-3000:]
    doc = json.loads(r.stdout.split("RESULT ", 1)[1])
    forked, spawned = doc["forked"], doc["spawned"]
    assert forked["seen"] == [doc["parent"]] * 2, "workers not forked"
    assert forked["own"] == [True, True], "worker_setup not run in each forked worker"
    assert doc["in_parent"] is None, "worker_setup ran in the parent"
    assert spawned["seen"] == [None, None], "forked beside another thread"
    assert "WORKER-NOISE" not in r.stderr + r.stdout, "a worker's Dask logs not silenced"
    for run in (forked, spawned):
        assert run["total"] == 45
        assert run["left"] == [], "a worker process outlived its cluster"
        assert 8787 not in run["ports"]
        assert run["codes"] == [404, 404, 404]


def test_server_output_kept_off_the_terminal_and_told_when_it_fails_to_start(capfd):
    """What the temporary server prints (e.g. Prefect's services cancelled while a run
    ended by SIGTERM stops it) goes to its own file, not the user's terminal; a server
    that exits before it is ready is reported with the end of what it printed."""
    import pytest
    from swathflow.flows import standby
    code = "import sys; print('starting'); sys.stderr.write('Traceback: no database\\n'); sys.exit(1)"
    proc = standby.spawn([sys.executable, "-c", code], dict(os.environ))
    proc.wait(timeout=60)
    seen = capfd.readouterr()
    assert "Traceback" not in seen.err + seen.out and "starting" not in seen.out
    assert standby.output_tail(proc) == "starting\nTraceback: no database"
    saved = dict(standby.SERVER)
    standby.SERVER.clear()
    standby.SERVER.update(process=proc, url="http://127.0.0.1:9/api", env={}, ready=False)
    try:
        with pytest.raises(RuntimeError, match="exited with code 1 before it was ready; "
                                               "it printed:\nstarting\nTraceback: no database"):
            standby.ready()
    finally:
        standby.SERVER.clear()
        standby.SERVER.update(saved)


def test_server_routes_built_before_the_first_request(monkeypatch):
    """The standby builds every route's request handling of Prefect's app before it serves
    (``standby.warm_routes``): FastAPI otherwise builds an included router's routes at the
    first request that reaches it, which the flow run's first requests waited for. Counted
    on FastAPI's own builder: a request after the warm-up builds nothing; the same request
    on an app not warmed does (so the count can tell)."""
    import asyncio

    import fastapi.routing as routing
    import httpx
    from prefect.server.api.server import create_app

    from swathflow.flows import standby
    built = []

    def version(app) -> int:        # a request in this process, no lifespan: no database
        async def get():
            async with httpx.AsyncClient(transport=httpx.ASGITransport(app=app),
                                         base_url="http://test") as client:
                return (await client.get("/api/admin/version")).status_code
        return asyncio.run(get())
    real = routing._populate_api_route_state

    def counted(*a, **k):
        built.append(a[1])
        return real(*a, **k)
    monkeypatch.setattr(routing, "_populate_api_route_state", counted)
    cold = create_app(ephemeral=True, ignore_cache=True)
    assert version(cold) == 200
    assert "/admin/version" in built      # paths of the app mounted at /api
    warm = create_app(ephemeral=True, ignore_cache=True)
    built.clear()
    assert standby.warm_routes(warm) > 100
    assert "/admin/version" in built and "/flow_runs/" in built
    n = len(built)
    assert version(warm) == 200
    assert len(built) == n, built[n:]


_STALE = """
import json, os, sys, time, urllib.request
from swathflow.flows import standby
standby.start()
spawned = standby._STANDBY["process"]
os.environ["PREFECT_CLIENT_MAX_RETRIES"] = "7"   # the command's settings, not the standby's
standby.serve()
url = standby.ready()
with urllib.request.urlopen(url + "/admin/version", timeout=30) as r:
    version = r.status
print("RESULT", json.dumps({"standby_code": spawned.wait(timeout=60),
                            "serving": standby.SERVER["process"].pid, "spawned": spawned.pid,
                            "args": standby.SERVER["process"].args[1:3], "version": version}))
"""


def test_standby_with_other_settings_is_replaced_by_prefects_command(tmp_path):
    """A standby that sees other Prefect settings than the command's (here a variable the
    command set after spawning it) does not serve: it exits with ``STALE`` once handed its
    port, and Prefect's own uvicorn command serves instead."""
    from swathflow.flows import standby
    env = {**os.environ, "PREFECT_HOME": str(tmp_path / "prefect-home")}
    env.pop("PREFECT_API_URL", None)
    env.pop("PREFECT_CLIENT_MAX_RETRIES", None)
    r = subprocess.run([sys.executable, "-c", _STALE], capture_output=True, text=True,
                       env=env, timeout=600)
    assert r.returncode == 0, r.stderr[-3000:]
    doc = json.loads(r.stdout.split("RESULT ", 1)[1])
    assert doc["standby_code"] == standby.STALE
    assert doc["serving"] != doc["spawned"]
    assert doc["args"] == ["-m", "uvicorn"] and doc["version"] == 200
