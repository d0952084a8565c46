"""The calibration report's figures, drawn on the reports' one canvas
(:class:`swathflow.drawing.Canvas`, no matplotlib) and returned as inline SVG for one
self-contained HTML file.

Residuals are observed minus computed in pixels (x = element, y = line). Figures: residual
vectors over the image per image, residual vectors over a map of the control points, and
residuals against time and each per-line quantity the sensor records (e.g. the swing angle),
per swing direction, before and after the adjustment.
"""
from __future__ import annotations

import numpy as np
import pandas as pd

from swathflow.drawing import Axes, Canvas, legend

COLORS = {"L": "#1f77b4", "R": "#d62728"}
OTHER = "#555555"
STAGES = ("before", "after")
M_PER_DEG = 111_320.0
# panel margins in canvas pixels: left (tick labels and the rotated label), right, top
# (title and arrow key), bottom (tick labels and the label)
LEFT, RIGHT, TOP, BOTTOM = 72, 24, 30, 46


def _boxes(ncols: int, nrows: int, pw: float, ph: float, gap: float = 40, below: float = 0):
    """A canvas with ``nrows`` x ``ncols`` plot boxes of ``pw`` x ``ph`` pixels (``below``:
    more room under each, for a legend)."""
    cw, ch = LEFT + pw + RIGHT + gap, TOP + ph + BOTTOM + below
    cv = Canvas(ncols * cw - gap, nrows * ch)
    return cv, [[(j * cw + LEFT, i * ch + TOP, j * cw + LEFT + pw, i * ch + TOP + ph)
                 for j in range(ncols)] for i in range(nrows)]


def _lim(v: np.ndarray, pad: float = 0.05, include_zero: bool = False) -> tuple[float, float]:
    v = v[np.isfinite(v)]
    if not v.size:
        return -1.0, 1.0
    lo, hi = float(v.min()), float(v.max())
    if include_zero:
        lo, hi = min(lo, 0.0), max(hi, 0.0)
    d = hi - lo if hi > lo else max(abs(hi), 1.0)
    return lo - pad * d, hi + pad * d


def _key(big: float) -> float:
    """A round arrow-key length (px) not above the largest residual ``big``."""
    k = float(10 ** np.floor(np.log10(big)))
    return next(m * k for m in (5, 2, 1) if m * k <= big)


def _fit(x, y, dx, dy, box, equal: bool = False):
    """Axis limits showing the points (x, y) and the arrow tips ``dx``, ``dy`` canvas pixels
    away from them inside ``box`` (``equal``: as many data units per pixel on both axes)."""
    x0, y0, x1, y1 = box
    xlim, ylim = _lim(x, 0.03), _lim(y, 0.03)
    for _ in range(6):                                 # the scale grows with the limits
        if equal:
            xlim, ylim = _equal(xlim, ylim, box)
        sx, sy = (xlim[1] - xlim[0]) / (x1 - x0), (ylim[1] - ylim[0]) / (y1 - y0)
        xlim = _lim(np.concatenate([x, x + dx * sx]), 0.03)
        ylim = _lim(np.concatenate([y, y + dy * sy]), 0.03)
    return _equal(xlim, ylim, box) if equal else (xlim, ylim)


def _equal(xlim, ylim, box):
    """Limits widened so that a data unit is as long on both axes of ``box``."""
    x0, y0, x1, y1 = box
    s = max((xlim[1] - xlim[0]) / (x1 - x0), (ylim[1] - ylim[0]) / (y1 - y0))
    cx, cy = sum(xlim) / 2, sum(ylim) / 2
    return ((cx - s * (x1 - x0) / 2, cx + s * (x1 - x0) / 2),
            (cy - s * (y1 - y0) / 2, cy + s * (y1 - y0) / 2))


def _vectors(cv: Canvas, box, x, y, u, v, q: pd.DataFrame, colors, frac: float,
             labels: tuple[str, str, str], equal: bool = False) -> None:
    """A panel of residual arrows (u right, v up, in residual pixels) at the data points
    (x, y): the longest ``frac`` of the box width, a key above the box's right end, the
    limits widened to hold every arrow; dots mark control points, open squares check
    points."""
    ok = np.isfinite(u) & np.isfinite(v) & np.isfinite(x) & np.isfinite(y)
    x, y, u, v = x[ok], y[ok], u[ok], v[ok]
    colors, check = np.asarray(colors, dtype=object)[ok], (q["role"] == "check").to_numpy()[ok]
    x0, y0, x1, _ = box
    mag = np.hypot(u, v)
    big = float(mag.max()) if mag.size and mag.max() > 0 else 1.0
    gain = frac * (x1 - x0) / big                     # canvas px per residual px
    xlim, ylim = _fit(x, y, u * gain, v * gain, box, equal)
    ax = Axes(cv, box, xlim, ylim, *labels, title_left=True)
    for xi, yi, ui, vi, col, chk in zip(x, y, u, v, colors, check):
        px, py = ax.x(xi), ax.y(yi)
        cv.arrow(px, py, px + ui * gain, py - vi * gain, stroke=col, width=1.2)
        if chk:
            cv.rect(px - 3.5, py - 3.5, 7, 7, stroke="#000000", width=0.9)
        else:
            cv.marker(px, py, 1.8, "#000000")
    key = _key(big)
    cv.arrow(x1 - 60 - key * gain, y0 - 12, x1 - 60, y0 - 12, stroke="#444444", width=1.2)
    cv.text(x1 - 54, y0 - 8, f"{key:g} px", 10)


