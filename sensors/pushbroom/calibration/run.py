"""Calibrating a push-broom camera: :func:`calibrate_pushbroom` (models, control points,
tie points, priors -> result) and the plugin's calibration strategy (a mission in, the same
result out)."""
from __future__ import annotations

import time
from typing import Mapping, Sequence

import numpy as np
import pandas as pd

from swathflow.calibration.unknowns import CalibrationError
from swathflow.sensors.pushbroom.calibration.problem import build_setup, check_gcps
from swathflow.sensors.pushbroom.calibration.result import (PushbroomCalibrationResult,
                                                            build_result)
from swathflow.sensors.pushbroom.calibration.solve import solve_joint, solve_two_step
from swathflow.sensors.pushbroom.calibration.ties import mission_ties

METHODS = ("joint", "two-step", "both")


def calibrate_pushbroom(models: Mapping[str, object], gcps: pd.DataFrame | None,
                        ties: pd.DataFrame | None = None, priors=None, *,
                        method: str = "joint", fixed: Sequence[str] = (),
                        robust: bool = True, vce: bool = True, obs_sigma_px: float = 1.0,
                        tie_sigma_px: float | None = None, alpha: float = 0.001,
                        calibration_images: Sequence[str] | None = None,
                        max_rounds: int = 50) -> PushbroomCalibrationResult:
    """Calibrate a push-broom camera from control points and tie points.

    models: image id -> PushbroomModel (every view and strip). gcps: rows gcp_id, image_id,
    line, element, X, Y, Z (ECEF), role (control/check; check points are only evaluated).
    ties: rows tie_id, image_id, line, element (ground unknown; two or more images each).
    priors: ParameterSet of prior values and sigmas (default: the first model's).
    method: "joint", "two-step" (the paper's iterative scheme), or "both" (joint, with the
    two-step solution as ``result.alternative``).
    """
    if method not in METHODS:
        raise CalibrationError(f"method must be one of {', '.join(METHODS)}, got {method!r}")
    if not models:
        raise CalibrationError("no images")
    models = {str(k): v for k, v in models.items()}
    first = next(iter(models.values()))
    if getattr(first, "name", "") != "pushbroom":
        raise CalibrationError("calibrate_pushbroom needs push-broom sensor models")
    priors = priors if priors is not None else first.parameters
    if gcps is not None:
        gcps = check_gcps(gcps, models)
    if calibration_images is None:
        calibration_images = list(models)
    calibration_images = [str(c) for c in calibration_images]
    for c in calibration_images:
        if c not in models:
            raise CalibrationError(f"calibration image {c!r} is not in the mission")
    t0 = time.perf_counter()
    st, info = build_setup(models, gcps, ties, priors, fixed, calibration_images)
    free = ~st.unk.fixed
    n_ctrl = int(np.sum(st.comp == "x"))
    if n_ctrl == 0:
        raise CalibrationError("no control points (role 'control') on the calibration "
                               "images: tie points alone do not fix the datum; add control "
                               "points to gcp.csv")
    tie_sigma = float(tie_sigma_px if tie_sigma_px is not None else obs_sigma_px)
    kw = dict(vce=vce, alpha=alpha, obs_sigma=float(obs_sigma_px), tie_sigma=tie_sigma)
    timings = {"setup": time.perf_counter() - t0}
    z0 = np.zeros(st.n)
    options = {"model": str(st.n_par), "fixed": list(fixed), "robust": robust, "vce": vce,
               "obs_sigma_px": obs_sigma_px, "tie_sigma_px": tie_sigma, "alpha": alpha,
               "unknowns_total": st.n, "tie_points": int(st.tie_ids.size),
               "observations": int(st.l_obs.size), "free": free}
    results = {}
    if method in ("joint", "both"):
        t1 = time.perf_counter()
        sol, _ = solve_joint(st, z0, free, robust=robust, **kw)
        timings["joint"] = time.perf_counter() - t1
        results["joint"] = (sol, [])
    if method in ("two-step", "both"):
        t1 = time.perf_counter()
        sol, rounds, conv = solve_two_step(st, z0, free, max_rounds=max_rounds, **kw)
        sol.converged = conv
        timings["two-step"] = time.perf_counter() - t1
        results["two-step"] = (sol, rounds)
    out = {}
    for name, (sol, rounds) in results.items():
        out[name] = build_result(st, sol, models, gcps, priors, name,
                                 {**options, "method": name}, calibration_images, rounds,
                                 timings, info["dropped_ties"])
    main = out["joint" if method in ("joint", "both") else "two-step"]
    if method == "both":
        main.alternative = out["two-step"]
    main.timings["total"] = time.perf_counter() - t0
    return main


# --- the plugin's calibration strategy ---------------------------------------------------
class PushbroomCalibration:
    """Control and tie points, orientation fixes, C0/C1 constraints (--method, --max-rounds).

    ``options.extra``: ``method`` (joint, two-step, both) and ``max_rounds``."""

    def calibrate(self, mission, options):
        if mission.gcps is None or not len(mission.gcps):
            raise CalibrationError(f"{mission.path}: no control points (add [gcp] file = "
                                   f"\"gcp.csv\" to mission.toml)")
        models = {iid: mission.model(iid) for iid in mission.image_ids}
        extra = dict(options.extra)
        return calibrate_pushbroom(models, mission.gcps, mission_ties(mission), mission.priors,
                                   method=str(extra.get("method") or "joint"),
                                   fixed=list(options.fixed), robust=options.robust,
                                   vce=options.vce, obs_sigma_px=options.sigma_px,
                                   calibration_images=(list(options.images)
                                                       if options.images else None),
                                   max_rounds=int(extra.get("max_rounds") or 50))


STRATEGY = PushbroomCalibration()
