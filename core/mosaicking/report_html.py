"""The mosaic report as one self-contained HTML file (inline CSS, matplotlib figures
inlined as SVG, no script, no external asset): ``<out>.html`` beside the mosaic.

Figures: the overlap graph (a node per strip or image at the centre of its swings, an edge
per overlap: used ones coloured by their residual after the network adjustment, skipped
dotted grey, rejected red), the per-overlap residuals on a map (the mosaic from its
overviews, each overlap's window coloured by its residual and its residual vector drawn at
the window's centre), and each node's offset with its 1-sigma bars and its radiometric
offset. Tables: nodes (offset, sigma, radiometric) and overlaps (measurement, sigma,
status, residual).
"""
from __future__ import annotations

import html
import os

import numpy as np

from swathflow.io import figure_svg, write_text

__all__ = ["mosaic_report_html"]

CSS = """
body{font-family:system-ui,sans-serif;margin:2em;color:#222;max-width:1200px}
h1{font-size:1.5em}h2{font-size:1.2em;margin-top:2em;border-bottom:1px solid #ccc}
table{border-collapse:collapse;margin:.5em 0;font-size:.85em}
td,th{border:1px solid #ccc;padding:2px 6px;text-align:right}
th{background:#f2f2f2}td.l,th.l{text-align:left}.bad{background:#fbb}.skip{color:#888}
figure{margin:1em 0}figure svg{max-width:100%;height:auto}
figcaption{color:#555;font-size:.85em}
"""


def _figure(w=10.0, h=6.0, cols=1):
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    fig = Figure(figsize=(w, h), dpi=96, layout="constrained")
    FigureCanvasAgg(fig)
    return fig, fig.subplots(1, cols, squeeze=False)[0]


def _residual(o) -> float:
    r = o.get("residual") or [None, None]
    if not o.get("used") or any(v is None for v in r):
        return np.nan
    return float(np.hypot(*r))


def _node_places(rep: dict, layout) -> dict:
    """Node name -> (column, row) centre of its swings on the grid."""
    per_image = bool(rep.get("per_image"))
    acc: dict = {}
    for s in layout.swings:
        key = str(s.image_id if per_image else s.strip)
        acc.setdefault(key, []).append((s.col + s.width / 2, s.row + s.height / 2))
    return {k: tuple(np.mean(v, axis=0)) for k, v in acc.items()}


def _node_of(rep: dict, layout) -> dict:
    per_image = bool(rep.get("per_image"))
    return {s.image_id: str(s.image_id if per_image else s.strip) for s in layout.swings}


def _norm(rep):
    from matplotlib import colors
    res = np.array([_residual(o) for o in rep.get("overlaps", [])])
    top = max(0.1, float(np.nanmax(res)) if np.isfinite(res).any() else 0.1)
    return res, colors.Normalize(0.0, top)


