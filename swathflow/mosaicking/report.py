"""The mosaic report's figures: where the seams are and how well they close, drawn by
matplotlib (:mod:`swathflow.drawing`: a Figure on the Agg canvas, no pyplot). The same
figures go into the report picture ``<out>.report.png`` and the HTML report (inline SVG).

- the residual map: the mosaic (grey, from its overviews) in its CRS with coordinates in
  metres, a scale bar and a north arrow; every overlap drawn as its window, coloured by the
  residual of its offset after the network adjustment, and the residual vector at its
  centre; skipped overlaps (low texture, too small) dotted grey, rejected ones outlined
  red;
- the overlap graph: each swing's footprint, a node per strip (or image) at the centre of
  its swings, and an edge per overlap between the centres of its two swings (so every
  overlap is drawn, also those between swings of one strip);
- the network's result per node: offset (row, col) with 1-sigma bars in grid pixels and in
  metres, and the radiometric balance (offset removed per node, in the data's units).
"""
from __future__ import annotations

import os

import numpy as np
from swathflow.figstyle import styled

__all__ = ["seams_picture", "map_figure", "graph_figure", "offsets_figure", "graph_edges",
           "arrow_ends", "node_line"]

COLOUR_MAP = "plasma"
#: a map figure's margins (inches: left, right, bottom, top): tick labels and axis labels
MAP_MARGINS = (0.85, 0.15, 0.6, 0.35)
SKIPPED, REJECTED, NODE, ANCHOR = "#888888", "#e00000", "#1f77b4", "#2ca02c"


def _residual(o) -> float:
    r = o.get("residual") or [None, None]
    if not o.get("used") or any(v is None for v in r):
        return np.nan
    return float(np.hypot(*r))


def _scale(rep):
    """Residuals of the overlaps (px) and the top of the colour scale."""
    res = np.array([_residual(o) for o in rep.get("overlaps", [])], float)
    top = max(0.1, float(np.nanmax(res)) if np.isfinite(res).any() else 0.1)
    return res, top


def _summary(rep) -> str:
    res, _ = _scale(rep)
    return (f"{int(np.isfinite(res).sum())} overlaps used, {len(rep.get('skipped', []))} "
            f"skipped, {len(rep.get('rejected', []))} rejected; sigma0 "
            f"{_sig(rep.get('sigma0'))}")


def _sig(v) -> str:
    return "-" if v is None else f"{v:.3g}"


def _res_m(layout) -> float:
    return abs(layout.transform.a)


def _to_map(layout, rows, cols):
    """Grid (row, col) -> map (x, y) in the grid's CRS."""
    t = layout.transform
    return t.c + np.asarray(cols, float) * t.a, t.f + np.asarray(rows, float) * t.e


def _crs_name(layout) -> str:
    if layout.crs is None:
        return "grid without CRS"
    import pyproj
    c = pyproj.CRS.from_user_input(layout.crs)
    return f"{c.name} (EPSG:{c.to_epsg()})" if c.to_epsg() else c.name


def _extent(layout):
    H, W = layout.shape
    x0, y1 = _to_map(layout, 0, 0)
    x1, y0 = _to_map(layout, H, W)
    return float(x0), float(x1), float(y0), float(y1)


def arrow_ends(rep: dict, layout, length: float = 0.1):
    """Each used overlap's residual vector on the map: ``(start, end)`` pairs in map
    coordinates, from the window's centre, scaled by one gain common to every arrow (the
    largest a ``length`` fraction of the map's larger side, shrunk to a quarter of that at
    most so that the arrows stay in the map; one still too long for its place is cut at
    the frame); and the gain (map units per px of residual)."""
    x0, x1, y0, y1 = _extent(layout)
    frame = (x0, y0, x1 - x0, y1 - y0)
    res, _ = _scale(rep)
    used = [(o, r) for o, r in zip(rep.get("overlaps", []), res) if np.isfinite(r)]
    big = max((r for _, r in used), default=0.0)
    gain = length * max(frame[2], frame[3]) / max(big, 1e-3)
    starts, dirs = [], []
    for o, _ in used:
        r0, c0, r1, c1 = o["window"]
        xc, yc = _to_map(layout, (r0 + r1) / 2, (c0 + c1) / 2)
        starts.append((float(xc), float(yc)))
        # residual (row, col) px -> map: col along x, row along -y (north-up grid)
        dirs.append((o["residual"][1] * abs(layout.transform.a),
                     o["residual"][0] * layout.transform.e))
    fit = gain
    for p, d in zip(starts, dirs):
        if np.hypot(*d) > 0:
            fit = min(fit, gain * _inside(p, (d[0] * gain, d[1] * gain), frame))
    gain = max(fit, 0.25 * gain)
    ends = []
    for p, d in zip(starts, dirs):
        t = _inside(p, (d[0] * gain, d[1] * gain), frame)
        ends.append((p, (p[0] + t * d[0] * gain, p[1] + t * d[1] * gain)))
    return ends, gain


