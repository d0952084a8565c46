"""Strip matching and feathered mosaicking of rectified swings (docs/references.md section 3).

Steps (:func:`mosaic` runs them all):

1. :func:`scan_inputs` reads the rectified swings' headers: one common grid (same CRS, pixel
   size, aligned transforms), each swing's place on it, image id and strip number.
2. :func:`find_overlaps` lists the pairs whose footprints overlap (bounds, then valid masks).
3. :func:`match_pair` estimates each overlap's systematic offset (swathflow.mosaicking.matching: the
   paper's minimum-mean-grey-difference search, phase correlation, least-squares polish,
   texture check, outlier rejection). Low-texture overlaps are reported and skipped.
4. :func:`solve_network` solves one least-squares network for per-strip (or per-image)
   offsets and radiometric offsets, anchored on given images (or, without anchors, on the
   mean of each connected group), with iterative rejection of inconsistent overlaps.
5. :func:`render_tile` blends the corrected swings with distance-transform feathering: the
   weight of a swing is its distance to its own footprint's edge (capped at ``feather``
   pixels), which is the paper's ``G = (Rl*Gr + Rr*Gl)/(Rl + Rr)`` for a straight overlap
   and works for any overlap shape. Tiles are computed over dask and streamed to disk, so
   memory does not grow with the mosaic; the result is a COG with overviews plus a PNG
   quicklook and a JSON report.

Offsets: a node's offset ``t = (drow, dcol)`` means its content sits ``t`` pixels away from
where it belongs (``image[x] = truth[x - t]``); the mosaic samples ``image[x + t]``.
Radiometric offset ``b``: ``image = truth + b``; the mosaic subtracts ``b``.
"""
from __future__ import annotations

import json
import os
import time
from typing import TYPE_CHECKING

import numpy as np

from swathflow.io import write_text
from swathflow.mosaicking.inputs import (TAG_DIRECTION, TAG_IMAGE, TAG_STRIP, Layout, Swing,
                                         _Handles, find_inputs, mission_strips, read_window,
                                         scan_inputs)
from swathflow.mosaicking.output import (level_overview, mosaic_array, overview, quicklook,
                                          render_tile, stretch, swing_cache, write_mosaic)

if TYPE_CHECKING:
    from swathflow.mosaicking.network import Network

# the matching's modules (overlaps, matching, network, seams) are imported on first use:
# a blend without matching does not load them
_LAZY = {"find_overlaps": "overlaps", "match_pair": "overlaps", "match_all": "overlaps",
         "plan": "overlaps", "_active_client": "overlaps", "Network": "network",
         "solve_network": "network", "seam_lines": "seams", "seam_visibility": "seams"}


