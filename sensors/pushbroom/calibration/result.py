"""The result of a push-broom calibration: a
:class:`~swathflow.calibration.result.CalibrationResult` (same report and file) plus tie
points, C0/C1 residuals, the method, the two-step rounds and the other solution; and how it
is built from the adjustment's solution."""
from __future__ import annotations

import os
from dataclasses import dataclass, field

import numpy as np
import pandas as pd

from swathflow.adjustment import Solution
from swathflow.calibration.result import CalibrationResult, residual_table, summarize
from swathflow.sensors.pushbroom.calibration.problem import Setup
from swathflow.sensors.pushbroom.viewing import continuity_matrix


@dataclass
class PushbroomCalibrationResult(CalibrationResult):
    """A :class:`~swathflow.calibration.result.CalibrationResult` (same report and file) plus the
    push-broom extras: tie points, C0/C1 residuals, the method and the other solution."""

    method: str = "joint"
    ties: pd.DataFrame | None = None             # tie ground coordinates and sigmas
    tie_residuals: pd.DataFrame | None = None
    continuity: pd.DataFrame | None = None       # label, residual (model units)
    rounds: list = field(default_factory=list)   # two-step history
    alternative: "PushbroomCalibrationResult | None" = None
    timings: dict = field(default_factory=dict)
    dropped_ties: list = field(default_factory=list)

    @property
    def max_continuity_residual(self) -> float:
        c = self.continuity
        return float(np.abs(c["residual"]).max()) if c is not None and len(c) else 0.0

    def summary_lines(self) -> list[str]:
        """What a person reads on the terminal after a calibration."""
        cx, cy = self.check_rms()
        out = [f"calibrated {self.options['model']} push-broom parameters ({self.method}) and "
               f"{self.options['tie_points']} tie points from "
               f"{self.options['observations'] // 2} image points in "
               f"{self.timings.get('total', float('nan')):.1f} s (sigma0 {self.sigma0:.3f}, "
               f"{len(self.rejected)} rejected, C0/C1 max residual "
               f"{self.max_continuity_residual:.1e})",
               f"  check points: RMS x {cx:.3f} y {cy:.3f} px"]
        if self.tie_residuals is not None:
            tr = self.tie_residuals[self.tie_residuals["used"]]
            out.append(f"  tie points:   RMS x {_rms(tr['x']):.3f} y {_rms(tr['y']):.3f} px "
                       f"({len(self.tie_residuals) - len(tr)} tie observations rejected)")
        if self.alternative is not None:
            a = self.alternative
            with np.errstate(invalid="ignore", divide="ignore"):
                d = np.abs(self.values - a.values) / np.where(self.sigmas > 0, self.sigmas,
                                                              np.nan)
            state = "converged" if a.solution.converged else "NOT converged (--max-rounds)"
            out.append(f"  two-step: {len(a.rounds)} rounds, {state}; largest difference "
                       f"from the joint solution {np.nanmax(d):.3f} sigma")
        return out

    def check_rms(self) -> tuple[float, float]:
        """RMS of the check-point residuals after calibration, (x, y) pixels."""
        r = self.residuals
        q = r[(r["stage"] == "after") & (r["role"] == "check")]
        return (float(np.sqrt(np.nanmean(q["x"] ** 2))),
                float(np.sqrt(np.nanmean(q["y"] ** 2))))

    def calibration_document(self) -> dict:
        doc = super().calibration_document()
        doc["method"] = self.method
        doc["continuity"] = {"max_abs": self.max_continuity_residual,
                             "residuals": dict(zip(self.continuity["label"],
                                                   self.continuity["residual"]))}
        if self.ties is not None:
            tr = self.tie_residuals[self.tie_residuals["used"]]
            doc["tie_points"] = {"n": int(len(self.ties)),
                                 "observations": int(len(self.tie_residuals)),
                                 "rejected_observations": int(len(self.tie_residuals)
                                                              - len(tr)),
                                 "single_ray": [str(t) for t in self.ties["tie_id"][
                                     self.ties["rays"] < 2]],
                                 "rms_x": _rms(tr["x"]), "rms_y": _rms(tr["y"]),
                                 "dropped": self.dropped_ties}
        if self.rounds:
            doc["two_step_rounds"] = self.rounds
            doc["two_step_converged"] = bool(self.solution.converged)
        if self.alternative is not None:
            a = self.alternative
            doc["alternative"] = {"method": a.method, "values": a.values, "sigmas": a.sigmas,
                                  "sigma0": a.sigma0, "rounds": a.rounds}
        doc["timings_s"] = self.timings
        return doc

    def extra_html(self) -> str:
        from swathflow.calibration.report import _table
        out = ["<h2>Push-broom calibration</h2>",
               f"<p>Method <b>{self.method}</b>. Residuals: x = element (across track along "
               f"the CCD line), y = line (along track). C0/C1 constraints (hard): largest "
               f"residual {self.max_continuity_residual:.3e}.</p>"]
        if self.ties is not None:
            tr = self.tie_residuals[self.tie_residuals["used"]]
            single = int((self.ties["rays"] < 2).sum())
            out.append(f"<p>{len(self.ties)} tie points ({len(self.tie_residuals)} image "
                       f"observations, {len(self.tie_residuals) - len(tr)} rejected as "
                       f"blunders): RMS x {_rms(tr['x']):.3f}, y {_rms(tr['y']):.3f} px; "
                       f"{len(self.dropped_ties)} dropped before the adjustment and "
                       f"{single} left with one ray after rejection (fewer than two "
                       f"rays: no tie).</p>")
        if self.continuity is not None and len(self.continuity):
            out.append(_table(self.continuity, 3, left=("label",)))
        if self.rounds:
            out.append("<h3>Two-step rounds</h3>")
            out.append(_table(pd.DataFrame(self.rounds), 4))
        if self.alternative is not None:
            a = self.alternative
            with np.errstate(invalid="ignore", divide="ignore"):
                d = (self.values - a.values) / np.where(self.sigmas > 0, self.sigmas, np.nan)
            tab = pd.DataFrame({"name": self.names, self.method: self.values,
                                "sigma": self.sigmas, a.method: a.values,
                                f"{a.method} sigma": a.sigmas, "difference / sigma": d})
            out.append(f"<h3>{_e(self.method)} vs {_e(a.method)}</h3>")
            out.append(_table(tab, 6, left=("name",)))
        if self.timings:
            out.append("<p class='note'>Timings (s): " + ", ".join(
                f"{k} {v:.2f}" for k, v in self.timings.items()) + "</p>")
        return "\n".join(out)

    def write(self, out_dir) -> dict[str, str]:
        from swathflow.formats.calibfile import write_calibration
        from swathflow.io import write_text
        from swathflow.calibration.report import render_report
        os.makedirs(out_dir, exist_ok=True)
        doc = self.calibration_document()
        cal = os.path.join(out_dir, "calibration.json")
        write_calibration(cal, doc.pop("sensor"), doc.pop("parameters"), **doc)
        html = render_report(self).replace("</body>", self.extra_html() + "</body>", 1)
        rep = os.path.join(out_dir, "report.html")
        write_text(rep, html)
        if self.ties is not None:
            from swathflow.io import atomic_path
            with atomic_path(os.path.join(out_dir, "ties.csv")) as tmp:
                self.ties.to_csv(tmp, index=False)
        return {"calibration": cal, "report": rep}


