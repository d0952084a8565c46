"""End-to-end mission flow: the whole run in a fresh process (imports, Prefect's ephemeral
server and the local Dask cluster included) with 1 and 2 Dask workers side by side, stage
by stage; a re-run with nothing to recompute (the `swathflow run` command itself); and,
optionally, the same stage functions called directly (no Prefect, no Dask).

Reproduce:  python benchmarks/bench_flow.py --preset survey --workers 1,2
            (also --preset demo, area; --direct adds the direct in-process run, --fixed
            the flow's fixed cost: every stage's output fresh, only the run manifest gone;
            --timeline: each run's timeline, stages and Dask tasks per worker, with the
            workers' idle time)
            python benchmarks/bench_flow.py --prefect 240
            (only Prefect's own cost: a flow of 240 task runs that do nothing, the CPU
            seconds of this process and of Prefect's temporary server, its start apart)
The mission is simulated once into --work (default: a temporary folder); the truth
calibration is passed so every run does the same work (ingest, POS, rectify, mosaic).
CPU seconds are the run's process and its reaped children (the Dask workers and Prefect's
temporary server; with --timeline each apart, and the run's CPU divided by the cores: no
schedule of that work on this machine ends sooner).
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from cputime import children_cpu  # this folder (the scripts' own)

# as `swathflow run` (flows/cli/commands.py) does it, through its own steps: the inputs
# checked (the mission loaded once, memoised for the flow; Prefect's temporary server
# starting meanwhile), then the flow, with the given number of Dask workers
_RUN = ("import time\nT0 = time.time()\nimport json, sys\n"
        "from swathflow.flows.cli import commands\n"
        "commands._checked(sys.argv[1], sys.argv[3])\n"
        "print('CHECKED', time.time())\n"
        "run = commands._flow_run()\n"
        "r = run(sys.argv[1], sys.argv[2], calibration=sys.argv[3], workers=int(sys.argv[4]))\n"
        "import resource\nu = resource.getrusage(resource.RUSAGE_SELF)\n"
        "print('OWN_CPU', u.ru_utime + u.ru_stime)\n"
        "import psutil\n"
        "for p in psutil.Process().children():   # Prefect's temporary server, stopped at exit\n"
        "    if 'uvicorn' in ' '.join(p.cmdline()):\n"
        "        c = p.cpu_times()\n"
        "        print('SERVER_CPU', c.user + c.system)\n"
        "print('T0', T0)\nprint('TIMINGS', json.dumps(r['timings']))\n")


#: the settings `swathflow run`'s main() gives its own process (flows/cli/main.py), for
#: the runs through the command's steps: its terminal quiet, and Prefect's temporary
#: server given up to 120 s to start (a new Prefect home builds its database)
_CLI_ENV = {"PREFECT_LOGGING_HANDLERS_CONSOLE_LEVEL": "CRITICAL",
            "DASK_LOGGING__DISTRIBUTED": "warning",
            "PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS": "120"}


# a flow of N task runs that do nothing, as the mission flow's rectify tasks are declared;
# the server's CPU read after it has recorded them (it records task runs from their events,
# in batches, after the flow has returned)
_PREFECT = ("import os, sys, time, resource\nN = int(sys.argv[1])\n"
            "from prefect import flow, task, unmapped\n"
            "from prefect.cache_policies import NO_CACHE\n"
            "@task(name='t', cache_policy=NO_CACHE, retries=1, retry_delay_seconds=2, "
            "task_run_name='t-{i}')\n"
            "def t(i: int, x: str) -> str:\n    return str(i)\n"
            "@flow(name='swathflow-bench-prefect', log_prints=False)\n"
            "def f(n: int):\n"
            "    return [x.result() for x in t.map(i=list(range(n)), x=unmapped('a'))]\n"
            "import psutil\n"
            "def server():\n"
            "    ps = [p for p in psutil.Process().children(recursive=True)\n"
            "          if 'uvicorn' in ' '.join(p.cmdline())]\n"
            "    return sum(p.cpu_times().user + p.cpu_times().system for p in ps)\n"
            "f(1)\ntime.sleep(10)\ns0 = server()\nc0 = time.process_time()\n"
            "f(N)\nc1 = time.process_time()\nlast, now = -1.0, server()\n"
            "while now - last > 0.5:\n    time.sleep(5)\n    last, now = now, server()\n"
            "print('START', s0)\nprint('OWN', c1 - c0)\nprint('SERVER', now - s0)\n")


def prefect_cost(n: int) -> int:
    """Prefect's own cost of ``n`` task runs (see :data:`_PREFECT`)."""
    wall, cpu, text = _timed([sys.executable, "-c", _PREFECT, str(n)])
    get = lambda k: float(text.split(k, 1)[1].split()[0])  # noqa: E731
    print(f"Prefect, {n} task runs that do nothing (load {os.getloadavg()[0]:.1f}): "
          f"temporary server's start and a first flow {get('START'):.1f} CPU-s; then "
          f"{n} task runs {get('OWN'):.2f} CPU-s in the flow's process and "
          f"{get('SERVER'):.2f} CPU-s in the server ({1e3 * get('SERVER') / n:.0f} ms a "
          f"task run, recorded after the flow returns); {cpu:.1f} CPU-s in all")
    print(f"reproduce: python benchmarks/bench_flow.py --prefect {n}")
    return 0


