"""The flow on Dask workers submitted as SLURM jobs (dask-jobqueue), on a single-node SLURM
cluster brought up and torn down by deploy/slurm/start.sh and stop.sh (Debian's slurm-wlm
and munge). Products are checked against the simulator's truth ortho."""
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from ops_util import ROOT, alive, free_port, pids_in, script, wait_for

pytestmark = [pytest.mark.slow, pytest.mark.usefixtures("prefect_harness")]


@pytest.fixture(scope="module")
def slurm(tmp_path_factory):
    """A running single-node SLURM cluster; yields the environment that reaches it."""
    folder = tmp_path_factory.mktemp("slurm")
    # OMP_NUM_THREADS=1 as a benchmarking shell exports it: start.sh must still give the node
    # every CPU (it once wrote `nproc`, which honours that variable: 1 CPU, one job at a time)
    env = dict(os.environ, SLURMCTLD_PORT=str(free_port()), SLURMD_PORT=str(free_port()),
               OMP_NUM_THREADS="1")
    pids, old = {}, os.environ.get("SLURM_CONF")
    try:
        out = script("slurm/start.sh", str(folder), env=env, timeout=600)
        assert out.strip().endswith(f"SLURM_CONF={folder}/slurm.conf")
        pids = pids_in(folder, "*.pid", "munge/*.pid")
        assert {"slurmctld.pid", "slurmd.pid", "munge/munged.pid"} <= set(pids), pids
        env["SLURM_CONF"] = str(folder / "slurm.conf")
        os.environ["SLURM_CONF"] = env["SLURM_CONF"]   # for dask-jobqueue's sbatch calls
        cpus = subprocess.run(["sinfo", "-h", "-N", "-o", "%c"], env=env, capture_output=True,
                              text=True, timeout=30, check=True).stdout.split()
        assert cpus == [str(os.cpu_count())], f"the node offers {cpus} CPUs, the machine has " \
            f"{os.cpu_count()}"
        yield {"env": env, "folder": folder}
    finally:
        script("slurm/stop.sh", str(folder), env=env, timeout=120)
        if old is None:
            os.environ.pop("SLURM_CONF", None)
        else:
            os.environ["SLURM_CONF"] = old
        left = {name: pid for name, pid in pids.items() if alive(pid)}
        assert not left, f"deploy/slurm/stop.sh left these running: {left}"


def _squeue(env) -> list[str]:
    r = subprocess.run(["squeue", "-h", "-o", "%i %T"], env=env, capture_output=True,
                       text=True, timeout=30, check=True)
    return r.stdout.split("\n")[:-1]


def _wait_for_workers(client, n, env, jobs_dir, timeout=240):
    """Wait for ``n`` workers; on time-out fail with the queue, the node and the job logs."""
    try:
        client.wait_for_workers(n, timeout=timeout)
    except Exception as exc:
        def sh(*cmd):
            return subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=30).stdout
        logs = "".join(f"--- {p.name}\n{p.read_text()[-1500:]}" for p in sorted(jobs_dir.glob("*")))
        pytest.fail(f"{exc}\nsqueue:\n{sh('squeue', '-o', '%i %T %r')}\n"
                    f"sinfo:\n{sh('sinfo', '-N', '-o', '%N %t %E %C %m')}\n{logs}")


def test_cli_runs_the_mission_on_slurm_worker_jobs(slurm, tiny_mission, tmp_path):
    """`swathflow run --cluster slurm` with DASK_CONFIG=deploy/dask: the workers are SLURM
    jobs (seen in slurmctld's log), the products match the truth, the jobs end with it."""
    from test_flow import _check_against_truth
    out = tmp_path / "out"
    cal = str(tiny_mission / "truth" / "calibration.json")
    env = dict(slurm["env"], DASK_CONFIG=str(ROOT / "deploy" / "dask"))
    r = subprocess.run([sys.executable, "-m", "swathflow.flows.cli", "run", str(tiny_mission),
                        "--out", str(out), "--calibration", cal, "--cluster", "slurm",
                        "--jobs", "2"], env=env, cwd=tmp_path, capture_output=True, text=True,
                       timeout=600)
    assert r.returncode == 0, r.stdout + r.stderr
    _check_against_truth(tiny_mission, {"rectified": sorted(map(str, out.glob("rectified/*.tif"))),
                                        "mosaic": str(out / "mosaic.tif")})
    log = (slurm["folder"] / "log" / "slurmctld.log").read_text()
    assert "Allocate JobId=" in log, "no SLURM job was started"
    deadline = time.time() + 60
    while _squeue(slurm["env"]) and time.time() < deadline:
        time.sleep(0.5)
    assert not _squeue(slurm["env"]), "worker jobs outlived the run"


def test_scale_from_one_to_two_jobs_and_scancel_one_mid_run(slurm, tiny_mission, tmp_path):
    from dask_jobqueue import SLURMCluster
    from distributed import Client
    from swathflow.flows.mission import run
    from test_flow import _check_against_truth
    out = tmp_path / "out"
    cal = str(tiny_mission / "truth" / "calibration.json")
    env = slurm["env"]
    with SLURMCluster(cores=1, processes=1, memory="2GB", walltime="00:30:00",
                      worker_extra_args=["--host", "127.0.0.1"],
                      scheduler_options={"host": "127.0.0.1", "dashboard_address": "127.0.0.1:0"},
                      log_directory=str(tmp_path / "jobs")) as cluster, \
            Client(cluster) as client:
        cluster.scale(jobs=1)
        _wait_for_workers(client, 1, env, tmp_path / "jobs")
        assert len(_squeue(env)) == 1 and "RUNNING" in _squeue(env)[0]
        cluster.scale(jobs=2)
        _wait_for_workers(client, 2, env, tmp_path / "jobs")
        jobs = _squeue(env)
        assert len(jobs) == 2 and all("RUNNING" in j for j in jobs), jobs
        job_of = {name: job.job_id for name, job in cluster.workers.items()}
        cancelled = {}

        def cancel_a_busy_job():
            deadline = time.time() + 300
            while time.time() < deadline and not cancelled:
                busy = [w for w, tasks in client.processing().items() if tasks]
                if busy:
                    name = client.scheduler_info()["workers"][busy[0]]["name"]
                    subprocess.run(["scancel", job_of[name]], env=env, check=True, timeout=30)
                    cancelled["job"] = job_of[name]
                    return
                time.sleep(0.01)

        t = threading.Thread(target=cancel_a_busy_job, daemon=True)
        t.start()
        result = run(tiny_mission, out, calibration=cal, dask_address=cluster.scheduler_address)
        t.join(5)
        assert cancelled, "no Dask work was seen on a SLURM worker to cancel its job"
        wait_for(lambda: not any(j.startswith(cancelled["job"] + " ") for j in _squeue(env)),
                 60, "the cancelled job is still in the queue", interval=0.5)
    _check_against_truth(tiny_mission, result)
    assert Path(result["mosaic"]).exists()
