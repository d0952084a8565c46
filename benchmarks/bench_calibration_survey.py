"""Calibration of the survey mission (240 swings, 1,252 control observations, 15
parameters): the whole command ``swathflow calibrate MISSION --out OUT`` (a fresh process:
start-up, loading, adjustment, residual tables, calibration.json and report.html; its CPU
time from ``resource.getrusage(RUSAGE_CHILDREN)``), calibrate() in this process (robust,
variance components, residual tables), the adjustment alone, and the same weighted
least-squares problem (no robust phase, no variance components) by our solver and by
scipy.optimize.least_squares (trust-region reflective, the same analytic sparse Jacobian).

Reproduce:
    swathflow simulate /tmp/survey --preset survey --seed 4
    python benchmarks/bench_calibration_survey.py /tmp/survey
(without a mission folder the benchmark simulates one first, which takes minutes).
CPU times are printed beside wall times: on a shared machine the wall time mostly waits.
"""
from __future__ import annotations

import argparse
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np


def _clock():
    return time.process_time(), time.perf_counter()


def _since(t):
    c, w = _clock()
    return c - t[0], w - t[1]


def _free_unknowns(P):
    """The Problem ``P``'s free unknowns (mask), observation sigmas, start values and the
    map from the free unknowns' values back to the whole vector (fixed ones held)."""
    free = ~P.fixed
    sig = np.concatenate([g.sigma for g in P.groups])
    x0 = P.x0.copy()

    def full(z):
        x = x0.copy()
        x[free] = z
        return x
    return free, sig, x0, full


def scipy_solve(P):
    """The Problem ``P`` (weighted least squares, fixed unknowns held) by
    scipy.optimize.least_squares with its analytic Jacobian (sparse)."""
    import scipy.sparse as sp
    from scipy.optimize import least_squares
    free, sig, x0, full = _free_unknowns(P)

    def fun(z):
        r, _ = P.evaluate(full(z), False)
        return np.nan_to_num(r / sig)

    def jac(z):
        _, J = P.evaluate(full(z), True)
        J = sp.csr_matrix(J)[:, free]
        J.data = np.nan_to_num(J.data)
        return -(sp.diags(1.0 / sig) @ J)

    res = least_squares(fun, x0[free], jac=jac, method="trf", x_scale="jac",
                        tr_solver="lsmr")
    return full(res.x), res.nfev, res.njev


def ceres_solve(P):
    """The Problem ``P`` by Ceres (pyceres, when installed; not a dependency): one residual
    block of every weighted residual over the free unknowns, our analytic Jacobian (dense:
    15 unknowns), Levenberg-Marquardt with its default tolerances."""
    import pyceres
    import scipy.sparse as sp
    free, sig, x0, full = _free_unknowns(P)

    class Cost(pyceres.CostFunction):
        def __init__(self):
            super().__init__()
            self.set_num_residuals(sig.size)
            self.set_parameter_block_sizes([int(free.sum())])

        def Evaluate(self, parameters, residuals, jacobians):
            want = jacobians is not None and jacobians[0] is not None
            r, J = P.evaluate(full(np.asarray(parameters[0])), want)
            residuals[:] = np.nan_to_num(r / sig)
            if want:
                Jd = sp.csr_matrix(J)[:, free].toarray()
                jacobians[0][:] = np.nan_to_num(-(Jd / sig[:, None])).ravel()
            return True

    z = x0[free].copy()
    prob = pyceres.Problem()
    prob.add_residual_block(Cost(), None, [z])
    opts = pyceres.SolverOptions()
    opts.linear_solver_type = pyceres.LinearSolverType.DENSE_QR
    summary = pyceres.SolverSummary()
    pyceres.solve(opts, prob, summary)
    return full(z), summary


