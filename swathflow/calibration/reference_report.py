"""The report section of a calibration from a reference: a map of the automatic control
points over the reference (drawn on the reports' canvas, swathflow.drawing: an SVG over a
grey PNG of the reference, each point a dot coloured by its residual after the adjustment,
rejected points as red crosses, residual vectors magnified) and the matching statistics
per swing."""
from __future__ import annotations

import numpy as np
import pandas as pd

from swathflow.calibration.report import _e, _table
from swathflow.drawing import Canvas, png_bytes

MAP_PX = 640


def grey(a: np.ndarray) -> np.ndarray:
    """``a`` as 8-bit grey + alpha, (2, rows, cols): stretched between its 1st and 99th
    percentiles, NaN black."""
    ok = np.isfinite(a)
    lo, hi = (np.percentile(a[ok], [1, 99]) if ok.any() else (0.0, 1.0))
    g = np.where(ok, np.clip((a - lo) / max(hi - lo, 1e-12), 0, 1) * 255, 0).astype(np.uint8)
    return np.stack([g, np.full_like(g, 255)])


def points_map(reference, points: pd.DataFrame, magnify: float = 20.0) -> str:
    """SVG text of the automatic points over the reference (each point's name and residual
    as its tooltip)."""
    if not len(points):
        return "<p>No automatic point.</p>"
    g = reference.grid
    r, c = g.rowcol(points["E"].to_numpy(), points["N"].to_numpy(), op=None)
    pad = 40
    r0, r1 = max(int(r.min()) - pad, 0), min(int(r.max()) + pad, g.height)
    c0, c1 = max(int(c.min()) - pad, 0), min(int(c.max()) + pad, g.width)
    sub = reference.image[r0:r1, c0:c1]
    step = max(1, int(np.ceil(max(sub.shape) / MAP_PX)))
    thumb = grey(sub[::step, ::step])
    h, w = thumb.shape[1:]
    zoom = max(1.0, MAP_PX / max(h, w))            # small maps are drawn larger
    x = (c - c0) / step * zoom
    y = (r - r0) / step * zoom
    h, w = int(round(h * zoom)), int(round(w * zoom))
    res = np.hypot(points["x"].to_numpy(float), points["y"].to_numpy(float))
    rej = points["rejected"].to_numpy(bool)
    cv = Canvas(w, h)
    cv.image(0, 0, w, h, thumb, png_bytes(thumb, level=6))
    for xi, yi, ri, rj, dx, dy, name in zip(x, y, res, rej, points["x"], points["y"],
                                            points["gcp_id"]):
        if rj:
            cv.line(xi - 4, yi - 4, xi + 4, yi + 4, stroke="#ee0000", width=2,
                    title=f"{name} rejected")
            cv.line(xi - 4, yi + 4, xi + 4, yi - 4, stroke="#ee0000", width=2)
            continue
        col = "#22aa22" if ri < 0.5 else "#ffbb00" if ri < 1.0 else "#ff6600"
        cv.marker(xi, yi, 3, col, title=f"{name}: x {dx:+.2f} y {dy:+.2f} px")
        if np.isfinite(ri):
            cv.line(xi, yi, xi + magnify * dx, yi + magnify * dy, stroke=col)
    return cv.svg()


def reference_section(rc) -> str:
    """HTML of the section for a ReferenceCalibrationResult ``rc``."""
    p = rc.points
    ref = rc.reference
    out = ["<h2>Automatic control from the reference</h2>",
           f"<p>Reference {_e(ref.path)} ({ref.res:.3f} m pixels), heights from "
           f"{_e(getattr(ref.dem, 'path', None) or 'the mission terrain')}; {len(p)} points "
           f"in the last round, {int(p['rejected'].sum()) if len(p) else 0} rejected by data "
           f"snooping; {len(rc.rounds)} rounds.</p>",
           "<p class='note'>Circles: accepted points, green below 0.5 px residual, orange "
           "below 1 px, red above (lines: residual x 20, element right, line down); red "
           "crosses: rejected (false matches: changed areas, repetitive texture, water)."
           "</p>", points_map(ref, p)]
    out.append("<h3>Rounds</h3>")
    rounds = pd.DataFrame(rc.rounds)
    if "design_warning" in rounds:
        rounds["design_warning"] = rounds["design_warning"].map(
            lambda t: "points on one side of the track" if t else "")
    out.append(_table(rounds, 3))
    out.append("<p class='note'>max_change_sigma: the largest change of a parameter since "
               "the previous round, in its sigmas. design_warning: the surveyed-point design "
               "check (points on both sides of the track per direction) failed; the priors "
               "kept the adjustment determined, and the sigmas show what the points fixed."
               "</p>")
    m = pd.DataFrame([{"image": s["image_id"], "status": s.get("status"),
                       "blocks": s["blocks"], "matched": s["matched"],
                       "dropped": ", ".join(f"{k} {v}" for k, v in s["reasons"].items()),
                       "coarse_shift": str(s.get("coarse_shift")),
                       "seconds": s.get("seconds")} for s in rc.matching])
    out.append("<h3>Matching per swing (last round)</h3>")
    out.append(_table(m, 3, left=("image", "status", "dropped", "coarse_shift")))
    if len(p):
        out.append("<h3>Residuals of the automatic points</h3>")
        summ = (p.assign(abs_x=p["x"].abs(), abs_y=p["y"].abs())
                .groupby(["image_id", "rejected"])
                .agg(n=("x", "size"), rms_x=("x", lambda v: float(np.sqrt(np.mean(v ** 2)))),
                     rms_y=("y", lambda v: float(np.sqrt(np.mean(v ** 2)))),
                     median_sigma_line=("sigma_line", "median"),
                     median_sigma_element=("sigma_element", "median")).reset_index())
        out.append(_table(summ, 3, left=("image_id",)))
    if getattr(rc, "ties", None) is not None:
        out.append(tie_section(rc.ties, rc.tie_matching))
    return "\n".join(out)


def tie_section(ties: pd.DataFrame, matching: list[dict]) -> str:
    """Tie points between left and right swings: matching per pair, residuals, and every
    rejected tie point with its residuals."""
    rej = ties[ties["rejected"]] if len(ties) else ties
    out = ["<h3>Tie points between left and right swings (last round)</h3>",
           f"<p>{ties['tie_id'].nunique() if len(ties) else 0} tie points, "
           f"{rej['tie_id'].nunique() if len(rej) else 0} rejected by data snooping (a tie "
           f"point is tested whole, in both swings). Their ground positions are unknowns of "
           f"the adjustment, their heights from the terrain.</p>"]
    m = pd.DataFrame([{"pair": t["pair"], "blocks": t["blocks"], "matched": t["matched"],
                       "kept": t.get("kept", t["matched"]),
                       "dropped": ", ".join(f"{k} {v}" for k, v in t["reasons"].items())}
                      for t in matching])
    if len(m):
        out.append(_table(m, 3, left=("pair", "dropped")))
    if len(ties):
        summ = (ties.assign(rejected=ties["rejected"].map({True: "yes", False: "no"}))
                .groupby(["image_id", "rejected"])
                .agg(n=("x", "size"), rms_x=("x", lambda v: float(np.sqrt(np.mean(v ** 2)))),
                     rms_y=("y", lambda v: float(np.sqrt(np.mean(v ** 2))))).reset_index())
        out.append(_table(summ, 3, left=("image_id", "rejected")))
    if len(rej):
        out.append("<h4>Rejected tie points</h4>")
        out.append(_table(rej[["tie_id", "image_id", "line", "element", "x", "y"]], 3,
                          left=("tie_id", "image_id")))
    return "\n".join(out)