def _timed(cmd: list[str]) -> tuple[float, float, str]:
    """Wall and CPU seconds of a command in a fresh process, and its stdout."""
    c0, t0 = children_cpu(), time.perf_counter()
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=7200,
                       env={**_CLI_ENV, **os.environ})
    wall, cpu = time.perf_counter() - t0, children_cpu() - c0
    if r.returncode:
        sys.exit(f"failed ({r.returncode}): {' '.join(cmd)}\n{r.stdout[-2000:]}{r.stderr[-3000:]}")
    return wall, cpu, r.stdout


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--preset", default="demo")
    ap.add_argument("--workers", default="1,2")
    ap.add_argument("--work", help="folder for the mission and outputs (kept)")
    ap.add_argument("--direct", action="store_true",
                    help="also call the stage functions directly in this process")
    ap.add_argument("--fixed", action="store_true",
                    help="also the flow's fixed cost: the run again with every stage's "
                         "output fresh but the run manifest removed (Prefect, Dask, the "
                         "mission, every freshness check)")
    ap.add_argument("--timeline", action="store_true",
                    help="also each run's timeline: when each stage ran (from the process's "
                         "start) and how busy each Dask worker was (the flow's task stream)")
    ap.add_argument("--per-swing", type=int, metavar="N",
                    help="only the rectify stage's CPU per swing in this process (N swings, "
                         "sync scheduler): run it with main's interpreter beside this one "
                         "to compare the engines")
    ap.add_argument("--prefect", type=int, metavar="N",
                    help="only Prefect's own cost of N task runs that do nothing")
    args = ap.parse_args(argv)
    if args.prefect:
        return prefect_cost(args.prefect)
    work = Path(args.work or tempfile.mkdtemp(prefix="swathflow-bench-"))
    mission = work / f"{args.preset}-mission"
    if not (mission / "mission.toml").exists():
        from swathflow.simulation import simulate
        t = time.perf_counter()
        simulate(mission, preset=args.preset, seed=0)
        print(f"simulated {args.preset} in {time.perf_counter() - t:.1f} s")
    cal = str(mission / "truth" / "calibration.json")
    if args.per_swing:
        return _per_swing(mission, cal, args.per_swing)
    cli = str(Path(sys.executable).with_name("swathflow"))
    rows = []
    for n in [int(x) for x in args.workers.split(",")]:
        out = work / f"out-flow-{n}"
        shutil.rmtree(out, ignore_errors=True)
        load0 = os.getloadavg()[0]
        timeline = work / f"timeline-{n}.json"
        if args.timeline:
            os.environ["SWATHFLOW_TASK_STREAM"] = str(timeline)
        wall, cpu, text = _timed([sys.executable, "-c", _RUN, str(mission), str(out), cal,
                                  str(n)])
        os.environ.pop("SWATHFLOW_TASK_STREAM", None)
        if args.timeline:
            t0 = float(text.split("T0", 1)[1].split()[0])
            _print_timeline(n, timeline, t0, wall, float(text.split("CHECKED", 1)[1].split()[0]))
            _print_swings(out, t0)
            own = float(text.split("OWN_CPU", 1)[1].split()[0])
            server = (float(text.split("SERVER_CPU", 1)[1].split()[0])
                      if "SERVER_CPU" in text else None)
            kids = (f"Prefect's server {server:.1f}, the Dask workers {cpu - own - server:.1f}"
                    if server is not None else
                    f"its children (the Dask workers and Prefect's server) {cpu - own:.1f}")
            print(f"  CPU-s: the run's process {own:.1f}, {kids}; {cpu:.1f} in all: on "
                  f"{os.cpu_count()} cores no run of this CPU ends in under "
                  f"{cpu / (os.cpu_count() or 1):.1f} s")
        stages = json.loads(text.split("TIMINGS", 1)[1])
        r_wall, r_cpu, r_text = _timed([cli, "run", str(mission), "--out", str(out),
                                        "--calibration", cal])
        assert "nothing to recompute" in r_text, r_text
        fixed = None
        if args.fixed:
            (out / "run.swathflow.json").unlink()
            fixed = _timed([sys.executable, "-c", _RUN, str(mission), str(out), cal,
                            str(n)])[:2]
        rows.append((n, wall, cpu, r_wall, r_cpu, stages, (load0, os.getloadavg()[0]),
                     fixed))
    direct = _direct(mission, cal, work / "out-direct") if args.direct else None
    print(f"swathflow flow benchmark: preset {args.preset}, {os.cpu_count()} cores, "
          f"load {os.getloadavg()[0]:.1f}")
    names = list(rows[0][5])
    print(f"  {'workers':>7} {'run wall s':>10} {'run CPU s':>9} {'no-op wall':>10} "
          f"{'no-op CPU':>9} {'outside':>8}  " + " ".join(f"{k:>15}" for k in names))
    for n, wall, cpu, rw, rc, st, load, fixed in rows:
        # outside the stages: imports, validation, Prefect's server, Dask's cluster
        print(f"  {n:>7} {wall:10.1f} {cpu:9.1f} {rw:10.2f} {rc:9.2f} "
              f"{wall - sum(st.values()):8.1f}  "
              + " ".join(f"{st.get(k, float('nan')):15.1f}" for k in names)
              + f"   (load {load[0]:.1f} -> {load[1]:.1f})")
        if fixed is not None:
            print(f"  {'':>7} fixed cost (every stage fresh, run manifest removed): "
                  f"{fixed[0]:.1f} s wall, {fixed[1]:.1f} CPU-s")
    if len(rows) > 1:
        print(f"  1 -> {rows[-1][0]} workers: {rows[0][1] / rows[-1][1]:.2f}x (run wall), "
              + ", ".join(f"{k} {rows[0][5][k] / max(rows[-1][5].get(k, 0), 1e-9):.2f}x"
                          for k in names))
    if direct is not None:
        print(f"  direct (stage functions in one process, no Prefect/Dask): {direct:.1f} s")
    print(f"reproduce: python benchmarks/bench_flow.py --preset {args.preset} "
          f"--workers {args.workers}" + (" --direct" if args.direct else "")
          + (" --fixed" if args.fixed else "") + (" --timeline" if args.timeline else ""))
    return 0


