"""End-to-end mission flow: wall time with 1 and 2 Dask workers, and the orchestration
overhead of Prefect against calling the same stage functions directly.

Reproduce:  python benchmarks/bench_flow.py --preset demo   (and --preset area)
The mission is simulated once into --work (default: a temporary folder); the truth
calibration is passed so every run does the same work (ingest, POS, rectify, mosaic).
"""
from __future__ import annotations

import argparse
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--preset", default="demo")
    ap.add_argument("--workers", default="1,2")
    ap.add_argument("--work", help="folder for the mission and outputs (kept)")
    args = ap.parse_args(argv)
    work = Path(args.work or tempfile.mkdtemp(prefix="swathflow-bench-"))
    mission = work / f"{args.preset}-mission"
    from swathflow.sensors.pendulum.simulate import simulate
    if not (mission / "mission.toml").exists():
        t = time.perf_counter()
        simulate(mission, preset=args.preset, seed=0)
        print(f"simulated {args.preset} in {time.perf_counter() - t:.1f} s")
    cal = str(mission / "truth" / "calibration.json")

    from distributed import Client, LocalCluster
    from swathflow.flows.mission import run
    from swathflow.ingest.mission import load_mission
    from swathflow.tasks import stages

    rows = []
    for n in [int(x) for x in args.workers.split(",")]:
        with LocalCluster(n_workers=n, threads_per_worker=1, processes=True,
                          dashboard_address=None, silence_logs=40) as cluster, \
                Client(cluster):
            out = work / f"out-flow-{n}"
            shutil.rmtree(out, ignore_errors=True)
            t = time.perf_counter()
            res = run(mission, out, calibration=cal, dask_address=cluster.scheduler_address)
            flow_s = time.perf_counter() - t
            out = work / f"out-direct-{n}"
            shutil.rmtree(out, ignore_errors=True)
            t = time.perf_counter()
            stages.ingest.fn(str(mission))
            stages.interpolate_pos.fn(str(mission), str(out))
            c = stages.calibrate.fn(str(mission), str(out), cal)
            rect = [stages.rectify.fn(str(mission), iid, c, str(out))
                    for iid in load_mission(mission).images]
            stages.mosaic.fn(rect, str(out))
            direct_s = time.perf_counter() - t
        rows.append((n, flow_s, direct_s, res["timings"]))
    print(f"swathflow flow benchmark: preset {args.preset}, {os.cpu_count()} cores")
    print(f"  {'workers':>7} {'flow s':>8} {'direct s':>9} {'overhead s':>10}   stages (flow)")
    for n, f, d, tm in rows:
        stages_txt = ", ".join(f"{k} {v:.1f}" for k, v in tm.items())
        print(f"  {n:>7} {f:8.1f} {d:9.1f} {f - d:10.1f}   {stages_txt}")
    if len(rows) > 1:
        print(f"  scaling 1 -> {rows[-1][0]} workers: {rows[0][1] / rows[-1][1]:.2f}x (flow)")
    print(f"reproduce: python benchmarks/bench_flow.py --preset {args.preset} "
          f"--workers {args.workers}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