def _inside(p, d, frame) -> float:
    """The largest ``t <= 1`` with ``p + t * d`` inside ``frame`` (x, y, w, h), less 1 % of
    the frame for the arrow's head, for ``p`` inside it."""
    x, y, w, h = frame
    t = 1.0
    for c, v, lo, hi, m in ((p[0], d[0], x, x + w, 0.01 * w), (p[1], d[1], y, y + h, 0.01 * h)):
        if v > 1e-12:
            t = min(t, max(0.0, hi - m - c) / v)
        elif v < -1e-12:
            t = min(t, max(0.0, c - lo - m) / -v)
    return t


def _backdrop(ax, grey, layout):
    """The mosaic's grey overview (2, rows, cols: grey + alpha) on its map extent."""
    rgba = np.empty(grey.shape[1:] + (4,), np.uint8)
    rgba[..., :3] = grey[0][..., None]
    rgba[..., 3] = grey[1]
    x0, x1, y0, y1 = _extent(layout)
    ax.imshow(rgba, extent=(x0, x1, y0, y1), interpolation="nearest", zorder=0)
    ax.set_xlim(x0, x1)
    ax.set_ylim(y0, y1)


def map_panel(ax, rep: dict, grey, layout):
    """The residual map on ``ax``; returns the colour mapping (for a colour bar)."""
    import matplotlib
    from matplotlib.collections import PatchCollection
    from matplotlib.patches import Rectangle

    from swathflow.drawing import map_frame
    res, top = _scale(rep)
    cmap = matplotlib.colormaps[COLOUR_MAP]
    norm = matplotlib.colors.Normalize(0.0, top)
    _backdrop(ax, grey, layout)
    # every overlap's window in one collection of its kind (one artist each, not one a
    # window: the survey's 600 windows drew in seconds as patches of their own)
    boxes: dict = {"used": [], "rejected": [], "skipped": []}
    colours = []
    for o, r in zip(rep.get("overlaps", []), res):
        r0, c0, r1, c1 = o["window"]
        x, y = _to_map(layout, r1, c0)                         # lower left corner
        w, h = (c1 - c0) * abs(layout.transform.a), (r1 - r0) * abs(layout.transform.e)
        kind = "used" if np.isfinite(r) else ("rejected" if o["ok"] else "skipped")
        boxes[kind].append(Rectangle((float(x), float(y)), float(w), float(h)))
        if kind == "used":
            colours.append(cmap(norm(r)))
    styles = {"used": dict(facecolors=colours, edgecolors="none", alpha=0.6),
              "rejected": dict(facecolors="none", edgecolors=REJECTED, linewidths=1.2),
              "skipped": dict(facecolors="none", edgecolors=SKIPPED, linewidths=0.8,
                              linestyles=":")}
    for kind, patches in boxes.items():
        if patches:
            ax.add_collection(PatchCollection(patches, match_original=False, **styles[kind]))
    kinds = {k for k, v in boxes.items() if v}
    ends, gain = arrow_ends(rep, layout)
    if ends:                # every residual vector in one quiver, from start to end
        (a, b) = np.array(ends, float).transpose(1, 0, 2)
        ax.quiver(a[:, 0], a[:, 1], b[:, 0] - a[:, 0], b[:, 1] - a[:, 1], angles="xy",
                  scale_units="xy", scale=1, color="#00bcd4", width=0.003, headwidth=4,
                  headlength=5, headaxislength=4.5, zorder=3)
    map_frame(ax, _crs_name(layout))
    _map_legend(ax, kinds, bool(ends), gain, layout)
    return matplotlib.cm.ScalarMappable(norm=norm, cmap=cmap)


def _map_legend(ax, kinds, arrows: bool, gain: float, layout) -> None:
    """Entries for what the map shows, only those drawn."""
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch
    handles = []
    if "used" in kinds:
        handles.append(Patch(fc="#cc4778", alpha=0.6, label="overlap window (colour: residual)"))
    if "rejected" in kinds:
        handles.append(Patch(fc="none", ec=REJECTED, label="rejected overlap"))
    if "skipped" in kinds:
        handles.append(Patch(fc="none", ec=SKIPPED, ls=":", label="skipped overlap"))
    if arrows:
        handles.append(Line2D([], [], color="#00bcd4", lw=1.3, marker=">", markevery=[1],
                              label=f"residual vector (1 px drawn {gain:.3g} m long)"))
    if handles:
        ax.legend(handles=handles, loc="upper left", fontsize=7.5, framealpha=0.85)