def image_vectors(res: pd.DataFrame, image_id: str) -> str:
    """Residual vectors over the image, line along, element across (an arrow's horizontal
    part is the line residual y, its vertical part the element residual x); before above
    after, each panel with its own scale."""
    r = res[res["image_id"] == image_id]
    cv, boxes = _boxes(1, 2, 860, 190)
    for (box,), stage in zip(boxes, STAGES):
        q = r[r["stage"] == stage]
        color = COLORS.get(str(q["direction"].iloc[0]) if len(q) else "", OTHER)
        _vectors(cv, box, q["line"].to_numpy(float), q["element"].to_numpy(float),
                 q["y"].to_numpy(float), q["x"].to_numpy(float), q, [color] * len(q), 0.07,
                 (f"{image_id}: {stage}", "line (px)", "element (px)"))
    return cv.svg()


def _named(direction) -> bool:
    """A direction worth a legend entry (sensors without swing directions leave it empty)."""
    return isinstance(direction, str) and direction not in ("", "nan", "None")


def _direction_entries(directions) -> list[tuple[str, str, str]]:
    return [("line", COLORS[d], f"direction {d}") for d in COLORS if d in set(directions)]


def map_vectors(res: pd.DataFrame) -> str:
    """Residual vectors over a map of the control points (east, north in metres from their
    centre), coloured by swing direction, before | after."""
    lat0 = float(np.nanmean(res["lat"]))
    lon0 = float(np.nanmean(res["lon"]))
    east = (res["lon"].to_numpy(float) - lon0) * M_PER_DEG * np.cos(np.radians(lat0))
    north = (res["lat"].to_numpy(float) - lat0) * M_PER_DEG
    res = res.assign(_e=east, _n=north)
    cv, boxes = _boxes(2, 1, 420, 340, below=18)
    for box, stage in zip(boxes[0], STAGES):
        q = res[res["stage"] == stage]
        colors = [COLORS.get(str(d), OTHER) for d in q["direction"]]
        _vectors(cv, box, q["_e"].to_numpy(float), q["_n"].to_numpy(float),
                 q["x"].to_numpy(float), q["y"].to_numpy(float), q, colors, 0.12,
                 (f"control points: {stage}", f"east (m) from {lon0:.5f}",
                  f"north (m) from {lat0:.5f}"), equal=True)
        entries = [("dot", "#000000", "control")]
        if (q["role"] == "check").any():
            entries.append(("square", "#000000", "check"))
        legend(cv, box[2], box[3] + 54, entries + _direction_entries(q["direction"]),
               across=True)
    return cv.svg()


def against(res: pd.DataFrame, column: str, label: str) -> str:
    """Residual x and y against ``column`` per direction: rows x, y; columns before, after."""
    cv, boxes = _boxes(2, 2, 420, 170)
    values = res[column].to_numpy(float)
    origin = np.nanmin(values) if column == "time" else 0.0
    xlim = _lim(values - origin)
    for j, stage in enumerate(STAGES):
        q = res[res["stage"] == stage]
        directions = list(dict.fromkeys(q["direction"]))
        for i, comp in enumerate(("x", "y")):
            ax = Axes(cv, boxes[i][j], xlim, _lim(q[comp].to_numpy(float), include_zero=True),
                      f"{comp} residual, {stage}",
                      label if column != "time" else f"{label} from {origin:.1f} s",
                      f"{comp} (px)", title_left=True)
            x0, y0, x1, _ = ax.box
            cv.line(x0, ax.y(0.0), x1, ax.y(0.0), stroke="#999999", width=0.8, dash=True)
            for d in directions:
                s = q[q["direction"] == d]
                col = COLORS.get(str(d), OTHER)
                for xv, yv in zip(s[column].to_numpy(float) - origin, s[comp].to_numpy(float)):
                    if np.isfinite(xv) and np.isfinite(yv):
                        cv.marker(ax.x(xv), ax.y(yv), 2.6, col)
            legend(cv, x1, y0 - 12, [("marker", COLORS.get(str(d), OTHER), f"direction {d}")
                                     for d in directions if _named(d)], across=True)
    return cv.svg()


def report_figures(res: pd.DataFrame) -> list[tuple[str, str, str]]:
    """(section, caption, inline SVG) for every figure the residual table supports."""
    need = {"line", "element", "lat", "lon"}
    if not need <= set(res.columns) or not res["stage"].isin(STAGES).any():
        return []
    res = res[res["role"].isin(["control", "check"])]
    caption = ("Residual vectors over the control points, before and after the adjustment; "
               "arrows in image pixels (horizontal part: element residual x, vertical part: line "
               "residual y; each panel has its own scale, see its key), coloured by swing "
               "direction; dots are control points, squares check points")
    out = [("map", caption, map_vectors(res))]
    quantities = [("time", "time (s)")] if "time" in res.columns else []
    quantities += [(c, c[len("line_"):].replace("_", " ")) for c in res.columns
                   if c.startswith("line_")]
    for col, label in quantities:
        out.append(("against", f"Residuals against {label}, per swing direction",
                    against(res, col, label)))
    for iid in dict.fromkeys(res["image_id"]):
        out.append(("image", f"Residual vectors over image {iid}", image_vectors(res, iid)))
    return out
