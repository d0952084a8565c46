"""Push-broom calibration time: the joint adjustment (bulk projection, tie points eliminated
by Schur complement) side by side with scipy.optimize.least_squares on the same problem.

Default preset ``pushbroom-bench``: two opposite strips of a three-line camera (3 x 256
elements per line, geometry only), 20 orientation fixes, 500 tie points, 100 control points,
0.3 px measurement noise. ``--preset pushbroom`` is the full push-broom preset (114
parameters: three lines of three segments, six fixes). Prints the problem size, the time
(wall and CPU) and the iterations of the adjustment, scipy's time and evaluations on the same
weighted least-squares problem (no variance components, no data snooping; the C0/C1
constraints held through their null space) and how far its answer is from ours, and the count of
parameters within 3 sigma of the simulator's truth.

Reproduce:  .venv/bin/python benchmarks/bench_calibration_pushbroom.py --vce --robust
            .venv/bin/python benchmarks/bench_calibration_pushbroom.py --preset pushbroom \\
                --seed 4 --vce --robust
            (add --two-step for the paper's iterative scheme, --no-scipy to skip scipy)
"""
from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np


def scipy_side_by_side(st, free, obs_sigma: float, tie_sigma: float, ours) -> str:
    """scipy.optimize.least_squares (trust-region reflective, sparse Jacobian, lsmr) on the
    weighted problem our solver solves without variance components and snooping; the C0/C1
    constraints held exactly by solving over their null space (the unknowns they touch)."""
    import scipy.linalg as sla
    import scipy.sparse as sp
    from scipy.optimize import least_squares
    P = st.problem(np.zeros(st.n), free, obs_sigma, tie_sigma)
    fr = np.flatnonzero(~P.fixed)
    sig = np.concatenate([g.sigma for g in P.groups])
    x0 = P.x0[fr]
    if P.constraints:
        A = np.vstack([sp.csr_matrix(a)[:, fr].toarray() for a, _ in P.constraints])
        d = np.concatenate([b for _, b in P.constraints])
        x0 = x0 + np.linalg.lstsq(A, d - A @ x0, rcond=None)[0]
        touched = np.flatnonzero(np.abs(A).sum(axis=0) > 0)
        Nc = sla.null_space(A[:, touched])
    else:
        touched, Nc = np.zeros(0, int), np.zeros((0, 0))
    rest = np.setdiff1d(np.arange(fr.size), touched)
    N = sp.hstack([sp.csr_matrix((np.ones(rest.size), (rest, np.arange(rest.size))),
                                 shape=(fr.size, rest.size)),
                   sp.csr_matrix((Nc.ravel(), (np.repeat(touched, Nc.shape[1]),
                                               np.tile(np.arange(Nc.shape[1]), touched.size))),
                                 shape=(fr.size, Nc.shape[1]))]).tocsr()

    def full(y):
        x = P.x0.copy()
        x[fr] = x0 + N @ y
        return x

    def fun(y):
        r, _ = P.evaluate(full(y), False)
        return np.where(np.isfinite(r), r / sig, 0.0)

    def jac(y):
        _, J = P.evaluate(full(y), True)
        J = sp.diags(1.0 / sig) @ sp.csr_matrix(J)[:, fr]
        J.data[~np.isfinite(J.data)] = 0.0
        return -(J @ N).tocsr()            # the residuals are observed - computed

    c0, w0 = time.process_time(), time.perf_counter()
    res = least_squares(fun, np.zeros(N.shape[1]), jac=jac, method="trf", tr_solver="lsmr",
                        x_scale="jac")
    wall, cpu = time.perf_counter() - w0, time.process_time() - c0
    x = full(res.x)[:st.n_par]
    s = ours.sigma[:st.n_par]
    dz = np.abs(x - ours.x[:st.n_par]) / np.where(s > 0, s, np.nan)
    dz_ours = ours.x[fr] - x0              # N's columns: unit vectors, then Nc orthonormal
    cost_ours = float(np.sum(fun(np.concatenate([dz_ours[rest],
                                                 Nc.T @ dz_ours[touched]])) ** 2))
    return (f"scipy least_squares (trf, sparse Jacobian, lsmr): {wall:.2f} s wall, "
            f"{cpu:.2f} s CPU, {res.nfev} evaluations, {res.njev} Jacobians ({res.message}); "
            f"cost {2 * res.cost:.2f} (ours {cost_ours:.2f}); largest parameter difference "
            f"from ours {np.nanmax(dz):.3f} sigma")


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--preset", default="pushbroom-bench",
                    help="push-broom simulator preset (pushbroom: the full 114 parameters)")
    ap.add_argument("--seed", type=int, default=5)
    ap.add_argument("--two-step", action="store_true", help="also run the two-step scheme")
    ap.add_argument("--vce", action="store_true", help="variance component estimation")
    ap.add_argument("--robust", action="store_true", help="robust phase and data snooping")
    ap.add_argument("--no-scipy", action="store_true", help="skip scipy's least_squares")
    a = ap.parse_args()
    from swathflow.ingest.mission import load_mission
    from swathflow.sensors.pushbroom.calibration import (calibrate_pushbroom, mission_ties,
                                                         solve_joint)
    from swathflow.sensors.pushbroom.calibration.problem import build_setup, check_gcps
    from swathflow.sensors.pushbroom.simulate import simulate as simulate_pushbroom
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "m"
        t0 = time.perf_counter()
        truth = simulate_pushbroom(path, a.preset, seed=a.seed, gcp_noise=0.3, tie_noise=0.3,
                                   render=False, write_ortho=False)
        t_sim = time.perf_counter() - t0
        m = load_mission(path)
        ties = mission_ties(m)
        models = {i: m.model(i) for i in m.image_ids}
        n_ctrl = int(m.gcps[m.gcps.role == "control"].gcp_id.nunique())
        print(f"preset {a.preset} seed {a.seed}: {len(models)} images, "
              f"{len(truth['fix_times'])} fixes, {ties.tie_id.nunique()} tie points "
              f"({len(ties)} observations), {n_ctrl} control points "
              f"({int((m.gcps.role == 'control').sum())} observations); simulated in "
              f"{t_sim:.1f} s")
        c0, w0 = time.process_time(), time.perf_counter()
        res = calibrate_pushbroom(models, m.gcps, ties, m.priors,
                                  method="both" if a.two_step else "joint",
                                  robust=a.robust, vce=a.vce, obs_sigma_px=0.3)
        wall, cpu = time.perf_counter() - w0, time.process_time() - c0
        o = res.options
        print(f"unknowns {o['unknowns_total']} ({o['model']} parameters + "
              f"{3 * o['tie_points']} tie coordinates), {o['observations']} observations")
        sol = res.solution
        print(f"joint: {res.timings['joint']:.2f} s, {sol.iterations} iterations "
              f"({len(sol.history)} steps taken), {sol.evaluations} evaluations, "
              f"{len(sol.rejected)} points rejected; sigma0 {res.sigma0:.3f}")
        if res.alternative is not None:
            alt = res.alternative
            d = np.abs(res.values - alt.values) / np.where(res.sigmas > 0, res.sigmas, np.nan)
            print(f"two-step: {res.timings['two-step']:.1f} s, {len(alt.rounds)} rounds "
                  f"({'converged' if alt.solution.converged else 'NOT converged'}: last "
                  f"joint step {alt.rounds[-1]['gap_sigma']:.3f} sigma); largest difference "
                  f"from the joint solution {np.nanmax(d):.2f} sigma")
        print(f"calibration: {wall:.2f} s wall, {cpu:.2f} s CPU")
        tru = json.loads((path / "truth" / "truth.json").read_text())["parameters"]
        tv = np.concatenate([tru[b.name] for b in res.parameters.blocks])
        z = np.abs(res.values - tv) / res.sigmas
        cx, cy = res.check_rms()
        print(f"truth: {int(np.sum(z <= 3))} of {z.size} parameters within 3 sigma, largest "
              f"|error| / sigma {np.nanmax(z):.2f} (median {np.nanmedian(z):.2f}); check "
              f"points RMS x {cx:.3f} y {cy:.3f} px; C0/C1 max residual "
              f"{res.max_continuity_residual:.1e}")
        if not a.no_scipy:
            st, _ = build_setup(models, check_gcps(m.gcps, models), ties, m.priors, (), list(models))
            free = ~st.unk.fixed
            w0 = time.perf_counter()
            ours, _ = solve_joint(st, np.zeros(st.n), free, vce=False, robust=False,
                                  alpha=0.001, obs_sigma=0.3, tie_sigma=0.3)
            print(f"ours on the same plain problem: {time.perf_counter() - w0:.2f} s wall, "
                  f"{ours.iterations} iterations, {ours.evaluations} evaluations")
            print(scipy_side_by_side(st, free, 0.3, 0.3, ours))


if __name__ == "__main__":
    main()
