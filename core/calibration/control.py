"""Sensor-model calibration from control points (papers.md section 1, and beyond it).

:func:`calibrate` estimates a sensor plugin's calibration parameters from image
observations of ground control points by weighted least squares
(:mod:`swathflow.adjustment.adjust`) on back-projection residuals in image space, with a
pseudo-observation (prior) for every parameter, variance component estimation, robust
blunder handling and optional time-linear drift of chosen parameter blocks.

It knows sensor models only through :class:`~swathflow.sensors.base.SensorModel`:
``ground_to_image``, ``ray``, ``with_vector`` and ``parameters``. The per-direction
variants (15 vs 12 parameters of the pendulum scanner) are expressed through parameter
block names ending in ``_L`` / ``_R``: ``shared_boresight`` merges every such pair into
one unknown.

Residuals follow spec/geometry.md: ``x`` = element (flight direction), ``y`` = line
(swing direction), observed minus computed, pixels.
"""
from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from typing import Mapping, Sequence

import numpy as np
import pandas as pd

from swathflow.adjustment.adjust import Problem, RankDeficiencyError, Solution, solve
from swathflow.errors import FormatError, SwathflowError

DIRECTION_SUFFIXES = ("_L", "_R")
DIRECTION_NAMES = {"L": "left-swing", "R": "right-swing"}
HOUR = 3600.0


class CalibrationError(SwathflowError):
    """The control points cannot determine the requested parameters."""


# --- partial derivatives ---------------------------------------------------------------
def _ray_miss(model, image, ground, basis):
    c, d = model.ray(image)
    u = ground - c
    u = u / np.linalg.norm(u, axis=-1, keepdims=True)
    diff = u - d
    return np.stack([np.einsum("ij,ij->i", basis[0], diff),
                     np.einsum("ij,ij->i", basis[1], diff)], axis=-1)


def _line_subset(model, image):
    """A copy of ``model`` whose line table holds only the lines around ``image`` points,
    and the points' coordinates in it. Per-line quantities are interpolated linearly
    between line centres (spec/geometry.md), so rays are unchanged; rebuilding the small
    model per parameter step is then cheap."""
    lines = model.lines
    nl = model.n_lines
    if nl < 8 or 4 * image.shape[0] >= nl:
        return model, image
    j = np.clip(np.floor(image[:, 0]), 0, nl - 2).astype(int)
    rows = np.unique(np.clip(np.concatenate([j - 1, j, j + 1, j + 2]), 0, nl - 1))
    sub = {k: (np.asarray(v)[rows] if np.ndim(v) == 1 and len(v) == nl else v)
           for k, v in lines.items()}
    try:
        small = type(model)(model.sensor, sub, model.trajectory, model.parameters,
                            **model.image_attrs)
    except Exception:            # a model that cannot be cut: use it whole
        return model, image
    im = image.copy()
    im[:, 0] = np.searchsorted(rows, j) + (image[:, 0] - j)
    return small, im