def _e(x) -> str:
    import html
    return html.escape(str(x))


def _rms(v) -> float:
    v = np.asarray(v, float)
    v = v[np.isfinite(v)]
    return float(np.sqrt(np.mean(v ** 2))) if v.size else float("nan")


def _parameter_solution(st: Setup, sol: Solution, priors, free):
    """The adjustment's solution restricted to the parameters and unscaled, and the
    parameter set with the solved values and sigmas."""
    n, S = st.n_par, st.scale
    x = st.params(sol.x)
    cov = sol.cov[:n, :n] * np.outer(S, S)
    fixedp = st.unk.fixed | ~free
    psol = Solution(list(st.unk.names), list(st.unk.units), x, st.p0.copy(), fixedp, cov,
                    sol.sigma0, sol.redundancy, sol.components, sol.residuals,
                    sol.normalized, sol.used, sol.rejected, sol.iterations, sol.evaluations,
                    sol.converged, sol.history,
                    None if sol.remaining is None else sol.remaining[:n] * S)
    sig = psol.sigma
    params = priors.with_vector(x)
    upd, i = {}, 0
    for b in params.blocks:
        upd[b.name] = {"sigma": list(sig[i:i + b.size])}
        i += b.size
    return psol, params.updated(upd), cov


def _point_residuals(st: Setup, models, gcps, x, calibration_images) -> pd.DataFrame:
    """Control- and check-point residuals before and after, per image."""
    vec_after = {iid: x for iid in models}
    vec_before = {iid: st.p0 for iid in models}
    if gcps is not None and len(gcps):
        res = pd.concat([residual_table(models, vec_before, gcps, "before"),
                         residual_table(models, vec_after, gcps, "after")], ignore_index=True)
    else:
        res = residual_table(models, vec_after, gcps.iloc[:0] if gcps is not None else
                             pd.DataFrame(columns=["image_id"]), "after")
    res["calibration_image"] = res["image_id"].isin(set(calibration_images))
    return res


