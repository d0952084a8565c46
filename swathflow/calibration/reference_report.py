"""The report section of a calibration from a reference: a map of the automatic control
points over the reference (matplotlib, :mod:`swathflow.drawing`: the reference in grey in
its own CRS with coordinates in metres, a scale bar and a north arrow; each point coloured
by its residual after the adjustment, rejected points as red crosses, residual vectors
magnified) and the matching statistics per swing, from the template
``reference_section.html.j2``."""
from __future__ import annotations

import numpy as np
import pandas as pd

from swathflow.pages import num, render, safe, table

MAP_PX = 640
#: residual classes of the map (px): below 0.5, below 1, above
CLASSES = ((0.5, "#22aa22", "below 0.5 px"), (1.0, "#ffbb00", "0.5-1 px"),
           (np.inf, "#ff6600", "1 px and above"))


def grey(a: np.ndarray) -> np.ndarray:
    """``a`` stretched to 0..1 between its 1st and 99th percentiles (NaN stays NaN)."""
    ok = np.isfinite(a)
    lo, hi = (np.percentile(a[ok], [1, 99]) if ok.any() else (0.0, 1.0))
    return np.where(ok, np.clip((a - lo) / max(hi - lo, 1e-12), 0, 1), np.nan)


def _crs_name(crs) -> str:
    import pyproj
    c = pyproj.CRS.from_user_input(crs)
    return f"{c.name} (EPSG:{c.to_epsg()})" if c.to_epsg() else c.name


def points_map(reference, points: pd.DataFrame, magnify: float = 20.0) -> str:
    """SVG text of the automatic points over the reference (ground coordinates)."""
    from swathflow.drawing import figure, map_frame, svg
    if not len(points):
        return "<p>No automatic point.</p>"
    g = reference.grid
    E, N = points["E"].to_numpy(float), points["N"].to_numpy(float)
    r, c = g.rowcol(E, N, op=None)
    pad = 40
    r0, r1 = max(int(np.min(r)) - pad, 0), min(int(np.max(r)) + pad, g.height)
    c0, c1 = max(int(np.min(c)) - pad, 0), min(int(np.max(c)) + pad, g.width)
    sub = reference.image[r0:r1, c0:c1]
    step = max(1, int(np.ceil(max(sub.shape) / MAP_PX)))
    t = g.transform
    extent = (t.c + c0 * t.a, t.c + c1 * t.a, t.f + r1 * t.e, t.f + r0 * t.e)
    fig = figure(8.0, 8.0 * (r1 - r0) / max(c1 - c0, 1) + 0.8)
    ax = fig.add_subplot()
    ax.imshow(grey(sub[::step, ::step]), cmap="gray", extent=extent, interpolation="nearest",
              vmin=0, vmax=1)
    ax.set_xlim(extent[0], extent[1])
    ax.set_ylim(extent[2], extent[3])
    res = np.hypot(points["x"].to_numpy(float), points["y"].to_numpy(float))
    rej = points["rejected"].to_numpy(bool)
    if rej.any():
        ax.scatter(E[rej], N[rej], marker="x", c="#ee0000", s=30, lw=1.5, label="rejected")
    lo = 0.0
    for hi, col, label in CLASSES:
        k = ~rej & (res >= lo) & (res < hi)
        lo = hi
        if not k.any():
            continue
        # residual x: element (right), y: line (down on the image, south on a north-up map)
        ax.quiver(E[k], N[k], magnify * points["x"].to_numpy(float)[k] * abs(t.a),
                  -magnify * points["y"].to_numpy(float)[k] * abs(t.e), color=col,
                  angles="xy", scale_units="xy", scale=1, width=0.003)
        ax.scatter(E[k], N[k], s=14, c=col, edgecolors="black", linewidths=0.4, label=label)
    # a tooltip a point (a transparent mark of its own, named, given its <title> below)
    names = points["gcp_id"].astype(str).to_numpy() if "gcp_id" in points else \
        np.array([f"point {i}" for i in range(len(points))])
    tips = {}
    for i in range(len(points)):
        ax.plot([E[i]], [N[i]], marker="o", ms=6, alpha=0.0, gid=f"point-{i}")
        tips[f"point-{i}"] = (f"{names[i]} rejected" if rej[i] else
                              f"{names[i]}: x {points['x'].iloc[i]:+.2f} "
                              f"y {points['y'].iloc[i]:+.2f} px")
    ax.set_title(f"automatic points after the adjustment (residual vectors x {magnify:g})")
    map_frame(ax, _crs_name(g.crs))
    ax.legend(loc="lower right", framealpha=0.85)
    return with_tooltips(svg(fig), tips)


