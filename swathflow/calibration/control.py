"""Sensor-model calibration from control points (docs/references.md section 1, and beyond it).

:func:`calibrate` estimates a sensor plugin's calibration parameters from image
observations of ground control points by weighted least squares
(:mod:`swathflow.adjustment`) on back-projection residuals in image space, with a
pseudo-observation (prior) for every parameter, variance component estimation, robust
blunder handling and optional time-linear drift of chosen parameter blocks.

It knows sensor models only through :class:`~swathflow.sensormodel.base.SensorModel`:
``ground_to_image``, ``ray``, ``with_vector`` and ``parameters``. The per-direction
variants (15 vs 12 parameters of the pendulum scanner) are expressed through parameter
block names ending in ``_L`` / ``_R``: ``shared_boresight`` merges every such pair into
one unknown.

Residuals follow docs/geometry.md: ``x`` = element (flight direction), ``y`` = line
(swing direction), observed minus computed, pixels.
"""
from __future__ import annotations

from typing import Mapping, Sequence

import numpy as np
import pandas as pd
import scipy.sparse as sp

from swathflow.adjustment import Problem, RankDeficiencyError, solve
from swathflow.calibration.evaluation import BulkObservations
from swathflow.calibration.result import (CalibrationResult, _direction, observation_context,
                                          residual_table, summarize)
from swathflow.calibration.unknowns import (DIRECTION_SUFFIXES, CalibrationError, Unknowns,
                                            build_unknowns, model_matrix, _swap_direction)
from swathflow.errors import FormatError

DIRECTION_NAMES = {"L": "left-swing", "R": "right-swing"}
HOUR = 3600.0


# --- partial derivatives ---------------------------------------------------------------
# --- unknowns and their mapping onto each image's model parameters ----------------------
    # model block -> (unknown block, drift-rate block or None)


def _image_time(model) -> float:
    lt = model.lines.get("time")
    return float(np.mean(lt)) if lt is not None and len(lt) else 0.0


# --- observations ------------------------------------------------------------------------
REQUIRED_COLUMNS = ("gcp_id", "image_id", "line", "element", "X", "Y", "Z", "role")


def _check_obs(obs: pd.DataFrame, models: Mapping) -> pd.DataFrame:
    missing = [c for c in REQUIRED_COLUMNS if c not in obs.columns]
    if missing:
        raise FormatError(f"control-point table: missing column(s) {', '.join(missing)}")
    obs = obs.reset_index(drop=True).copy()
    obs["role"] = obs["role"].astype(str).str.strip().str.lower()
    bad = ~obs["role"].isin(["control", "check"])
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise FormatError(f"control-point table row {i}: role {obs['role'][i]!r} must be "
                          f"'control' or 'check'")
    unknown = sorted(set(obs["image_id"].astype(str)) - set(map(str, models)))
    if unknown:
        raise FormatError(f"control points refer to unknown image(s) {', '.join(unknown)}; "
                          f"images: {', '.join(map(str, models))}")
    obs["image_id"] = obs["image_id"].astype(str)
    vals = obs[["line", "element", "X", "Y", "Z"]].to_numpy(float)
    bad = ~np.isfinite(vals).all(axis=1)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise FormatError(f"control-point table row {i} (gcp {obs['gcp_id'][i]}): "
                          f"non-numeric line/element/X/Y/Z")
    return obs


