"""Writing the mosaic: tiles blended from the corrected swings on threads (compiled kernels
that release the GIL), streamed into a tiled GeoTIFF, copied into a COG with overviews by
GDAL's COG driver (the rectification's writer, :mod:`swathflow.rectification.writing`);
the PNG quicklook."""
from __future__ import annotations

import contextlib
import os
import threading
import time

import numpy as np

from swathflow.io import atomic_path, scratch_path
from swathflow.mosaicking.inputs import Layout, _Handles, read_window

__all__ = ["swing_cache", "render_tile", "write_mosaic", "mosaic_array", "quicklook",
           "overview", "stretch"]


def swing_cache(layout: Layout, offsets, radiometric, feather: int = 64, handles=None,
                max_bytes: int = 512 * 2 ** 20):
    """A :class:`swathflow.blend.SwingCache` of the swings corrected by ``offsets`` and
    ``radiometric`` (per swing), read through ``handles``."""
    from swathflow.mosaicking.blend import Scratch, SwingCache, corrected_swing
    handles = handles or _Handles()
    offsets = np.asarray(offsets, float)
    radiometric = np.asarray(radiometric, float)
    scratch = Scratch()         # the reading's and the correction's arrays, per thread

    def make(k, empty):
        sw = layout.swings[k]
        val, ok = read_window(handles, sw, sw.row, sw.col, sw.row + sw.height,
                              sw.col + sw.width, scratch=scratch.get)
        return corrected_swing(val, ok, sw.row, sw.col, offsets[k], radiometric[k], feather,
                               empty=empty, scratch=scratch.get)
    return SwingCache(make, max_bytes)


def render_tile(layout: Layout, r0, c0, r1, c1, offsets, cache, mode: str = "feather",
                sel=None):
    """Blend grid window ``[r0,r1) x [c0,c1)`` from the corrected swings in ``cache``
    (:func:`swing_cache`; ``offsets`` (n_swings, 2) are the ones it was made with).
    ``mode``: see :func:`swathflow.blend.blend_tile`. Returns (values, valid)."""
    from swathflow.mosaicking.blend import blend_tile
    offsets = np.asarray(offsets, float)
    ext = np.array([s.extent for s in layout.swings], float)
    lo = ext[:, :2] - np.floor(offsets)                  # corrected swing bounds
    hi = ext[:, 2:] - np.floor(offsets)
    hit = (lo[:, 0] < r1) & (hi[:, 0] > r0) & (lo[:, 1] < c1) & (hi[:, 1] > c0)
    if sel is not None:
        hit &= sel
    return blend_tile([cache.get(int(k)) for k in np.nonzero(hit)[0]], r0, c0, r1, c1, mode)


class _Blender:
    """The blended tiles of a mosaic as a picklable dask block function: each process (a
    thread pool, or a distributed worker) builds its own swing cache and dataset handles
    on first use, so the lazy mosaic computes on any scheduler."""

    def __init__(self, layout: Layout, offsets, radiometric, feather: int, mode: str):
        self.layout, self.feather, self.mode = layout, feather, mode
        self.offsets = np.asarray(offsets, float)
        self.radiometric = np.asarray(radiometric, float)
        self._cache = self._handles = None
        self._lock = threading.Lock()

    def __getstate__(self):
        return {k: v for k, v in self.__dict__.items()
                if k not in ("_cache", "_handles", "_lock")}

    def __setstate__(self, state):
        self.__dict__.update(state, _cache=None, _handles=None, _lock=threading.Lock())

    def cache(self):
        with self._lock:
            if self._cache is None:
                self._handles = _Handles()
                self._cache = swing_cache(self.layout, self.offsets, self.radiometric,
                                          self.feather, self._handles)
            return self._cache

    def __call__(self, x, block_info=None):
        (a, b), (c, d) = block_info[None]["array-location"]
        v, _ = render_tile(self.layout, a, c, b, d, self.offsets, self.cache(), self.mode)
        return v.astype(np.float32)

    def close(self):
        if self._handles is not None:
            self._handles.close()