def _rejected(sol: Solution, res: pd.DataFrame) -> pd.DataFrame:
    """The points the robust phase or data snooping rejected, GCPs and ties alike; marks
    rejected control points in ``res`` (role ``rejected``)."""
    rej_rows = []
    after = res[res["stage"] == "after"]
    for r in sol.rejected:
        name = str(r["name"])
        pid, _, iid = name.rpartition("@")
        is_tie = pid.startswith("tie ")
        pid = pid[4:] if is_tie else pid
        q = after[(after["gcp_id"] == pid) & (after["image_id"] == iid)]
        rej_rows.append({"name": name, "statistic": r["statistic"], "critical": r["critical"],
                         "phase": r["phase"], "gcp_id": pid, "image_id": iid,
                         "x": float(q["x"].iloc[0]) if len(q) else np.nan,
                         "y": float(q["y"].iloc[0]) if len(q) else np.nan})
    rej = pd.DataFrame(rej_rows, columns=["name", "statistic", "critical", "phase", "gcp_id",
                                          "image_id", "x", "y"])
    bad = set(zip(rej["gcp_id"], rej["image_id"]))
    res["rejected"] = [(g, i) in bad and s == "after" and ro == "control" for g, i, s, ro in
                       zip(res["gcp_id"], res["image_id"], res["stage"], res["role"])]
    res["role"] = np.where(res["rejected"], "rejected", res["role"])
    return rej


def _tie_tables(st: Setup, sol: Solution):
    """Tie points (ground coordinates, sigmas, rays left) and their image residuals, or
    ``(None, None)`` without ties."""
    if not st.tie_ids.size:
        return None, None
    from swathflow.geometry.geodesy import ecef_to_geodetic
    T = st.ties(sol.x)
    tc = np.diag(sol.cov)[st.n_par:].reshape(-1, 3)
    llh = ecef_to_geodetic(T)
    ties = pd.DataFrame({"tie_id": st.tie_ids, "X": T[:, 0], "Y": T[:, 1], "Z": T[:, 2],
                         "lat": llh[:, 0], "lon": llh[:, 1], "h": llh[:, 2],
                         "sigma_X": np.sqrt(np.clip(tc[:, 0], 0, None)),
                         "sigma_Y": np.sqrt(np.clip(tc[:, 1], 0, None)),
                         "sigma_Z": np.sqrt(np.clip(tc[:, 2], 0, None))})
    r = sol.residuals["image"]
    used = sol.used["image"]
    rows = []
    for iid, sl, _, ti in st.spans:
        if ti is None:
            continue
        rr = r[sl].reshape(-1, 2)
        rows.append(pd.DataFrame({"tie_id": st.tie_ids[ti], "image_id": iid,
                                  "x": rr[:, 1], "y": rr[:, 0],
                                  "used": used[sl].reshape(-1, 2).all(1)}))
    tie_res = pd.concat(rows, ignore_index=True)
    # rays left after blunder rejection: a tie seen by fewer than two is not a tie
    rays = tie_res.groupby("tie_id")["used"].sum()
    ties["rays"] = rays.reindex(ties["tie_id"]).fillna(0).astype(int).to_numpy()
    return ties, tie_res


def build_result(st: Setup, sol: Solution, models, gcps, priors, method, options,
                 calibration_images, rounds=(), timings=None,
                 dropped=()) -> PushbroomCalibrationResult:
    """The result of one solution ``sol`` of the problem ``st`` (``options["free"]``: the
    parameters that were free; the other options are recorded)."""
    psol, params, cov = _parameter_solution(st, sol, priors, options["free"])
    x = psol.x
    res = _point_residuals(st, models, gcps, x, calibration_images)
    rej = _rejected(sol, res)
    summary = summarize(res)
    ties, tie_res = _tie_tables(st, sol)
    A, labels = continuity_matrix(next(iter(models.values())).sensor, params)
    cont = pd.DataFrame({"label": labels, "residual": A @ x})
    opts = {k: v for k, v in options.items() if k != "free"}
    return PushbroomCalibrationResult(
        "pushbroom", st.unk, psol, params, cov, res, summary, rej, {iid: x for iid in models},
        list(calibration_images), opts, None, method=method, ties=ties,
        tie_residuals=tie_res, continuity=cont, rounds=list(rounds),
        timings=dict(timings or {}), dropped_ties=list(dropped))