def _check_design(models, obs: pd.DataFrame, unknowns: Unknowns, min_per_side: int = 3):
    """Clear errors when the control points cannot determine the free parameters."""
    ctrl = obs[obs["role"] == "control"]
    nfree = int((~unknowns.fixed).sum())
    npts = len(ctrl)
    if npts == 0:
        raise CalibrationError("no control points (role 'control') on the calibration images: "
                               "add control points to gcp.csv")
    need = max(nfree, 6)
    if npts < need:
        raise CalibrationError(
            f"too few control points: {npts} image observations of control points for "
            f"{nfree} free parameters; add at least {need - npts} more (spread over both "
            f"sides of the track in left and right swings), or fix parameters (--fix)")
    dirs = {iid: _direction(m) for iid, m in models.items()}
    ctrl_dir = ctrl["image_id"].map(dirs)
    # every free per-direction block needs control points in that direction
    for uname, idx in unknowns.blocks.items():
        if unknowns.fixed[idx].all():
            continue
        for suf in DIRECTION_SUFFIXES:
            base = uname[:-len("_rate")] if uname.endswith("_rate") else uname
            if base.endswith(suf):
                d = suf[1:]
                n_d = int((ctrl_dir == d).sum())
                if n_d < 3:
                    raise CalibrationError(
                        f"{uname} ({DIRECTION_NAMES.get(d, d)} parameters) needs control "
                        f"points on {d} images, found {n_d}: add at least {3 - n_d} on "
                        f"{d} images, use the 12-parameter model (--model 12, one boresight "
                        f"for both directions) or fix it (--fix {uname})")
    # swing side coverage (sensors with a per-line swing angle)
    for d in sorted(set(ctrl_dir)):
        sel = ctrl[ctrl_dir == d]
        swing = []
        for iid, grp in sel.groupby("image_id"):
            lines = models[iid].lines
            if "swing" not in lines:
                swing = None
                break
            sw = np.asarray(lines["swing"], float)
            swing.append(np.interp(grp["line"].to_numpy(float), np.arange(sw.size), sw))
        if swing is None:
            continue
        swing = np.concatenate(swing)
        left, right = int((swing > 5.0).sum()), int((swing < -5.0).sum())
        if min(left, right) < min_per_side:
            side, other = ("left", "right") if right < left else ("right", "left")
            raise CalibrationError(
                f"the control points of {DIRECTION_NAMES.get(d, d)} ({d}) images lie on one "
                f"side of the track ({left} left, {right} right of nadir by more than 5 deg): "
                f"lever arms and mounting angles are then inseparable; add at least "
                f"{min_per_side - min(left, right)} control points on the {other} side "
                f"(swing angle {'< -5' if other == 'right' else '> 5'} deg) of {d} images")


# --- the calibration ---------------------------------------------------------------------
def calibrate(models: Mapping[str, object], obs: pd.DataFrame, priors=None, *,
              shared_boresight: bool = False, fixed: Sequence[str] = (),
              drift: bool | Sequence[str] = False, drift_sigma: float = 1.0,
              robust: bool = True, vce: bool = True, vce_priors: bool = False,
              obs_sigma_px: float = 1.0,
              alpha: float = 0.001, calibration_images: Sequence[str] | None = None,
              t_ref: float | None = None, check_design: bool = True,
              ties: pd.DataFrame | None = None) -> CalibrationResult:
    """Calibrate from control points.

    models: image id -> SensorModel (one per swing); their parameters are replaced.
    obs: rows gcp_id, image_id, line, element, X, Y, Z (ECEF), role (control/check).
    priors: ParameterSet of prior values and sigmas (default: the first model's).
    calibration_images: images whose control points enter the adjustment (default: every
        image with control points); the others are validated only (cross-application).
    vce: estimate the variance components of the x and the y image observations.
    vce_priors: also estimate one variance component for all priors (pseudo-observations).
        Off by default: the priors are heterogeneous (a lever arm known to 1 m, a
        boresight to 5 deg), and one factor for all of them, estimated from about 15
        pseudo-observations, can tighten a prior that is off by two of its sigmas until it
        biases the estimate. Its estimate is reported either way (``components``).
    ties: optional tie observations (:data:`swathflow.calibration.ties.TIE_COLUMNS`): image
        points of one ground point in several images, whose ground position is three extra
        unknowns (east, north, up corrections from X, Y, Z; the up one with a 1 m prior)
        with their own variance components; summarised in ``options["ties"]``.
    """
    if not models:
        raise CalibrationError("no images")
    models = {str(k): v for k, v in models.items()}
    obs = _check_obs(obs, models)
    first = next(iter(models.values()))
    priors = priors if priors is not None else first.parameters
    calibration_images = _calibration_images(obs, models, calibration_images)
    unk = build_unknowns(priors, shared_boresight, fixed, drift, drift_sigma)
    times = {iid: _image_time(m) for iid, m in models.items()}
    if drift and t_ref is None:
        t_ref = float(np.mean([times[c] for c in calibration_images]))
    dt = {iid: ((times[iid] - t_ref) / HOUR if drift else 0.0) for iid in models}
    mats = {iid: model_matrix(m, unk, dt[iid]) for iid, m in models.items()}
    cal_obs = obs[obs["image_id"].isin(calibration_images) & (obs["role"] == "control")]
    if check_design:
        _check_design({c: models[c] for c in calibration_images}, cal_obs, unk)
    order = {iid: k for k, iid in enumerate(calibration_images)}
    cal_obs = cal_obs.iloc[np.argsort(cal_obs["image_id"].map(order).to_numpy(),
                                      kind="stable")]
    sol = _adjust(models, mats, unk, cal_obs, obs_sigma_px, vce, vce_priors, robust, alpha,
                  ties)
    sol, tie_info = _split_ties(sol, len(unk.names))
    params, cov_ref = _model_parameters(first, unk, sol)
    vec_after = {iid: mats[iid] @ sol.x for iid in models}
    residuals = _residuals(models, obs, mats, unk, vec_after, first.parameters)
    residuals["calibration_image"] = residuals["image_id"].isin(set(calibration_images))
    rej = _rejected(sol, cal_obs, residuals)
    residuals["role"] = np.where(residuals["rejected"], "rejected", residuals["role"])
    return CalibrationResult(getattr(first, "name", ""), unk, sol, params, cov_ref, residuals,
                             summarize(residuals), rej, vec_after, list(calibration_images),
                             {"model": "12" if shared_boresight else str(len(params.vector())),
                              "shared_boresight": shared_boresight, "fixed": list(fixed),
                              "drift": drift if isinstance(drift, bool) else list(drift),
                              "robust": robust, "vce": vce, "vce_priors": vce_priors,
                              "obs_sigma_px": obs_sigma_px,
                              "alpha": alpha, "ties": tie_info},
                             t_ref if drift else None)