def graph_figure(rep: dict, layout) -> str:
    """The overlap graph over the grid (y down, as the mosaic)."""
    from matplotlib import colormaps
    from matplotlib.cm import ScalarMappable
    places, node_of = _node_places(rep, layout), _node_of(rep, layout)
    res, norm = _norm(rep)
    cmap = colormaps["plasma"]
    fig, (ax,) = _figure(10, 5.5)
    for o, r in zip(rep.get("overlaps", []), res):
        a, b = places.get(node_of.get(o["ref"])), places.get(node_of.get(o["mov"]))
        if a is None or b is None:
            continue
        style = dict(color=cmap(norm(r)), lw=2.5) if np.isfinite(r) else (
            dict(color="red", lw=1.5) if o["ok"] else dict(color="0.6", lw=1, ls=":"))
        ax.plot([a[0], b[0]], [a[1], b[1]], zorder=1, **style)
    sig = {n["node"]: n["sigma"] for n in rep.get("nodes", [])}
    anchors = set(rep.get("anchors", []))
    for name, (x, y) in places.items():
        ax.scatter([x], [y], s=90, zorder=2, marker="s" if name in anchors else "o",
                   color="tab:green" if name in anchors else "tab:blue")
        s = sig.get(name) or [None, None]
        ax.annotate(f"{name}\n" + ("σ " + "/".join("-" if v is None else f"{v:.2f}" for v in s)),
                    (x, y), textcoords="offset points", xytext=(6, 6), fontsize=7)
    ax.set_xlim(0, layout.shape[1])
    ax.set_ylim(layout.shape[0], 0)
    ax.set_aspect("equal")
    ax.set_xlabel("grid column (px)")
    ax.set_ylabel("grid row (px)")
    ax.set_title(f"{len(places)} nodes (square: anchor), {len(rep.get('overlaps', []))} "
                 f"overlaps: colour = residual, red = rejected, dotted = skipped", fontsize=9)
    fig.colorbar(ScalarMappable(norm=norm, cmap=cmap), ax=ax, fraction=0.03,
                 label="residual after adjustment (px)")
    return figure_svg(fig, "mosaic")


def residual_map_figure(rep: dict, mosaic_path, max_side: int = 900) -> str:
    """The residual of every overlap on the mosaic: window coloured, vector at its centre
    (the largest drawn a tenth of the map wide; the scale is in the title)."""
    import rasterio
    from matplotlib import colormaps, patches
    from matplotlib.cm import ScalarMappable
    with rasterio.open(mosaic_path) as ds:
        f = max(1.0, max(ds.width, ds.height) / max_side)
        shape = (max(1, int(ds.height / f)), max(1, int(ds.width / f)))
        img = ds.read(1, out_shape=shape, masked=True).astype(float).filled(np.nan)
    res, norm = _norm(rep)
    cmap = colormaps["plasma"]
    fig, (ax,) = _figure(10, 5.5)
    ok = np.isfinite(img)
    if ok.any():
        lo, hi = np.percentile(img[ok], [2, 98])
        ax.imshow(img, cmap="gray", vmin=lo, vmax=hi, interpolation="nearest")
    used = [np.hypot(*o["residual"]) for o, r in zip(rep.get("overlaps", []), res)
            if np.isfinite(r)]
    gain = 0.1 * max(img.shape) * f / max(max(used, default=0.0), 1e-3)   # grid px per px
    xs, ys, us, vs = [], [], [], []
    for o, r in zip(rep.get("overlaps", []), res):
        r0, c0, r1, c1 = (v / f for v in o["window"])
        kw = dict(facecolor=cmap(norm(r)), alpha=0.45, edgecolor="none") if np.isfinite(r) \
            else dict(facecolor="none", edgecolor="red" if o["ok"] else "0.55",
                      ls="-" if o["ok"] else ":")
        ax.add_patch(patches.Rectangle((c0, r0), max(c1 - c0, 1), max(r1 - r0, 1), **kw))
        if np.isfinite(r):
            xs.append((c0 + c1) / 2)
            ys.append((r0 + r1) / 2)
            us.append(o["residual"][1] * gain / f)
            vs.append(o["residual"][0] * gain / f)
    if xs:
        ax.quiver(xs, ys, us, vs, angles="xy", scale_units="xy", scale=1, color="cyan",
                  width=0.003)
    ax.set_xticks([])
    ax.set_yticks([])
    ax.set_title(f"per-overlap residuals on the mosaic (arrows: {gain:.3g} grid px per px of "
                 f"residual)", fontsize=9)
    fig.colorbar(ScalarMappable(norm=norm, cmap=cmap), ax=ax, fraction=0.03,
                 label="residual after adjustment (px)")
    return figure_svg(fig, "mosaic")


def offsets_figure(rep: dict) -> str:
    from swathflow.mosaicking.report import _nodes_panel
    fig, axes = _figure(11, 4, cols=2)
    _nodes_panel(axes[0], axes[1], rep)
    return figure_svg(fig, "mosaic")


