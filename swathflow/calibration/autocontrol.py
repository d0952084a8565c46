"""Calibration without surveyed control: automatic control points from a reference
orthophoto and DEM (:mod:`swathflow.calibration.reference`), adjusted by the generic
control-point adjustment (:func:`swathflow.calibration.control.calibrate`, each point with its
own a-priori sigma), and repeated: re-rectify with the new parameters, re-match, re-adjust,
until no free parameter moves by more than ``tol_sigma`` of its sigma between rounds
(0.25 by default: re-rendering and re-matching alone move them by about 0.1-0.2 sigma).

False matches (repetitive texture, areas changed since the reference, water) are rejected by
the adjustment's data snooping; the result lists them, and its report maps every automatic
point over the reference with its residual.
"""
from __future__ import annotations

import os
import time
from dataclasses import dataclass, field
from typing import Callable, Mapping

import numpy as np
import pandas as pd

from swathflow.calibration.control import calibrate
from swathflow.calibration.reference import (DEFAULT_SETTINGS, MatchSettings, Reference,
                                             match_swing, open_reference)
from swathflow.calibration.result import CalibrationResult
from swathflow.calibration.ties import match_ties
from swathflow.calibration.unknowns import CalibrationError


@dataclass
class ReferenceCalibrationResult:
    """A calibration from a reference: the adjustment's result of the last round, the
    automatic points with their residuals, and the rounds."""

    result: CalibrationResult
    points: pd.DataFrame                 # last round's points + x, y residuals, rejected
    rounds: list[dict]
    matching: list[dict]                 # per swing of the last round
    reference: Reference
    settings: MatchSettings
    timings: dict = field(default_factory=dict)
    ties: pd.DataFrame | None = None     # last round's tie observations + residuals, rejected
    tie_matching: list[dict] = field(default_factory=list)     # per pair of swings

    @property
    def parameters(self):
        return self.result.parameters

    def __getattr__(self, name):          # the CalibrationResult's views (sigma0, ...)
        if name == "result":
            raise AttributeError(name)
        return getattr(self.result, name)

    def reference_document(self) -> dict:
        p = self.points
        return {"ortho": self.reference.path,
                "dem": getattr(self.reference.dem, "path", None),
                "resolution_m": self.reference.res,
                "settings": {k: getattr(self.settings, k)
                             for k in self.settings.__dataclass_fields__},
                "points": int(len(p)), "rejected": int(p["rejected"].sum()) if len(p) else 0,
                "rounds": self.rounds, "matching": self.matching, "timings_s": self.timings,
                **({"ties": _tie_summary(self.ties, self.tie_matching)}
                   if self.ties is not None else {})}

    def summary_lines(self) -> list[str]:
        p = self.points
        out = self.result.summary_lines()
        out.append(f"automatic control from {os.path.basename(self.reference.path)} "
                   f"({self.reference.res:.2f} m): {len(p)} points, "
                   f"{int(p['rejected'].sum()) if len(p) else 0} rejected, "
                   f"{len(self.rounds)} rounds, matching "
                   f"{self.timings.get('matching', 0.0):.1f} s, total "
                   f"{self.timings.get('total', 0.0):.1f} s")
        if self.ties is not None:
            t = _tie_summary(self.ties, self.tie_matching)
            out.append(f"tie points between left and right swings: {t['points']} "
                       f"({t['rejected']} rejected{': ' if t['rejected'] else ''}"
                       f"{', '.join(t['rejected_ids'])}), residual RMS "
                       f"{t['rms_px'] if t['rms_px'] is not None else float('nan'):.3f} px")
        return out

    def write(self, out_dir) -> dict[str, str]:
        """``calibration.json`` (with a ``reference`` section), ``report.html`` (with the
        map of the automatic points) and ``reference_points.csv``."""
        from swathflow.calibration.report import render_report
        from swathflow.calibration.reference_report import reference_section
        from swathflow.formats.calibfile import write_calibration
        from swathflow.io import write_text
        os.makedirs(out_dir, exist_ok=True)
        doc = self.result.calibration_document()
        doc["reference"] = self.reference_document()
        cal = os.path.join(out_dir, "calibration.json")
        write_calibration(cal, doc.pop("sensor"), doc.pop("parameters"), **doc)
        html = render_report(self.result)
        html = html.replace("</body>", reference_section(self) + "</body>")
        rep = os.path.join(out_dir, "report.html")
        write_text(rep, html)
        pts = os.path.join(out_dir, "reference_points.csv")
        write_text(pts, self.points.to_csv(index=False, float_format="%.6f"))
        out = {"calibration": cal, "report": rep, "points": pts}
        if self.ties is not None:
            out["ties"] = os.path.join(out_dir, "tie_points.csv")
            write_text(out["ties"], self.ties.to_csv(index=False, float_format="%.6f"))
        return out


