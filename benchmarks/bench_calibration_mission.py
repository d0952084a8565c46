"""A mission-scale calibration: 50 swings of the paper's scanner (tests/test_calibration.py
geometry), 10,000 tie points between neighbouring swings of opposite directions (their
ground coordinates 30,000 unknowns, eliminated 3 x 3 per point) and 10 control points per
swing; robust, with variance components. Prints the time (CPU and wall), the peak memory,
the iterations and the agreement with the truth.

Reproduce:  python benchmarks/bench_calibration_mission.py [--swings 50] [--ties 10000]
"""
from __future__ import annotations

import argparse
import importlib.util
import os
import resource
import time

import numpy as np
import pandas as pd

HERE = os.path.dirname(os.path.abspath(__file__))
spec = importlib.util.spec_from_file_location(
    "tc", os.path.join(HERE, "..", "tests", "test_calibration.py"))
tc = importlib.util.module_from_spec(spec)
spec.loader.exec_module(tc)


def tie_table(models, n_ties, seed=0, sigma=0.5):
    """Tie points between swings i and i+1 (opposite directions), from the TRUE models,
    N(0, sigma) image noise, start ground positions 3 m off horizontally, N(0, 1 m) up."""
    from swathflow.calibration.ties import TIE_COLUMNS, _enu_axes
    rng = np.random.default_rng(seed)
    ids = list(models)
    pairs = list(zip(ids[:-1], ids[1:]))
    per = int(np.ceil(n_ties / len(pairs)))
    out, k = [], 0
    for a, b in pairs:
        ma, mb = (models[i].with_parameters(tc.TRUTH) for i in (a, b))
        nl, ne = ma.shape
        img = np.stack([rng.uniform(0.05 * nl, 0.95 * nl, 6 * per),
                        rng.uniform(20, ne - 20, 6 * per)], -1)
        G = ma.image_to_ground(img, 5.0)
        ib = mb.ground_to_image(G)
        ok = np.flatnonzero(np.isfinite(ib).all(1) & (ib[:, 1] > 20) & (ib[:, 1] < ne - 20))
        ok = ok[:min(per, n_ties - k)]
        g = G[ok]
        off = np.einsum("mij,mj->mi", _enu_axes(g), np.stack(
            [np.full(ok.size, 3.0), np.full(ok.size, -3.0), rng.normal(0, 1, ok.size)], -1))
        tid = [f"T{k + j:05d}" for j in range(ok.size)]
        for iid, p in ((a, img[ok]), (b, ib[ok])):
            out.append(pd.DataFrame({
                "tie_id": tid, "image_id": iid,
                "line": p[:, 0] + rng.normal(0, sigma, ok.size),
                "element": p[:, 1] + rng.normal(0, sigma, ok.size),
                "sigma_line": sigma, "sigma_element": sigma,
                "X": g[:, 0] + off[:, 0], "Y": g[:, 1] + off[:, 1], "Z": g[:, 2] + off[:, 2],
                "E": 0.0, "N": 0.0, "match_sigma": sigma}))
        k += ok.size
    return pd.concat(out, ignore_index=True)[list(TIE_COLUMNS)]


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--swings", type=int, default=50)
    ap.add_argument("--ties", type=int, default=10000)
    ap.add_argument("--control", type=int, default=10, help="control points per swing")
    a = ap.parse_args()
    from swathflow.calibration.control import calibrate
    t = time.perf_counter()
    models = tc.flight(n_swings=a.swings)
    priors = models["L1"].parameters.updated(u_sen=[0.0, 0.0, -2.0])
    obs = tc.noisy(tc.ground_points(models, tc.TRUTH, n_ctrl=a.control, n_chk=0, seed=3))
    ties = tie_table(models, a.ties)
    print(f"mission: {len(models)} swings, {ties.tie_id.nunique()} tie points "
          f"({len(ties)} observations), {len(obs)} control observations; set up in "
          f"{time.perf_counter() - t:.1f} s")
    rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    c, w = time.process_time(), time.perf_counter()
    res = calibrate(models, obs, priors, ties=ties)
    cpu, wall = time.process_time() - c, time.perf_counter() - w
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    sol, info = res.solution, res.options["ties"]
    truth = np.concatenate([tc.TRUTH[k] for k in tc.ORDER])
    z = np.abs(sol.x - truth) / np.where(sol.sigma > 0, sol.sigma, np.nan)
    print(f"unknowns: {len(sol.names)} parameters + {3 * info['points']} tie coordinates "
          f"(eliminated)")
    print(f"calibrate (robust, VCE): cpu {cpu:.1f} s, wall {wall:.1f} s; peak memory "
          f"{rss / 1024:.0f} MB (before the adjustment {rss0 / 1024:.0f} MB); "
          f"{sol.iterations} iterations, {sol.evaluations} evaluations")
    print(f"sigma0 {sol.sigma0:.3f}; tie components "
          + ", ".join(f"{k} {v['sigma_factor']:.3f}" for k, v in info["components"].items())
          + f"; {info['rejected']} tie points and {len(res.rejected)} control points "
            f"rejected; largest |estimate - truth| {np.nanmax(z):.2f} sigma")


if __name__ == "__main__":
    main()