def image_partials(model, ground, image=None, names: Sequence[str] | None = None,
                   skip: Sequence[bool] | None = None, central: bool = True) -> np.ndarray:
    """d(line, element)/d(parameter), ``(n, 2, P)``, by the implicit function theorem.

    The image point ``image`` of ``ground`` (default: ``model.ground_to_image``) is where
    the ray meets the point. With ``F`` the angular miss between the ray of an image point
    and the direction to the ground point (two components across the ray),
    ``d(image)/dp = -(dF/dimage)^-1 dF/dp``; both by finite differences of
    :meth:`ray`, which is direct, so this needs no iterative back-projection per parameter
    (``model.parameter_partials`` needs two). ``skip`` marks parameters known to have no
    effect (their columns are zero)."""
    ground = np.asarray(ground, float).reshape(-1, 3)
    if image is None:
        image = model.ground_to_image(ground, clip=False)
    image = np.asarray(image, float).reshape(-1, 2)
    params = model.parameters
    flat = params.flat_names()
    units = params.flat_units()
    sel = list(range(len(flat))) if names is None else [flat.index(n) for n in names]
    out = np.zeros((ground.shape[0], 2, len(sel)))
    ok = np.isfinite(image).all(axis=1) & np.isfinite(ground).all(axis=1)
    if not ok.any():
        return np.where(ok[:, None, None], out, np.nan)
    g, im = ground[ok], image[ok]
    model, im = _line_subset(model, im)
    _, d0 = model.ray(im)
    a = np.eye(3)[np.argmin(np.abs(d0), axis=1)]
    b1 = np.cross(d0, a)
    b1 /= np.linalg.norm(b1, axis=1, keepdims=True)
    b2 = np.cross(d0, b1)
    basis = (b1, b2)
    f0 = _ray_miss(model, im, g, basis)
    hl = 1e-3
    d_img = np.empty((g.shape[0], 2, 2))
    for k in range(2):
        e = np.zeros(2)
        e[k] = hl
        d_img[:, :, k] = (_ray_miss(model, im + e, g, basis)
                          - _ray_miss(model, im - e, g, basis)) / (2 * hl)
    v0 = params.vector()
    cols = np.zeros((g.shape[0], 2, len(sel)))
    for c, i in enumerate(sel):
        if skip is not None and skip[c]:
            continue
        h = model.fd_steps.get(units[i], model.fd_steps.get("", 1e-6))
        vp = v0.copy()
        vp[i] += h
        fp = _ray_miss(model.with_vector(vp), im, g, basis)
        if central:
            vm = v0.copy()
            vm[i] -= h
            fm = _ray_miss(model.with_vector(vm), im, g, basis)
            cols[:, :, c] = (fp - fm) / (2 * h)
        else:
            cols[:, :, c] = (fp - f0) / h
    out[ok] = -np.linalg.solve(d_img, cols)
    out[~ok] = np.nan
    return out


# --- unknowns and their mapping onto each image's model parameters ----------------------
@dataclass
class Unknowns:
    names: list[str]
    units: list[str]
    value: np.ndarray
    sigma: np.ndarray
    fixed: np.ndarray
    blocks: dict[str, list[int]]            # unknown block -> its unknown indices
    block_units: dict[str, str]
    model_map: dict[str, tuple[str, str | None]] = field(default_factory=dict)
    # model block -> (unknown block, drift-rate block or None)


def _flat(name, size, i):
    return name if size == 1 else f"{name}[{i}]"


