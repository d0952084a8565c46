"""The calibration report's figures, drawn by matplotlib (:mod:`swathflow.drawing`: a
Figure on the Agg canvas, no pyplot) and returned as inline SVG for one self-contained HTML
file.

- the ground map: each control and check point's ground error (image-derived minus
  surveyed, east and north in metres: :mod:`swathflow.calibration.accuracy`) as a vector on
  a map in the points' UTM zone (coordinates in metres, a scale bar, a north arrow), before
  and after the adjustment on one extent (each with its vector key);
- residuals (px) against time and each per-line quantity the sensor records (e.g. the
  swing angle), per swing direction, before and after;
- per image: the residual vectors (px) over the image, before and after on one extent
  (each with its vector key).
"""
from __future__ import annotations

import numpy as np
import pandas as pd

from swathflow.calibration.accuracy import point_errors
from swathflow.drawing import DIRECTION_COLOURS, figure, map_frame, svg

OTHER = "#555555"
STAGES = ("before", "after")


def _colour(direction) -> str:
    return DIRECTION_COLOURS.get(str(direction), OTHER)


def _named(direction) -> bool:
    """A direction worth a legend entry (sensors without swing directions leave it empty)."""
    return isinstance(direction, str) and direction not in ("", "nan", "None")


def _pad(lo: float, hi: float, frac: float = 0.06) -> tuple[float, float]:
    d = hi - lo if hi > lo else max(abs(hi), 1.0)
    return lo - frac * d, hi + frac * d


def _key_length(big: float) -> float:
    """A round vector-key length not above the largest vector ``big``."""
    big = max(big, 1e-9)
    k = float(10 ** np.floor(np.log10(big)))
    return next(m * k for m in (5, 2, 1) if m * k <= big)


def _quiver_pair(axes, xs, ys, us, vs, colours, checks, key_units: str, box_frac=0.12):
    """Vectors (u right, v up) at (x, y) on each of ``axes`` (before, after; one extent):
    on each panel the longest vector ``box_frac`` of the axes' width, and a key in the
    panel's upper left corner giving its scale (the errors after the adjustment are often
    a hundredth of those before: one scale would hide them)."""
    width = abs(np.subtract(*axes[0].get_xlim()))
    height = abs(np.subtract(*axes[0].get_ylim()))
    room = min(box_frac * width, 0.3 * height)           # the longest arrow, data units
    for ax, x, y, u, v, c, chk in zip(axes, xs, ys, us, vs, colours, checks):
        mag = np.hypot(u, v)
        big = float(np.nanmax(mag)) if np.isfinite(mag).any() else 1.0
        big = big if big > 0 else 1.0
        key = _key_length(big)
        q = ax.quiver(x, y, u, v, color=c, angles="xy", scale_units="xy",
                      scale=big / room, width=0.004, zorder=3)
        ax.scatter(x[~chk], y[~chk], s=9, c="black", marker="o", zorder=4,
                   label="control point")
        if chk.any():
            ax.scatter(x[chk], y[chk], s=30, facecolors="none", edgecolors="black",
                       marker="s", zorder=4, label="check point")
        ax.quiverkey(q, 0.10, 0.93, key, f"{key:g} {key_units}", labelpos="E",
                     coordinates="axes", color="#444444",
                     fontproperties={"size": 8})


def _points_on_map(res: pd.DataFrame):
    """Per stage: the points' UTM coordinates and ground errors, and the CRS's name."""
    from swathflow.geometry.geodesy import transformer, utm_crs_for
    lat0, lon0 = float(np.nanmean(res["lat"])), float(np.nanmean(res["lon"]))
    crs = utm_crs_for(lat0, lon0)
    tr = transformer("EPSG:4326", crs)
    pos = (res.groupby("gcp_id", sort=False)[["lon", "lat"]].mean())
    e, n = tr.transform(pos["lon"].to_numpy(), pos["lat"].to_numpy())
    place = pd.DataFrame({"E": e, "N": n}, index=pos.index)
    errs = point_errors(res)
    direction = (res.groupby("gcp_id")["direction"]
                 .agg(lambda d: d.iloc[0] if d.nunique() == 1 else "both"))
    name = f"{crs.name} (EPSG:{crs.to_epsg()})" if crs.to_epsg() else crs.name
    return place, errs, direction, name


