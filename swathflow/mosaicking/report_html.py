"""The mosaic report as one self-contained HTML file from the Jinja2 template
``swathflow/templates/mosaic_report.html.j2`` (autoescaped; inline CSS, figures inlined as
SVG, no script, no external asset): ``<out>.html`` beside the mosaic.

Figures (:mod:`swathflow.mosaicking.report`, matplotlib): the overlap graph (every overlap
an edge between its swings' centres: used ones coloured by their residual after the
network adjustment, skipped dotted grey, rejected red), the per-overlap residuals on a map
(the mosaic from its overviews in its CRS, with coordinates, a scale bar and a north arrow;
each overlap's window coloured by its residual and its residual vector drawn at the
window's centre), and each node's offset with its 1-sigma bars and its radiometric offset.
Tables: nodes (offset and sigma in grid pixels and metres, radiometric) and overlaps
(measurement, sigma, status, residual in pixels and metres).
"""
from __future__ import annotations

import os

from swathflow.io import write_text
from swathflow.pages import num, render, safe
from swathflow.figstyle import styled

__all__ = ["mosaic_report_html", "write_report"]


def _en(v, res: float, sign: bool = True):
    """(row, col) in grid pixels -> (east, north) in metres (north = -row on a north-up
    grid; ``sign=False`` for sigmas); None stays None."""
    if v is None or any(x is None for x in v):
        return None
    return [v[1] * res, (-v[0] if sign else v[0]) * res]


def _sigma(v) -> str:
    return "anchor" if v is None or all(x is None for x in v) else num(v)


def _rows(rep: dict, res: float):
    nodes = [{"node": str(n["node"]), "offset": num(n["offset"]),
              "offset_m": num(_en(n["offset"], res)), "sigma": _sigma(n["sigma"]),
              "sigma_m": _sigma(_en(n["sigma"], res, False)),
              "radiometric": num(n["radiometric"])}
             for n in rep.get("nodes", [])]
    overlaps = []
    for o in rep.get("overlaps", []):
        overlaps.append({"cls": "skip" if not o["ok"] else ("bad" if not o.get("used") else ""),
                         "pair": f"{o['ref']} / {o['mov']}", "status": str(o["status"]),
                         "offset": num(o["offset"]), "sigma": num(o["sigma"]),
                         "residual": num(o.get("residual")),
                         "residual_m": num(_en(o.get("residual"), res)),
                         "used": num(bool(o.get("used"))) or "no",
                         "pixels": num(o.get("pixels"))})
    return nodes, overlaps


@styled
def mosaic_report_html(mosaic_path, rep: dict, layout, html_path, grey=None,
                       f=None, png=None) -> str:
    """Write the mosaic report of a finished mosaic (``rep``: its mosaic.json content)
    to ``html_path`` atomically (``grey``, ``f``: the mosaic's overview as for
    :func:`swathflow.mosaicking.report.seams_picture`, read when not given; ``png``: it
    encoded, unused: the map figure embeds the overview itself). Returns the path."""
    from swathflow.drawing import svg
    from swathflow.mosaicking.output import overview, stretch
    from swathflow.mosaicking.report import graph_figure, map_figure, offsets_figure
    if grey is None:
        data, f = overview(mosaic_path, 900)
        grey = stretch(data)
    res = abs(layout.transform.a)
    nodes, overlaps = _rows(rep, res)
    figs = [("Overlap graph", "Each swing's footprint (grey), a node per strip (or image) at "
             "the centre of its swings, and an edge per overlap between its two swings' "
             "centres; coordinates in metres.", graph_figure(rep, layout)),
            ("Residuals on the map", "Each overlap's window and residual vector after the "
             "network adjustment, on the mosaic; coordinates in metres.",
             map_figure(rep, grey, layout)),
            ("Offsets", "Each node's offset with its 1-sigma bars (grid pixels left, metres "
             "right), and the radiometric offset removed (data units).",
             offsets_figure(rep, layout))]
    grid = rep.get("grid", {})
    page = render(
        "mosaic_report.html.j2", name=os.path.basename(os.fspath(mosaic_path)),
        n_swings=len(layout.swings), shape=layout.shape, crs=str(grid.get("crs")),
        res=num(res), blend=num(rep.get("blend")), feather=num(rep.get("feather_px")),
        feather_m=num((rep.get("feather_px") or 0) * res, 1), anchor=num(rep.get("anchor")),
        sigma0=num(rep.get("sigma0")), n_skipped=len(rep.get("skipped", [])),
        n_rejected=len(rep.get("rejected", [])),
        figures=[{"title": t, "caption": c, "svg": safe(svg(fig))} for t, c, fig in figs],
        nodes=nodes, overlaps=overlaps)
    write_text(os.fspath(html_path), page)
    return os.fspath(html_path)


def write_report(mosaic_path, rectified, strips: dict | None = None) -> dict:
    """Make the mosaic's report picture and HTML page (``<out>.report.png``,
    ``<out>.html``) from the finished mosaic, its ``<out>.json`` and the rectified swings
    it was made of (``strips``: image id -> strip, as given to the mosaic): what a flow
    submits off its critical path after a mosaic written with ``report=False`` for the
    pictures. Returns the paths."""
    import json

    from swathflow.mosaicking.inputs import scan_inputs
    from swathflow.mosaicking.output import overview, stretch
    from swathflow.mosaicking.report import seams_picture
    stem = os.path.splitext(os.fspath(mosaic_path))[0]
    with open(stem + ".json", encoding="utf-8") as fh:
        rep = json.load(fh)
    layout = scan_inputs(rectified, strips)
    data, f = overview(mosaic_path, 1024)
    grey = stretch(data)
    return {"picture": seams_picture(mosaic_path, rep, layout, stem + ".report.png", grey, f),
            "html": mosaic_report_html(mosaic_path, rep, layout, stem + ".html", grey, f)}
