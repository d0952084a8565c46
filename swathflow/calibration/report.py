"""The calibration report: one self-contained HTML file from the Jinja2 template
``swathflow/templates/calibration_report.html.j2`` (autoescaped; inline CSS; figures drawn
by matplotlib and inlined as SVG; no external asset).

Layout follows the paper's tables (docs/references.md section 1) and a photogrammetrist's sign-off:
the ground accuracy of the control and check points in metres (east, north, up; ASPRS
layout) beside the image residuals in pixels, parameters, variance components,
correlations, residual statistics before / after per image, direction and role (Tables
5-7), the figures (ground errors on a map, residuals against time and the per-line
quantities, residual vectors over each image), the cross-application table and the
rejected points.

:func:`write_report` takes any calibration result (a
:class:`~swathflow.calibration.result.CalibrationResult`, a reference calibration's, a
sensor plugin's with ``extra_html``) and is what a flow submits off its critical path.
"""
from __future__ import annotations

import math
import os

import numpy as np
import pandas as pd

from swathflow.calibration.accuracy import accuracy_table, point_errors
from swathflow.calibration.result import summarize
from swathflow.io import write_text
from swathflow.pages import num, render, safe, table
from swathflow.figstyle import styled

__all__ = ["render_report", "write_report", "table", "summarize_frame"]

#: units of the accuracy table's columns
ACCURACY_UNITS = {"points": "", "with_up": "", "mean_E": "m", "mean_N": "m", "mean_U": "m",
                  "RMSE_E": "m", "RMSE_N": "m", "RMSE_H": "m", "RMSE_U": "m", "max_H": "m",
                  "max_U": "m", "H95": "m", "V95": "m", "rms_x_px": "px", "rms_y_px": "px"}


def _correlations(names, corr, hi=0.9, mid=0.7) -> dict:
    rows = []
    for i, n in enumerate(names):
        cells = []
        for j in range(len(names)):
            v = corr[i, j]
            cls = "hi" if i != j and abs(v) >= hi else ("mid" if i != j and abs(v) >= mid
                                                         else "")
            cells.append((f"{v:+.2f}", cls))
        rows.append((n, cells))
    return {"names": list(names), "rows": rows}


def _paper_tables(summary: pd.DataFrame) -> list[dict]:
    """Each image in the layout of the paper's Tables 5-6: before | after control | after
    check (| cross), mean and std of x and y (px), and n (the summary read once: a
    survey has hundreds of images)."""
    rows: dict = {}
    for r in summary.to_dict(orient="records"):
        rows.setdefault(r["image_id"], {})[(r["stage"], r["role"])] = r
    order = [("before", "control"), ("after", "control"), ("after", "check"),
             ("cross", "control"), ("cross", "check")]
    out = []
    for image, cells in rows.items():
        cols = [c for c in order if c in cells]
        body = [(f"{stat} (px)", [num(cells[c][f"{stat}_{axis}"]) for c in cols
                                  for axis in ("x", "y")]) for stat in ("mean", "std")]
        out.append({"image": image, "cols": [f"{st} / {ro}" for st, ro in cols],
                    "rows": body, "n": [num(cells[c]["n"]) for c in cols]})
    return out


def _cross(res: pd.DataFrame) -> dict | None:
    if not (res["stage"] == "cross").any():
        return None
    q = res[res["role"].isin(["control", "check"]) & res["stage"].isin(["after", "cross"])]
    keys = [q["image_id"], q["stage"]]
    stats = q.groupby(keys, sort=False).agg(mean_x=("x", "mean"), std_x=("x", "std"),
                                            mean_y=("y", "mean"), std_y=("y", "std"))
    stats["n"] = q[["x", "y"]].notna().all(axis=1).groupby(keys, sort=False).sum()
    direction = q.groupby("image_id", sort=False)["direction"].first()
    rows = []
    for iid, d in direction.items():
        other = {"L": "R", "R": "L"}.get(d, "?")
        for stage, label in (("after", f"own ({d}) parameters"),
                             ("cross", f"{other} parameters")):
            st = (stats.loc[(iid, stage)] if (iid, stage) in stats.index
                  else pd.Series({"n": 0}, dtype=float))
            rows.append({"image": iid, "direction": d, "parameters": label,
                         "n": int(st.get("n", 0)),
                         **{c: st.get(c, np.nan) for c in ("mean_x", "std_x", "mean_y",
                                                           "std_y")}})
    px = {c: "px" for c in ("mean_x", "std_x", "mean_y", "std_y")}
    return table(pd.DataFrame(rows), 3, left=("image", "direction", "parameters"), units=px)


def _variance_components(result) -> dict:
    vc = pd.DataFrame([{"component": k, "sigma_factor": v["sigma_factor"],
                        "redundancy": v["redundancy"], "n": v["n"],
                        "estimated": v["estimated"],
                        "test_factor": math.sqrt(v["vpv"] / v["redundancy"])
                        if v["redundancy"] and v["redundancy"] > 0 else float("nan")}
                       for k, v in result.components.items()])
    return table(vc, 3, left=("component",))


