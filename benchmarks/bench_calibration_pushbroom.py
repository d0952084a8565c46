"""Push-broom calibration time: 20 orientation fixes, 500 tie points, 100 control points.

Simulates preset ``pushbroom-bench`` (two opposite strips of a three-line camera, 3 x 256
elements per line, geometry only, 0.3 px measurement noise) and times the joint sparse
adjustment (and, with --two-step, the paper's iterative two-step scheme), printing the
problem size, the times and the agreement with the truth.

Reproduce:  /tmp/venv/bin/python benchmarks/bench_calibration_pushbroom.py [--two-step] [--vce]
"""
from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--two-step", action="store_true", help="also run the two-step scheme")
    ap.add_argument("--vce", action="store_true", help="variance component estimation")
    ap.add_argument("--robust", action="store_true", help="robust phase and data snooping")
    a = ap.parse_args()
    from swathflow.sensors.pushbroom.calibration import calibrate_pushbroom, mission_ties
    from swathflow.ingest.mission import load_mission
    from swathflow.sensors.pushbroom.simulate import simulate as simulate_pushbroom
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "m"
        t0 = time.perf_counter()
        truth = simulate_pushbroom(path, "pushbroom-bench", seed=5, gcp_noise=0.3,
                                   tie_noise=0.3)
        t_sim = time.perf_counter() - t0
        m = load_mission(path)
        ties = mission_ties(m)
        models = {i: m.model(i) for i in m.image_ids}
        n_ctrl = int(m.gcps[m.gcps.role == "control"].gcp_id.nunique())
        print(f"mission: {len(models)} images, {len(truth['fix_times'])} fixes, "
              f"{ties.tie_id.nunique()} tie points ({len(ties)} observations), {n_ctrl} "
              f"control points ({int((m.gcps.role == 'control').sum())} observations); "
              f"simulated in {t_sim:.1f} s")
        c0, w0 = time.process_time(), time.perf_counter()
        res = calibrate_pushbroom(models, m.gcps, ties, m.priors,
                                  method="both" if a.two_step else "joint",
                                  robust=a.robust, vce=a.vce, obs_sigma_px=0.3)
        wall, cpu = time.perf_counter() - w0, time.process_time() - c0
        o = res.options
        print(f"unknowns {o['unknowns_total']} ({o['model']} parameters + "
              f"{3 * o['tie_points']} tie coordinates), {o['observations']} observations")
        print(f"joint: {res.timings['joint']:.1f} s, {res.solution.iterations} iterations, "
              f"{res.solution.evaluations} evaluations; sigma0 {res.sigma0:.3f}")
        if res.alternative is not None:
            alt = res.alternative
            d = np.abs(res.values - alt.values) / np.where(res.sigmas > 0, res.sigmas, np.nan)
            print(f"two-step: {res.timings['two-step']:.1f} s, {len(alt.rounds)} rounds "
                  f"({'converged' if alt.solution.converged else 'NOT converged'}: last "
                  f"joint step {alt.rounds[-1]['gap_sigma']:.3f} sigma); largest difference "
                  f"from the joint solution {np.nanmax(d):.2f} sigma")
        print(f"total: {wall:.1f} s wall, {cpu:.1f} s CPU")
        tru = json.loads((path / "truth" / "truth.json").read_text())["parameters"]
        tv = np.concatenate([tru[b.name] for b in res.parameters.blocks])
        z = np.abs(res.values - tv) / res.sigmas
        cx, cy = res.check_rms()
        print(f"truth: largest |error| / sigma {np.nanmax(z):.2f} (median "
              f"{np.nanmedian(z):.2f}); check points RMS x {cx:.3f} y {cy:.3f} px; "
              f"C0/C1 max residual {res.max_continuity_residual:.1e}")


if __name__ == "__main__":
    main()
