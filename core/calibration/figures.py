"""The calibration report's figures, drawn with matplotlib (a figure on its own canvas, no
pyplot state) and returned as inline SVG for one self-contained HTML file.

Residuals are observed minus computed in pixels (x = element, y = line). Figures: residual
vectors over the image per image, residual vectors over a map of the control points, and
residuals against time and each per-line quantity the sensor records (e.g. the swing angle),
per swing direction, before and after the adjustment.
"""
from __future__ import annotations


import numpy as np
import pandas as pd

from swathflow.io import figure_svg

COLORS = {"L": "#1f77b4", "R": "#d62728"}
OTHER = "#555555"
STAGES = ("before", "after")
M_PER_DEG = 111_320.0


def _figure(ncols: int, nrows: int = 1, size=(5.2, 3.6)):
    """A figure on its own canvas with fixed margins (in inches: constrained layout costs
    half a second a figure)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    w, h = size[0] * ncols, size[1] * nrows
    fig = Figure(figsize=(w, h), dpi=96)
    FigureCanvasAgg(fig)
    fig.subplots_adjust(left=0.75 / w, right=1 - 0.2 / w, bottom=0.6 / h, top=1 - 0.45 / h,
                        wspace=1.3 / size[0], hspace=1.0 / size[1])
    return fig, fig.subplots(nrows, ncols, squeeze=False)




def _scale(u: np.ndarray, v: np.ndarray, length: float) -> tuple[float, float]:
    """quiver scale (residual pixels per arrow unit) drawing the largest residual ``length``
    long, and a round key length in pixels."""
    mag = np.hypot(u, v)
    mag = mag[np.isfinite(mag)]
    big = float(mag.max()) if mag.size and mag.max() > 0 else 1.0
    key = float(10 ** np.floor(np.log10(big)))
    key = next(k * key for k in (5, 2, 1) if k * key <= big)
    return big / max(length, 1e-9), key


def _quiver(ax, x, y, u, v, q: pd.DataFrame, color, xy: bool, extent: float) -> None:
    """Arrows (u, v) at (x, y): in data units on equal axes (``xy``), else in screen
    directions scaled to the axes width; dots mark control points, squares check points."""
    ok = np.isfinite(u) & np.isfinite(v)
    if xy:
        scale, key = _scale(u[ok], v[ok], 0.12 * extent)
        kw = {"angles": "xy", "scale_units": "xy", "scale": scale}
    else:
        scale, key = _scale(u[ok], v[ok], 0.08)
        kw = {"angles": "uv", "scale_units": "width", "scale": scale}
    colors = [color] * int(ok.sum()) if isinstance(color, str) else list(np.asarray(
        color, dtype=object)[ok])
    qv = ax.quiver(x[ok], y[ok], u[ok], v[ok], color=colors, width=0.003, **kw)
    check = (q["role"] == "check").to_numpy() & ok
    ax.scatter(x[ok & ~check], y[ok & ~check], s=10, c="k", marker="o", label="control")
    if check.any():
        ax.scatter(x[check], y[check], s=22, facecolors="none", edgecolors="k", marker="s",
                   label="check")
    ax.quiverkey(qv, 0.86, 1.04, key, f"{key:g} px", labelpos="E", coordinates="axes")


def image_vectors(res: pd.DataFrame, image_id: str) -> str:
    """Residual vectors over the image, line along, element across (an arrow's horizontal
    part is the line residual y, its vertical part the element residual x); before above
    after, each panel with its own scale."""
    r = res[res["image_id"] == image_id]
    fig, axes = _figure(1, 2, size=(10.0, 2.7))
    for ax, stage in zip(axes[:, 0], STAGES):
        q = r[r["stage"] == stage]
        color = COLORS.get(str(q["direction"].iloc[0]) if len(q) else "", OTHER)
        _quiver(ax, q["line"].to_numpy(float), q["element"].to_numpy(float),
                q["y"].to_numpy(float), q["x"].to_numpy(float), q, color, False, 1.0)
        ax.set_title(f"{image_id}: {stage}", loc="left")
        ax.set_xlabel("line (px)")
        ax.set_ylabel("element (px)")
    return figure_svg(fig)


def map_vectors(res: pd.DataFrame) -> str:
    """Residual vectors over a map of the control points (east, north in metres from their
    centre), coloured by swing direction, before | after."""
    lat0 = float(np.nanmean(res["lat"]))
    lon0 = float(np.nanmean(res["lon"]))
    east = (res["lon"].to_numpy(float) - lon0) * M_PER_DEG * np.cos(np.radians(lat0))
    north = (res["lat"].to_numpy(float) - lat0) * M_PER_DEG
    res = res.assign(_e=east, _n=north)
    fig, axes = _figure(2, size=(5.6, 4.6))
    ext = max(np.ptp(east), np.ptp(north), 1.0)
    for ax, stage in zip(axes[0], STAGES):
        q = res[res["stage"] == stage]
        colors = [COLORS.get(str(d), OTHER) for d in q["direction"]]
        _quiver(ax, q["_e"].to_numpy(float), q["_n"].to_numpy(float), q["x"].to_numpy(float),
                q["y"].to_numpy(float), q, colors, True, ext)
        ax.set_title(f"control points: {stage}", loc="left")
        ax.set_xlabel(f"east (m) from {lon0:.5f}")
        ax.set_ylabel(f"north (m) from {lat0:.5f}")
        ax.set_aspect("equal", adjustable="datalim")
        for d, c in COLORS.items():
            if (q["direction"] == d).any():
                ax.plot([], [], color=c, label=f"direction {d}")
        ax.legend(loc="lower right", fontsize=8)
    return figure_svg(fig)


def against(res: pd.DataFrame, column: str, label: str) -> str:
    """Residual x and y against ``column`` per direction: rows x, y; columns before, after."""
    fig, axes = _figure(2, 2, size=(5.2, 2.8))
    values = res[column].to_numpy(float)
    origin = np.nanmin(values) if column == "time" else 0.0
    for j, stage in enumerate(STAGES):
        q = res[res["stage"] == stage]
        for i, comp in enumerate(("x", "y")):
            ax = axes[i][j]
            for d in dict.fromkeys(q["direction"]):
                s = q[q["direction"] == d]
                ax.scatter(s[column].to_numpy(float) - origin, s[comp], s=12,
                           color=COLORS.get(str(d), OTHER), label=f"direction {d}")
            ax.axhline(0.0, color="#999", lw=0.8, ls="--")
            ax.set_title(f"{comp} residual, {stage}", loc="left")
            ax.set_xlabel(label if column != "time" else f"{label} from {origin:.1f} s")
            ax.set_ylabel(f"{comp} (px)")
            if len(q):
                ax.legend(fontsize=8, loc="upper right")
    return figure_svg(fig)


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