def build_unknowns(priors, shared_boresight: bool = False, fixed: Sequence[str] = (),
                   drift: bool | Sequence[str] = False, drift_sigma: float = 1.0,
                   directions: Sequence[str] = ("L", "R")) -> Unknowns:
    """The adjustment's unknowns from the prior :class:`ParameterSet`.

    shared_boresight: each pair ``NAME_L`` / ``NAME_R`` becomes one unknown ``NAME``.
    fixed: block names (``opk_sen``) or flat names (``opk_sen[1]``) held at their priors.
    drift: True (every per-direction block) or block names: adds ``NAME_rate`` unknowns in
        units per hour with prior 0 +- ``drift_sigma``.
    """
    blocks = list(priors.blocks)
    names, units, value, sigma, fix = [], [], [], [], []
    ublocks: dict[str, list[int]] = {}
    bunits: dict[str, str] = {}
    model_map: dict[str, tuple[str, str | None]] = {}
    paired = {}
    if shared_boresight:
        bnames = {b.name for b in blocks}
        for b in blocks:
            for suf in DIRECTION_SUFFIXES:
                if b.name.endswith(suf):
                    base = b.name[:-len(suf)]
                    if all(base + s in bnames for s in DIRECTION_SUFFIXES):
                        paired[b.name] = base
        if not paired:
            raise CalibrationError("shared boresight (12-parameter model) needs parameter "
                                   "blocks named NAME_L and NAME_R; this sensor has "
                                   + ", ".join(b.name for b in blocks))

    def add_block(uname, size, unit, vals, sigs):
        idx = []
        for i in range(size):
            names.append(_flat(uname, size, i))
            units.append(unit)
            value.append(vals[i])
            sigma.append(sigs[i])
            fix.append(False)
            idx.append(len(names) - 1)
        ublocks[uname] = idx
        bunits[uname] = unit

    for b in blocks:
        uname = paired.get(b.name, b.name)
        if uname not in ublocks:
            if uname != b.name:      # merged pair: average the priors
                pair = [priors.block(uname + s) for s in DIRECTION_SUFFIXES]
                vals = np.mean([p.value for p in pair], axis=0)
                sigs = np.min([p.sigma for p in pair], axis=0)
            else:
                vals, sigs = b.value, b.sigma
            add_block(uname, b.size, b.units, vals, sigs)
            for i, f in enumerate(b.fixed):
                if f:
                    fix[ublocks[uname][i]] = True
        model_map[b.name] = (uname, None)
    if drift:
        if drift is True:
            dblocks = [b.name for b in blocks if b.name.endswith(DIRECTION_SUFFIXES)]
            if not dblocks:
                raise CalibrationError("drift=True drifts the per-direction blocks (NAME_L, "
                                       "NAME_R), and this sensor has none: name the blocks")
        else:
            dblocks = list(drift)
        for name in dblocks:
            if name not in model_map:
                raise CalibrationError(f"drift: no parameter block {name!r}; known: "
                                       + ", ".join(model_map))
            uname = model_map[name][0]
            rname = uname + "_rate"
            if rname not in ublocks:
                size = len(ublocks[uname])
                add_block(rname, size, bunits[uname] + "/h", [0.0] * size,
                          [drift_sigma] * size)
            model_map[name] = (uname, rname)
    fixed_arr = np.array(fix, bool)
    for f in fixed:
        if f in ublocks:
            fixed_arr[ublocks[f]] = True
        elif f in names:
            fixed_arr[names.index(f)] = True
        elif f in model_map:
            fixed_arr[ublocks[model_map[f][0]]] = True
        else:
            raise CalibrationError(f"--fix {f}: no such parameter; known: "
                                   + ", ".join(list(ublocks) + names))
    return Unknowns(names, units, np.array(value, float), np.array(sigma, float), fixed_arr,
                    ublocks, bunits, model_map)


def model_matrix(model, unknowns: Unknowns, dt_hours: float = 0.0) -> np.ndarray:
    """M with ``model_vector = M @ x`` for one image (dt_hours: image time - t_ref)."""
    ps = model.parameters
    rows = []
    for b in ps.blocks:
        if b.name not in unknowns.model_map:
            raise CalibrationError(f"model parameter {b.name!r} has no unknown")
        uname, rname = unknowns.model_map[b.name]
        for i in range(b.size):
            row = np.zeros(len(unknowns.names))
            row[unknowns.blocks[uname][i]] = 1.0
            if rname is not None:
                row[unknowns.blocks[rname][i]] = dt_hours
            rows.append(row)
    return np.array(rows)


def _image_time(model) -> float:
    lt = model.lines.get("time")
    return float(np.mean(lt)) if lt is not None and len(lt) else 0.0


def _direction(model) -> str:
    return str(model.image_attrs.get("direction", "")).upper()