def graph_edges(rep: dict, layout) -> list[dict]:
    """The overlap graph's edges, one per overlap: its swings (``ref``, ``mov``), their
    nodes, the map positions of the two swings' centres and the overlap's state
    (``used``, ``rejected`` or ``skipped``) and residual (px)."""
    per_image = bool(rep.get("per_image"))
    centre = {s.image_id: _to_map(layout, s.row + s.height / 2, s.col + s.width / 2)
              for s in layout.swings}
    node_of = {s.image_id: str(s.image_id if per_image else s.strip) for s in layout.swings}
    res, _ = _scale(rep)
    out = []
    for o, r in zip(rep.get("overlaps", []), res):
        a, b = centre.get(o["ref"]), centre.get(o["mov"])
        if a is None or b is None:
            continue
        state = "used" if np.isfinite(r) else ("rejected" if o["ok"] else "skipped")
        out.append({"ref": o["ref"], "mov": o["mov"], "nodes": (node_of[o["ref"]],
                                                                   node_of[o["mov"]]),
                    "a": (float(a[0]), float(a[1])), "b": (float(b[0]), float(b[1])),
                    "state": state, "residual": r})
    return out


def _node_places(rep: dict, layout) -> dict:
    """Node name -> map (x, y) centre of its swings."""
    per_image = bool(rep.get("per_image"))
    acc: dict = {}
    for s in layout.swings:
        key = str(s.image_id if per_image else s.strip)
        acc.setdefault(key, []).append(_to_map(layout, s.row + s.height / 2,
                                               s.col + s.width / 2))
    return {k: tuple(np.mean(np.array(v, float), axis=0)) for k, v in acc.items()}


def graph_panel(ax, rep: dict, layout):
    """The overlap graph on ``ax`` (map coordinates); returns the colour mapping."""
    import matplotlib

    from swathflow.drawing import map_frame
    _, top = _scale(rep)
    cmap = matplotlib.colormaps[COLOUR_MAP]
    norm = matplotlib.colors.Normalize(0.0, top)
    x0, x1, y0, y1 = _extent(layout)
    ax.set_xlim(x0, x1)
    ax.set_ylim(y0, y1)
    # the footprints, the edges and the swings' centres one collection each (one artist
    # each, not one a swing and two an overlap: 1,200 artists on the survey)
    _footprints(ax, layout)
    edges = graph_edges(rep, layout)
    _edges(ax, edges, cmap, norm)
    places = _node_places(rep, layout)
    anchors = set(rep.get("anchors", []))
    _nodes(ax, rep, places, anchors)
    map_frame(ax, _crs_name(layout))
    _graph_legend(ax, {e["state"] for e in edges}, bool(anchors & set(places)), cmap)
    return matplotlib.cm.ScalarMappable(norm=norm, cmap=cmap)


def _footprints(ax, layout) -> None:
    """Every swing's rectangle on the grid, one collection."""
    from matplotlib.collections import PatchCollection
    from matplotlib.patches import Rectangle
    boxes = []
    for s in layout.swings:
        x, y = _to_map(layout, s.row + s.height, s.col)
        boxes.append(Rectangle((float(x), float(y)), s.width * abs(layout.transform.a),
                               s.height * abs(layout.transform.e)))
    if boxes:
        ax.add_collection(PatchCollection(boxes, facecolors="#f3f3f3", edgecolors="#bbbbbb",
                                          linewidths=0.6, zorder=0))


_EDGE_STYLE = {"used": (2.5, "solid"), "rejected": (1.5, "solid"), "skipped": (1.0, ":")}


def _edges(ax, edges: list, cmap, norm) -> None:
    """Every overlap an edge between its swings' centres (one collection, in the order of
    the overlaps), coloured by its residual when used, and the centres."""
    from matplotlib.collections import LineCollection
    if not edges:
        return
    ax.add_collection(LineCollection(
        [[e["a"], e["b"]] for e in edges], zorder=2, capstyle="round",
        colors=[cmap(norm(e["residual"])) if e["state"] == "used" else
                REJECTED if e["state"] == "rejected" else SKIPPED for e in edges],
        linewidths=[_EDGE_STYLE[e["state"]][0] for e in edges],
        linestyles=[_EDGE_STYLE[e["state"]][1] for e in edges]))
    ends = np.array([p for e in edges for p in (e["a"], e["b"])], float)
    ax.plot(ends[:, 0], ends[:, 1], "o", ms=2.5, color="#555555", zorder=3)