def map_vectors(res: pd.DataFrame) -> str:
    """Ground errors (m) of the points on a UTM map, before | after: one extent, one vector
    scale; coloured by the swing direction that saw the point (grey: both)."""
    place, errs, direction, crs_name = _points_on_map(res)
    fig = figure(10.5, 5.4, margins=(0.85, 0.15, 0.95, 0.3), wspace=0.12)
    axes = fig.subplots(1, 2, sharex=True, sharey=True)
    lo_e, hi_e = _pad(place["E"].min(), place["E"].max(), 0.15)
    lo_n, hi_n = _pad(place["N"].min(), place["N"].max(), 0.15)
    we = max(hi_e - lo_e, 0.6 * (hi_n - lo_n))        # one extent for both panels, not
    wn = max(hi_n - lo_n, 0.6 * (hi_e - lo_e))        # flatter than 0.6 either way
    ce, cn = (lo_e + hi_e) / 2, (lo_n + hi_n) / 2
    xs, ys, us, vs, cs, chks = [], [], [], [], [], []
    for ax, stage in zip(axes, STAGES):
        ax.set_xlim(ce - we / 2, ce + we / 2)
        ax.set_ylim(cn - wn / 2, cn + wn / 2)
        q = errs[errs["stage"] == stage]
        p = place.loc[q["gcp_id"]]
        xs.append(p["E"].to_numpy())
        ys.append(p["N"].to_numpy())
        us.append(q["east"].to_numpy(float))
        vs.append(q["north"].to_numpy(float))
        cs.append([_colour(direction.get(g)) if direction.get(g) != "both" else "#2ca02c"
                   for g in q["gcp_id"]])
        chks.append((q["role"] == "check").to_numpy())
        ax.set_title(f"ground error, {stage} the adjustment")
    _quiver_pair(axes, xs, ys, us, vs, cs, chks, "m")
    for ax in axes:
        map_frame(ax, crs_name)
    axes[1].set_ylabel("")
    _legend(fig, axes[1], direction)
    return svg(fig)


def _legend(fig, ax, direction) -> None:
    """Point kinds and the colours actually drawn."""
    from matplotlib.lines import Line2D
    handles, labels = ax.get_legend_handles_labels()
    seen = set(direction)
    for d in DIRECTION_COLOURS:
        if d in seen:
            handles.append(Line2D([], [], color=DIRECTION_COLOURS[d], lw=2))
            labels.append(f"seen in direction {d} only")
    if "both" in seen:
        handles.append(Line2D([], [], color="#2ca02c", lw=2))
        labels.append("seen in both directions")
    if not any(d in seen for d in list(DIRECTION_COLOURS) + ["both"]) and len(seen):
        handles.append(Line2D([], [], color=OTHER, lw=2))
        labels.append("ground error")
    fig.legend(handles, labels, loc="lower center", ncols=len(handles), frameon=False)


def image_vectors(res: pd.DataFrame, image_id: str) -> str:
    """Residual vectors (px) over the image, line along, element across; before above
    after, on one extent (each panel's vector scale in its key)."""
    r = res[res["image_id"] == image_id]
    fig = figure(10.5, 5.0, margins=(0.8, 1.45, 0.55, 0.3), hspace=0.3)
    axes = fig.subplots(2, 1, sharex=True, sharey=True)
    lines, elems = r["line"].to_numpy(float), r["element"].to_numpy(float)
    xlim = _pad(np.nanmin(lines), np.nanmax(lines), 0.04)
    ylim = _pad(np.nanmin(elems), np.nanmax(elems), 0.25)
    xs, ys, us, vs, cs, chks = [], [], [], [], [], []
    for ax, stage in zip(axes, STAGES):
        ax.set_xlim(*xlim)
        ax.set_ylim(*ylim)
        q = r[r["stage"] == stage]
        xs.append(q["line"].to_numpy(float))
        ys.append(q["element"].to_numpy(float))
        us.append(q["y"].to_numpy(float))
        vs.append(q["x"].to_numpy(float))
        cs.append([_colour(d) for d in q["direction"]])
        chks.append((q["role"] == "check").to_numpy())
        ax.set_title(f"{image_id}: {stage} the adjustment")
        ax.set_ylabel("element (px)")
    axes[1].set_xlabel("line (px)")
    _quiver_pair(axes, xs, ys, us, vs, cs, chks, "px", box_frac=0.05)
    fig.legend(*axes[0].get_legend_handles_labels(), loc="upper right", frameon=False)
    return svg(fig)


