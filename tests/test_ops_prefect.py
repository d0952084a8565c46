"""The inbox deployment on a production-shaped Prefect: PostgreSQL (Debian's, through
asyncpg) started by deploy/postgres/start.sh, the server and a process worker started by
deploy/prefect/start.sh, the deployment from deploy/prefect.yaml, the webhook alert from
deploy/prefect/alerts.py received by a listener in this test. Three missions arrive at
once, one of them broken (its POS file is missing): the two good ones are done and match
the truth, the parent run ends Failed with the broken one and its reason in the state
message, the failure event is emitted and the webhook is called, and a run after the fix
finishes it without redoing the others. No 'database is locked' in the server log, and
nothing is left running."""
import contextlib
import json
import os
import shutil
import subprocess
import sys
import tempfile
import threading
import time
import urllib.request
from http.server import BaseHTTPRequestHandler, HTTPServer
from pathlib import Path

import pytest

from ops_util import BIN, LOOPBACK_HEX, ROOT, alive, free_port, listening_on, pids_in, script, wait_for

pytestmark = pytest.mark.slow
PREFECT = str(BIN / "prefect")


class _Hook(BaseHTTPRequestHandler):
    received: list = []

    def do_POST(self):  # noqa: N802 (http.server's name)
        n = int(self.headers.get("Content-Length") or 0)
        _Hook.received.append(self.rfile.read(n).decode())
        self.send_response(204)
        self.end_headers()

    def log_message(self, *args):
        pass


def _api(env, path, body=None):
    url = env["PREFECT_API_URL"] + path
    data = None if body is None else json.dumps(body).encode()
    req = urllib.request.Request(url, data=data, method="POST" if data else "GET",
                                 headers={"Content-Type": "application/json"})
    with urllib.request.urlopen(req, timeout=30) as r:
        return json.loads(r.read())


def _prefect(env, *args, timeout=180):
    r = subprocess.run([PREFECT, *args], env=env, cwd=ROOT, capture_output=True, text=True,
                       timeout=timeout)
    assert r.returncode == 0, f"prefect {' '.join(args)} failed:\n{r.stdout}\n{r.stderr}"
    return r.stdout


def _run_inbox(env, inbox, products, cal, timeout=900) -> dict:
    """Trigger the inbox deployment, wait for its run to end, return the run."""
    out = _prefect(env, "deployment", "run", "swathflow-inbox/inbox",
                   "--param", f"inbox={inbox}", "--param", f"out_root={products}",
                   "--param", f"calibration={cal}")
    run_id = next(line.split()[-1] for line in out.splitlines() if "UUID" in line)
    def ended():
        run = _api(env, f"/flow_runs/{run_id}")
        return run if run["state_type"] in ("COMPLETED", "FAILED", "CRASHED", "CANCELLED") \
            else None

    return wait_for(ended, timeout, "the inbox run did not end")


@contextlib.contextmanager
def _services(tmp_path):
    """PostgreSQL, the Prefect server and its worker, through the deploy/ scripts; yields
    the environment that reaches them and the server's folder. Stops them by PID and checks
    that none of their PIDs is left running."""
    pg = Path(tempfile.mkdtemp(prefix="swathflow-test-pg-", dir="/tmp"))  # postgres must reach it
    pf = tmp_path / "prefect"
    env = {k: v for k, v in os.environ.items() if not k.startswith("PREFECT_")}
    pg_port, pf_port = free_port(), free_port()
    env.update(PATH=f"{BIN}:{env['PATH']}", POSTGRES_PORT=str(pg_port),
               PREFECT_PORT=str(pf_port), PREFECT_HOME=str(tmp_path / "prefect-home"),
               SWATHFLOW_HOME=str(ROOT), PREFECT_LOGGING_LEVEL="INFO")
    seen: dict = {}
    try:
        line = script("postgres/start.sh", str(pg), env=env, timeout=300).strip().splitlines()[-1]
        env["PREFECT_API_DATABASE_CONNECTION_URL"] = line.split("=", 1)[1]
        assert env["PREFECT_API_DATABASE_CONNECTION_URL"].startswith("postgresql+asyncpg://")
        seen.update({f"pg/{k}": v for k, v in pids_in(pg).items()})
        line = script("prefect/start.sh", str(pf), env=env, timeout=400).strip().splitlines()[-1]
        env["PREFECT_API_URL"] = line.split("=", 1)[1]
        seen.update({f"prefect/{k}": v for k, v in pids_in(pf).items()})
        assert set(seen) == {"pg/postgres.pid", "prefect/server.pid", "prefect/worker.pid"}
        for port in (pg_port, pf_port):
            assert listening_on(port) and set(listening_on(port)) <= LOOPBACK_HEX, port
        yield env, pf
        # the server kept its runs in PostgreSQL (not in a SQLite file)
        count = subprocess.run(["runuser", "-u", "postgres", "--", "psql", "-h", str(pg / "socket"),
                                "-p", str(pg_port), "-d", "prefect", "-qAt", "-c",
                                "select count(*) from flow_run"], capture_output=True, text=True,
                               timeout=60, check=True).stdout
        assert int(count) >= 5, f"{count} flow runs in PostgreSQL"
        assert not list((tmp_path / "prefect-home").glob("*.db")), "a SQLite database was used"
    finally:
        script("prefect/stop.sh", str(pf), env=env, timeout=120)
        script("postgres/stop.sh", str(pg), env=env, timeout=120)
        shutil.rmtree(pg, ignore_errors=True)
    time.sleep(0.5)
    left = {k: pid for k, pid in seen.items() if alive(pid)}
    assert not left, f"left running after the stop scripts: {left}"


