"""The mosaic report's figures: where the seams are and how well they close.

Drawn on :class:`swathflow.mosaicking.drawing.Canvas` (no matplotlib: its import and layout
cost seconds, more than the blending): the same panels go into the report picture
``<out>.report.png`` (rasterised) and the HTML report (inline SVG).

- the residual map: the mosaic (grey, from its overviews) with every overlap drawn as its
  window, coloured by the residual of its offset after the network adjustment (px), and
  the residual vector at its centre; skipped overlaps (low texture, too small) dotted grey,
  rejected ones outlined in red;
- the overlap graph: a node per strip or image at the centre of its swings, an edge per
  overlap coloured the same way;
- the network's result per node: offset (row, col) with 1-sigma bars, and the radiometric
  balance (offset removed per node).
"""
from __future__ import annotations

import os

import numpy as np

from swathflow.io import atomic_path
from swathflow.drawing import Axes, Canvas, colour, colour_bar

__all__ = ["seams_picture", "map_figure", "graph_figure", "offsets_figure"]


def _residual(o) -> float:
    r = o.get("residual") or [None, None]
    if not o.get("used") or any(v is None for v in r):
        return np.nan
    return float(np.hypot(*r))


def _scale(rep):
    """Residuals of the overlaps and the top of the colour scale."""
    res = np.array([_residual(o) for o in rep.get("overlaps", [])], float)
    top = max(0.1, float(np.nanmax(res)) if np.isfinite(res).any() else 0.1)
    return res, top


def _summary(rep) -> str:
    res, _ = _scale(rep)
    return (f"{int(np.isfinite(res).sum())} overlaps used (colour: residual), "
            f"{len(rep.get('skipped', []))} skipped (dotted), {len(rep.get('rejected', []))} "
            f"rejected (red); sigma0 {rep.get('sigma0')}")


def map_panel(cv: Canvas, box, rep: dict, grey, f: float, png=None) -> None:
    """The residual map in ``box`` (x0, y0, x1, y1): ``grey`` the (2, rows, cols) uint8
    grey + alpha overview of the mosaic, decimated by ``f`` from the grid (``png``: it
    encoded)."""
    res, top = _scale(rep)
    rows, cols = grey.shape[1:]
    x0, y0, x1, y1 = box
    s = min((x1 - x0) / cols, (y1 - y0) / rows)
    w, h = cols * s, rows * s
    cv.image(x0, y0, w, h, grey, png)
    cv.rect(x0, y0, w, h, stroke="#444444", width=0.8)
    k = s / f                                  # canvas px per grid px
    gain = _arrow_gain(rep.get("overlaps", []), res, (x0, y0, w, h), k)
    for o, r in zip(rep.get("overlaps", []), res):
        r0, c0, r1, c1 = o["window"]
        xa, ya, ww, hh = x0 + c0 * k, y0 + r0 * k, max((c1 - c0) * k, 1), max((r1 - r0) * k, 1)
        if np.isfinite(r):
            cv.rect(xa, ya, ww, hh, fill=colour(r / top), opacity=0.6)
        elif o["ok"]:
            cv.rect(xa, ya, ww, hh, stroke="#e00000", width=1.2)
        else:
            cv.rect(xa, ya, ww, hh, stroke="#777777", width=0.8, dash=True)
    for o, r in zip(rep.get("overlaps", []), res):
        if np.isfinite(r):
            r0, c0, r1, c1 = o["window"]
            xc, yc = x0 + (c0 + c1) / 2 * k, y0 + (r0 + r1) / 2 * k
            dx, dy = o["residual"][1] * gain, o["residual"][0] * gain
            t = _inside((xc, yc), (dx, dy), (x0, y0, w, h))
            cv.arrow(xc, yc, xc + t * dx, yc + t * dy)
    cv.text(x0, y0 + h + 16, f"arrows: residual vectors, {gain / k:.3g} grid px per px", 10)
    colour_bar(cv, (x0 + w + 14, y0, x0 + w + 28, y0 + min(h, 320)), top,
               "residual after adjustment (px)")


def _inside(p, d, frame) -> float:
    """The largest ``t <= 1`` with ``p + t * d`` inside ``frame`` (x, y, w, h), less the
    room of an arrow head (6 px), for ``p`` inside it."""
    x, y, w, h = frame
    t = 1.0
    for c, v, lo, hi in ((p[0], d[0], x, x + w), (p[1], d[1], y, y + h)):
        if v > 1e-9:
            t = min(t, max(0.0, hi - 3.0 - c) / v)
        elif v < -1e-9:
            t = min(t, max(0.0, c - lo - 3.0) / -v)
    return t