def against(res: pd.DataFrame, column: str, label: str) -> str:
    """Residual x and y (px) against ``column`` per direction: rows x, y; columns before,
    after (one ``column`` axis; each panel's residual axis its own: the residuals after
    the adjustment are often a hundredth of those before)."""
    fig = figure(10.5, 5.2, margins=(0.8, 1.35, 0.55, 0.3), hspace=0.35, wspace=0.15)
    axes = fig.subplots(2, 2, sharex=True)
    values = res[column].to_numpy(float)
    origin = float(np.nanmin(values)) if column == "time" else 0.0
    for j, stage in enumerate(STAGES):
        q = res[res["stage"] == stage]
        for i, comp in enumerate(("x", "y")):
            ax = axes[i][j]
            ax.axhline(0.0, color="#999999", lw=0.8, ls="--")
            for d, s in q.groupby("direction", sort=False):
                ax.scatter(s[column].to_numpy(float) - origin, s[comp].to_numpy(float), s=10,
                           color=_colour(d), label=f"direction {d}" if _named(d) else None)
            ax.set_title(f"{comp} residual, {stage} the adjustment")
            if j == 0:
                ax.set_ylabel(f"{comp} ({'element' if comp == 'x' else 'line'}) residual (px)")
            if i == 1:
                ax.set_xlabel(label if column != "time" else f"{label} from {origin:.1f} s")
    if any(_named(d) for d in res["direction"].unique()):
        fig.legend(*axes[0][0].get_legend_handles_labels(), loc="upper right",
                   frameon=False)
    return svg(fig)


def report_figures(res: pd.DataFrame) -> list[tuple[str, str, str]]:
    """(section, caption, inline SVG) for every figure the residual table supports."""
    need = {"line", "element", "lat", "lon"}
    if not need <= set(res.columns) or not res["stage"].isin(STAGES).any():
        return []
    res = res[res["role"].isin(["control", "check"]) & res["stage"].isin(STAGES)]
    caption = ("Ground error of each point (position from the image minus the surveyed "
               "position, east and north in metres; a point seen in two or more images from "
               "their rays' intersection), before and after the adjustment, on one extent "
               "(each panel's vector scale in its key); dots: control points, squares: check "
               "points")
    out = [("map", caption, map_vectors(res))]
    quantities = [("time", "time (s)")] if "time" in res.columns else []
    quantities += [(c, _quantity_label(c)) for c in res.columns if c.startswith("line_")]
    for col, label in quantities:
        out.append(("against", f"Image residuals (px) against {label}, per swing direction",
                    against(res, col, label)))
    for iid in _worst_images(res):
        out.append(("image", f"Residual vectors (px) over image {iid}, before and after the "
                    "adjustment on one extent (each panel's vector scale in its key)",
                    image_vectors(res, iid)))
    return out


#: most images drawn one by one (a survey has hundreds: their statistics are in the tables)
MAX_IMAGES = 6


def _worst_images(res: pd.DataFrame) -> list:
    """The images to draw: all of them, or the :data:`MAX_IMAGES` with the largest RMS
    residual after the adjustment, in their order in the table."""
    ids = list(dict.fromkeys(res["image_id"]))
    if len(ids) <= MAX_IMAGES:
        return ids
    after = res[res["stage"] == "after"]
    rms = (after.assign(r2=after["x"] ** 2 + after["y"] ** 2).groupby("image_id")["r2"]
           .mean().reindex(ids).fillna(np.inf))
    keep = set(rms.sort_values(ascending=False, kind="stable").index[:MAX_IMAGES])
    return [i for i in ids if i in keep]


def _quantity_label(column: str) -> str:
    name = column[len("line_"):].replace("_", " ")
    return f"{name} (deg)" if any(k in name for k in ("swing", "roll", "pitch", "angle",
                                                        "heading", "yaw")) else name


__all__ = ["report_figures", "map_vectors", "image_vectors", "against"]