def _swap_direction(vec: np.ndarray, params) -> np.ndarray:
    """A model vector with every NAME_L / NAME_R pair exchanged (cross-application)."""
    out = vec.copy()
    names = params.names
    pos, i = {}, 0
    for b in params.blocks:
        pos[b.name] = (i, b.size)
        i += b.size
    for n in names:
        if n.endswith("_L") and n[:-2] + "_R" in pos:
            (a, s), (c, _) = pos[n], pos[n[:-2] + "_R"]
            out[a:a + s], out[c:c + s] = vec[c:c + s], vec[a:a + s]
    return out


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
def residual_table(models: Mapping, vectors: Mapping[str, np.ndarray], obs: pd.DataFrame,
                   stage: str) -> pd.DataFrame:
    """Observed minus computed per observation: x (element), y (line), pixels."""
    out = []
    for iid, grp in obs.groupby("image_id", sort=False):
        m = models[iid].with_vector(vectors[iid])
        comp = m.ground_to_image(grp[["X", "Y", "Z"]].to_numpy(float), clip=False)
        out.append(pd.DataFrame({
            "row": grp.index.to_numpy(), "gcp_id": grp["gcp_id"].to_numpy(), "image_id": iid,
            "direction": _direction(models[iid]), "role": grp["role"].to_numpy(),
            "stage": stage, "x": grp["element"].to_numpy(float) - comp[:, 1],
            "y": grp["line"].to_numpy(float) - comp[:, 0]}, index=grp.index))
    if not out:
        return pd.DataFrame(columns=["row", "gcp_id", "image_id", "direction", "role", "stage",
                                     "x", "y"])
    return pd.concat(out).sort_index()


def summarize(res: pd.DataFrame, by=("stage", "image_id", "direction", "role")) -> pd.DataFrame:
    """Mean, std (ddof 1), RMS of x and y and counts per group (NaN rows counted apart)."""
    rows = []
    for key, g in res.groupby(list(by), sort=False):
        ok = g[["x", "y"]].notna().all(axis=1)
        x, y = g.loc[ok, "x"].to_numpy(), g.loc[ok, "y"].to_numpy()
        row = dict(zip(by, key if isinstance(key, tuple) else (key,)))
        row.update(n=int(ok.sum()), n_unprojected=int((~ok).sum()),
                   mean_x=float(x.mean()) if x.size else np.nan,
                   std_x=float(x.std(ddof=1)) if x.size > 1 else np.nan,
                   mean_y=float(y.mean()) if y.size else np.nan,
                   std_y=float(y.std(ddof=1)) if y.size > 1 else np.nan,
                   rms_x=float(np.sqrt(np.mean(x ** 2))) if x.size else np.nan,
                   rms_y=float(np.sqrt(np.mean(y ** 2))) if y.size else np.nan)
        rows.append(row)
    return pd.DataFrame(rows)


