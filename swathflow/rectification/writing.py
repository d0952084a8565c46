"""Streaming Cloud-Optimized GeoTIFF writing: memory bounded by the tiles in flight.

Each output is streamed window by window into a tiled GeoTIFF beside its target (the
``.part``), with the COG's own codec and predictor: each tile is compressed once, by
:mod:`.tilecodec` (ISA-L) where nothing reads the ``.part``'s pixels back (GDAL then
writes its tags alone), else by GDAL as it arrives. The overviews are reduced here, each
level from the one above (:func:`.halve.halve`, nodata-aware): the first in memory as
the tiles arrive (:class:`_Level1`), or, past :data:`LEVEL1_RAM_BYTES`, block by block
from the ``.part`` (:func:`build_overviews`). Then :mod:`.tifflayout` copies every
compressed tile, unchanged, into the layout of GDAL's COG driver, atomically. (Copying
through the COG driver decompressed and compressed every tile again: 0.5-0.7 CPU-s per 21
Mpx; its overview step re-read a pixel-interleaved source once per band: 135 CPU-s for a
1400 x 1354 x 100-band output.) Multi-band outputs are band-interleaved (a band's tile is
contiguous) with their band descriptions and wavelengths. Integer outputs without a
nodata value carry an internal mask band (the last plane of the array, 0 / 255): those
go through GDAL's COG driver, which builds the mask's overviews too.
"""
from __future__ import annotations

import contextlib
import io
import math
import os
import warnings
from collections.abc import Mapping
from typing import TYPE_CHECKING

import numpy as np
from swathflow.io import atomic_path, scratch_path
from swathflow.rectification.halve import halve as _halve
from swathflow.rectification.store import store_here
from swathflow.rectification.tilecodec import TileSink, can_encode, with_tiles

if TYPE_CHECKING:   # an annotation only: the mosaic's writer does not import pyproj for it
    from swathflow.geometry.grid import Grid

#: GDAL block cache while writing (MB): GDAL's default is 5 % of the machine's memory
GDAL_CACHE_MB = 256
#: the streamed .part file is uncompressed below this size (bytes), else deflate level 1
PART_RAW_BYTES = 2 ** 30
#: deflate level of the COG: with the predictor, level 1 measured 20 % faster than 6 and
#: no larger (2.61 vs 2.65 MB on a 2.5 Mpx uint16 swing)
DEFLATE_LEVEL = 1
#: ZSTD level of the COG (``--compress zstd``): with the predictor, level 1 compressed the
#: demo's uint16 swings 1.6x faster than DEFLATE level 1, 4 % larger
ZSTD_LEVEL = 1
#: the codecs a COG may be written with (``--compress``): DEFLATE opens in every GDAL
#: and every TIFF reader; ZSTD needs GDAL 2.3 or later built with libzstd (rasterio's and
#: GDAL's usual builds are)
CODECS = ("deflate", "zstd")


class _WindowWriter:
    """A ``__setitem__`` target for :func:`.store.store_here` writing windows of a rasterio
    dataset (2-D: band 1; 3-D: bands); with ``valid`` (a (rows, cols) uint8 array) the
    written windows' valid mask filled in as it goes (:func:`valid_mask`)."""

    def __init__(self, dst, bands: int | None = None, mask: bool = False, level1=None,
                 valid=None, nodata=None, sink=None):
        self.dst = dst
        self.bands = bands
        self.mask = mask
        self.level1 = level1        # the first overview level, reduced tile by tile
        self.valid, self.nodata = valid, nodata
        self.sink = sink            # a TileSink: the tiles compressed here, not by GDAL

    def __setitem__(self, key, value):
        from rasterio.windows import Window
        if self.level1 is not None:
            self.level1.add(key[-2:], np.asarray(value))
        if self.valid is not None:
            self.valid[key[-2:]] = valid_mask(np.asarray(value), self.nodata, self.mask)
        if self.sink is not None:
            rs, cs = key[-2:]
            self.sink.put(rs.start, cs.start, np.asarray(value))
            return
        if self.mask:                       # last plane: the mask band (0 / 255)
            _, rs, cs = key
            win = Window(cs.start, rs.start, cs.stop - cs.start, rs.stop - rs.start)
            value = np.asarray(value)
            self.dst.write(value[:-1], window=win)
            self.dst.write_mask(value[-1].astype(np.uint8), window=win)
            return
        if self.bands is None:
            rs, cs = key
            self.dst.write(np.asarray(value), 1, window=Window(cs.start, rs.start,
                                                              cs.stop - cs.start,
                                                              rs.stop - rs.start))
        else:
            _, rs, cs = key
            self.dst.write(np.asarray(value), window=Window(cs.start, rs.start,
                                                            cs.stop - cs.start,
                                                            rs.stop - rs.start))