def mosaic_array(layout: Layout, offsets, radiometric, feather: int = 64,
                 mode: str = "feather", tile: int = 1024):
    """The mosaic as a lazy float32 dask array over the layout's grid (NaN = nodata),
    tiles of ``tile`` pixels blended when computed. Returns (array, blender); the
    blender's :meth:`_Blender.close` closes this process's dataset handles."""
    import dask.array as da
    from dask.base import tokenize
    blender = _Blender(layout, offsets, radiometric, feather, mode)
    H, W = layout.shape
    name = "mosaic-" + tokenize([s.path for s in layout.swings], layout.shape,
                                tuple(layout.transform)[:6], blender.offsets,
                                blender.radiometric, feather, mode, tile)
    arr = da.zeros((H, W), chunks=(tile, tile), dtype=np.float32).map_blocks(
        blender, dtype=np.float32, name=name)
    return arr, blender


def _to_dtype(block, dtype, nodata):
    """A float32 tile with NaN for no data, cast to the output dtype with ``nodata``."""
    if dtype.kind in "ui":
        info = np.iinfo(dtype)
        bad = ~np.isfinite(block)
        out = np.clip(np.round(np.where(bad, 0, block)), info.min, info.max).astype(dtype)
        out[bad] = nodata
        return out
    out = block.astype(dtype)
    if nodata is not None and not np.isnan(nodata):
        out[~np.isfinite(out)] = nodata
    return out


def _tile_swings(layout: Layout, tiles, offsets):
    """The swings the tiles need, each once, in the order the tiles first need them."""
    offsets = np.asarray(offsets, float)
    ext = np.array([s.extent for s in layout.swings], float).reshape(-1, 4)
    lo = ext[:, :2] - np.floor(offsets)
    hi = ext[:, 2:] - np.floor(offsets)
    seen: dict = {}
    for r0, c0, r1, c1 in tiles:
        hit = (lo[:, 0] < r1) & (hi[:, 0] > r0) & (lo[:, 1] < c1) & (hi[:, 1] > c0)
        seen.update((int(k), None) for k in np.nonzero(hit)[0] if int(k) not in seen)
    return list(seen)


def _render_all(layout, ds, tiles, offsets, cache, mode, dtype, nodata, workers):
    """Render ``tiles`` (r0, c0, r1, c1) on ``workers`` threads (the kernels release the
    GIL) and write each into ``ds`` as it is done; at most two tiles per thread are in
    flight, so memory is bounded by the threads, not by the mosaic. When every corrected
    swing fits in the cache they are made first, all threads at it, in the order the tiles
    need them (else the first tiles' threads wait on each other's swings: the 48-swing
    mosaic's first tiles ran on about one core)."""
    from concurrent.futures import FIRST_COMPLETED, ThreadPoolExecutor, wait
    from rasterio.windows import Window
    lock = threading.Lock()
    need = _tile_swings(layout, tiles, offsets)
    # a corrected swing: float32 values and weights over its extent (+1 row and column)
    size = sum(8 * (layout.swings[k].height + 1) * (layout.swings[k].width + 1) for k in need)
    first = need if size <= cache.max_bytes else []

    def job(t):
        r0, c0, r1, c1 = t
        v, _ = render_tile(layout, r0, c0, r1, c1, offsets, cache, mode)
        out = _to_dtype(v, dtype, nodata)
        with lock:
            ds.write(out, 1, window=Window(c0, r0, c1 - c0, r1 - r0))

    n = max(1, int(workers or os.cpu_count() or 1))
    with ThreadPoolExecutor(n) as ex:
        pending = {ex.submit(cache.get, k) for k in first}
        for t in tiles:
            if len(pending) >= 2 * n:
                done, pending = wait(pending, return_when=FIRST_COMPLETED)
                for f in done:
                    f.result()
            pending.add(ex.submit(job, t))
        for f in pending:
            f.result()


