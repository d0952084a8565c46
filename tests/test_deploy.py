"""The scheduled deployment for real: a local Prefect server on loopback, a process work
pool, `prefect deploy` from deploy/prefect.yaml, a triggered run executed by a process
worker on the tiny mission. Everything started here is stopped here."""
import json
import os
import shutil
import socket
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PREFECT = str(Path(sys.executable).with_name("prefect"))


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _prefect(env, *args, timeout=180, cwd=ROOT):
    r = subprocess.run([PREFECT, *args], env=env, cwd=cwd, capture_output=True, text=True,
                       timeout=timeout)
    assert r.returncode == 0, f"prefect {' '.join(args)} failed:\n{r.stdout}\n{r.stderr}"
    return r.stdout


@pytest.mark.slow
def test_cron_deployment_runs_the_tiny_mission_on_a_process_worker(tiny_mission, tmp_path):
    port = _free_port()
    env = {k: v for k, v in os.environ.items() if not k.startswith("PREFECT_")}
    env.update(PREFECT_HOME=str(tmp_path / "prefect-home"),
               PREFECT_API_URL=f"http://127.0.0.1:{port}/api",
               PREFECT_SERVER_ANALYTICS_ENABLED="false", PREFECT_SERVER_UI_ENABLED="false",
               PREFECT_LOGGING_LEVEL="WARNING", SWATHFLOW_HOME=str(ROOT))
    server = subprocess.Popen([PREFECT, "server", "start", "--host", "127.0.0.1", "--port",
                               str(port), "--no-ui", "--analytics-off"], env=env,
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                              start_new_session=True)
    try:
        deadline = time.time() + 120
        while True:
            try:
                with urllib.request.urlopen(f"http://127.0.0.1:{port}/api/health", timeout=2):
                    break
            except OSError:
                if time.time() > deadline or server.poll() is not None:
                    pytest.fail("the Prefect server did not start")
                time.sleep(0.5)
        inbox, products = tmp_path / "inbox", tmp_path / "products"
        shutil.copytree(tiny_mission, inbox / "flight-001")
        cal = str(tiny_mission / "truth" / "calibration.json")
        _prefect(env, "work-pool", "create", "swathflow-process", "--type", "process")
        elsewhere = tmp_path / "elsewhere"      # not the repository: entrypoints are modules
        elsewhere.mkdir()
        _prefect(env, "--no-prompt", "deploy", "--prefect-file",
                 str(ROOT / "deploy" / "prefect.yaml"), "--all", cwd=elsewhere)
        out = _prefect(env, "deployment", "inspect", "swathflow-inbox/inbox")
        assert "*/15 * * * *" in out, "the cron schedule was not deployed"
        _prefect(env, "deployment", "run", "swathflow-inbox/inbox",
                 "--param", f"inbox={inbox}", "--param", f"out_root={products}",
                 "--param", f"calibration={cal}")
        _prefect(env, "worker", "start", "--pool", "swathflow-process", "--run-once",
                 timeout=600)
        done = products / "flight-001" / "DONE.json"
        assert done.exists(), "the deployment's run did not finish the mission"
        result = json.loads(done.read_text())
        assert Path(result["mosaic"]).exists()
        assert len(result["rectified"]) == 2 and all(Path(p).exists() for p in result["rectified"])
    finally:
        os.killpg(server.pid, 15)
        try:
            server.wait(20)
        except subprocess.TimeoutExpired:
            os.killpg(server.pid, 9)
