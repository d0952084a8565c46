"""The calibration report: one self-contained HTML file (inline CSS, figures drawn on the
reports' canvas, swathflow.drawing, and inlined as SVG; no external assets).

Layout follows the paper's tables (papers.md section 1): parameters, correlations,
residual statistics before / after per image, direction and role (Tables 5-7), residual
figures (the paper's Figures 3-7 as vectors over each image and over the control points, and
residuals against time and the per-line quantities such as the swing angle, per direction,
before and after), the cross-application table and the rejected points.
"""
from __future__ import annotations

import html
import math

import numpy as np
import pandas as pd

from swathflow.io import write_text

CSS = """
body{font-family:system-ui,sans-serif;margin:2em;color:#222;max-width:1200px}
h1{font-size:1.5em}h2{font-size:1.2em;margin-top:2em;border-bottom:1px solid #ccc}
table{border-collapse:collapse;margin:.5em 0;font-size:.85em}
td,th{border:1px solid #ccc;padding:2px 6px;text-align:right}
th{background:#f2f2f2}td.l,th.l{text-align:left}
.hi{background:#fbb}.mid{background:#fde2b8}.note{color:#666;font-size:.85em}
figure{margin:1em 0}figure svg{max-width:100%;height:auto}
figcaption{color:#555;font-size:.85em}
"""


def _e(x) -> str:
    return html.escape(str(x))


def _f(x, nd=3) -> str:
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "-"
    if isinstance(x, (bool, np.bool_)):
        return "yes" if x else ""
    if isinstance(x, (int, np.integer)):
        return str(int(x))
    try:
        v = float(x)
    except (TypeError, ValueError):
        return _e(x)
    if v != 0 and (abs(v) < 10 ** -nd or abs(v) >= 1e6):
        return f"{v:.{nd}e}"
    return f"{v:.{nd}f}"


def _table(df: pd.DataFrame, nd=3, left=()) -> str:
    head = "".join(f"<th class='{'l' if c in left else ''}'>{_e(c)}</th>" for c in df.columns)
    rows = []
    for _, r in df.iterrows():
        rows.append("<tr>" + "".join(
            f"<td class='l'>{_e(r[c])}</td>" if c in left else f"<td>{_f(r[c], nd)}</td>"
            for c in df.columns) + "</tr>")
    return f"<table><tr>{head}</tr>{''.join(rows)}</table>"


def _corr_table(names, corr, hi=0.9, mid=0.7) -> str:
    head = "<th></th>" + "".join(f"<th>{_e(n)}</th>" for n in names)
    rows = []
    for i, n in enumerate(names):
        cells = []
        for j in range(len(names)):
            v = corr[i, j]
            cls = "hi" if i != j and abs(v) >= hi else ("mid" if i != j and abs(v) >= mid
                                                         else "")
            cells.append(f"<td class='{cls}'>{v:+.2f}</td>")
        rows.append(f"<tr><th class='l'>{_e(n)}</th>{''.join(cells)}</tr>")
    return f"<table><tr>{head}</tr>{''.join(rows)}</table>"


def _paper_table(summary: pd.DataFrame, image: str) -> str:
    """One image in the layout of the paper's Tables 5-6: before | after control | after
    check, mean and std of x and y."""
    s = summary[summary["image_id"] == image]

    def cell(stage, role, stat):
        r = s[(s["stage"] == stage) & (s["role"] == role)]
        return _f(r.iloc[0][stat]) if len(r) else "-"

    cols = [("before", "control"), ("after", "control"), ("after", "check"),
            ("cross", "control"), ("cross", "check")]
    cols = [c for c in cols if ((s["stage"] == c[0]) & (s["role"] == c[1])).any()]
    head1 = "".join(f"<th colspan='2'>{_e(st)} / {_e(ro)}</th>" for st, ro in cols)
    head2 = "".join("<th>x</th><th>y</th>" for _ in cols)
    body = ""
    for stat, label in (("mean", "mean"), ("std", "std"), ("n", "n")):
        cells = ""
        for st, ro in cols:
            if stat == "n":
                cells += f"<td colspan='2'>{cell(st, ro, 'n')}</td>"
            else:
                cells += f"<td>{cell(st, ro, stat + '_x')}</td><td>{cell(st, ro, stat + '_y')}</td>"
        body += f"<tr><th class='l'>{label}</th>{cells}</tr>"
    return (f"<h3>{_e(image)}</h3><table><tr><th></th>{head1}</tr><tr><th></th>{head2}</tr>"
            f"{body}</table>")