def _nodes(ax, rep: dict, places: dict, anchors: set) -> None:
    """The network's nodes (anchors as squares), labelled with their sigmas when there
    are few enough to read."""
    sig = {n["node"]: n["sigma"] for n in rep.get("nodes", [])}
    label = len(places) <= 60
    # with more than a dozen nodes their sigmas would overlap one another: names only
    # (the offsets panel gives every node's sigma)
    with_sigma = len(places) <= 12
    for q, (name, (x, y)) in enumerate(places.items()):
        a = name in anchors
        ax.plot(x, y, "s" if a else "o", ms=8, color=ANCHOR if a else NODE, mec="white",
                zorder=4)
        if label:
            sg = sig.get(name) or [None, None]
            text = (f"{name} (anchor)" if a else
                    f"{name} σ {'/'.join(_sig(v) for v in sg)} px" if with_sigma else
                    str(name))
            ax.annotate(text, (x, y), xytext=(0, 9 if q % 2 == 0 else -14),
                        textcoords="offset points", ha="center", fontsize=7.5, zorder=5,
                        bbox=dict(boxstyle="round,pad=0.1", fc="white", ec="none", alpha=0.7))


def _graph_legend(ax, states: set, anchored: bool, cmap) -> None:
    """The legend of what the graph draws (an anchor square only where one is drawn)."""
    from matplotlib.lines import Line2D
    handles = [Line2D([], [], marker="o", ls="", color=NODE, label="node (strip or image)")]
    if anchored:
        handles.append(Line2D([], [], marker="s", ls="", color=ANCHOR, label="anchor node"))
    handles.append(Line2D([], [], marker="o", ls="", ms=2.5, color="#555555",
                          label="swing centre"))
    if "used" in states:
        handles.append(Line2D([], [], color=cmap(0.6), lw=2.5, label="overlap (colour: residual)"))
    if "rejected" in states:
        handles.append(Line2D([], [], color=REJECTED, lw=1.5, label="rejected overlap"))
    if "skipped" in states:
        handles.append(Line2D([], [], color=SKIPPED, lw=1.0, ls=":", label="skipped overlap"))
    ax.legend(handles=handles, loc="upper left", fontsize=7.5, framealpha=0.85)


def _node_order(name):
    try:
        return (0, float(name), "")
    except ValueError:
        return (1, 0.0, name)


