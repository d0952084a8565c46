"""Calibration from a reference orthophoto (automatic control) beside the same mission
calibrated from its hand-measured control points (gcp.csv, 1 px noise).

Reproduce:
    .venv/bin/python benchmarks/bench_reference.py --preset tiny --seed 3
    .venv/bin/python benchmarks/bench_reference.py --preset demo --seed 1 --factor 3
    .venv/bin/python benchmarks/bench_reference.py --preset tiny --seed 6 --factor 3 \
        --swings 4 --along-overlap 0.5 --ties --rounds 3
(the mission is rendered from tests/data/real/autzen/autzen.jpg). The
reference is the truth ortho degraded (``--factor`` x coarser, blur, gamma 0.8, 8-bit noise,
3 changed patches). Prints the matching time per swing and per round, the whole calibration
time, and per parameter the sigma and the error against the truth (in sigmas) of both
calibrations. With ``--ties`` a third calibration adds tie points between overlapping left
and right swings, and the sigmas of the left-minus-right boresight are printed for the
three. Times are wall (perf_counter) and this process's CPU (process_time).
"""
import argparse
import json
import os
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
AUTZEN = [HERE.parent / "tests/data/real/autzen/autzen.jpg"]


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--preset", default="tiny")
    ap.add_argument("--seed", type=int, default=3)
    ap.add_argument("--factor", type=int, default=2)
    ap.add_argument("--rounds", type=int, default=4)
    ap.add_argument("--mission", help="an already simulated mission folder (with truth/)")
    ap.add_argument("--swings", type=int, help="swings per strip (simulation override)")
    ap.add_argument("--along-overlap", type=float, help="overlap of consecutive swings")
    ap.add_argument("--ties", action="store_true", help="also calibrate with tie points")
    args = ap.parse_args()
    from swathflow.calibration.autocontrol import calibrate_mission_from_reference
    from swathflow.calibration.control import calibrate
    from swathflow.calibration.strategy import calibrate_mission
    from swathflow.calibration.unknowns import CalibrationError
    from swathflow.ingest.mission import load_mission
    from swathflow.simulation import simulate
    from swathflow.simulation.reference import degrade_reference
    tex = next((p for p in AUTZEN if p.exists()), None)
    if tex is None:
        print("autzen.jpg not found: nothing to benchmark")
        return
    work = Path(args.mission) if args.mission else Path(tempfile.mkdtemp()) / "m"
    if not args.mission:
        t = time.perf_counter()
        over = {k: v for k, v in (("swings_per_strip", args.swings),
                                  ("along_overlap", args.along_overlap)) if v is not None}
        simulate(work, args.preset, seed=args.seed, texture=str(tex), **over)
        print(f"simulated {args.preset} seed {args.seed} in {time.perf_counter() - t:.1f} s")
    ref = work / f"ref_x{args.factor}.tif"
    info = degrade_reference(work / "truth" / "ortho.tif", ref, factor=args.factor, seed=1)
    truth = json.loads((work / "truth" / "calibration.json").read_text())["parameters"]
    nadir = json.loads((work / "truth" / "truth.json").read_text())["nadir_gsd_m"]
    m = load_mission(work)
    print(f"reference {info['res']:.2f} m pixels ({info['res'] / nadir:.1f} x the nadir raw "
          f"pixel of {nadir:.3f} m); {len(m.image_ids)} swings; {os.cpu_count()} cores")

    t = time.perf_counter()
    try:
        gcp = calibrate_mission(m)
        note = ""
    except CalibrationError as exc:       # tiny's hand points can sit on one side of nadir
        gcp = calibrate({iid: m.model(iid) for iid in m.image_ids}, m.gcps, m.priors,
                        check_design=False)
        note = f" (design check off: {str(exc)[:60]}...)"
    t_gcp = time.perf_counter() - t
    t, c = time.perf_counter(), time.process_time()
    rc = calibrate_mission_from_reference(m, str(ref), max_rounds=args.rounds)
    t_ref, c_ref = time.perf_counter() - t, time.process_time() - c
    rt = None
    if args.ties:
        t, c = time.perf_counter(), time.process_time()
        rt = calibrate_mission_from_reference(m, str(ref), max_rounds=args.rounds, ties=True)
        t_tie, c_tie = time.perf_counter() - t, time.process_time() - c

    print(f"\n{'round':>5} {'points':>7} {'rejected':>8} {'sigma0':>7} {'change/sigma':>12} "
          f"{'matching s':>10} {'s/swing':>8}")
    n = len(m.image_ids)
    for r in rc.rounds:
        print(f"{r['round']:5d} {r['points']:7d} {r['rejected']:8d} {r['sigma0']:7.3f} "
              f"{r['max_change_sigma']:12.2f} {r['matching_s']:10.1f} "
              f"{r['matching_s'] / n:8.2f}")
    print("last round per swing: " + ", ".join(f"{s['image_id']} {s['seconds']:.2f} s "
                                                 f"({s['matched']}/{s['blocks']} blocks)"
                                                 for s in rc.matching))
    print(f"whole calibration: reference {t_ref:.1f} s wall, {c_ref:.1f} s CPU; hand-measured "
          f"control {t_gcp:.1f} s wall ({len(m.gcps)} observations){note}")
    if rt is not None:
        _print_ties(rt, t_tie, c_tie, [gcp, rc, rt], truth)

    print(f"\n{'parameter':<14} {'ref sigma':>10} {'ref err/sig':>11} {'gcp sigma':>10} "
          f"{'gcp err/sig':>11}")
    zr, zg = [], []
    for b in rc.parameters.blocks:
        g = gcp.parameters.block(b.name)
        tv = np.array(truth[b.name]["value"])
        for i in range(b.size):
            er = (b.value[i] - tv[i]) / b.sigma[i]
            eg = (g.value[i] - tv[i]) / g.sigma[i]
            zr.append(er)
            zg.append(eg)
            print(f"{b.name + f'[{i}]':<14} {b.sigma[i]:10.4f} {er:11.2f} {g.sigma[i]:10.4f} "
                  f"{eg:11.2f}")
    print(f"max |err|/sigma: reference {np.max(np.abs(zr)):.2f}, control points "
          f"{np.max(np.abs(zg)):.2f}")