def render_report(result) -> str:
    """HTML text of the report for a :class:`~swathflow.calibration.result.CalibrationResult`."""
    opts = result.options
    sol = result.solution
    out = [f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>swathflow calibration"
           f"</title><style>{CSS}</style></head><body>",
           "<h1>swathflow calibration report</h1>",
           f"<p>Sensor <b>{_e(result.sensor)}</b>, {_e(opts.get('model'))}-parameter model"
           f"{' (shared boresight)' if opts.get('shared_boresight') else ''}; calibration "
           f"images {_e(', '.join(result.calibration_images))}; sigma0 "
           f"<b>{_f(result.sigma0)}</b>; redundancy {_f(sol.redundancy, 1)}; "
           f"{sol.iterations} iterations ({'converged' if sol.converged else 'NOT converged'});"
           f" {len(result.rejected)} rejected point(s). Residuals are observed minus computed "
           f"in pixels: x = element (flight direction), y = line (swing direction).</p>"]
    if opts.get("fixed"):
        out.append(f"<p>Fixed: {_e(', '.join(opts['fixed']))}</p>")
    # parameters
    tab = result.parameter_table()
    out.append("<h2>Parameters</h2>")
    out.append(_table(tab[["name", "units", "value", "sigma", "prior", "prior_sigma", "change",
                           "fixed", "data_share"]], 5, left=("name", "units")))
    out.append("<p class='note'>data_share = 1 - (sigma / prior sigma)^2: the part of the "
               "information that comes from the control points (near 0: the prior decides)."
               "</p>")
    if result.t_ref is not None:
        out.append(f"<p>Drift reference time t_ref = {result.t_ref:.3f} s; *_rate unknowns "
                   f"are per hour.</p>")
    # variance components
    vc = pd.DataFrame([{"component": k, "sigma_factor": v["sigma_factor"],
                        "redundancy": v["redundancy"], "n": v["n"],
                        "estimated": v["estimated"],
                        "test_factor": math.sqrt(v["vpv"] / v["redundancy"])
                        if v["redundancy"] and v["redundancy"] > 0 else float("nan")}
                       for k, v in result.components.items()])
    out.append("<h2>Variance components</h2>")
    out.append(_table(vc, 3, left=("component",)))
    out.append("<p class='note'>sigma_factor multiplies the a-priori sigmas (estimated: "
               "variance component estimation); test_factor = sqrt(v'Pv / redundancy) of "
               "the final solution (about 1 when the weights fit the data).</p>")
    # correlations
    out.append("<h2>Correlation matrix</h2>")
    free = ~result.unknowns.fixed
    names = [n for n, f in zip(result.names, free) if f]
    corr = result.correlation[np.ix_(free, free)]
    out.append(_corr_table(names, corr))
    strong = result.strong_correlations(0.9)
    if strong:
        out.append("<p>Strongly correlated pairs (|r| &ge; 0.9): " + "; ".join(
            f"{_e(a)} / {_e(b)} {c:+.4f}" for a, b, c in strong[:20]) + "</p>")
    # residual statistics
    summ = result.summary
    out.append("<h2>Residual statistics per image</h2>")
    out.append("<p class='note'>Layout of the paper's Tables 5-7; 'cross' applies the "
               "other swing direction's parameters.</p>")
    for iid in dict.fromkeys(summ["image_id"]):
        out.append(_paper_table(summ, iid))
    out.append("<h2>Per direction and role</h2>")
    res = result.residuals
    by_dir = summarize_frame(res, ("stage", "direction", "role"))
    out.append(_table(by_dir, 3, left=("stage", "direction", "role")))
    # cross application
    if (res["stage"] == "cross").any():
        out.append("<h2>Cross-application</h2>")
        rows = []
        for iid in dict.fromkeys(res["image_id"]):
            r = res[(res["image_id"] == iid) & res["role"].isin(["control", "check"])]
            d = r["direction"].iloc[0]
            other = {"L": "R", "R": "L"}.get(d, "?")
            for stage, label in (("after", f"own ({d}) parameters"),
                                 ("cross", f"{other} parameters")):
                q = r[r["stage"] == stage]
                rows.append({"image": iid, "direction": d, "parameters": label,
                             "n": int(q[["x", "y"]].notna().all(axis=1).sum()),
                             "mean_x": q["x"].mean(), "std_x": q["x"].std(),
                             "mean_y": q["y"].mean(), "std_y": q["y"].std()})
        out.append(_table(pd.DataFrame(rows), 3, left=("image", "direction", "parameters")))
    # rejected
    out.append("<h2>Rejected points</h2>")
    if len(result.rejected):
        out.append(_table(result.rejected, 3, left=("name", "phase", "gcp_id", "image_id")))
    else:
        out.append("<p>None.</p>")
    out.extend(_figures_html(res))
    out.append("</body></html>")
    return "\n".join(out)


def _figures_html(res: pd.DataFrame) -> list[str]:
    """The figures as inline SVG (one self-contained file)."""
    from .figures import report_figures
    figs = report_figures(res)
    if not figs:
        return ["<h2>Residual figures</h2><p>No residuals to draw.</p>"]
    heads = {"map": "Residuals on the ground", "against": "Residuals against time and the "
             "per-line quantities", "image": "Residual vectors per image"}
    out, shown = [], set()
    for section, caption, svg in figs:
        if section not in shown:
            out.append(f"<h2>{_e(heads[section])}</h2>")
            shown.add(section)
        out.append(f"<figure role='img' aria-label='{_e(caption)}'>{svg}"
                   f"<figcaption>{_e(caption)}</figcaption></figure>")
    return out


def summarize_frame(res: pd.DataFrame, by) -> pd.DataFrame:
    from swathflow.calibration.result import summarize
    return summarize(res, by)


def write_report(result, path) -> None:
    """Write the report atomically."""
    write_text(path, render_report(result))