def valid_mask(value, nodata, mask_plane: bool = False) -> np.ndarray:
    """The valid mask (uint8, 255 valid, 0 not) of a window ``value`` (rows, cols) or
    (bands, rows, cols) as written, as rasterio's ``dataset_mask`` reads it back from the
    file: with ``mask_plane`` the last plane (the mask band); else valid where any band is
    not ``nodata`` (not NaN for a NaN nodata); without nodata, everywhere."""
    if mask_plane:
        return np.where(value[-1] > 0, np.uint8(255), np.uint8(0))
    planes = value if value.ndim == 3 else value[None]
    if nodata is None:
        return np.full(planes.shape[1:], 255, np.uint8)
    if isinstance(nodata, float) and math.isnan(nodata):
        ok = ~np.isnan(planes).all(axis=0)
    else:
        ok = (planes != _as_type(nodata, planes.dtype)).any(axis=0)
    return ok.view(np.uint8) * np.uint8(255)


def _as_type(value, dtype):
    """``value`` in ``dtype`` where it is exactly one of its values (the comparison then
    stays in the data's type), else as it is (numpy compares by value)."""
    try:
        v = dtype.type(value)
    except (OverflowError, ValueError):
        return value
    return v if float(v) == float(value) else value


def _band_metadata(dst, infos) -> None:
    """Band descriptions, wavelengths (ENVI-style items, and GDAL's IMAGERY domain
    CENTRAL_WAVELENGTH_UM / FWHM_UM where the unit is known) on an open dataset."""
    from swathflow.rectification.rawimage import _UNITS_NM
    for i, b in enumerate(infos, start=1):
        if b.description:
            dst.set_band_description(i, b.description)
        dst.update_tags(i, **b.tags())
        um = _UNITS_NM.get((b.units or "").lower().replace("µ", "u"))
        if b.wavelength is not None and um:
            imagery = {"CENTRAL_WAVELENGTH_UM": repr(b.wavelength * um / 1e3)}
            if b.fwhm is not None:
                imagery["FWHM_UM"] = repr(b.fwhm * um / 1e3)
            dst.update_tags(i, ns="IMAGERY", **imagery)


def write_cog(path, arrays, grid: Grid | None, nodata=None, tags: Mapping | None = None,
              blocksize: int = 512, dtype=None, compress: str = "deflate",
              overview_resampling: str = "average", scheduler=None) -> None:
    """Compute a dask/numpy array (2-D, or 3-D bands) and write it as a Cloud-Optimized
    GeoTIFF atomically, window by window. See :func:`write_cogs`."""
    write_cogs([{"path": path, "array": arrays, "grid": grid, "nodata": nodata, "tags": tags,
                     "dtype": dtype}], blocksize, compress, overview_resampling, scheduler)


def _part_profile(o, shape, bands, dtype, blocksize, compress) -> dict:
    """The rasterio profile of an output's streamed .part GeoTIFF: compressed as the COG
    (:func:`_compression`); with a mask band (read once by GDAL's COG driver)
    uncompressed unless large."""
    from swathflow.formats.raster import _crs
    rows, cols = shape[-2:]
    count = (bands or 1) - (1 if o.get("mask") else 0)
    small = rows * cols * (bands or 1) * dtype.itemsize < PART_RAW_BYTES
    # band-interleaved: a band's block is one contiguous read for the overviews, and its
    # compressed tiles are the COG's (a pixel-interleaved .part measured twice the COG
    # driver's copy CPU at 100 bands)
    profile = {"driver": "GTiff", "width": cols, "height": rows, "count": count,
               "dtype": dtype.name, "tiled": True, "blockxsize": blocksize,
               "blockysize": blocksize, "compress": "none" if small else compress,
               "BIGTIFF": "IF_SAFER", "interleave": "band"}
    if not o.get("mask"):           # laid out by tifflayout, which fills left-out tiles
        profile.update(_compression(compress, dtype), sparse_ok=True)
    elif not small and compress == "deflate":
        profile["zlevel"] = 1
    if o.get("grid") is not None:
        profile.update(crs=_crs(o["grid"].crs), transform=o["grid"].transform)
    if o.get("nodata") is not None:
        profile["nodata"] = o["nodata"]
    return profile