def _arrow_gain(overlaps, res, frame, k) -> float:
    """Canvas px per px of residual, common to every arrow: the largest arrow a tenth of
    the map's size, shrunk (to a quarter of that at most) so that the arrows stay in the
    map; one still too long for its place is cut at the frame (:func:`_inside`)."""
    used = res[np.isfinite(res)]
    gain = 0.1 * max(frame[2], frame[3]) / max(float(used.max()) if used.size else 0.0, 1e-3)
    fit = gain
    for o, r in zip(overlaps, res):
        if np.isfinite(r) and r > 0:
            r0, c0, r1, c1 = o["window"]
            p = (frame[0] + (c0 + c1) / 2 * k, frame[1] + (r0 + r1) / 2 * k)
            d = (o["residual"][1] * gain, o["residual"][0] * gain)
            fit = min(fit, gain * _inside(p, d, frame))
    return max(fit, 0.25 * gain)


def _node_order(name):
    try:
        return (0, float(name), "")
    except ValueError:
        return (1, 0.0, name)


def _lim(lo, hi, pad=0.08):
    lo, hi = float(np.nanmin(lo)), float(np.nanmax(hi))
    if not np.isfinite(lo) or not np.isfinite(hi):
        return -1.0, 1.0
    lo, hi = min(lo, 0.0), max(hi, 0.0)
    d = max(hi - lo, 1e-3)
    return lo - pad * d, hi + pad * d


