"""Writing the mosaic: tiles blended from the corrected swings over dask threads, streamed
into a tiled GeoTIFF, converted to a COG with overviews; the PNG quicklook."""
from __future__ import annotations

import os
import threading
import time

import numpy as np

from swathflow.io import atomic_path
from swathflow.mosaicking.inputs import Layout, _Handles, read_window

__all__ = ["swing_cache", "render_tile", "write_mosaic", "mosaic_array", "quicklook"]


def swing_cache(layout: Layout, offsets, radiometric, feather: int = 64, handles=None,
                max_bytes: int = 512 * 2 ** 20):
    """A :class:`swathflow.blend.SwingCache` of the swings corrected by ``offsets`` and
    ``radiometric`` (per swing), read through ``handles``."""
    from swathflow.mosaicking.blend import SwingCache, corrected_swing
    handles = handles or _Handles()
    offsets = np.asarray(offsets, float)
    radiometric = np.asarray(radiometric, float)

    def make(k):
        sw = layout.swings[k]
        val, ok = read_window(handles, sw, sw.row, sw.col, sw.row + sw.height,
                              sw.col + sw.width)
        return corrected_swing(val, ok, sw.row, sw.col, offsets[k], radiometric[k], feather)
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


class _Writer:
    """A dask ``store`` target writing windows into an open rasterio dataset."""

    def __init__(self, ds, nodata, dtype):
        self.ds, self.nodata, self.dtype = ds, nodata, np.dtype(dtype)

    def __setitem__(self, key, block):
        from rasterio.windows import Window
        rs, cs = key
        out = block
        if self.dtype.kind in "ui":
            info = np.iinfo(self.dtype)
            bad = ~np.isfinite(out)
            out = np.clip(np.round(np.where(bad, 0, out)), info.min, info.max)
            out = out.astype(self.dtype)
            out[bad] = self.nodata
        else:
            out = out.astype(self.dtype)
            if self.nodata is not None and not np.isnan(self.nodata):
                out[~np.isfinite(out)] = self.nodata
        self.ds.write(out, 1, window=Window(cs.start, rs.start, cs.stop - cs.start,
                                            rs.stop - rs.start))


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


def write_mosaic(layout: Layout, out, offsets, radiometric, feather: int = 64,
                 mode: str = "feather", tile: int = 1024, workers: int | None = None,
                 dtype=None, nodata=None, cog: bool = True, blocksize: int = 512) -> dict:
    """Render the mosaic tile by tile over dask (threads) into ``out`` (a COG with
    overviews when ``cog``), atomically. Memory is bounded by ``workers`` tiles."""
    import dask.array as da
    import rasterio
    from rasterio.shutil import copy as rio_copy
    dtypes = {s.dtype for s in layout.swings}
    if dtype is None:
        dtype = "float32" if len(dtypes) != 1 or next(iter(dtypes)).startswith("float") \
            else next(iter(dtypes))
    dtype = np.dtype(dtype)
    if nodata is None:
        nds = {s.nodata for s in layout.swings}
        nd = nds.pop() if len(nds) == 1 else None
        nodata = nd if nd is not None else (float("nan") if dtype.kind == "f" else 0)
    H, W = layout.shape
    offsets = np.asarray(offsets, float)
    radiometric = np.asarray(radiometric, float)
    arr, blender = mosaic_array(layout, offsets, radiometric, feather, mode, tile)
    profile = dict(driver="GTiff", width=W, height=H, count=1, dtype=dtype.name,
                   crs=layout.crs, transform=layout.transform, nodata=nodata, tiled=True,
                   blockxsize=blocksize, blockysize=blocksize, compress="deflate",
                   BIGTIFF="IF_SAFER")
    t0 = time.perf_counter()
    out = os.fspath(out)
    try:
        with atomic_path(out, suffix=".tif") as final:
            tmp = final + ".stage.tif" if cog else final
            try:
                with rasterio.open(tmp, "w", **profile) as ds:
                    da.store(arr, _Writer(ds, nodata, dtype), lock=threading.Lock(),
                             scheduler="threads", num_workers=workers)
                    ds.update_tags(product="mosaic", blend=mode, software="swathflow")
                t_render = time.perf_counter() - t0
                if cog:
                    with rasterio.Env(GDAL_NUM_THREADS=str(workers or os.cpu_count() or 1)):
                        rio_copy(tmp, final, driver="COG", COMPRESS="DEFLATE",
                                 BLOCKSIZE=blocksize, OVERVIEW_RESAMPLING="AVERAGE",
                                 PREDICTOR="YES", BIGTIFF="IF_SAFER")
            finally:
                if cog and os.path.exists(tmp):
                    os.remove(tmp)
    finally:
        blender.close()
    return {"seconds_render": t_render, "seconds_total": time.perf_counter() - t0,
            "shape": [H, W], "dtype": dtype.name}


def quicklook(src_path, png_path, max_side: int = 1024) -> None:
    """An 8-bit PNG preview (2-98 % stretch) read from the COG's overviews."""
    import rasterio
    with rasterio.open(src_path) as ds:
        f = max(1.0, max(ds.width, ds.height) / max_side)
        shape = (max(1, int(ds.height / f)), max(1, int(ds.width / f)))
        a = ds.read(1, out_shape=shape, masked=True).astype(float)
    data = a.filled(np.nan)
    ok = np.isfinite(data)
    img = np.zeros(shape, np.uint8)
    alpha = np.where(ok, 255, 0).astype(np.uint8)
    if ok.any():
        lo, hi = np.percentile(data[ok], [2, 98])
        img = np.clip((np.nan_to_num(data) - lo) / max(hi - lo, 1e-12) * 254 + 1, 1, 255)
        img = np.where(ok, img, 0).astype(np.uint8)
    import warnings
    with atomic_path(png_path, suffix=".png") as tmp, warnings.catch_warnings():
        warnings.simplefilter("ignore", rasterio.errors.NotGeoreferencedWarning)
        with rasterio.open(tmp, "w", driver="PNG", width=shape[1], height=shape[0], count=2,
                           dtype="uint8") as dst:
            dst.write(img, 1)
            dst.write(alpha, 2)
    aux = png_path + ".aux.xml"
    if os.path.exists(aux):
        os.remove(aux)