#: the first overview level is reduced in memory, tile by tile as the tiles arrive, when
#: it holds at most this many bytes (a quarter of the output); larger outputs build their
#: overviews from the streamed ``.part`` (:func:`build_overviews`)
LEVEL1_RAM_BYTES = 256 << 20


class _Level1:
    """The first overview level of an output (``(bands, ceil(rows / 2), ceil(cols / 2))``),
    filled by :func:`.halve.halve` from each full-resolution tile as it is written (tiles start
    on even rows and columns)."""

    def __init__(self, bands, rows, cols, dtype, nodata, resampling):
        self.array = np.empty((bands, -(-rows // 2), -(-cols // 2)), dtype)
        self.fill, self.use_nd = _fill(dtype, nodata)
        self.average = resampling.lower() == "average"
        self.is_int = dtype.kind in "ui"

    def add(self, key, value):
        rs, cs = key
        v = value if value.ndim == 3 else value[None]
        r, c = rs.start // 2, cs.start // 2
        _halve(v, self.fill, self.use_nd, self.average, self.is_int, self.array, r, c)


def _fill(dtype, nodata):
    """(value of an overview pixel without valid data, whether ``nodata`` is a number)."""
    use_nd = nodata is not None and not math.isnan(nodata)
    fill = nodata if nodata is not None else (np.nan if dtype.kind == "f" else 0)
    return float(fill), use_nd


def _level1_here(o, arr, blocksize, overview_resampling) -> bool:
    """Whether an output's first overview level is reduced in memory as its tiles arrive
    (:class:`_Level1`): no mask band, every tile starting on an even row and column, and
    the level within :data:`LEVEL1_RAM_BYTES`."""
    if o.get("mask") or overview_resampling.lower() not in ("average", "nearest"):
        return False
    rows, cols = arr.shape[-2:]
    if not overview_factors(rows, cols, blocksize):
        return False
    for chunks in arr.chunks[-2:]:
        if any(c % 2 for c in chunks[:-1]):
            return False
    nb = arr.shape[0] if arr.ndim == 3 else 1
    return nb * -(-rows // 2) * -(-cols // 2) * arr.dtype.itemsize <= LEVEL1_RAM_BYTES


#: the GTiff creation options :func:`_compression` sets
_CODEC_OPTIONS = ("compress", "zlevel", "zstd_level", "predictor")


def _compression(compress: str, dtype) -> dict:
    """GTiff creation options of the COG's tiles: DEFLATE at :data:`DEFLATE_LEVEL` or
    ZSTD at :data:`ZSTD_LEVEL`, with the predictor (horizontal differencing for integers,
    the floating-point one for floats, as the COG driver's ``PREDICTOR=YES``); other
    codecs at their defaults."""
    pred = 3 if np.dtype(dtype).kind == "f" else 2
    if compress.lower() == "deflate":
        return {"compress": "deflate", "zlevel": DEFLATE_LEVEL, "predictor": pred}
    if compress.lower() == "zstd":
        return {"compress": "zstd", "zstd_level": ZSTD_LEVEL, "predictor": pred}
    return {"compress": compress}


def write_cogs(outputs, blocksize: int = 512, compress: str = "deflate",
               overview_resampling: str = "average", scheduler=None) -> None:
    """Write several rasters computed in ONE dask graph (shared tiles computed once).

    Each output is a dict: ``path``, ``array`` (dask or numpy, 2-D or bands x rows x cols),
    ``grid`` (None: ungeoreferenced, raw geometry), ``nodata``, ``tags``, ``dtype``, and
    optionally ``valid``, a (rows, cols) uint8 array filled with the written data's valid
    mask (:func:`valid_mask`) as the windows are written. Each
    is streamed into a tiled GeoTIFF beside its target (memory bounded by the tiles in
    flight), then laid out as a COG with internal overviews, atomically.

    GDAL compresses each tile once, as it is streamed (the ``.part`` holds the COG's
    compressed tiles); the overviews are reduced here (:class:`_Level1` in memory as the
    tiles arrive, or :func:`build_overviews` from the ``.part`` for outputs whose first
    level would not fit in :data:`LEVEL1_RAM_BYTES`) and compressed by GDAL too; then
    :mod:`.tifflayout` copies every compressed tile into the COG layout
    (:func:`_layout_cog`). Outputs with a mask band go through GDAL's COG driver
    (:func:`_to_cog`), which writes the mask's overviews as well."""
    import dask.array as da
    import rasterio
    with contextlib.ExitStack() as stack:
        sources, targets, parts = [], [], []
        for o in outputs:
            arr = o["array"]
            if not hasattr(arr, "chunks"):
                # name=False: not hashed (sha1 of every pixel: 3 ns/px, a sixth of the write)
                arr = da.from_array(np.asarray(arr), chunks=blocksize, name=False)
            dtype = np.dtype(o.get("dtype") or arr.dtype)
            if dtype != arr.dtype:
                arr = arr.astype(dtype)
            if arr.ndim == 3 and len(arr.chunks[0]) > 1:
                arr = arr.rechunk({0: -1})         # a window is written with all its bands
            bands = arr.shape[0] if arr.ndim == 3 else None
            if bands == 1 and not o.get("mask"):
                arr, bands = arr[0], None
            level1 = None
            profile = _part_profile(o, arr.shape, bands, dtype, blocksize, compress)
            if _level1_here(o, arr, blocksize, overview_resampling):
                level1 = _Level1(bands or 1, *arr.shape[-2:], dtype, o.get("nodata"),
                                 overview_resampling)
            final = stack.enter_context(atomic_path(o["path"], suffix=".tif"))
            in_memory = _part_in_memory(o, arr, level1, blocksize)
            part = stack.enter_context(rasterio.MemoryFile() if in_memory
                                       else scratch_path(os.fspath(o["path"]), "part.tif"))
            with warnings.catch_warnings(), rasterio.Env(GDAL_TIFF_INTERNAL_MASK=True):
                warnings.simplefilter("ignore", rasterio.errors.NotGeoreferencedWarning)
                dst = stack.enter_context(part.open(**profile) if hasattr(part, "open")
                                          else rasterio.open(part, "w", **profile))
            if o.get("tags"):
                dst.update_tags(**{k: str(v) for k, v in o["tags"].items()})
            _band_metadata(dst, o.get("bands") or ())
            sink = tile_sink(stack, o["path"], profile, arr.shape,
                             not o.get("mask") and _on_tile_grid(arr, blocksize), level1,
                             o.get("nodata"), in_memory)
            sources.append(arr)
            targets.append(_WindowWriter(dst, bands, bool(o.get("mask")), level1,
                                         o.get("valid"), o.get("nodata"), sink))
            parts.append((dst, part, final, o["path"], level1, profile, sink))
        with rasterio.Env(GDAL_CACHEMAX=GDAL_CACHE_MB, GDAL_TIFF_INTERNAL_MASK=True):
            store_here(sources, targets, scheduler)
        for (dst, part, final, path, level1, profile, sink), o in zip(parts, outputs):
            dst.close()
            if o.get("mask"):
                _to_cog(part, final, blocksize, compress, overview_resampling)
            else:
                _layout_cog(part, final, os.fspath(path), level1, profile, blocksize,
                            overview_resampling, sink)


def _on_tile_grid(arr, blocksize: int) -> bool:
    """Whether every block of the dask array ``arr`` starts on the tile grid."""
    return not any(c % blocksize for chunks in arr.chunks[-2:] for c in chunks[:-1])


def tile_sink(stack, target, profile: dict, shape, aligned: bool, level1, nodata,
              in_memory: bool = False) -> TileSink | None:
    """Where an output's tiles are compressed here (:mod:`.tilecodec`, ISA-L) rather than
    by GDAL, their :class:`~.tilecodec.TileSink` (entered on ``stack``): the windows
    written are ``aligned`` on the tile grid, the ``.part``'s GTiff creation options
    ``profile`` have a codec :func:`~.tilecodec.can_encode` takes, and nothing reads the
    ``.part``'s pixels back (the overviews reduced in memory, ``level1``, or none). In
    memory with ``in_memory``, else in a scratch file beside ``target``. None: GDAL
    compresses the tiles (``shape``: (rows, cols) or (bands, rows, cols))."""
    blocksize = profile["blockxsize"]
    if not aligned or not can_encode(profile, profile["dtype"]) or (
            level1 is None and overview_factors(*shape[-2:], blocksize)):
        return None
    f = io.BytesIO() if in_memory else stack.enter_context(
        open(stack.enter_context(scratch_path(os.fspath(target), "tiles")), "w+b"))
    return TileSink(f, shape[0] if len(shape) == 3 else 1, *shape[-2:], blocksize,
                    profile.get("predictor"), nodata)


#: an output's ``.part`` is a GeoTIFF in memory (no file made, renamed, read back and
#: removed: 2 of 9 ms of a survey swing's write) when its pixels hold at most this many bytes
PART_RAM_BYTES = 64 << 20


def _part_in_memory(o, arr, level1, blocksize) -> bool:
    """Whether an output's ``.part`` is kept in memory: no mask band (GDAL's COG driver
    reads it from disk), at most :data:`PART_RAM_BYTES`, and any overviews reduced as the
    tiles arrive (:class:`_Level1`: :func:`build_overviews` never reads it)."""
    if o.get("mask") or arr.nbytes > PART_RAM_BYTES:
        return False
    return level1 is not None or not overview_factors(*arr.shape[-2:], blocksize)


def overview_factors(height: int, width: int, blocksize: int) -> list[int]:
    """The COG driver's default overview levels (GDAL 3.10): halve while the last level,
    counted as ``size // factor``, exceeds one block (1400 x 1354 with 512 blocks: factors
    2 and 4; 8200 x 2600: 2 to 16). The levels themselves are ``ceil(size / factor)``
    pixels (gdaladdo's sizes), so each of their pixels covers whole pixels above it."""
    f, out = 1, []
    while max(height // f, width // f) > blocksize:
        f *= 2
        out.append(f)
    return out


def build_overviews(part: str, paths: list[str], blocksize: int, resampling: str,
                    compression: Mapping | None = None) -> None:
    """Write the overview levels of the tiled GeoTIFF ``part`` into ``paths`` (factor 2,
    4, ...: each level from the one above it), block by block: every output block of
    ``blocksize`` pixels is reduced from the four blocks above it (``blocksize`` even),
    one at a time with all their bands, so memory is bounded by two blocks (and GDAL's
    cache) and each source block is read once."""
    import rasterio
    from rasterio.windows import Window
    average = resampling.lower() == "average"
    src_path = part
    for path in paths:
        with rasterio.open(src_path) as src:
            profile = src.profile
            h, w = -(-src.height // 2), -(-src.width // 2)
            for k in _CODEC_OPTIONS:
                profile.pop(k, None)
            profile.update(height=h, width=w, tiled=True, blockxsize=blocksize,
                           blockysize=blocksize, BIGTIFF="IF_SAFER", sparse_ok=True,
                           **(compression or {"compress": "none"}))
            profile["transform"] = src.transform @ src.transform.scale(src.width / w,
                                                                     src.height / h)
            dt = np.dtype(src.dtypes[0])
            fill, use_nd = _fill(dt, src.nodata)
            with warnings.catch_warnings(), rasterio.open(path, "w", **profile) as dst:
                warnings.simplefilter("ignore", rasterio.errors.NotGeoreferencedWarning)
                for r0 in range(0, h, blocksize):
                    for c0 in range(0, w, blocksize):
                        nr, nc = min(blocksize, h - r0), min(blocksize, w - c0)
                        out = np.empty((src.count, nr, nc), dt)
                        for sr in range(2 * r0, min(2 * (r0 + nr), src.height), blocksize):
                            for sc in range(2 * c0, min(2 * (c0 + nc), src.width), blocksize):
                                block = src.read(window=Window(
                                    sc, sr, min(blocksize, src.width - sc),
                                    min(blocksize, src.height - sr)))
                                i, j = (sr - 2 * r0) // 2, (sc - 2 * c0) // 2
                                _halve(block, fill, use_nd, average, dt.kind in "ui",
                                       out, i, j)
                        dst.write(out, window=Window(c0, r0, nc, nr))
        src_path = path


def _layout_cog(part, final: str, target: str, level1: _Level1 | None, profile: dict,
                blocksize: int, resampling: str, sink=None) -> None:
    """Write the COG ``final`` from the compressed ``.part`` (a path, or a MemoryFile when
    ``level1`` is given or there are no overviews) and its overviews, each level
    compressed by GDAL into a tiled GeoTIFF: from the first level in memory (``level1``:
    the next levels reduced from it, each in a GeoTIFF in memory), or else built from the
    ``.part`` by :func:`build_overviews` into scratch files beside ``target``. Then
    :func:`.tifflayout.write_cog_layout` copies every level's compressed tiles. With
    ``sink`` (a :class:`.tilecodec.TileSink`) the full resolution's tiles are the sink's,
    the ``.part`` giving its tags only; the levels in memory are then compressed here too."""
    from swathflow.rectification.tifflayout import nodata_tiles, read_first_ifd, write_cog_layout
    rows, cols = profile["height"], profile["width"]
    n_levels = len(overview_factors(rows, cols, blocksize))
    compression = {k: profile[k] for k in _CODEC_OPTIONS if k in profile}
    with contextlib.ExitStack() as stack:
        if level1 is not None:
            overviews = _levels_in_memory(level1, n_levels, profile, compression, blocksize,
                                          here=sink is not None)
        else:
            paths = [stack.enter_context(scratch_path(target, f"ovr{k}.tif"))
                     for k in range(n_levels)]
            with _cache_env():
                build_overviews(part, paths, blocksize, resampling, compression)
            files = [stack.enter_context(open(p, "rb")) for p in paths]
            overviews = [(read_first_ifd(f), f) for f in files]
        with _opened(part) as src, open(final, "wb") as out:
            first = read_first_ifd(src)
            levels = [with_tiles(first, sink) if sink is not None else (first, src)]
            levels += overviews
            left_out = any((i.counts == 0).any() for i, _ in levels)
            empty = nodata_tiles(profile["dtype"], profile.get("nodata"), compression,
                                 blocksize) if left_out else None
            write_cog_layout(out, levels, empty)


def _opened(part):
    """``part`` (a path, or a rasterio MemoryFile: a binary file object) open for reading."""
    if isinstance(part, (str, os.PathLike)):
        return open(part, "rb")
    part.seek(0)
    return contextlib.nullcontext(part)


def _cache_env():
    """GDAL's block cache while writing: :data:`GDAL_CACHE_MB`, not 5 % of the machine."""
    import rasterio
    return rasterio.Env(GDAL_CACHEMAX=GDAL_CACHE_MB)


def _levels_in_memory(level1: _Level1, n_levels: int, profile: dict, compression: dict,
                      blocksize: int, here: bool = False) -> list:
    """The overview levels from the first one in memory, each reduced from the one above
    and compressed by GDAL into a tiled GeoTIFF in memory: (IFD, binary file object)
    pairs. With ``here`` the tiles are compressed by :mod:`.tilecodec` instead (GDAL
    writes the level's tags alone)."""
    from rasterio.errors import NotGeoreferencedWarning
    from rasterio.io import MemoryFile

    from swathflow.rectification.tifflayout import read_first_ifd
    ov_profile = {k: profile[k] for k in ("count", "dtype", "nodata", "interleave")
                  if k in profile}
    ov_profile.update(driver="GTiff", tiled=True, blockxsize=blocksize, blockysize=blocksize,
                      sparse_ok=True, **compression)
    lv = level1.array
    levels = []
    for k in range(n_levels):
        if k:
            nxt = np.empty((lv.shape[0], -(-lv.shape[1] // 2), -(-lv.shape[2] // 2)), lv.dtype)
            _halve(lv, level1.fill, level1.use_nd, level1.average, level1.is_int, nxt)
            lv = nxt
        with MemoryFile() as mem, warnings.catch_warnings():
            warnings.simplefilter("ignore", NotGeoreferencedWarning)
            with mem.open(width=lv.shape[2], height=lv.shape[1], **ov_profile) as dst:
                if not here:
                    dst.write(lv)
            f = io.BytesIO(mem.read())
        if here:
            sink = TileSink(io.BytesIO(), *lv.shape, blocksize, compression.get("predictor"),
                            profile.get("nodata"))
            sink.put(0, 0, lv)
            levels.append(with_tiles(read_first_ifd(f), sink))
        else:
            levels.append((read_first_ifd(f), f))
    return levels


def _to_cog(part: str, final: str, blocksize: int, compress: str,
            overview_resampling: str) -> None:
    """Lay ``part`` (an output with a mask band) out as a COG at ``final`` with GDAL's COG
    driver, which builds the overviews of the bands and of the mask."""
    import rasterio
    from rasterio.shutil import copy as rio_copy
    levels = {"deflate": DEFLATE_LEVEL, "zstd": ZSTD_LEVEL}
    pred = ({"PREDICTOR": "YES", "LEVEL": levels[compress.lower()]}
            if compress.lower() in levels else {})
    opts = dict(driver="COG", COMPRESS=compress.upper(), BLOCKSIZE=blocksize,
                OVERVIEW_RESAMPLING=overview_resampling.upper(), BIGTIFF="IF_SAFER", **pred)
    with warnings.catch_warnings(), _cache_env():
        warnings.simplefilter("ignore", rasterio.errors.NotGeoreferencedWarning)
        rio_copy(part, final, **opts)