def __getattr__(name):
    if name in _LAZY:
        from importlib import import_module
        return getattr(import_module(f"swathflow.mosaicking.{_LAZY[name]}"), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


__all__ = ["Swing", "Layout", "scan_inputs", "render_tile", "write_mosaic", "mosaic",
           "mission_strips", "find_inputs", "quicklook", "TAG_IMAGE", "TAG_STRIP",
           "TAG_DIRECTION", "read_window", "swing_cache", "network_report", "plan_mosaic",
           "finish_mosaic", "mosaic_array", "swing_store", "load_kernels",
           "load_kernels_async", *_LAZY]


def mosaic(paths, out, per_image: bool = False, anchors=(), feather: int = 64,
           mode: str = "feather", balance: bool = True, match: bool = True,
           max_shift: int = 12, block: int = 128, min_texture: float = 1.0, tile: int = 1024,
           workers: int | None = None, png: bool = True, report: bool = True,
           cog: bool = True, strips: dict | None = None, log=None,
           cache_mb: int = 64, control: dict | None = None) -> dict:
    """Match, adjust and blend rectified swings ``paths`` into the mosaic ``out``
    (:func:`plan_mosaic`, then :func:`finish_mosaic`).

    ``control``: image id -> ``(offset (drow, dcol), sigma (row, col))`` in grid pixels,
    each image's absolute offset measured on its control points; the network is then tied
    to the ground (absolute offsets with their sigmas) instead of to ``anchors`` alone.
    GDAL's block cache is capped at ``cache_mb`` so memory stays bounded (GDAL's default is
    5 % of RAM). Returns the report (also written to ``<out>.json`` when ``report``, with
    the seams/residuals picture ``<out>.report.png``): per-node offsets and radiometric
    offsets with their sigmas, every overlap with its measurement, status and residual,
    and the timing. ``log``: an optional progress callback taking one line of text.
    """
    import rasterio
    t0 = time.perf_counter()
    handles = swing_store()
    try:
        with rasterio.Env(GDAL_CACHEMAX=int(cache_mb)):
            plan_ = plan_mosaic(paths, per_image, anchors, feather, mode, balance, match,
                                max_shift, block, min_texture, workers, strips, log, control,
                                handles)
        return finish_mosaic(plan_, out, feather, mode, tile, workers, png, report, cog, t0,
                             cache_mb, handles)
    finally:
        handles.close()


def swing_store(keep_mb: int = 512) -> _Handles:
    """The dataset handles of one mosaic run, keeping the decoded swings between the
    matching and the blend when all of them fit in ``keep_mb`` (each swing then decoded
    once; :meth:`_Handles.keep_if_fits`, called by :func:`plan_mosaic`). 512 MB holds the
    16x benchmark's 768 swings (354 MB): its matching took 26.5 CPU-s / 109 s wall reading
    windows through GDAL, 22.5 / 42 s slicing the kept swings."""
    return _Handles(keep_bytes=int(keep_mb) * 2 ** 20)


def plan_mosaic(paths, per_image: bool = False, anchors=(), feather: int = 64,
                mode: str = "feather", balance: bool = True, match: bool = True,
                max_shift: int = 12, block: int = 128, min_texture: float = 1.0,
                workers: int | None = None, strips: dict | None = None, log=None,
                control: dict | None = None, handles=None):
    """The mosaic's inputs and corrections, before any blending: ``(layout, offsets,
    radiometric, report)`` (the overlaps matched and the network solved when ``match``;
    arguments as :func:`mosaic`; ``handles``: a :func:`swing_store` shared with
    :func:`finish_mosaic`)."""
    t0 = time.perf_counter()
    loading = load_kernels_async(matching=match)
    try:
        layout = scan_inputs(paths, strips, handles)
        if handles is not None:
            handles.keep_if_fits(layout.swings)
            handles.prefetch(layout.swings, workers)
    finally:
        loading.result()
    n_sw = len(layout.swings)
    rep = _header(layout, per_image, mode, feather)
    off, rad = np.zeros((n_sw, 2)), np.zeros(n_sw)
    if match:
        from swathflow.mosaicking.overlaps import plan
        net, pairs, matches, keys = plan(layout, per_image, anchors, max_shift, block,
                                         min_texture, workers, log, control, handles)
        rep.update(network_report(layout, net, pairs, matches, control))
        rep["seconds_match"] = round(time.perf_counter() - t0, 3)
        # the offsets as mosaic.json gives them (4 decimals) are the ones applied, so a
        # run over part of the area with the report's offsets gives the same pixels
        node_of = {k: q for q, k in enumerate(net.nodes)}
        off = np.array([[round(float(v), 4) for v in net.offsets[node_of[k]]]
                        for k in keys]).reshape(-1, 2)
        if balance:
            rad = np.array([round(float(net.radiometric[node_of[k]]), 4) for k in keys])
        _log_matching(log, rep)
    return layout, off, rad, rep


def finish_mosaic(planned, out, feather: int = 64, mode: str = "feather", tile: int = 1024,
                  workers: int | None = None, png: bool = True, report: bool = True,
                  cog: bool = True, t0: float | None = None, cache_mb: int = 64,
                  handles=None) -> dict:
    """Blend a :func:`plan_mosaic` result into the COG ``out`` (tiles over dask threads,
    streamed, atomic, GDAL's block cache capped at ``cache_mb``), then the quicklook, the
    report picture and ``<out>.json`` (with GDAL's default cache: the overview reads are
    many times slower under the cap). ``handles``: the :func:`swing_store` of the
    matching, if any."""
    import rasterio
    t0 = time.perf_counter() if t0 is None else t0
    load_kernels()
    layout, off, rad, rep = planned
    rep = dict(rep)
    early = []          # the products made from the first overview level, on a thread

    def products_now(level, nodata):
        if not (cog and (png or (report and "overlaps" in rep))):
            return
        data = level_overview(level, nodata, layout.shape, QUICKLOOK_SIDE)
        if data is not None:
            early.append(_submit(_products, out, dict(rep), png, report, layout, data))

    try:
        with rasterio.Env(GDAL_CACHEMAX=int(cache_mb)):
            rep.update(write_mosaic(layout, out, off, rad, feather, mode, tile, workers,
                                    cog=cog, handles=handles, on_level1=products_now))
    except BaseException:
        for f in early:
            f.exception()       # waited for; the mosaic's error is the one raised
        raise
    made = [f.result() for f in early]
    if made:
        rep["seconds_quicklook"] = made[0]["seconds_quicklook"]
    else:
        _products(out, rep, png, report, layout)
    rep["seconds"] = round(time.perf_counter() - t0, 3)
    rep["mpx_per_s"] = round(layout.shape[0] * layout.shape[1] / 1e6 / rep["seconds"], 3)
    if report:
        write_text(os.path.splitext(os.fspath(out))[0] + ".json", json.dumps(rep, indent=1))
    return rep


def load_kernels(matching: bool = False) -> None:
    """Load the mosaic's compiled kernels (numba's start and its cache: the blend's, and
    with ``matching`` the matching's) without the collector's passes (numba makes some
    100 000 objects as it starts, all of which live to the end: 0.15-0.2 CPU-s of passes
    on the 48-swing benchmark; :mod:`swathflow.collector`).
    The first time in a process the objects then alive are frozen: the 48-swing mosaic's
    exit cost 0.20-0.23 CPU-s, now about 0.03."""
    from swathflow.collector import uncollected
    first = not _FROZEN
    with uncollected(freeze=first):
        from swathflow.mosaicking import kernels
        if matching:
            from swathflow.mosaicking import block_kernels, match_kernels  # noqa: F401
        z = np.zeros((1, 1), np.float32)
        kernels.normalise(z, z)             # numba's first call: its runtime
        if first:
            _FROZEN.append(True)


#: the longest side of the quicklook and of the report's backdrop (pixels)
QUICKLOOK_SIDE = 1024

_FROZEN: list = []     # load_kernels froze the start-up objects (once per process)


def load_kernels_async(matching: bool = False):
    """:func:`load_kernels` on a thread of its own, started now; returns its future
    (``result()`` waits for it and raises what it raised). :func:`plan_mosaic` reads the
    swings' headers and decodes the swings (GDAL releases the GIL) meanwhile: numba's
    start is the largest fixed cost of a mosaic (about 0.4 CPU-s, 48-swing benchmark)."""
    return _submit(load_kernels, matching, name="swathflow-kernels")


def _submit(fn, *args, name: str = "swathflow-products"):
    """``fn(*args)`` on a thread of its own, started now: its future."""
    from concurrent.futures import ThreadPoolExecutor
    ex = ThreadPoolExecutor(1, thread_name_prefix=name)
    try:
        return ex.submit(fn, *args)
    finally:
        ex.shutdown(wait=False)


def _header(layout: Layout, per_image, mode, feather) -> dict:
    return {"format": "swathflow-mosaic/1", "inputs": len(layout.swings), "grid": {
        "shape": list(layout.shape), "res": layout.res, "crs": layout.crs.to_string()
        if layout.crs else None, "transform": list(layout.transform)[:6]},
        "per_image": per_image, "blend": mode, "feather_px": feather}


def _r4(v):
    return None if v is None or not np.isfinite(v) else round(float(v), 4)


def network_report(layout: Layout, net: Network, pairs, matches, control=None) -> dict:
    """The matching and network part of mosaic.json."""
    overlaps = []
    for q, ((i, j, win, n), m) in enumerate(zip(pairs, matches)):
        d = m.to_dict()
        d.update(ref=layout.swings[i].image_id, mov=layout.swings[j].image_id,
                 window=list(win), pixels=n, used=bool(net.used[q]),
                 residual=[_r4(v) for v in net.residuals[q]])
        overlaps.append(d)
    return {
        "anchor": "gcp" if control else ("images" if net.anchored else "mean"),
        "nodes": [{"node": str(k), "offset": [round(float(v), 4) for v in net.offsets[q]],
                   "sigma": [_r4(v) for v in net.sigmas[q]],
                   "radiometric": round(float(net.radiometric[q]), 4)}
                  for q, k in enumerate(net.nodes)],
        "control": [{"image": iid, "offset": [_r4(v) for v in o], "sigma": [_r4(v) for v in s]}
                    for iid, (o, s) in sorted((control or {}).items())],
        "anchors": [str(a) for a in net.anchored],
        "free_groups": [[str(v) for v in g] for g in net.free_groups],
        "sigma0": _r4(net.sigma0),
        "overlaps": overlaps,
        "skipped": [{"ref": o["ref"], "mov": o["mov"], "status": o["status"]}
                    for o in overlaps if not o["ok"]],
        "rejected": [{"ref": o["ref"], "mov": o["mov"], "residual": o["offset"]}
                     for o in overlaps if o["ok"] and not o["used"]]}


def _log_matching(log, rep) -> None:
    if not log:
        return
    log(f"matched {len(rep['overlaps'])} overlaps ({len(rep['skipped'])} skipped) in "
        f"{rep['seconds_match']:.1f} s")
    for s in rep["skipped"]:
        log(f"  skipped {s['ref']} / {s['mov']}: {s['status']}")


def _products(out, rep, png, report, layout, data=None) -> dict:
    """The quicklook PNG, the seams/residuals picture and the HTML report, from one read
    of the mosaic's overviews (or ``data``, that read's result: :func:`finish_mosaic`
    makes them from the first overview level while the COG is laid out). The report
    picture is drawn and encoded on a second thread while this one encodes the quicklook
    and writes the HTML (Pillow's encoder and resampling release the GIL). Returns
    ``rep``, with the time taken."""
    stem = os.path.splitext(os.fspath(out))[0]
    t1 = time.perf_counter()
    figures = report and "overlaps" in rep
    if png or figures:
        from concurrent.futures import ThreadPoolExecutor

        from swathflow.io import png_bytes
        data, f = overview(out, QUICKLOOK_SIDE) if data is None else data
        grey = stretch(data)
        with ThreadPoolExecutor(1, thread_name_prefix="swathflow-report") as ex:
            picture = None
            if figures:
                from swathflow.mosaicking.report import seams_picture
                from swathflow.mosaicking.report_html import mosaic_report_html
                picture = ex.submit(seams_picture, out, rep, layout, stem + ".report.png",
                                    grey, f)
            encoded = png_bytes(grey)           # the quicklook, also the maps' backdrop
            if png:
                quicklook(out, stem + ".png", png=encoded)
            if figures:
                mosaic_report_html(out, rep, layout, stem + ".html", grey, f, encoded)
                picture.result()
    rep["seconds_quicklook"] = round(time.perf_counter() - t1, 3)
    return rep