def offsets_panels(ax_off, ax_rad, rep: dict, res_m: float) -> None:
    """Each node's offset (row, col) with 1-sigma bars (px, and m on the right axis), and
    its radiometric offset."""
    nodes = sorted(rep.get("nodes", []), key=lambda n: _node_order(n["node"]))
    if not nodes:
        return
    n = len(nodes)
    x = np.arange(n)
    off = np.array([n_["offset"] for n_ in nodes], float).reshape(-1, 2)
    sig = np.array([[np.nan if v is None else v for v in n_["sigma"]] for n_ in nodes],
                   float).reshape(-1, 2)
    for axis, dx, col, mk, name in ((0, -0.12, "#1f77b4", "o", "row offset"),
                                    (1, 0.12, "#ff7f0e", "s", "column offset")):
        ax_off.errorbar(x + dx, off[:, axis], yerr=np.nan_to_num(sig[:, axis]), fmt=mk,
                        color=col, ms=4, capsize=2, label=name)
    ax_off.axhline(0, color="#999999", lw=0.6)
    ax_off.set_ylabel("offset (grid px)")
    sec = ax_off.secondary_yaxis("right", functions=(lambda v: v * res_m,
                                                     lambda v: v / res_m))
    sec.set_ylabel("offset (m)")
    ax_off.set_title(f"network: {rep.get('anchor', '')} anchored, offsets with 1-sigma bars")
    ax_off.legend(loc="best", fontsize=7.5)
    rad = np.array([n_["radiometric"] for n_ in nodes], float)
    ax_rad.bar(x, rad, color="#2ca02c", width=0.6)
    ax_rad.axhline(0, color="#999999", lw=0.6)
    ax_rad.set_title("radiometric balance per node")
    ax_rad.set_ylabel("radiometric offset removed (data units)")
    ax_rad.set_xlabel("node (strip or image)")
    step = max(1, n // 24)
    for ax in (ax_off, ax_rad):
        ax.set_xticks(x[::step], [str(nodes[q]["node"]) for q in range(0, n, step)])
        ax.set_xlim(-0.6, n - 0.4)


def _fit(shape, w, h):
    """Width and height (inches) of a map panel for a ``shape`` (rows, cols) area within
    w x h."""
    s = min(w / shape[1], h / shape[0])
    return shape[1] * s, shape[0] * s


def map_figure(rep: dict, grey, layout):
    """The residual map as a figure (with its colour bar)."""
    from swathflow.drawing import figure
    pw, ph = _fit(layout.shape, 8.0, 7.0)
    fig = figure(pw + 2.4, ph + 1.3, margins=MAP_MARGINS)
    ax = fig.add_subplot()
    sm = map_panel(ax, rep, grey, layout)
    ax.set_title("per-overlap residuals on the mosaic: " + _summary(rep), fontsize=9)
    _colour_bar(fig, ax, sm, rep)
    return fig


def _colour_bar(fig, ax, sm, rep, shrink=0.8) -> None:
    """The residual colour bar, when an overlap is coloured by its residual."""
    if np.isfinite(_scale(rep)[0]).any():
        fig.colorbar(sm, ax=ax, shrink=shrink, label="residual after adjustment (px)")


def graph_figure(rep: dict, layout):
    from swathflow.drawing import figure
    pw, ph = _fit(layout.shape, 8.0, 7.0)
    fig = figure(pw + 2.4, ph + 1.3, margins=MAP_MARGINS)
    ax = fig.add_subplot()
    sm = graph_panel(ax, rep, layout)
    ax.set_title(f"{len(_node_places(rep, layout))} nodes, {len(rep.get('overlaps', []))} "
                 f"overlaps (each an edge between its swings' centres)", fontsize=9)
    _colour_bar(fig, ax, sm, rep)
    return fig


def offsets_figure(rep: dict, layout):
    from swathflow.drawing import figure
    fig = figure(10.5, 3.6, margins=(0.75, 0.2, 0.6, 0.35), wspace=0.45)
    a, b = fig.subplots(1, 2)
    offsets_panels(a, b, rep, _res_m(layout))
    a.set_xlabel("node (strip or image)")
    return fig


@styled
def seams_picture(mosaic_path, rep: dict, layout, png_path, grey=None, f=None) -> str:
    """Draw the report picture of a finished mosaic (``rep``: its mosaic.json content)
    into ``png_path`` (atomically): the residual map and the per-node offsets. ``grey``,
    ``f``: the mosaic's overview (:func:`swathflow.mosaicking.output.overview`), read when
    not given. Returns the path."""
    from swathflow.drawing import figure, write_png
    from swathflow.mosaicking.output import overview, stretch
    if grey is None:
        data, f = overview(mosaic_path, 900)
        grey = stretch(data)
    pw, ph = _fit(layout.shape, 7.5, 7.5)
    fig = figure(pw + 8.0, max(ph + 1.3, 7.0), margins=(0.85, 0.8, 0.6, 0.6), wspace=0.45,
                 hspace=0.35)
    grid = fig.add_gridspec(2, 2, width_ratios=[pw + 1.5, 6.0])
    ax = fig.add_subplot(grid[:, 0])
    sm = map_panel(ax, rep, grey, layout)
    _colour_bar(fig, ax, sm, rep, 0.6)
    offsets_panels(fig.add_subplot(grid[0, 1]), fig.add_subplot(grid[1, 1]), rep,
                   _res_m(layout))
    fig.suptitle(f"mosaic {os.path.basename(os.fspath(mosaic_path))}: {layout.shape[0]} x "
                 f"{layout.shape[1]} px of {_res_m(layout):g} m, {len(layout.swings)} "
                 f"swings. " + _summary(rep), fontsize=10)
    return write_png(fig, png_path)


def node_line(nd: dict, res_m: float | None = None) -> str:
    """A node of mosaic.json as a person reads it on the terminal: offset (row, col) in
    grid pixels (and metres with ``res_m``, the pixel size), its 1-sigma ("anchor" for a
    node held fixed), the radiometric offset."""
    off = nd["offset"]
    sg = nd.get("sigma") or [None, None]
    text = f"node {nd['node']}: offset (row, col) ({off[0]:+.3f}, {off[1]:+.3f}) px"
    if res_m:
        text += f" = ({off[0] * res_m:+.3f}, {off[1] * res_m:+.3f}) m"
    if all(v is None for v in sg):
        text += ", held (anchor)"
    else:
        text += f", sigma ({_sig(sg[0])}, {_sig(sg[1])}) px"
    return text + f", radiometric {nd['radiometric']:+.3f}"