def _tile_order(layout: Layout, tile: int):
    """The tiles in bands at least a swing wide, down the bands when the swings are taller
    than wide (strips flown along the rows), else along them, row by row within a band:
    consecutive tiles then share their swings, so the swing cache holds the few swings of
    one band instead of a whole row of strips, and a strip is crossed by fewer bands (each
    band that reaches a swing corrects it again once the cache has let it go: the 1.06 Gpx
    regional mosaic's 320 swings were corrected 1834 times in bands one tile wide)."""
    H, W = layout.shape
    heights = np.median([s.height for s in layout.swings])
    widths = np.median([s.width for s in layout.swings])
    tall = heights > widths
    g = max(1, int(np.ceil((widths if tall else heights) / tile)))     # tiles a band
    rows, cols = list(range(0, H, tile)), list(range(0, W, tile))
    if tall:
        order = [(r, c) for b in range(0, len(cols), g) for r in rows for c in cols[b:b + g]]
    else:
        order = [(r, c) for b in range(0, len(rows), g) for c in cols for r in rows[b:b + g]]
    return [(r, c, min(H, r + tile), min(W, c + tile)) for r, c in order]


def write_mosaic(layout: Layout, out, offsets, radiometric, feather: int = 64,
                 mode: str = "feather", tile: int = 1024, workers: int | None = None,
                 dtype=None, nodata=None, cog: bool = True, blocksize: int = 512,
                 handles=None, on_level1=None, tags=None) -> dict:
    """Render the mosaic tile by tile on ``workers`` threads into ``out`` (a COG with
    overviews when ``cog``, else a tiled GeoTIFF), atomically. Memory is bounded by
    ``workers`` tiles and the swing cache (its swings in memory mappings of their own,
    outside the C heap: see :class:`swathflow.mosaicking.blend.Mappings`), which is let go
    before the COG is made. ``handles``: the :class:`_Handles` to read the swings through
    (its own if None). ``on_level1``: called with the COG's first overview level
    (:func:`level_overview`'s argument) and the nodata value once the COG is written and
    before it is renamed into place. ``tags``: more dataset tags (e.g. the mission and the
    calibration; values that are not strings as JSON) beside ``product``, ``blend``, the
    software's version and the TIFF date and software tags.

    The tiles are streamed into a tiled GeoTIFF beside ``out`` and copied into the COG by
    GDAL's COG driver (:func:`swathflow.rectification.writing.copy_to_cog`: DEFLATE level 1
    with the predictor, average overviews)."""
    import rasterio

    from swathflow.rectification import writing
    dtype, nodata = _output_type(layout, dtype, nodata)
    H, W = layout.shape
    offsets = np.asarray(offsets, float)
    radiometric = np.asarray(radiometric, float)
    own = handles is None
    handles = handles or _Handles()
    cache = swing_cache(layout, offsets, radiometric, feather, handles)
    tiles = _tile_order(layout, tile)
    profile = writing.part_profile((H, W), 1, dtype, blocksize, "deflate", nodata=nodata)
    profile.update(crs=layout.crs, transform=layout.transform)
    if not cog:
        profile.update(writing.compression("deflate", dtype))
    n = max(1, int(workers or os.cpu_count() or 1))
    t0 = time.perf_counter()
    out = os.fspath(out)
    try:
        with atomic_path(out, suffix=".part.tif") as final, contextlib.ExitStack() as stack:
            part = stack.enter_context(scratch_path(out, "stream.tif")) if cog else final
            with rasterio.open(part, "w", **profile) as ds:
                ds.update_tags(**writing.product_tags(
                    {"product": "mosaic", "blend": mode, **(tags or {})}))
                ds.set_band_description(1, _description(layout))
                _render_all(layout, ds, tiles, offsets, cache, mode, dtype, nodata, n)
                if cog:
                    writing.build_overviews(ds, blocksize, "average")
            t_render = time.perf_counter() - t0
            del cache       # its corrected swings unmapped before the COG is made
            if cog:
                writing.copy_to_cog(part, final, blocksize, "deflate", "average")
                if on_level1 is not None and writing.overview_factors(H, W, blocksize):
                    with rasterio.open(final, overview_level=0) as ov:
                        on_level1(ov.read(1), nodata)
    finally:
        if own:
            handles.close()
    return {"seconds_render": t_render, "seconds_total": time.perf_counter() - t0,
            "shape": [H, W], "dtype": dtype.name}