def offsets_panels(cv: Canvas, box_off, box_rad, rep: dict) -> None:
    """Each node's offset (row, col) with 1-sigma bars, and its radiometric offset."""
    nodes = sorted(rep.get("nodes", []), key=lambda n: _node_order(n["node"]))
    if not nodes:
        return
    n = len(nodes)
    off = np.array([n_["offset"] for n_ in nodes], float).reshape(-1, 2)
    sig = np.nan_to_num(np.array([[np.nan if v is None else v for v in n_["sigma"]]
                                  for n_ in nodes], float).reshape(-1, 2))
    step = max(1, n // 24)
    ticks = [(q, str(nodes[q]["node"])) for q in range(0, n, step)]
    ax = Axes(cv, box_off, (-0.7, n - 0.3), _lim(off - sig, off + sig),
              f"network: {rep.get('anchor', '')} anchored, offsets with 1-sigma bars",
              ylabel="offset (px)", xticks=ticks)
    cv.line(ax.x(-0.7), ax.y(0), ax.x(n - 0.3), ax.y(0), stroke="#999999", width=0.6)
    for axis, dx, col, sq in ((0, -0.12, "#1f77b4", False), (1, 0.12, "#ff7f0e", True)):
        for q in range(n):
            x, v, e = ax.x(q + dx), off[q, axis], sig[q, axis]
            cv.line(x, ax.y(v - e), x, ax.y(v + e), stroke=col, width=1.2)
            cv.marker(x, ax.y(v), 3.2, col, square=sq)
    x1, y0 = box_off[2], box_off[1]
    cv.marker(x1 - 120, y0 + 14, 3.2, "#1f77b4")
    cv.text(x1 - 112, y0 + 18, "row offset", 10)
    cv.marker(x1 - 120, y0 + 30, 3.2, "#ff7f0e", square=True)
    cv.text(x1 - 112, y0 + 34, "column offset", 10)
    rad = np.array([n_["radiometric"] for n_ in nodes], float)
    ax = Axes(cv, box_rad, (-0.7, n - 0.3), _lim(rad, rad),
              "radiometric balance per node", "node (strip or image)",
              "radiometric offset removed", xticks=ticks)
    half = min(0.35, 0.4 * (ax.x(1) - ax.x(0)))
    for q in range(n):
        xa, xb = ax.x(q) - half * (ax.x(1) - ax.x(0)), ax.x(q) + half * (ax.x(1) - ax.x(0))
        ya, yb = sorted((ax.y(0), ax.y(rad[q])))
        cv.rect(xa, ya, xb - xa, max(yb - ya, 0.5), fill="#2ca02c")
    cv.line(ax.x(-0.7), ax.y(0), ax.x(n - 0.3), ax.y(0), stroke="#999999", width=0.6)


def _node_places(rep: dict, layout) -> dict:
    """Node name -> (column, row) centre of its swings on the grid."""
    per_image = bool(rep.get("per_image"))
    acc: dict = {}
    for s in layout.swings:
        key = str(s.image_id if per_image else s.strip)
        acc.setdefault(key, []).append((s.col + s.width / 2, s.row + s.height / 2))
    return {k: tuple(np.mean(v, axis=0)) for k, v in acc.items()}


def graph_panel(cv: Canvas, box, rep: dict, layout) -> None:
    """The overlap graph over the grid (y down, as the mosaic)."""
    per_image = bool(rep.get("per_image"))
    places = _node_places(rep, layout)
    node_of = {s.image_id: str(s.image_id if per_image else s.strip) for s in layout.swings}
    res, top = _scale(rep)
    H, W = layout.shape
    x0, y0, x1, y1 = box
    s = min((x1 - x0) / W, (y1 - y0) / H)
    box = (x0, y0, x0 + W * s, y0 + H * s)
    ax = Axes(cv, box, (0, W), (0, H), "", "grid column (px)", "grid row (px)", yflip=True)
    for o, r in zip(rep.get("overlaps", []), res):
        a, b = places.get(node_of.get(o["ref"])), places.get(node_of.get(o["mov"]))
        if a is None or b is None:
            continue
        kw = (dict(stroke=colour(r / top), width=2.5) if np.isfinite(r) else
              dict(stroke="#e00000", width=1.5) if o["ok"] else
              dict(stroke="#999999", width=1.0, dash=True))
        cv.line(ax.x(a[0]), ax.y(a[1]), ax.x(b[0]), ax.y(b[1]), **kw)
    sig = {n["node"]: n["sigma"] for n in rep.get("nodes", [])}
    anchors = set(rep.get("anchors", []))
    label = len(places) <= 60
    for q, (name, (x, y)) in enumerate(places.items()):
        a = name in anchors
        cv.marker(ax.x(x), ax.y(y), 5, "#2ca02c" if a else "#1f77b4", square=a)
        if label:                         # alternately above and below: neighbours apart
            sg = sig.get(name) or [None, None]
            cv.text(ax.x(x), ax.y(y) + (-9 - 11 * (q % 2) if q % 4 < 2 else 18 + 11 * (q % 2)),
                    f"{name} σ " + "/".join(
                "-" if v is None else f"{v:.2f}" for v in sg), 9, "middle")
    colour_bar(cv, (box[2] + 14, y0, box[2] + 28, y0 + min(box[3] - y0, 300)), top,
               "residual after adjustment (px)")


def _fit(shape, w, h):
    """Width and height of a panel for a ``shape`` (rows, cols) area within w x h."""
    s = min(w / shape[1], h / shape[0])
    return shape[1] * s, shape[0] * s


def map_figure(rep: dict, grey, f: float, png=None) -> Canvas:
    pw, ph = _fit(grey.shape[1:], 760, 560)
    cv = Canvas(int(pw) + 110, int(ph) + 56)
    cv.text(10, 18, "per-overlap residuals on the mosaic: " + _summary(rep), 12)
    map_panel(cv, (10, 30, 10 + pw, 30 + ph), rep, grey, f, png)
    return cv


def graph_figure(rep: dict, layout) -> Canvas:
    pw, ph = _fit(layout.shape, 760, 520)
    cv = Canvas(int(pw) + 190, int(ph) + 90)
    cv.text(10, 18, f"{len(_node_places(rep, layout))} nodes (square: anchor), "
                    f"{len(rep.get('overlaps', []))} overlaps: colour = residual, red = "
                    f"rejected, dotted = skipped", 12)
    graph_panel(cv, (70, 34, 70 + pw, 34 + ph), rep, layout)
    return cv


def offsets_figure(rep: dict) -> Canvas:
    cv = Canvas(1000, 380)
    offsets_panels(cv, (70, 30, 480, 300), (580, 30, 990, 300), rep)
    return cv


def seams_picture(mosaic_path, rep: dict, layout, png_path, grey=None, f=None) -> str:
    """Draw the report picture of a finished mosaic (``rep``: its mosaic.json content)
    into ``png_path`` (atomically): the residual map and the per-node offsets. ``grey``,
    ``f``: the mosaic's overview (:func:`swathflow.mosaicking.output.overview`), read when
    not given. Returns the path."""
    from swathflow.mosaicking.output import overview, stretch
    if grey is None:
        data, f = overview(mosaic_path, 900)
        grey = stretch(data)
    pw, ph = _fit(grey.shape[1:], 760, 640)
    cv = Canvas(int(pw) + 640, max(int(ph) + 70, 700))
    cv.text(10, 20, f"mosaic {os.path.basename(os.fspath(mosaic_path))}: {layout.shape[0]} x "
                    f"{layout.shape[1]} px, {len(layout.swings)} swings. " + _summary(rep), 13)
    map_panel(cv, (10, 40, 10 + pw, 40 + ph), rep, grey, f)
    x = int(pw) + 170
    offsets_panels(cv, (x, 60, x + 440, 330), (x, 390, x + 440, 620), rep)
    png_path = os.fspath(png_path)
    with atomic_path(png_path, suffix=".png") as tmp:
        cv.png(tmp)
    return png_path