def whole_command(path, out) -> tuple[float, float]:
    """CPU and wall seconds of ``swathflow calibrate path --out out`` in a fresh process."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    w = time.perf_counter()
    subprocess.run([sys.executable, "-c", "import sys; from swathflow.flows.cli import main; "
                    "sys.exit(main())", "calibrate", "-q", str(path), "--out", str(out)],
                   check=True)
    wall = time.perf_counter() - w
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    return (after.ru_utime - before.ru_utime + after.ru_stime - before.ru_stime), wall


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("mission", nargs="?", help="a simulated survey mission (default: "
                                               "simulate one)")
    ap.add_argument("--no-scipy", action="store_true")
    ap.add_argument("--no-ceres", action="store_true", help="skip pyceres even if installed")
    a = ap.parse_args()
    from swathflow.adjustment import solve
    from swathflow.calibration import control
    from swathflow.ingest.mission import load_mission
    with tempfile.TemporaryDirectory() as tmp:
        path = a.mission
        if path is None:
            from swathflow.sensors.pendulum.simulate import simulate
            path = Path(tmp) / "survey"
            simulate(path, "survey", seed=4)
        cpu, wall = whole_command(path, Path(tmp) / "out")
        print(f"swathflow calibrate {path} --out OUT (whole command, report included): "
              f"cpu {cpu:.2f} s, wall {wall:.2f} s")
        m = load_mission(path)
        models = {i: m.model(i) for i in m.image_ids}
        captured, adj = {}, {}
        orig = control.solve

        def timed(P, **kw):
            captured["P"] = P
            t = _clock()
            s = orig(P, **kw)
            adj["t"] = _since(t)
            return s

        control.solve = timed
        t = _clock()
        res = control.calibrate(models, m.gcps, m.priors)
        cal = _since(t)
        control.solve = orig
        sol = res.solution
        n_obs = int((m.gcps.role == "control").sum())
        print(f"survey: {len(models)} swings, {n_obs} control observations, "
              f"{len(sol.names)} parameters")
        print(f"calibrate (robust, VCE): cpu {cal[0]:.2f} s, wall {cal[1]:.2f} s")
        print(f"  adjustment alone: cpu {adj['t'][0]:.2f} s, wall {adj['t'][1]:.2f} s; "
              f"{sol.iterations} iterations, {sol.evaluations} evaluations, "
              f"{len(sol.rejected)} rejected, sigma0 {sol.sigma0:.3f}")
        P = captured["P"]
        t = _clock()
        plain = solve(P, vce=False, robust=False, jac_refresh=0.0)
        tp = _since(t)
        print(f"plain weighted LS, ours: cpu {tp[0]:.2f} s, wall {tp[1]:.2f} s, "
              f"{plain.iterations} iterations, {plain.evaluations} evaluations")
        if not a.no_scipy:
            t = _clock()
            xs, nfev, njev = scipy_solve(P)
            ts = _since(t)
            d = np.abs(xs - plain.x) / np.where(plain.sigma > 0, plain.sigma, np.nan)
            print(f"plain weighted LS, scipy least_squares (trf, lsmr, sparse analytic J): cpu "
                  f"{ts[0]:.2f} s, wall {ts[1]:.2f} s, {nfev} evaluations, {njev} "
                  f"Jacobians; largest difference from ours {np.nanmax(d):.3f} sigma")
        if not a.no_ceres:
            try:
                import pyceres  # noqa: F401
            except ImportError:
                print("pyceres not installed: no Ceres comparison (pip install pyceres)")
                return
            t = _clock()
            xc, summary = ceres_solve(P)
            tc = _since(t)
            d = np.abs(xc - plain.x) / np.where(plain.sigma > 0, plain.sigma, np.nan)
            print(f"plain weighted LS, Ceres (pyceres, LM, dense QR, our analytic J): cpu "
                  f"{tc[0]:.2f} s, wall {tc[1]:.2f} s, "
                  f"{summary.num_successful_steps + summary.num_unsuccessful_steps} "
                  f"iterations, {summary.num_residual_evaluations} evaluations; largest "
                  f"difference from ours {np.nanmax(d):.3f} sigma")


if __name__ == "__main__":
    main()