@dataclass
class CalibrationResult:
    """Everything a calibration produced (see :func:`calibrate`)."""

    sensor: str
    unknowns: Unknowns
    solution: Solution
    parameters: object                  # model-level ParameterSet (values, sigmas)
    model_cov: np.ndarray               # covariance of the model-level flat vector at t_ref
    residuals: pd.DataFrame             # per observation, stages before/after/cross
    summary: pd.DataFrame
    rejected: pd.DataFrame
    image_vectors: dict[str, np.ndarray]
    calibration_images: list[str]
    options: dict
    t_ref: float | None = None

    # unknown-level views
    @property
    def names(self) -> list[str]:
        return self.solution.names

    @property
    def values(self) -> np.ndarray:
        return self.solution.x

    @property
    def sigmas(self) -> np.ndarray:
        return self.solution.sigma

    @property
    def covariance(self) -> np.ndarray:
        return self.solution.cov

    @property
    def correlation(self) -> np.ndarray:
        return self.solution.corr

    @property
    def sigma0(self) -> float:
        return self.solution.sigma0

    @property
    def components(self) -> dict:
        return self.solution.components

    @property
    def iterations(self) -> int:
        return self.solution.iterations

    def parameter_table(self) -> pd.DataFrame:
        s = self.solution
        u = self.unknowns
        with np.errstate(invalid="ignore", divide="ignore"):
            share = 1.0 - (s.sigma / u.sigma) ** 2
        return pd.DataFrame({"name": s.names, "units": s.units, "value": s.x,
                             "sigma": s.sigma, "prior": u.value, "prior_sigma": u.sigma,
                             "change": s.x - u.value, "fixed": u.fixed,
                             "data_share": np.where(u.fixed, np.nan, share)})

    def strong_correlations(self, threshold: float = 0.9) -> list[tuple[str, str, float]]:
        c = self.correlation
        i, j = np.triu_indices_from(c, k=1)
        keep = np.abs(c[i, j]) >= threshold
        return sorted(((self.names[a], self.names[b], float(c[a, b]))
                       for a, b in zip(i[keep], j[keep])), key=lambda t: -abs(t[2]))

    def calibration_document(self) -> dict:
        """Keyword arguments for :func:`swathflow.formats.calibfile.write_calibration`."""
        ps = self.parameters
        params = {b.name: {"value": list(b.value), "sigma": list(b.sigma), "units": b.units}
                  for b in ps.blocks}
        summ = {}
        for _, r in self.summary.iterrows():
            key = f"{r['image_id']}/{r['role']}/{r['stage']}"
            summ[key] = {k: (None if isinstance(r[k], float) and not math.isfinite(r[k])
                             else r[k]) for k in ("n", "mean_x", "std_x", "mean_y", "std_y",
                                                  "rms_x", "rms_y")}
        extra = {"sigma0": self.sigma0, "residuals": summ,
                 "model": self.options.get("model"),
                 "calibration_images": self.calibration_images,
                 "variance_components": {k: {"sigma_factor": v["sigma_factor"],
                                             "redundancy": v["redundancy"],
                                             "estimated": v["estimated"]}
                                         for k, v in self.components.items()},
                 "rejected": self.rejected.to_dict(orient="records"),
                 "unknowns": {"names": self.names, "units": self.solution.units,
                              "value": self.values, "sigma": self.sigmas,
                              "correlation": self.correlation},
                 "iterations": self.iterations, "converged": self.solution.converged}
        if self.t_ref is not None:
            rates = {n: {"value": [self.values[i] for i in idx],
                         "sigma": [self.sigmas[i] for i in idx],
                         "units": self.unknowns.block_units[n]}
                     for n, idx in self.unknowns.blocks.items() if n.endswith("_rate")}
            extra["drift"] = {"t_ref": self.t_ref, "rates": rates,
                              "note": "value(t) = value + rate * (t - t_ref) / 3600"}
        return {"sensor": self.sensor, "parameters": params, **extra}

    def summary_lines(self) -> list[str]:
        """What a person reads on the terminal after a calibration."""
        s = self.summary
        out = [f"calibrated {len(self.unknowns.names)} parameters from "
               f"{int((self.residuals['stage'] == 'after').sum())} image points "
               f"(sigma0 {self.sigma0:.3f}, {len(self.rejected)} rejected, "
               f"{self.iterations} iterations)"]
        for _, r in s[s["stage"] == "after"].iterrows():
            out.append(f"  {r['image_id']:>8} {r['role']:<8} n={r['n']:4d}  mean x "
                       f"{r['mean_x']:+8.3f} y {r['mean_y']:+8.3f}  std x {r['std_x']:7.3f} "
                       f"y {r['std_y']:7.3f} px")
        return out

    def write(self, out_dir) -> dict[str, str]:
        """Write ``calibration.json`` and ``report.html`` into ``out_dir`` (atomically)."""
        from swathflow.formats.calibfile import write_calibration
        from swathflow.calibration.report import write_report
        os.makedirs(out_dir, exist_ok=True)
        doc = self.calibration_document()
        cal = os.path.join(out_dir, "calibration.json")
        write_calibration(cal, doc.pop("sensor"), doc.pop("parameters"), **doc)
        rep = os.path.join(out_dir, "report.html")
        write_report(self, rep)
        return {"calibration": cal, "report": rep}