def _print_timeline(n: int, path: Path, t0: float, wall: float, checked: float) -> None:
    """The run's timeline (``SWATHFLOW_TASK_STREAM``, see flows/mission.py): when the
    inputs' check ended, each stage's span from the process's start, and each worker's
    busy share of the rectify stage with its idle gaps longer than 0.5 s."""
    doc = json.loads(path.read_text())
    print(f"timeline, {n} worker(s) (s from the process's start; run {wall:.1f} s): "
          f"inputs checked at {checked - t0:.1f}, flow's cluster up at "
          f"{doc['flow_start'] - t0:.1f}")
    for name, (a, b) in doc["stages"].items():
        print(f"  {name:>16} {a - t0:7.1f} -> {b - t0:7.1f}  ({b - a:6.1f} s)")
    a, b = doc["stages"].get("rectify", (t0, t0 + wall))
    for w in doc["workers"]:
        spans = sorted((t["start"], t["stop"]) for t in doc["tasks"] if t["worker"] == w
                       and a <= t["start"] <= b)
        busy = sum(s1 - s0 for s0, s1 in spans)
        gaps, last = [], a
        for s0, s1 in spans:
            if s0 - last > 0.5:
                gaps.append(f"{last - t0:.1f}+{s0 - last:.1f}")
            last = max(last, s1)
        if b - last > 0.5:
            gaps.append(f"{last - t0:.1f}+{b - last:.1f}")
        print(f"  worker {w}: {len(spans)} tasks, busy {busy:.1f} s of the rectify stage's "
              f"{b - a:.1f} ({busy / max(b - a, 1e-9):.0%}); idle gaps > 0.5 s (at+for): "
              + (", ".join(gaps) or "none"))