def _output_type(layout: Layout, dtype=None, nodata=None):
    """The mosaic's data type and nodata value: as given, else the swings' own when they
    agree (float32 and NaN when they do not, or are floats)."""
    dtypes = {s.dtype for s in layout.swings}
    if dtype is None:
        dtype = "float32" if len(dtypes) != 1 or next(iter(dtypes)).startswith("float") \
            else next(iter(dtypes))
    dtype = np.dtype(dtype)
    if nodata is None:
        nds = {s.nodata for s in layout.swings}
        nd = nds.pop() if len(nds) == 1 else None
        nodata = nd if nd is not None else (float("nan") if dtype.kind == "f" else 0)
    return dtype, nodata


def _description(layout: Layout) -> str:
    """The mosaic's band description: the swings' first band's, when they agree, else
    ``band 1``."""
    import rasterio
    names = set()
    for s in layout.swings[:8]:
        with rasterio.open(s.path) as ds:
            names.add(ds.descriptions[0] or "")
    name = names.pop() if len(names) == 1 else ""
    return name or "band 1"


def overview(src_path, max_side: int = 1024):
    """The mosaic read from its COG overviews at most ``max_side`` pixels a side: (float
    values with NaN for no data, decimation factor)."""
    import rasterio
    with rasterio.open(src_path) as ds:
        f = max(1.0, max(ds.width, ds.height) / max_side)
        shape = (max(1, int(ds.height / f)), max(1, int(ds.width / f)))
        a = ds.read(1, out_shape=shape, masked=True).astype(np.float32)
    return a.filled(np.nan), f


def level_overview(level, nodata, shape, max_side: int = 1024):
    """What :func:`overview` reads from the COG of ``shape`` (rows, cols), taken from its
    first overview level ``level`` (the array the COG's level is written from) when that is
    the level :func:`overview` reads whole (the same size); else None."""
    H, W = shape
    f = max(1.0, max(W, H) / max_side)
    if f == 1.0 or (max(1, int(H / f)), max(1, int(W / f))) != level.shape:
        return None
    a = level.astype(np.float32)
    if nodata is not None and not np.isnan(nodata):
        a[level == nodata] = np.nan
    return a, f


def stretch(data):
    """(2, rows, cols) uint8 grey (2-98 % stretch, 1..255) and alpha (255 where valid)."""
    ok = np.isfinite(data)
    img = np.zeros(data.shape, np.uint8)
    if ok.any():
        lo, hi = np.percentile(data[ok], [2, 98])
        v = np.clip((np.nan_to_num(data) - lo) / max(hi - lo, 1e-12) * 254 + 1, 1, 255)
        img = np.where(ok, v, 0).astype(np.uint8)
    return np.stack([img, np.where(ok, 255, 0).astype(np.uint8)])


def quicklook(src_path, png_path, max_side: int = 1024, grey=None, png=None) -> None:
    """An 8-bit grey + alpha PNG preview (2-98 % stretch) read from the COG's overviews
    (``grey``: that preview already made by :func:`stretch` of :func:`overview`; ``png``:
    it already encoded)."""
    from swathflow.io import png_bytes
    if png is None:
        png = png_bytes(stretch(overview(src_path, max_side)[0]) if grey is None else grey)
    with atomic_path(os.fspath(png_path), suffix=".png") as tmp, open(tmp, "wb") as fh:
        fh.write(png)
