"""A calibration's result: parameters with sigmas, residuals before/after/cross-applied (in
pixels, with what carries them to the ground in metres), rejected points; written as
calibration.json (the report, report.html, is :func:`swathflow.calibration.report
.write_report`: the report depends on the result, never the reverse)."""
from __future__ import annotations

import math
import os
from dataclasses import dataclass
from typing import Mapping

import numpy as np
import pandas as pd

from swathflow.adjustment import Solution
from swathflow.calibration.accuracy import JACOBIAN, MONO, ground_jacobian, mono_errors
from swathflow.calibration.points import point_context
from swathflow.sensormodel.projection import projectors
from swathflow.calibration.unknowns import Unknowns


def _direction(model) -> str:
    return str(model.image_attrs.get("direction", "")).upper()


def _by_image(obs: pd.DataFrame) -> np.ndarray:
    """Positions of ``obs`` grouped by image (images in order of appearance, rows stable)."""
    codes = pd.factorize(obs["image_id"])[0]
    return np.argsort(codes, kind="stable")


def observation_context(models: Mapping, obs: pd.DataFrame) -> pd.DataFrame:
    """Each observation's context (:func:`~swathflow.calibration.points.point_context`),
    rows in the order of ``obs``; it does not depend on the parameters: one table serves
    every stage."""
    perm = _by_image(obs)
    srt = obs.iloc[perm]
    parts = [pd.DataFrame(point_context(models[iid], grp))
             for iid, grp in srt.groupby("image_id", sort=False)]
    if not parts:
        return pd.DataFrame(index=obs.index)
    ctx = pd.concat(parts, ignore_index=True)
    inv = np.empty_like(perm)
    inv[perm] = np.arange(perm.size)
    return ctx.iloc[inv].set_axis(obs.index)


def _project_all(models: Mapping, vectors: Mapping, ids: np.ndarray, xyz: np.ndarray):
    """``project(points, partials)`` over the observations (image ``ids``, in that order):
    one bulk call per sensor (:meth:`SensorModel.projector`), each image's ``vectors``."""
    order = list(dict.fromkeys(ids.tolist()))
    pos = {iid: k for k, iid in enumerate(order)}
    image = np.array([pos[i] for i in ids], dtype=np.intp)
    groups = []
    for proj, members in projectors([models[iid] for iid in order]):
        rows = np.flatnonzero(np.isin(image, members))
        V = np.stack([np.asarray(vectors[order[k]], float) for k in members])
        groups.append((proj, rows, np.searchsorted(members, image[rows]), V))

    def project(points, partials=False):
        out = np.full((len(points), 2), np.nan)
        dg = np.full((len(points), 2, 3), np.nan) if partials else None
        for proj, rows, local, V in groups:
            p = proj.project(local, points[rows], V, partials)
            out[rows] = p.image
            if partials:
                dg[rows] = p.d_ground
        return (out, dg) if partials else out

    return project


def residual_table(models: Mapping, vectors: Mapping[str, np.ndarray], obs: pd.DataFrame,
                   stage: str, context: pd.DataFrame | None = None) -> pd.DataFrame:
    """Observed minus computed per observation: x (element), y (line), pixels; with the
    point's context (:func:`observation_context`; ``context``: already computed for
    ``obs``) and the model's Jacobian d(line, element) / d(east, north, up) in px per metre
    at the surveyed point (:data:`~swathflow.calibration.accuracy.JACOBIAN`, from the
    projector's analytic partials) and the observation's own ground error east, north in
    metres (:data:`~swathflow.calibration.accuracy.MONO`): what
    :func:`~swathflow.calibration.accuracy.point_errors` makes the ground errors of. Every
    image's observations in one bulk projection per sensor."""
    if not len(obs):
        return pd.DataFrame(columns=["row", "gcp_id", "image_id", "direction", "role", "stage",
                                     "x", "y"])
    ctx = observation_context(models, obs) if context is None else context
    perm = _by_image(obs)                # one image's rows together: the projector's order
    obs, ctx = obs.iloc[perm], ctx.iloc[perm]
    first = dict.fromkeys(obs["image_id"])
    ids = obs["image_id"].to_numpy()
    xyz = obs[["X", "Y", "Z"]].to_numpy(float)
    observed = obs[["line", "element"]].to_numpy(float)
    project = _project_all(models, vectors, ids, xyz)
    comp, dg = project(xyz, True)
    lat, lon = ctx["lat"].to_numpy(float), ctx["lon"].to_numpy(float)
    jac = ground_jacobian(dg, lat, lon)
    mono = mono_errors(project, xyz, lat, lon, observed, jac, comp)
    jac = jac.reshape(-1, 6)
    dirs = {iid: _direction(models[iid]) for iid in first}
    out = pd.DataFrame({
        "row": obs.index.to_numpy(), "gcp_id": obs["gcp_id"].to_numpy(), "image_id": ids,
        "direction": [dirs[i] for i in ids], "role": obs["role"].to_numpy(),
        "stage": stage, "x": observed[:, 1] - comp[:, 1], "y": observed[:, 0] - comp[:, 0],
        **{c: ctx[c].to_numpy() for c in ctx.columns},
        **{c: jac[:, k] for k, c in enumerate(JACOBIAN)},
        **{c: mono[:, k] for k, c in enumerate(MONO)}}, index=obs.index)
    return out.sort_index(kind="stable")