def _print_swings(out: Path, t0: float) -> None:
    """When the swings were rectified, from their files and manifests (each records its
    seconds; the file's time is its end), independent of Dask's task stream (which
    records only what ends while the flow runs)."""
    spans = []
    for m in (out / "rectified").glob("*.tif.swathflow.json"):
        end = m.with_name(m.name[:-len(".swathflow.json")]).stat().st_mtime
        spans.append((end - json.loads(m.read_text())["seconds"], end))
    if spans:
        print(f"  swings: {len(spans)} rectified from {min(spans)[0] - t0:.1f} to "
              f"{max(e for _, e in spans) - t0:.1f} s, {sum(e - s for s, e in spans):.1f} "
              f"worker-s in all")


def _per_swing(mission, cal, n: int) -> int:
    """The rectify stage's CPU and wall seconds per swing, in this process (one warm-up
    swing first: imports, numba's cache), on swings from the middle of the mission."""
    import dask
    from swathflow.tasks import stages
    out = tempfile.mkdtemp(prefix="swathflow-bench-swings-")
    ids = list(stages._load(str(mission)).images)
    ids = ids[len(ids) // 2:][:n + 1]
    with dask.config.set(scheduler="sync"):
        stages.rectify.fn(str(mission), ids[0], cal, out)
        c, t = time.process_time(), time.perf_counter()
        for iid in ids[1:]:
            stages.rectify.fn(str(mission), iid, cal, out)
        c, t = time.process_time() - c, time.perf_counter() - t
    shutil.rmtree(out, ignore_errors=True)
    print(f"rectify per swing ({len(ids) - 1} swings, one process, load "
          f"{os.getloadavg()[0]:.1f}): {c / (len(ids) - 1):.3f} CPU-s, "
          f"{t / (len(ids) - 1):.3f} s wall ({sys.executable})")
    return 0


def _direct(mission, cal, out) -> float:
    """The same stages called as plain functions (no Prefect, no Dask), in this process."""
    import dask
    from swathflow.ingest.mission import load_mission
    from swathflow.tasks import stages
    shutil.rmtree(out, ignore_errors=True)
    t = time.perf_counter()
    with dask.config.set(scheduler="sync"):
        stages.ingest.fn(str(mission))
        stages.interpolate_pos.fn(str(mission), str(out))
        c = stages.calibrate.fn(str(mission), str(out), cal)
        rect = [stages.rectify.fn(str(mission), iid, c, str(out))
                for iid in load_mission(mission).images]
        stages.mosaic.fn(rect, str(out), str(mission), c)
    return time.perf_counter() - t


if __name__ == "__main__":
    sys.exit(main())