def _accuracy(res: pd.DataFrame) -> dict | None:
    pts = point_errors(res[res["role"].isin(["control", "check"])])
    if not len(pts):
        return None
    acc = accuracy_table(pts, res)
    has_up = bool(acc["with_up"].any())
    if not has_up:           # every point seen once: up is not observed
        acc = acc.drop(columns=["with_up", "mean_U", "RMSE_U", "max_U", "V95"])
        pts = pts.drop(columns=["up"])
    acc = acc.sort_values(["stage", "role"], key=lambda s: s.map(
        {"before": 0, "after": 1, "cross": 2, "control": 0, "check": 1}).fillna(9))
    return {"table": table(acc, 3, left=("stage", "role"), units=ACCURACY_UNITS),
            "points": table(pts[pts["stage"] == "after"].drop(columns="stage"), 3,
                            left=("role", "gcp_id"),
                            units={c: "m" for c in ("east", "north", "up", "horizontal")}),
            "has_check": bool((pts["role"] == "check").any()), "has_up": has_up}


def _figures(res: pd.DataFrame) -> list[dict]:
    from swathflow.calibration.figures import report_figures
    from swathflow.calibration.figures import MAX_IMAGES
    n = res["image_id"].nunique()
    heads = {"map": "Ground errors on the map", "against": "Residuals against time and "
             "the per-line quantities", "image": "Residual vectors per image"
             if n <= MAX_IMAGES else f"Residual vectors per image: the {MAX_IMAGES} of {n} "
             f"images with the largest residuals after the adjustment"}
    out, shown = [], set()
    for section, caption, fig in report_figures(res):
        out.append({"head": heads[section] if section not in shown else None,
                    "caption": caption, "svg": safe(fig)})
        shown.add(section)
    return out


def _parts(result):
    """The CalibrationResult inside ``result`` and the extra HTML sections of its kind
    (a reference calibration's automatic points, a sensor plugin's ``extra_html``)."""
    extra = []
    core = result
    if hasattr(result, "reference") and hasattr(result, "result"):
        from swathflow.calibration.reference_report import reference_section
        core = result.result
        extra.append(reference_section(result))
    if hasattr(result, "extra_html"):
        extra.append(result.extra_html())
    return core, extra


def render_report(result) -> str:
    """HTML text of the report for a :class:`~swathflow.calibration.result.CalibrationResult`
    (the page ends with ``</body></html>``)."""
    opts = result.options
    sol = result.solution
    free = ~result.unknowns.fixed
    names = [n for n, f in zip(result.names, free) if f]
    res = result.residuals
    tab = result.parameter_table()[["name", "units", "value", "sigma", "prior",
                                    "prior_sigma", "change", "fixed", "data_share"]]
    rejected = (table(result.rejected, 3, left=("name", "phase", "gcp_id", "image_id",
                                                 "reason"))
                if len(result.rejected) else None)
    dropped = int(result.rejected["phase"].eq("dropped").sum()) if len(result.rejected) else 0
    px = {c: "px" for c in ("mean_x", "std_x", "mean_y", "std_y", "rms_x", "rms_y")}
    return render(
        "calibration_report.html.j2", result=result, opts=opts, sol=sol,
        model=opts.get("model"), shared=bool(opts.get("shared_boresight")),
        fixed=opts.get("fixed") or (), sigma0=num(result.sigma0),
        redundancy=num(sol.redundancy, 1), n_rejected=len(result.rejected) - dropped,
        n_dropped=dropped,
        accuracy=_accuracy(res),
        parameters=table(tab, 5, left=("name", "units")),
        t_ref=None if result.t_ref is None else f"{result.t_ref:.3f}",
        components=_variance_components(result),
        correlations=_correlations(names, result.correlation[np.ix_(free, free)]),
        strong=[(a, b, f"{c:+.4f}") for a, b, c in result.strong_correlations(0.9)[:20]],
        images=_paper_tables(result.summary),
        by_direction=table(summarize_frame(res, ("stage", "direction", "role")), 3,
                           left=("stage", "direction", "role"), units=px),
        cross=_cross(res), rejected=rejected, figures=_figures(res), extra=[])


def summarize_frame(res: pd.DataFrame, by) -> pd.DataFrame:
    return summarize(res, by)


@styled
def report_html(result) -> str:
    """The whole report of any calibration result (with its kind's extra sections)."""
    core, extra = _parts(result)
    page = render_report(core)
    if extra:
        page = page.replace("</body>", "\n".join(extra) + "</body>", 1)
    return page


def write_report(result, path) -> str:
    """Write the report of a calibration result to ``path`` atomically (matplotlib and
    Jinja2 imported here); returns the path. Made off the flow's critical path: a flow
    submits it (a thread, a Prefect task or a Dask future) once ``calibration.json`` is
    written."""
    path = os.fspath(path)
    write_text(path, report_html(result))
    return path


def _table(df: pd.DataFrame, nd: int = 3, left=()) -> str:
    """HTML text of a DataFrame's table (for the sections sensor plugins add)."""
    return render("table.html.j2", t=table(df, nd, left))