def _tie_summary(ties: pd.DataFrame, matching: list[dict]) -> dict:
    ok = ~ties["rejected"].to_numpy(bool) if len(ties) else np.zeros(0, bool)
    r = ties.loc[ok, ["x", "y"]].to_numpy(float) if len(ties) else np.zeros((0, 2))
    rej = sorted(set(ties.loc[~ok, "tie_id"])) if len(ties) else []
    return {"points": int(ties["tie_id"].nunique()) if len(ties) else 0,
            "observations": int(len(ties)), "rejected": len(rej), "rejected_ids": rej,
            "rms_px": float(np.sqrt(np.mean(r ** 2))) if r.size else None,
            "pairs": matching}


def _ties_with_residuals(ties: pd.DataFrame, res: CalibrationResult) -> pd.DataFrame:
    info = res.options.get("ties") or {}
    out = ties.reset_index(drop=True).copy()
    r = info.pop("residuals", None)
    r = np.full((len(out), 2), np.nan) if r is None else np.asarray(r).reshape(-1, 2)
    out["y"], out["x"] = r[:, 0], r[:, 1]
    out["rejected"] = out["tie_id"].isin(set(info.get("rejected_names", [])))
    return out


def _change_in_sigmas(prev: CalibrationResult | None, res: CalibrationResult) -> float:
    if prev is None:
        return np.inf
    free = ~res.unknowns.fixed
    s = np.where(res.sigmas > 0, res.sigmas, np.inf)
    return float(np.max(np.abs(res.values - prev.values)[free] / s[free]))


def _with_residuals(obs: pd.DataFrame, res: CalibrationResult) -> pd.DataFrame:
    after = res.residuals[res.residuals["stage"] == "after"].set_index("row")
    out = obs.copy()
    out["x"] = after["x"].reindex(out.index).to_numpy()
    out["y"] = after["y"].reindex(out.index).to_numpy()
    out["rejected"] = after["rejected"].reindex(out.index).fillna(False).to_numpy(bool)
    return out


def _adjust_round(models, obs, priors, options) -> tuple[CalibrationResult, str]:
    """One adjustment. The control-point design check (points on both sides of the track
    in every swing direction) is written for surveyed points; automatic points fall where
    the texture is, so a failed check only warns (reported per round): the priors keep the
    adjustment determined and the sigmas say how well each parameter is known. A rank
    deficiency still fails."""
    try:
        return calibrate(models, obs, priors, **options), ""
    except CalibrationError as exc:
        if options.get("check_design") is False:
            raise
        return calibrate(models, obs, priors, **{**options, "check_design": False}), str(exc)


