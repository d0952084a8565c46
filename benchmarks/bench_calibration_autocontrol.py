"""Automatic control at mission scale: ``swathflow calibrate MISSION --reference REF --ties``
on the survey mission (240 swings), the reference the simulator's truth orthophoto degraded
as a real one is (``swathflow.simulation.reference.degrade_reference``: 2x coarser, blur,
gamma 0.8, 8-bit noise, 3 changed patches). The command's own code path (load, calibrate,
calibration.json, report.html), in this process; prints per round the points, the tie
points, the matching, tie matching and adjustment times, and the whole command's time,
and each parameter's error against the truth in sigmas.

Reproduce:
    swathflow simulate /tmp/survey --preset survey --seed 4
    python benchmarks/bench_calibration_autocontrol.py /tmp/survey [--rounds 4] [--factor 2]
Times are wall (perf_counter) and this process's CPU (process_time): on a shared machine
the wall time mostly waits.
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import tempfile
import time
from pathlib import Path


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("mission", help="a simulated survey mission (with truth/ortho.tif)")
    ap.add_argument("--rounds", type=int, default=4)
    ap.add_argument("--factor", type=int, default=2, help="reference pixel / truth pixel")
    ap.add_argument("--no-ties", action="store_true")
    a = ap.parse_args()
    from swathflow.calibration.report import write_report
    from swathflow.calibration.strategy import CalibrationOptions, calibrate_mission
    from swathflow.ingest.mission import load_mission
    from swathflow.simulation.reference import degrade_reference
    work = Path(a.mission)
    with tempfile.TemporaryDirectory() as tmp:
        ref = Path(tmp) / f"ref_x{a.factor}.tif"
        t = time.perf_counter()
        info = degrade_reference(work / "truth" / "ortho.tif", ref, factor=a.factor, seed=1)
        print(f"reference: {info['res']:.2f} m pixels, degraded in "
              f"{time.perf_counter() - t:.1f} s")
        c, w = time.process_time(), time.perf_counter()
        m = load_mission(work)
        opts = CalibrationOptions(reference=str(ref), ties=not a.no_ties,
                                  max_rounds=a.rounds)
        res = calibrate_mission(m, opts, progress=lambda line: print("  " + line, flush=True))
        out = Path(tmp) / "out"
        res.write(out)
        write_report(res, out / "report.html")
        cpu, wall = time.process_time() - c, time.perf_counter() - w
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    ties = "" if a.no_ties else " --ties"
    print(f"command: swathflow calibrate {work} --reference REF{ties} --rounds {a.rounds} "
          f"--out OUT ({len(m.image_ids)} swings)")
    print(f"{'round':>5} {'points':>7} {'ties':>6} {'rejected':>8} {'sigma0':>7} "
          f"{'change/sigma':>12} {'match s':>8} {'ties s':>7} {'adjust s':>8}")
    for r in res.rounds:
        print(f"{r['round']:5d} {r['points']:7d} {r['ties']:6d} {r['rejected']:8d} "
              f"{r['sigma0']:7.3f} {r['max_change_sigma']:12.2f} {r['matching_s']:8.1f} "
              f"{r['tie_matching_s']:7.1f} {r['adjust_s']:8.1f}")
    inner = res.result
    print(f"whole command: wall {wall:.1f} s, cpu {cpu:.1f} s; peak memory {rss:.0f} MB; "
          f"last adjustment {inner.iterations} iterations")
    comps = inner.options.get("ties") or {}
    if comps:
        print("tie variance components: " + ", ".join(
            f"{k} {v['sigma_factor']:.3f}" for k, v in comps["components"].items()))
    truth = json.loads((work / "truth" / "calibration.json").read_text())["parameters"]
    z = [(f"{b.name}[{i}]", (b.value[i] - truth[b.name]["value"][i]) / b.sigma[i])
         for b in res.parameters.blocks for i in range(b.size) if b.sigma[i] > 0]
    worst = max(z, key=lambda t: abs(t[1]))
    print(f"largest |estimate - truth|: {abs(worst[1]):.2f} sigma ({worst[0]}); "
          f"{os.cpu_count()} cores")


if __name__ == "__main__":
    main()
