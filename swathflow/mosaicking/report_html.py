"""The mosaic report as one self-contained HTML file (inline CSS, figures inlined as SVG,
no script, no external asset): ``<out>.html`` beside the mosaic.

Figures (swathflow.mosaicking.report, drawn without matplotlib): the overlap graph (a node
per strip or image at the centre of its swings, an edge per overlap: used ones coloured by
their residual after the network adjustment, skipped dotted grey, rejected red), the
per-overlap residuals on a map (the mosaic from its overviews, each overlap's window
coloured by its residual and its residual vector drawn at the window's centre), and each
node's offset with its 1-sigma bars and its radiometric offset. Tables: nodes (offset,
sigma, radiometric) and overlaps (measurement, sigma, status, residual).
"""
from __future__ import annotations

import html
import os

import numpy as np

from swathflow.io import write_text

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


def mosaic_report_html(mosaic_path, rep: dict, layout, html_path, grey=None,
                       f=None, png=None) -> str:
    """Write the mosaic report of a finished mosaic (``rep``: its mosaic.json content)
    to ``html_path`` atomically (``grey``, ``f``: the mosaic's overview as for
    :func:`swathflow.mosaicking.report.seams_picture`, read when not given; ``png``: it
    encoded). Returns the path."""
    from swathflow.mosaicking.output import overview, stretch
    from swathflow.mosaicking.report import graph_figure, map_figure, offsets_figure
    if grey is None:
        data, f = overview(mosaic_path, 900)
        grey = stretch(data)
    name = html.escape(os.path.basename(os.fspath(mosaic_path)))
    grid = rep.get("grid", {})
    head = (f"<p>{len(layout.swings)} swings on a {layout.shape[0]} x {layout.shape[1]} px grid "
            f"({html.escape(str(grid.get('crs')))}, {_fmt(grid.get('res'))} m); blend "
            f"{_fmt(rep.get('blend'))}, feather {_fmt(rep.get('feather_px'))} px; network "
            f"anchored on {_fmt(rep.get('anchor'))}, sigma0 {_fmt(rep.get('sigma0'))}; "
            f"{len(rep.get('skipped', []))} overlaps skipped, "
            f"{len(rep.get('rejected', []))} rejected.</p>")
    figs = [("Overlap graph", "Nodes at the centre of their swings; an edge per overlap.",
             graph_figure(rep, layout).svg()),
            ("Residuals on the map", "Each overlap's window and residual vector after the "
             "network adjustment.", map_figure(rep, grey, f, png).svg()),
            ("Offsets", "Each node's offset with its 1-sigma bars, and the radiometric "
             "offset removed.", offsets_figure(rep).svg())]
    body = "".join(f"<h2>{t}</h2><figure>{svg}<figcaption>{c}</figcaption></figure>"
                   for t, c, svg in figs)
    doc = (f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>swathflow mosaic "
           f"{name}</title><style>{CSS}</style></head><body><h1>Mosaic {name}</h1>{head}"
           f"{body}{_tables(rep)}</body></html>")
    write_text(os.fspath(html_path), doc)
    return os.fspath(html_path)