def summarize(res: pd.DataFrame, by=("stage", "image_id", "direction", "role")) -> pd.DataFrame:
    """Mean, std (ddof 1), RMS of x and y and counts per group (NaN rows counted apart);
    groups in order of appearance."""
    cols = ["n", "n_unprojected", "mean_x", "std_x", "mean_y", "std_y", "rms_x", "rms_y"]
    if not len(res):
        return pd.DataFrame(columns=list(by) + cols)
    ok = res[["x", "y"]].notna().all(axis=1).to_numpy()
    x = np.where(ok, res["x"].to_numpy(float), 0.0)
    y = np.where(ok, res["y"].to_numpy(float), 0.0)
    frame = pd.DataFrame({"ok": ok.astype(float), "bad": (~ok).astype(float), "x": x, "y": y,
                          "x2": x * x, "y2": y * y})
    keys = [res[b].to_numpy() for b in by]
    g = frame.groupby(keys, sort=False, dropna=False).sum()
    n = g["ok"].to_numpy()
    with np.errstate(invalid="ignore", divide="ignore"):
        mx, my = g["x"].to_numpy() / n, g["y"].to_numpy() / n
        vx = (g["x2"].to_numpy() - n * mx ** 2) / (n - 1)
        vy = (g["y2"].to_numpy() - n * my ** 2) / (n - 1)
        out = {"n": n.astype(int), "n_unprojected": g["bad"].to_numpy().astype(int),
               "mean_x": mx, "std_x": np.where(n > 1, np.sqrt(np.clip(vx, 0, None)), np.nan),
               "mean_y": my, "std_y": np.where(n > 1, np.sqrt(np.clip(vy, 0, None)), np.nan),
               "rms_x": np.sqrt(g["x2"].to_numpy() / n), "rms_y": np.sqrt(g["y2"].to_numpy() / n)}
    idx = g.index.to_frame(index=False)
    idx.columns = list(by)
    return pd.concat([idx, pd.DataFrame(out)], axis=1)


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
        dropped = int(self.rejected["phase"].eq("dropped").sum()) if len(self.rejected) else 0
        out = [f"calibrated {len(self.unknowns.names)} parameters from "
               f"{int((self.residuals['stage'] == 'after').sum())} image points "
               f"(sigma0 {self.sigma0:.3f}, {len(self.rejected) - dropped} rejected, "
               + (f"{dropped} dropped (not computable), " if dropped else "")
               + f"{self.iterations} iterations)"]
        for _, r in s[s["stage"] == "after"].iterrows():
            out.append(f"  {r['image_id']:>8} {r['role']:<8} n={r['n']:4d}  mean x "
                       f"{r['mean_x']:+8.3f} y {r['mean_y']:+8.3f}  std x {r['std_x']:7.3f} "
                       f"y {r['std_y']:7.3f} px")
        return out

    def write(self, out_dir) -> dict[str, str]:
        """Write ``calibration.json`` into ``out_dir`` (atomically); the report is
        :func:`swathflow.calibration.report.write_report` (made off the critical path)."""
        from swathflow.formats.calibfile import write_calibration
        os.makedirs(out_dir, exist_ok=True)
        doc = self.calibration_document()
        cal = os.path.join(out_dir, "calibration.json")
        write_calibration(cal, doc.pop("sensor"), doc.pop("parameters"), **doc)
        return {"calibration": cal}
