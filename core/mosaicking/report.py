"""The mosaic report picture: where the seams are and how well they close.

Left: the mosaic (grey, from its overviews) with every overlap drawn as its window,
coloured by the residual of its offset after the network adjustment (px); skipped overlaps
(low texture, too small) dotted grey, rejected ones outlined in red. Right: the
network's result per node: offset (row, col) with error bars, and the radiometric balance
(offset removed per node).
"""
from __future__ import annotations

import os

import numpy as np

from swathflow.io import atomic_path

__all__ = ["seams_picture"]


def _backdrop(path, max_side: int = 900):
    import rasterio
    with rasterio.open(path) as ds:
        f = max(1.0, max(ds.width, ds.height) / max_side)
        shape = (max(1, int(ds.height / f)), max(1, int(ds.width / f)))
        a = ds.read(1, out_shape=shape, masked=True).astype(float).filled(np.nan)
    return a, f


def _residual(o):
    r = o.get("residual") or [None, None]
    if not o.get("used") or any(v is None for v in r):
        return np.nan
    return float(np.hypot(*r))


def _overlaps_panel(ax, rep, img, f):
    from matplotlib import cm, colors, patches
    from matplotlib.collections import PatchCollection
    ok = np.isfinite(img)
    if ok.any():
        lo, hi = np.percentile(img[ok], [2, 98])
        ax.imshow(img, cmap="gray", vmin=lo, vmax=hi, interpolation="nearest")
    res = np.array([_residual(o) for o in rep["overlaps"]])
    top = max(0.1, float(np.nanmax(res)) if np.isfinite(res).any() else 0.1)
    norm = colors.Normalize(0.0, top)
    cmap = cm.get_cmap("plasma") if hasattr(cm, "get_cmap") else cm.plasma
    used, skipped, rejected, colours = [], [], [], []
    for o, r in zip(rep["overlaps"], res):
        r0, c0, r1, c1 = (v / f for v in o["window"])
        rect = patches.Rectangle((c0, r0), max(c1 - c0, 1.0), max(r1 - r0, 1.0))
        if not o["ok"]:
            skipped.append(rect)
        elif not o["used"]:
            rejected.append(rect)
        else:
            used.append(rect)
            colours.append(cmap(norm(r)))
    ax.add_collection(PatchCollection(used, facecolors=colours, edgecolors="none",
                                      alpha=0.75))
    ax.add_collection(PatchCollection(skipped, facecolors="none", edgecolors="0.55",
                                      lw=0.4, linestyle=":"))
    ax.add_collection(PatchCollection(rejected, facecolors="none", edgecolors="red", lw=1.2))
    sm = cm.ScalarMappable(norm=norm, cmap=cmap)
    ax.figure.colorbar(sm, ax=ax, fraction=0.04, pad=0.02,
                       label="overlap residual after adjustment (px)")
    n_used = int(np.isfinite(res).sum())
    ax.set_title(f"{n_used} overlaps used (colour: residual), "
                 f"{len(rep['skipped'])} skipped (dotted), {len(rep['rejected'])} rejected "
                 f"(red); sigma0 {rep.get('sigma0')}", fontsize=9)
    ax.set_xticks([])
    ax.set_yticks([])


def _node_order(name):
    try:
        return (0, float(name), "")
    except ValueError:
        return (1, 0.0, name)


def _nodes_panel(ax_off, ax_rad, rep):
    nodes = sorted(rep["nodes"], key=lambda n: _node_order(n["node"]))
    x = np.arange(len(nodes))
    off = np.array([n["offset"] for n in nodes], float)
    sig = np.array([[np.nan if v is None else v for v in n["sigma"]] for n in nodes], float)
    ax_off.errorbar(x - 0.1, off[:, 0], yerr=np.nan_to_num(sig[:, 0]), fmt="o", ms=3,
                    label="row offset")
    ax_off.errorbar(x + 0.1, off[:, 1], yerr=np.nan_to_num(sig[:, 1]), fmt="s", ms=3,
                    label="column offset")
    ax_off.axhline(0, color="0.5", lw=0.5)
    ax_off.set_ylabel("offset (px)")
    ax_off.legend(fontsize=7, loc="best")
    ax_off.set_title(f"network: {rep.get('anchor', '')} anchored, offsets with 1-sigma bars",
                     fontsize=9)
    rad = np.array([n["radiometric"] for n in nodes], float)
    ax_rad.bar(x, rad, color="tab:green")
    ax_rad.axhline(0, color="0.5", lw=0.5)
    ax_rad.set_ylabel("radiometric offset removed")
    ax_rad.set_title("radiometric balance per node", fontsize=9)
    step = max(1, len(nodes) // 24)
    for ax in (ax_off, ax_rad):
        ax.set_xticks(x[::step])
        ax.set_xticklabels([n["node"] for n in nodes][::step], fontsize=7, rotation=90)
    ax_rad.set_xlabel("node (strip or image)")


def seams_picture(mosaic_path, rep: dict, layout, png_path) -> str:
    """Draw the report picture of a finished mosaic (``rep``: its mosaic.json content)
    into ``png_path`` (atomically). Returns the path."""
    import matplotlib
    matplotlib.use("Agg", force=False)
    from matplotlib.figure import Figure
    img, f = _backdrop(mosaic_path)
    fig = Figure(figsize=(13, 7), dpi=110, layout="constrained")
    gs = fig.add_gridspec(2, 2, width_ratios=[1.5, 1])
    _overlaps_panel(fig.add_subplot(gs[:, 0]), rep, img, f)
    _nodes_panel(fig.add_subplot(gs[0, 1]), fig.add_subplot(gs[1, 1]), rep)
    fig.suptitle(f"mosaic {os.path.basename(os.fspath(mosaic_path))}: "
                 f"{layout.shape[0]} x {layout.shape[1]} px, {len(layout.swings)} swings",
                 fontsize=10)
    png_path = os.fspath(png_path)
    with atomic_path(png_path, suffix=".png") as tmp:
        fig.savefig(tmp, format="png")
    return png_path