def _check_failed_run(env, run, inbox, products):
    """The first run: Failed naming flight-c and why; flight-a and -b done and correct."""
    from test_flow import _check_against_truth
    assert run["state_type"] == "FAILED", run["state"]
    message = run["state"]["message"]
    assert "1 of 3 missions failed" in message and "flight-c" in message, message
    assert "pos.sbet" in message, message                     # the reason, not just a name
    assert "flight-a" not in message and "flight-b" not in message, message
    for name in ("flight-a", "flight-b"):
        result = json.loads((products / name / "DONE.json").read_text())
        _check_against_truth(inbox / name, result)
    assert not (products / "flight-c" / "DONE.json").exists()
    children = _api(env, "/flow_runs/filter", {"flow_runs": {"parent_flow_run_id": {
        "any_": [run["id"]]}}})
    states = sorted(c["state_type"] for c in children)
    assert states == ["COMPLETED", "COMPLETED", "FAILED"], states


def _check_failure_alert(env, run):
    """The failure event of the inbox run is recorded, and the automation's webhook call
    (with the run's flow and the broken mission in its text) reaches the listener."""
    query = {"filter": {"event": {"name": ["prefect.flow-run.Failed"]},
                        "any_resource": {"id": [f"prefect.flow-run.{run['id']}"]}}}
    # events are stored in batches, seconds later
    wait_for(lambda: _api(env, "/events/filter", query)["events"], 120,
             "no prefect.flow-run.Failed event for the inbox run")
    wait_for(lambda: any("swathflow-inbox" in b and "flight-c" in b for b in _Hook.received),
             120, f"no alert for the failed inbox run: {_Hook.received}")


def test_inbox_on_postgres_backed_server_with_a_broken_mission(tiny_mission, tmp_path):
    from test_flow import _check_against_truth
    hook = HTTPServer(("127.0.0.1", 0), _Hook)
    threading.Thread(target=hook.serve_forever, daemon=True).start()
    inbox, products = tmp_path / "inbox", tmp_path / "products"
    for name in ("flight-a", "flight-b", "flight-c"):
        shutil.copytree(tiny_mission, inbox / name)
    pos = inbox / "flight-c" / "pos.sbet"
    pos.rename(tmp_path / "pos.sbet.saved")           # flight-c arrives without its POS
    cal = str(tiny_mission / "truth" / "calibration.json")
    try:
        with _services(tmp_path) as (env, pf):
            subprocess.run([sys.executable, str(ROOT / "deploy" / "prefect" / "alerts.py"),
                            f"http://127.0.0.1:{hook.server_port}/alert"], env=env, check=True,
                           timeout=120, capture_output=True)
            _prefect(env, "--no-prompt", "deploy", "--prefect-file", "deploy/prefect.yaml",
                     "--name", "inbox")
            schedules = _prefect(env, "deployment", "schedule", "ls", "swathflow-inbox/inbox")
            assert "*/15 * * * *" in schedules and "False" in schedules, schedules  # inactive

            run = _run_inbox(env, inbox, products, cal)
            _check_failed_run(env, run, inbox, products)
            _check_failure_alert(env, run)

            done_before = {n: (products / n / "DONE.json").stat().st_mtime_ns
                           for n in ("flight-a", "flight-b")}
            (tmp_path / "pos.sbet.saved").rename(pos)            # the operator fixes flight-c
            run = _run_inbox(env, inbox, products, cal)
            assert run["state_type"] == "COMPLETED", run["state"]
            _check_against_truth(inbox / "flight-c",
                                 json.loads((products / "flight-c" / "DONE.json").read_text()))
            assert {n: (products / n / "DONE.json").stat().st_mtime_ns
                    for n in done_before} == done_before, "finished missions were redone"
            log = (pf / "server.log").read_text()
            assert "database is locked" not in log
    finally:
        hook.shutdown()