def with_tooltips(text: str, tips: dict[str, str]) -> str:
    """SVG text with a ``<title>`` (the browser's tooltip) in each group named in
    ``tips`` (matplotlib writes an artist's ``gid`` as its group's id)."""
    from html import escape
    for gid, tip in tips.items():
        head = f'<g id="{gid}">'
        text = text.replace(head, f"{head}<title>{escape(tip)}</title>", 1)
    return text


def _frame(df: pd.DataFrame, nd=3, left=()) -> dict:
    return table(df, nd, left)


def reference_section(rc) -> str:
    """HTML of the section for a ReferenceCalibrationResult ``rc``."""
    p = rc.points
    ref = rc.reference
    rounds = pd.DataFrame(rc.rounds)
    if "design_warning" in rounds:
        rounds["design_warning"] = rounds["design_warning"].map(
            lambda t: "points on one side of the track" if t else "")
    m = pd.DataFrame([{"image": s["image_id"], "status": s.get("status"),
                       "blocks": s["blocks"], "matched": s["matched"],
                       "dropped": ", ".join(f"{k} {v}" for k, v in s["reasons"].items()),
                       "coarse_shift": str(s.get("coarse_shift")),
                       "seconds": s.get("seconds")} for s in rc.matching])
    summ = None
    if len(p):
        summ = (p.groupby(["image_id", "rejected"])
                .agg(n=("x", "size"), rms_x=("x", lambda v: float(np.sqrt(np.mean(v ** 2)))),
                     rms_y=("y", lambda v: float(np.sqrt(np.mean(v ** 2)))),
                     median_sigma_line=("sigma_line", "median"),
                     median_sigma_element=("sigma_element", "median")).reset_index())
        summ = _frame(summ, 3, left=("image_id",))
    return render(
        "reference_section.html.j2", path=str(ref.path), res=f"{ref.res:.3f}",
        dem=str(getattr(ref.dem, "path", None) or "the mission terrain"), n=len(p),
        n_rejected=int(p["rejected"].sum()) if len(p) else 0, n_rounds=len(rc.rounds),
        map=safe(points_map(ref, p)), rounds=_frame(rounds, 3),
        matching=_frame(m, 3, left=("image", "status", "dropped", "coarse_shift")),
        summary=summ,
        ties=safe(tie_section(rc.ties, rc.tie_matching))
        if getattr(rc, "ties", None) is not None else None)


def tie_section(ties: pd.DataFrame, matching: list[dict]) -> str:
    """Tie points between left and right swings: matching per pair, residuals, and every
    rejected tie point with its residuals."""
    rej = ties[ties["rejected"]] if len(ties) else ties
    m = pd.DataFrame([{"pair": t["pair"], "blocks": t["blocks"], "matched": t["matched"],
                       "kept": t.get("kept", t["matched"]),
                       "dropped": ", ".join(f"{k} {v}" for k, v in t["reasons"].items())}
                      for t in matching])
    summ = None
    if len(ties):
        summ = (ties.assign(rejected=ties["rejected"].map({True: "yes", False: "no"}))
                .groupby(["image_id", "rejected"])
                .agg(n=("x", "size"), rms_x=("x", lambda v: float(np.sqrt(np.mean(v ** 2)))),
                     rms_y=("y", lambda v: float(np.sqrt(np.mean(v ** 2))))).reset_index())
        summ = _frame(summ, 3, left=("image_id", "rejected"))
    return render(
        "tie_section.html.j2", n=num(ties["tie_id"].nunique() if len(ties) else 0),
        n_rejected=num(rej["tie_id"].nunique() if len(rej) else 0),
        matching=_frame(m, 3, left=("pair", "dropped")) if len(m) else None, summary=summ,
        rejected=_frame(rej[["tie_id", "image_id", "line", "element", "x", "y"]], 3,
                        left=("tie_id", "image_id")) if len(rej) else None)