def calibrate(models: Mapping[str, object], obs: pd.DataFrame, priors=None, *,
              shared_boresight: bool = False, fixed: Sequence[str] = (),
              drift: bool | Sequence[str] = False, drift_sigma: float = 1.0,
              robust: bool = True, vce: bool = True, vce_priors: bool = False,
              obs_sigma_px: float = 1.0,
              alpha: float = 0.001, calibration_images: Sequence[str] | None = None,
              t_ref: float | None = None, check_design: bool = True) -> CalibrationResult:
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
    """
    if not models:
        raise CalibrationError("no images")
    models = {str(k): v for k, v in models.items()}
    obs = _check_obs(obs, models)
    first = next(iter(models.values()))
    priors = priors if priors is not None else first.parameters
    sensor = getattr(first, "name", "")
    if calibration_images is None:
        calibration_images = sorted(set(obs.loc[obs["role"] == "control", "image_id"]),
                                    key=list(models).index)
    calibration_images = [str(c) for c in calibration_images]
    for c in calibration_images:
        if c not in models:
            raise CalibrationError(f"calibration image {c!r} is not in the mission")
    unk = build_unknowns(priors, shared_boresight, fixed, drift, drift_sigma)
    times = {iid: _image_time(m) for iid, m in models.items()}
    if drift and t_ref is None:
        t_ref = float(np.mean([times[c] for c in calibration_images]))
    dt = {iid: ((times[iid] - t_ref) / HOUR if drift else 0.0) for iid in models}
    mats = {iid: model_matrix(m, unk, dt[iid]) for iid, m in models.items()}
    cal_obs = obs[obs["image_id"].isin(calibration_images) & (obs["role"] == "control")]
    if check_design:
        _check_design({c: models[c] for c in calibration_images}, cal_obs, unk)

    # the adjustment: one group of image observations, rows (line, element) per point
    order = {iid: k for k, iid in enumerate(calibration_images)}
    cal_obs = cal_obs.iloc[np.argsort(cal_obs["image_id"].map(order).to_numpy(),
                                      kind="stable")]
    groups = [(iid, g) for iid, g in cal_obs.groupby("image_id", sort=False)]
    n_obs = sum(len(g) for _, g in groups)
    l_obs = np.empty(2 * n_obs)
    spans = []
    k = 0
    for iid, g in groups:
        sl = slice(2 * k, 2 * (k + len(g)))
        l_obs[sl] = g[["line", "element"]].to_numpy(float).ravel()
        spans.append((iid, sl, g[["X", "Y", "Z"]].to_numpy(float)))
        k += len(g)
    skip_cache: dict[str, np.ndarray] = {}
    cache: dict = {}
    n = len(unk.names)

    def fn(x, jacobian=True):
        key = x.tobytes()
        if key not in cache:
            cache.clear()
            comp = np.empty(2 * n_obs)
            mods = {}
            for iid, sl, G in spans:
                m = models[iid].with_vector(mats[iid] @ x)
                mods[iid] = m
                comp[sl] = m.ground_to_image(G, clip=False).ravel()
            cache[key] = (comp, mods, None)
        comp, mods, J = cache[key]
        r = l_obs - comp
        if jacobian and J is None:
            J = np.zeros((2 * n_obs, n))
            for iid, sl, G in spans:
                M = mats[iid]
                used = np.flatnonzero(np.any(M[:, ~unk.fixed] != 0, axis=1))
                skip = skip_cache.get(iid)
                img = comp[sl].reshape(-1, 2)
                names = [mods[iid].parameters.flat_names()[i] for i in used]
                D = image_partials(mods[iid], G, img, names,
                                   None if skip is None else skip[used])
                if skip is None:
                    sk = np.zeros(M.shape[0], bool)
                    sk[used] = np.all(np.nan_to_num(D) == 0, axis=(0, 1))
                    skip_cache[iid] = sk
                J[sl] = (D @ M[used]).reshape(-1, n)
            cache[key] = (comp, mods, J)
        return r, (J if jacobian else None)

    point_names = np.array([f"{g}@{i}" for i, g in zip(cal_obs["image_id"], cal_obs["gcp_id"])],
                           dtype=object)
    P = Problem(unk.names, unk.value, unk.units)
    P.fix(unk.fixed)
    P.add_observations("image", fn, np.full(2 * n_obs, float(obs_sigma_px)),
                       component=np.tile(np.array(["y", "x"], dtype=object), n_obs),
                       point=np.repeat(np.arange(n_obs), 2), point_names=point_names,
                       robust=True)
    P.add_priors(unk.value, np.where(unk.fixed, np.inf, unk.sigma), name="priors")
    try:
        comps = (["x", "y"] + (["priors"] if vce_priors else [])) if vce else False
        sol = solve(P, vce=comps, robust=robust, alpha=alpha)
    except RankDeficiencyError as exc:
        raise CalibrationError(
            f"the control points cannot determine the parameters: {exc}. Add control points "
            f"(on both swing sides of left and right swings), give finite prior sigmas, or "
            f"fix parameters (--fix NAME)") from None

    # model-level results (at t_ref), residuals before / after / cross-applied
    vec_after = {iid: mats[iid] @ sol.x for iid in models}
    vec_before = {iid: mats[iid] @ unk.value for iid in models}
    Mref = model_matrix(first, unk, 0.0)
    vref = Mref @ sol.x
    cov_ref = Mref @ sol.cov @ Mref.T
    sig_ref = np.sqrt(np.clip(np.diag(cov_ref), 0, None))
    params = first.parameters.with_vector(vref)
    i = 0
    upd = {}
    for b in params.blocks:
        upd[b.name] = {"sigma": list(sig_ref[i:i + b.size])}
        i += b.size
    params = params.updated(upd)
    res = [residual_table(models, vec_before, obs, "before"),
           residual_table(models, vec_after, obs, "after")]
    cross = {iid: _swap_direction(v, first.parameters) for iid, v in vec_after.items()}
    if any(not np.array_equal(cross[i], vec_after[i]) for i in models):
        res.append(residual_table(models, cross, obs, "cross"))
    residuals = pd.concat(res, ignore_index=True)
    cal_set = set(calibration_images)
    residuals["calibration_image"] = residuals["image_id"].isin(cal_set)
    rej = pd.DataFrame(sol.rejected, columns=["group", "point", "name", "statistic",
                                              "critical", "phase"])
    if len(rej):
        sub = cal_obs.iloc[rej["point"].to_numpy()]
        rej["gcp_id"] = sub["gcp_id"].to_numpy()
        rej["image_id"] = sub["image_id"].to_numpy()
        after = residuals[residuals["stage"] == "after"].set_index("row")
        rr = after.loc[sub.index]
        rej["x"] = rr["x"].to_numpy()
        rej["y"] = rr["y"].to_numpy()
        rej = rej.drop(columns=["group", "point"])
        residuals["rejected"] = residuals["row"].isin(set(sub.index))
    else:
        residuals["rejected"] = False
        rej = pd.DataFrame(columns=["name", "statistic", "critical", "phase", "gcp_id",
                                    "image_id", "x", "y"])
    role = np.where(residuals["rejected"], "rejected", residuals["role"])
    residuals["role"] = role
    summary = summarize(residuals)
    return CalibrationResult(sensor, unk, sol, params, cov_ref, residuals, summary, rej,
                             vec_after, list(calibration_images),
                             {"model": "12" if shared_boresight else str(len(vref)),
                              "shared_boresight": shared_boresight, "fixed": list(fixed),
                              "drift": drift if isinstance(drift, bool) else list(drift),
                              "robust": robust, "vce": vce, "vce_priors": vce_priors,
                              "obs_sigma_px": obs_sigma_px,
                              "alpha": alpha},
                             t_ref if drift else None)