def _calibration_images(obs, models, chosen) -> list[str]:
    if chosen is None:
        chosen = sorted(set(obs.loc[obs["role"] == "control", "image_id"]),
                        key=list(models).index)
    chosen = [str(c) for c in chosen]
    for c in chosen:
        if c not in models:
            raise CalibrationError(f"calibration image {c!r} is not in the mission")
    return chosen


def _residual_function(models, mats, unk, spans, n_obs, sparse_total=None):
    """``fn(x, jacobian)`` of the adjustment: observed minus computed image coordinates of
    the control points and their partials (every image in one bulk evaluation,
    :class:`~swathflow.calibration.evaluation.BulkObservations`), cached for the last
    ``x``. ``sparse_total``: the Jacobian as a sparse matrix over that many unknowns (the
    calibration unknowns first)."""
    n = len(unk.names)
    image_ids = np.concatenate([[iid] * ((sl.stop - sl.start) // 2)
                                for iid, sl, _, _ in spans]) if spans else np.zeros(0)
    bulk = BulkObservations(models, mats, image_ids)
    ground = np.concatenate([G for _, _, G, _ in spans]) if spans else np.zeros((0, 3))
    l_obs = np.concatenate([lo for _, _, _, lo in spans]) if spans else np.zeros(0)
    cache: dict = {}

    def fn(x, jacobian_wanted=True):
        xc = np.asarray(x[:n], float)
        key = xc.tobytes()
        ent = cache.get(key)
        if ent is None or (jacobian_wanted and ent[1] is None):
            comp, d_x, _ = bulk.evaluate(xc, ground, jacobian_wanted)
            J = None
            if jacobian_wanted:
                J = d_x.reshape(2 * n_obs, n)
                if sparse_total is not None:
                    J = sp.hstack([sp.csr_matrix(J),
                                   sp.csr_matrix((2 * n_obs, sparse_total - n))], "csr")
            ent = (comp.ravel(), J)
            cache.clear()
            cache[key] = ent
        comp, J = ent
        return l_obs - comp, (J if jacobian_wanted else None)

    return fn


def _observation_sigmas(cal_obs: pd.DataFrame, obs_sigma_px: float) -> np.ndarray:
    """A-priori sigmas (line, element per point): the optional columns ``sigma_line`` and
    ``sigma_element`` (automatic control points carry their own), else ``obs_sigma_px``."""
    n = len(cal_obs)
    if {"sigma_line", "sigma_element"} <= set(cal_obs.columns):
        sig = cal_obs[["sigma_line", "sigma_element"]].to_numpy(float)
        sig = np.where(np.isfinite(sig) & (sig > 0), sig, float(obs_sigma_px))
        return sig.ravel()
    return np.full(2 * n, float(obs_sigma_px))


def _split_ties(sol, n: int):
    """The solution restricted to the calibration unknowns, and a summary of the tie
    points (their ground corrections are nuisance unknowns)."""
    import dataclasses
    if len(sol.names) == n:
        return sol, None
    rej = [r for r in sol.rejected if r["group"] == "tie"]
    res = sol.residuals.get("tie", np.zeros(0)).reshape(-1, 2)
    used = sol.used.get("tie", np.ones(2 * len(res), bool)).reshape(-1, 2).all(axis=1)
    info = {"observations": int(len(res)), "points": int((len(sol.names) - n) // 3),
            "rejected": len(rej), "rms_px": float(np.sqrt(np.nanmean(res[used] ** 2)))
            if used.any() else None, "rejected_names": [r["name"] for r in rej],
            "components": {k: v for k, v in sol.components.items() if k.startswith("tie")},
            "residuals": res}
    keep = dataclasses.replace(
        sol, names=sol.names[:n], units=sol.units[:n], x=sol.x[:n], x0=sol.x0[:n],
        fixed=sol.fixed[:n], cov=(sol.cov[:n, :n].toarray() if sp.issparse(sol.cov)
                                  else sol.cov[:n, :n]),
        rejected=[r for r in sol.rejected if r["group"] != "tie"],
        remaining=None if sol.remaining is None else sol.remaining[:n])
    return keep, info


def _adjust(models, mats, unk, cal_obs, obs_sigma_px, vce, vce_priors, robust, alpha,
            ties=None):
    """The adjustment: one group of image observations, rows (line, element) per point,
    and the priors as pseudo-observations; with ``ties`` a group of tie observations whose
    ground corrections are extra unknowns."""
    spans = []
    k = 0
    for iid, g in cal_obs.groupby("image_id", sort=False):
        spans.append((iid, slice(2 * k, 2 * (k + len(g))), g[["X", "Y", "Z"]].to_numpy(float),
                      g[["line", "element"]].to_numpy(float).ravel()))
        k += len(g)
    n_obs = k
    point_names = np.array([f"{g}@{i}" for i, g in zip(cal_obs["image_id"], cal_obs["gcp_id"])],
                           dtype=object)
    n = len(unk.names)
    tie_names, tie_prior, tg = [], np.zeros(0), None
    if ties is not None and len(ties):
        from swathflow.calibration.ties import tie_group
        ties = ties.reset_index(drop=True)
        tie_names, tie_prior, *tg = tie_group(models, mats, unk, ties,
                                              n + 3 * ties["tie_id"].nunique())
    n_total = n + len(tie_names)
    zeros = np.zeros(len(tie_names))
    P = Problem(list(unk.names) + tie_names, np.concatenate([unk.value, zeros]),
                list(unk.units) + ["m"] * len(tie_names))
    P.fix(np.concatenate([unk.fixed, zeros.astype(bool)]))
    P.add_observations("image", _residual_function(models, mats, unk, spans, n_obs,
                                                   n_total if tg else None),
                       _observation_sigmas(cal_obs, obs_sigma_px),
                       component=np.tile(np.array(["y", "x"], dtype=object), n_obs),
                       point=np.repeat(np.arange(n_obs), 2), point_names=point_names,
                       robust=True)
    P.add_priors(np.concatenate([unk.value, zeros]),
                 np.concatenate([np.where(unk.fixed, np.inf, unk.sigma),
                                 np.full(len(tie_names), np.inf)]), name="priors")
    if tg:
        fn, sigma, point, pnames = tg
        # their own variance components: image-to-image matches and POS noise between
        # two swings, not the reference's accuracy
        P.add_observations("tie", fn, sigma,
                           component=np.tile(np.array(["tie_y", "tie_x"], object),
                                             sigma.size // 2),
                           point=point, point_names=pnames, robust=True)
        # the tie points' heights from the terrain; a weak horizontal prior only keeps a
        # point whose observations were rejected determined (not counted)
        P.eliminate(np.arange(n, n_total).reshape(-1, 3))      # Schur: 3x3 per tie point
        P.add_priors(np.zeros(n_total),
                     np.concatenate([np.full(n, np.inf),
                                     np.where(np.isfinite(tie_prior), tie_prior, 1e3)]),
                     name="tie_ground", counted=False)
    try:
        comps = (["x", "y"] + (["tie_x", "tie_y"] if tg else [])
                 + (["priors"] if vce_priors else [])) if vce else False
        # converged when the step is below a hundredth of a sigma (the crossing's tolerance
        # floors it near 1e-3 sigma with tens of thousands of tie unknowns)
        return solve(P, vce=comps, robust=robust, alpha=alpha, jac_refresh=0.0, tol=0.01)
    except RankDeficiencyError as exc:
        raise CalibrationError(
            f"the control points cannot determine the parameters: {exc}. Add control points "
            f"(on both swing sides of left and right swings), give finite prior sigmas, or "
            f"fix parameters (--fix NAME)") from None


def _model_parameters(first, unk, sol):
    """The model-level parameters (at t_ref) with their sigmas, and their covariance."""
    Mref = model_matrix(first, unk, 0.0)
    cov_ref = Mref @ sol.cov @ Mref.T
    sig_ref = np.sqrt(np.clip(np.diag(cov_ref), 0, None))
    params = first.parameters.with_vector(Mref @ sol.x)
    upd, i = {}, 0
    for b in params.blocks:
        upd[b.name] = {"sigma": list(sig_ref[i:i + b.size])}
        i += b.size
    return params.updated(upd), cov_ref


def _residuals(models, obs, mats, unk, vec_after, prior_params) -> pd.DataFrame:
    """Residuals before and after, and cross-applied (left parameters on right images and
    the reverse) where the sensor has per-direction blocks."""
    vec_before = {iid: mats[iid] @ unk.value for iid in models}
    ctx = observation_context(models, obs)
    res = [residual_table(models, vec_before, obs, "before", ctx),
           residual_table(models, vec_after, obs, "after", ctx)]
    cross = {iid: _swap_direction(v, prior_params) for iid, v in vec_after.items()}
    if any(not np.array_equal(cross[i], vec_after[i]) for i in models):
        res.append(residual_table(models, cross, obs, "cross", ctx))
    return pd.concat(res, ignore_index=True)


#: why a control observation is dropped from the adjustment
DROPPED_REASON = ("its ground position does not project into the image (outside the "
                  "swing's lines or field of view): check its coordinates and height")
#: the columns of a result's ``rejected`` table
REJECTED_COLUMNS = ["name", "statistic", "critical", "phase", "gcp_id", "image_id", "x", "y",
                    "reason"]


def _rejected(sol, cal_obs, residuals) -> pd.DataFrame:
    """The points the blunder tests rejected, with their residuals after, then the control
    observations the adjustment could not use (phase ``dropped``: not computable, e.g. a
    point 9 km off its image), each with its ``reason``; marks the rejected ones in
    ``residuals`` (column ``rejected``)."""
    rej = pd.DataFrame(sol.rejected, columns=["group", "point", "name", "statistic",
                                              "critical", "phase"])
    after = residuals[residuals["stage"] == "after"].set_index("row")
    if len(rej):
        sub = cal_obs.iloc[rej["point"].to_numpy()]
        rej["gcp_id"] = sub["gcp_id"].to_numpy()
        rej["image_id"] = sub["image_id"].to_numpy()
        rr = after.loc[sub.index]
        rej["x"] = rr["x"].to_numpy()
        rej["y"] = rr["y"].to_numpy()
        rej["reason"] = "its residual fails the blunder test (statistic above critical)"
        residuals["rejected"] = residuals["row"].isin(set(sub.index))
    else:
        residuals["rejected"] = False
    lost = cal_obs[after.loc[cal_obs.index, ["x", "y"]].isna().any(axis=1).to_numpy()]
    dropped = pd.DataFrame({
        "name": [f"{g}@{i}" for g, i in zip(lost["gcp_id"], lost["image_id"])],
        "statistic": np.nan, "critical": np.nan, "phase": "dropped",
        "gcp_id": lost["gcp_id"].to_numpy(), "image_id": lost["image_id"].to_numpy(),
        "x": np.nan, "y": np.nan, "reason": DROPPED_REASON})
    parts = [p[REJECTED_COLUMNS] for p in (rej.drop(columns=["group", "point"]), dropped)
             if len(p)]
    return (pd.concat(parts, ignore_index=True) if parts
            else pd.DataFrame(columns=REJECTED_COLUMNS))