def calibrate_from_reference(models: Mapping[str, object], sources: Mapping[str, object],
                             terrain, reference: Reference, priors=None, *,
                             settings: MatchSettings = DEFAULT_SETTINGS,
                             raw_gsd: float | None = None, max_rounds: int = 4,
                             tol_sigma: float = 0.25, ties: bool = False,
                             progress: Callable[[str], None] | None = None,
                             **calibrate_options) -> ReferenceCalibrationResult:
    """Calibrate ``models`` (image id -> SensorModel, at their prior parameters) from
    automatic control points against ``reference``.

    sources: image id -> raw image (anything :class:`~swathflow.rectification.rectify.RawSource`
        reads). terrain: the mission's terrain (rectification, and heights when the
        reference has no DEM). raw_gsd: the raw pixel's ground size (sets the rendering's
        supersampling). calibrate_options: passed to
        :func:`~swathflow.calibration.control.calibrate` (shared_boresight, fixed, robust...).
    ties: also match overlapping left and right swings with each other
        (:mod:`swathflow.calibration.ties`): tie points with unknown ground in the same
        adjustment.
    """
    from swathflow.rectification.rectify import RawSource
    say = progress or (lambda _line: None)
    t_start = time.perf_counter()
    srcs = {iid: s if isinstance(s, RawSource) else RawSource(s) for iid, s in sources.items()}
    current = dict(models)
    rounds: list[dict] = []
    prev = res = None
    t_match = 0.0
    tie_obs, tie_stats = None, []
    for k in range(1, max(int(max_rounds), 1) + 1):
        t0 = time.perf_counter()
        tables, stats = [], []
        for iid, m in current.items():
            t1 = time.perf_counter()
            pts, st = match_swing(iid, m, srcs[iid], terrain, reference, settings, raw_gsd)
            st["seconds"] = round(time.perf_counter() - t1, 3)
            tables.append(pts)
            stats.append(st)
        obs = pd.concat([t for t in tables if len(t)] or tables, ignore_index=True)
        t_match = time.perf_counter() - t0
        say(f"round {k}: {len(obs)} automatic control points "
            f"({', '.join(str(s['image_id']) + ' ' + str(s['matched']) for s in stats)}) "
            f"in {t_match:.1f} s")
        if len(obs) == 0:
            raise CalibrationError(
                f"{reference.path}: no automatic control point matched (statuses: "
                f"{', '.join(sorted({s['status'] for s in stats}))}); check that the "
                f"reference covers the flight, is north-up and has texture")
        t_ties = 0.0
        if ties:
            t0, tie_stats = time.perf_counter(), []
            tie_obs = match_ties(current, srcs, terrain, reference, settings, raw_gsd,
                                 tie_stats)
            t_ties = time.perf_counter() - t0
            say(f"round {k}: {tie_obs['tie_id'].nunique()} tie points "
                f"({', '.join(t['pair'] + ' ' + str(t['kept']) for t in tie_stats)}) "
                f"in {t_ties:.1f} s")
        t0 = time.perf_counter()
        res, warning = _adjust_round(models, obs, priors, {**calibrate_options,
                                                           "ties": tie_obs})
        t_adjust = time.perf_counter() - t0
        change = _change_in_sigmas(prev, res)
        rounds.append({"round": k, "points": int(len(obs)), "rejected": int(len(res.rejected)),
                       "sigma0": float(res.sigma0), "max_change_sigma": change,
                       "matching_s": round(t_match, 3), "design_warning": warning,
                       "ties": (res.options.get("ties") or {}).get("points", 0),
                       "tie_matching_s": round(t_ties, 3), "adjust_s": round(t_adjust, 3)})
        rounds[-1]["converged"] = bool(change < tol_sigma)
        current = {iid: models[iid].with_vector(res.image_vectors[iid]) for iid in models}
        if change < tol_sigma:
            break
        prev = res
    assert res is not None
    return ReferenceCalibrationResult(
        res, _with_residuals(obs, res), rounds, stats, reference, settings,
        {"matching": round(t_match, 3), "total": round(time.perf_counter() - t_start, 3)},
        _ties_with_residuals(tie_obs, res) if tie_obs is not None else None, tie_stats)


# --- the mission-level entry point ------------------------------------------------------------
def reference_paths(mission, ortho: str | None = None,
                    dem: str | None = None) -> tuple[str, str | None] | None:
    """The reference orthophoto and DEM to use: the given ones, else the mission's
    ``[reference]`` table (``ortho``, ``dem``; paths relative to the mission folder)."""
    if ortho:
        return str(ortho), (str(dem) if dem else None)
    table = (mission.config or {}).get("reference")
    if not table:
        return None
    if "ortho" not in table:
        raise CalibrationError(f"{mission.path}/mission.toml: [reference] needs ortho = "
                               f"\"<orthophoto file>\"")
    root = str(mission.path)
    path = os.path.join(root, str(table["ortho"]))
    d = table.get("dem")
    return path, (os.path.join(root, str(d)) if d else None)


def calibrate_mission_from_reference(mission, ortho: str, dem: str | None = None, *,
                                     settings: MatchSettings = DEFAULT_SETTINGS,
                                     max_rounds: int = 4, ties: bool = False,
                                     progress: Callable[[str], None] | None = None,
                                     **calibrate_options) -> ReferenceCalibrationResult:
    """:func:`calibrate_from_reference` over a loaded mission's images."""
    ref = open_reference(ortho, dem)
    models = {iid: mission.model(iid) for iid in mission.image_ids}
    sources = {iid: mission.image(iid).load() for iid in mission.image_ids}   # read once
    return calibrate_from_reference(models, sources, mission.terrain, ref, mission.priors,
                                    settings=settings, raw_gsd=float(mission.gsd),
                                    max_rounds=max_rounds, progress=progress, ties=ties,
                                    **calibrate_options)