def _fmt(v, nd=3) -> str:
    if v is None or (isinstance(v, float) and not np.isfinite(v)):
        return "-"
    if isinstance(v, (list, tuple)):
        return ", ".join(_fmt(x, nd) for x in v)
    if isinstance(v, bool):
        return "yes" if v else "no"
    if isinstance(v, (int, float)):
        return f"{v:.{nd}f}" if isinstance(v, float) else str(v)
    return html.escape(str(v))


def _tables(rep: dict) -> str:
    rows = "".join(f"<tr><td class='l'>{_fmt(n['node'])}</td><td>{_fmt(n['offset'])}</td>"
                   f"<td>{_fmt(n['sigma'])}</td><td>{_fmt(n['radiometric'])}</td></tr>"
                   for n in rep.get("nodes", []))
    out = ["<h2>Nodes</h2><table><tr><th class='l'>node</th><th>offset (row, col) px</th>"
           f"<th>sigma (row, col) px</th><th>radiometric offset</th></tr>{rows}</table>"]
    rows = []
    for o in rep.get("overlaps", []):
        cls = "skip" if not o["ok"] else ("bad" if not o.get("used") else "")
        rows.append(f"<tr class='{cls}'><td class='l'>{_fmt(o['ref'])} / {_fmt(o['mov'])}</td>"
                    f"<td class='l'>{_fmt(o['status'])}</td><td>{_fmt(o['offset'])}</td>"
                    f"<td>{_fmt(o['sigma'])}</td><td>{_fmt(o.get('residual'))}</td>"
                    f"<td>{_fmt(o.get('used'))}</td><td>{_fmt(o.get('pixels'))}</td></tr>")
    out.append("<h2>Overlaps</h2><table><tr><th class='l'>ref / mov</th><th class='l'>status"
               "</th><th>offset (row, col) px</th><th>sigma px</th><th>residual px</th>"
               f"<th>used</th><th>pixels</th></tr>{''.join(rows)}</table>")
    return "".join(out)


def mosaic_report_html(mosaic_path, rep: dict, layout, html_path) -> str:
    """Write the mosaic report of a finished mosaic (``rep``: its mosaic.json content)
    to ``html_path`` atomically. Returns the path."""
    name = html.escape(os.path.basename(os.fspath(mosaic_path)))
    grid = rep.get("grid", {})
    head = (f"<p>{len(layout.swings)} swings on a {layout.shape[0]} x {layout.shape[1]} px grid "
            f"({html.escape(str(grid.get('crs')))}, {_fmt(grid.get('res'))} m); blend "
            f"{_fmt(rep.get('blend'))}, feather {_fmt(rep.get('feather_px'))} px; network "
            f"anchored on {_fmt(rep.get('anchor'))}, sigma0 {_fmt(rep.get('sigma0'))}; "
            f"{len(rep.get('skipped', []))} overlaps skipped, "
            f"{len(rep.get('rejected', []))} rejected.</p>")
    figs = [("Overlap graph", "Nodes at the centre of their swings; an edge per overlap.",
             graph_figure(rep, layout)),
            ("Residuals on the map", "Each overlap's window and residual vector after the "
             "network adjustment.", residual_map_figure(rep, mosaic_path)),
            ("Offsets", "Each node's offset with its 1-sigma bars, and the radiometric "
             "offset removed.", offsets_figure(rep))]
    body = "".join(f"<h2>{t}</h2><figure>{svg}<figcaption>{c}</figcaption></figure>"
                   for t, c, svg in figs)
    doc = (f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>swathflow mosaic "
           f"{name}</title><style>{CSS}</style></head><body><h1>Mosaic {name}</h1>{head}"
           f"{body}{_tables(rep)}</body></html>")
    write_text(os.fspath(html_path), doc)
    return os.fspath(html_path)