def _lr_sigma(res) -> np.ndarray:
    """Sigmas of opk_pos_L - opk_pos_R (deg) from the model-level covariance."""
    sizes = [b.size for b in res.parameters.blocks]
    off = dict(zip([b.name for b in res.parameters.blocks], np.cumsum([0] + sizes[:-1])))
    iL, iR, C = off["opk_pos_L"], off["opk_pos_R"], res.model_cov
    return np.sqrt([C[iL + k, iL + k] + C[iR + k, iR + k] - 2 * C[iL + k, iR + k]
                    for k in range(3)])


def _print_ties(rt, t_tie, c_tie, results, truth):
    print(f"\nwith tie points: {rt.timings['total']:.1f} s wall, {c_tie:.1f} s CPU "
          f"(call {t_tie:.1f} s); last round "
          + ", ".join(f"{p['pair']} {p['kept']}/{p['matched']} ({p['seconds']:.2f} s)"
                      for p in rt.tie_matching)
          + f" ties kept/matched (matching time); "
          f"{int(rt.ties['rejected'].sum()) // 2} tie point(s) rejected")
    print(f"{'L - R boresight sigma (deg)':<30} {'omega':>8} {'phi':>8} {'kappa':>8}")
    for name, res in zip(("hand-measured control", "reference", "reference + ties"),
                         results):
        s = _lr_sigma(res)
        print(f"{name:<30} {s[0]:8.4f} {s[1]:8.4f} {s[2]:8.4f}")
    z = [abs(b.value[i] - truth[b.name]["value"][i]) / b.sigma[i]
         for b in rt.parameters.blocks for i in range(b.size)]
    print(f"max |err|/sigma with ties: {max(z):.2f}")


if __name__ == "__main__":
    main()
