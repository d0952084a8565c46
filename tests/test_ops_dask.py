"""The flow on a standalone Dask cluster started from Dask's own command lines (`dask
scheduler`, two `dask worker`) by deploy/dask/start.sh, not a LocalCluster: one worker is
killed mid-run (its whole process group, by the PID start.sh recorded) and the products
still match the simulator's truth. deploy/dask/stop.sh leaves nothing running."""
import os
import signal
import subprocess
import sys
import threading
import time

import pytest

from ops_util import BIN, LOOPBACK_HEX, alive, free_port, listening_on, pids_in, script

pytestmark = pytest.mark.slow


def test_standalone_cluster_survives_a_killed_worker(tiny_mission, tmp_path):
    from distributed import Client
    from test_flow import _check_against_truth
    folder, out = tmp_path / "dask", tmp_path / "out"
    port = free_port()
    env = dict(os.environ, PATH=f"{BIN}:{os.environ['PATH']}", DASK_SCHEDULER_PORT=str(port))
    cal = str(tiny_mission / "truth" / "calibration.json")
    seen: set[int] = set()
    try:
        address = script("dask/start.sh", str(folder), "2", env=env, timeout=180).strip()
        assert address == f"tcp://127.0.0.1:{port}"
        assert listening_on(port) and set(listening_on(port)) <= LOOPBACK_HEX
        pids = pids_in(folder)
        assert set(pids) == {"scheduler.pid", "worker-1.pid", "worker-2.pid"}
        seen |= set(pids.values())
        with Client(address, timeout=30) as client:
            workers = client.run(os.getpid)
            assert len(workers) == 2
            seen |= set(workers.values())
            # each worker process belongs to the process group of one `dask worker` command
            group_of = {addr: os.getpgid(pid) for addr, pid in workers.items()}
            assert set(group_of.values()) == {pids["worker-1.pid"], pids["worker-2.pid"]}
            killed = {}

            def kill_a_busy_worker():
                deadline = time.time() + 300
                while time.time() < deadline and not killed:
                    busy = [w for w, tasks in client.processing().items() if tasks]
                    if busy:
                        os.killpg(group_of[busy[0]], signal.SIGKILL)
                        killed["group"] = group_of[busy[0]]
                        return
                    time.sleep(0.01)

            t = threading.Thread(target=kill_a_busy_worker, daemon=True)
            t.start()
            r = subprocess.run([sys.executable, "-m", "swathflow.flows.cli", "run",
                                str(tiny_mission), "--out", str(out), "--calibration", cal,
                                "--dask-address", address], env=env, capture_output=True,
                               text=True, timeout=600)
            t.join(5)
            assert r.returncode == 0, r.stdout + r.stderr
            assert killed, "no Dask work was seen on a worker to kill it"
            assert not alive(killed["group"])
            assert len(client.scheduler_info()["workers"]) == 1
        _check_against_truth(tiny_mission, {
            "rectified": sorted(map(str, out.glob("rectified/*.tif"))),
            "mosaic": str(out / "mosaic.tif")})
    finally:
        script("dask/stop.sh", str(folder), env=env, timeout=120)
    time.sleep(0.5)
    left = sorted(pid for pid in seen if alive(pid))
    assert not left, f"processes left running after deploy/dask/stop.sh: {left}"
    assert not pids_in(folder), "PID files left behind"
