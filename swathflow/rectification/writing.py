"""Cloud-Optimized GeoTIFFs written by GDAL's COG driver (through rasterio), in bounded memory.

Each output's blocks are computed on the active Dask scheduler and written window by window
(:func:`.store.store_here`) into a tiled GeoTIFF beside the target, the ``.part`` (in
memory when small), with the product's tags and band metadata. GDAL's COG driver then
copies the ``.part`` into the COG (``rasterio.shutil.copy(..., driver="COG")``): it builds
the overviews (:data:`OVERVIEW_RESAMPLING` by default, nodata-aware), compresses every tile
(DEFLATE or ZSTD at level 1 with the predictor) on :data:`NUM_THREADS` and lays the file
out. The COG is written under a temporary name beside the target and renamed into place
(:func:`swathflow.io.atomic_path`): a failed or interrupted write leaves nothing behind.
Integer outputs without a nodata value carry an internal mask band (the last plane of the
array, 0 / 255), whose overviews GDAL builds too.

Every COG carries the product's tags (values that are not strings as JSON), the software
and its version (``software``, and the standard ``TIFFTAG_SOFTWARE``), the time it was
written (``TIFFTAG_DATETIME``, UTC) and a description for every band.
"""
from __future__ import annotations

import contextlib
import datetime
import json
import math
import os
import warnings
from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING

import numpy as np
from swathflow.io import atomic_path, scratch_path
from swathflow.rectification.store import store_here

if TYPE_CHECKING:   # an annotation only: the mosaic's writer does not import pyproj for it
    from swathflow.geometry.grid import Grid

#: GDAL block cache while writing (MB): GDAL's default is 5 % of the machine's memory
GDAL_CACHE_MB = 256
#: the streamed GeoTIFF is uncompressed below this size (bytes), else ZSTD level 1 without
#: predictor (cheap to write and read back). On a 100 x 1024 x 2048 uint16 cube the writer
#: took 13.2 CPU-s with it uncompressed, 18.1 in ZSTD-1, 21.3 in DEFLATE-1 with predictor
PART_RAW_BYTES = 8 << 30
#: an output's ``.part`` is a GeoTIFF in memory (no file made, read back and removed) when
#: its pixels hold at most this many bytes
PART_RAM_BYTES = 64 << 20
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
#: the COG driver's NUM_THREADS: tiles and overviews compressed on every core
NUM_THREADS = "ALL_CPUS"
#: the COG driver's BIGTIFF: a BigTIFF when the file could pass 4 GB
BIGTIFF = "IF_SAFER"


class _WindowWriter:
    """A ``__setitem__`` target for :func:`.store.store_here` writing windows of a rasterio
    dataset (2-D: band 1; 3-D: bands; with ``mask``, the last plane as the mask band);
    with ``valid`` (a (rows, cols) uint8 array) the written windows' valid mask filled in
    as it goes (:func:`valid_mask`)."""

    def __init__(self, dst, mask: bool = False, valid=None, nodata=None):
        self.dst = dst
        self.mask = mask
        self.valid, self.nodata = valid, nodata

    def __setitem__(self, key, value):
        from rasterio.windows import Window
        value = np.asarray(value)
        rs, cs = key[-2:]
        if self.valid is not None:
            self.valid[rs, cs] = valid_mask(value, self.nodata, self.mask)
        win = Window(cs.start, rs.start, cs.stop - cs.start, rs.stop - rs.start)
        if self.mask:                       # last plane: the mask band (0 / 255)
            self.dst.write(value[:-1], window=win)
            self.dst.write_mask(value[-1].astype(np.uint8), window=win)
        elif value.ndim == 2:
            self.dst.write(value, 1, window=win)
        else:
            self.dst.write(value, window=win)


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


def tag_text(value) -> str:
    """A tag's value as GDAL stores it: a string as it is, anything else as JSON (numbers
    as numbers, mappings and lists as JSON objects and arrays; numpy scalars by value)."""
    if isinstance(value, str):
        return value
    if isinstance(value, np.generic):
        value = value.item()
    return json.dumps(value, default=str)


def product_tags(tags: Mapping | None) -> dict:
    """The dataset tags of a product: ``tags`` (values by :func:`tag_text`), the software
    and its version (``software`` unless given, and TIFF's ``TIFFTAG_SOFTWARE``) and the
    time of writing (TIFF's ``TIFFTAG_DATETIME``, ``YYYY:MM:DD HH:MM:SS``, UTC)."""
    from swathflow._version import __version__
    out = {str(k): tag_text(v) for k, v in (tags or {}).items()}
    software = f"swathflow {__version__}"
    out.setdefault("software", software)
    now = datetime.datetime.now(datetime.timezone.utc)
    out.update(TIFFTAG_SOFTWARE=software, TIFFTAG_DATETIME=now.strftime("%Y:%m:%d %H:%M:%S"))
    return out


def band_descriptions(count: int, infos=(), given: Sequence[str] | None = None) -> list[str]:
    """A description for each of ``count`` bands: ``given`` when it names them all, else
    each band's :class:`~.rawimage.BandInfo` description, else ``band <n>`` (the raw
    file's band number where known)."""
    if given is not None and len(given) == count and all(given):
        return [str(d) for d in given]
    infos = list(infos or ())
    out = []
    for i in range(count):
        b = infos[i] if i < len(infos) else None
        out.append(b.description if b is not None and b.description
                   else f"band {b.index if b is not None else i + 1}")
    return out


def _band_metadata(dst, infos, descriptions: Sequence[str]) -> None:
    """Band descriptions, wavelengths (ENVI-style items, and GDAL's IMAGERY domain
    CENTRAL_WAVELENGTH_UM / FWHM_UM where the unit is known) on an open dataset."""
    from swathflow.rectification.rawimage import _UNITS_NM
    for i, d in enumerate(descriptions, start=1):
        dst.set_band_description(i, d)
    for i, b in enumerate(infos or (), start=1):
        if i > len(descriptions):
            break
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


def part_profile(shape, count: int, dtype, blocksize: int, compress: str, grid=None,
                 nodata=None) -> dict:
    """The rasterio profile of an output's streamed ``.part`` GeoTIFF (``shape``: (rows,
    cols); ``count`` bands besides any mask band): tiled as the COG, band-interleaved (a
    band's block is one contiguous read when GDAL builds the overviews), uncompressed
    unless past :data:`PART_RAW_BYTES`."""
    from swathflow.formats.raster import _crs
    rows, cols = shape
    dtype = np.dtype(dtype)
    small = rows * cols * count * dtype.itemsize < PART_RAW_BYTES
    profile = {"driver": "GTiff", "width": cols, "height": rows, "count": count,
               "dtype": dtype.name, "tiled": True, "blockxsize": blocksize,
               "blockysize": blocksize, "BIGTIFF": "IF_SAFER", "interleave": "band"}
    profile.update({"compress": "none"} if small else {"compress": "zstd", "zstd_level": 1})
    if grid is not None:
        profile.update(crs=_crs(grid.crs), transform=grid.transform)
    if nodata is not None:
        profile["nodata"] = nodata
    return profile


def compression(compress: str, dtype) -> dict:
    """GTiff creation options of tiles compressed as the COG's: DEFLATE at
    :data:`DEFLATE_LEVEL` or ZSTD at :data:`ZSTD_LEVEL`, with the predictor (horizontal
    differencing for integers, the floating-point one for floats, as the COG driver's
    ``PREDICTOR=YES``); other codecs at their defaults."""
    pred = 3 if np.dtype(dtype).kind == "f" else 2
    if compress.lower() == "deflate":
        return {"compress": "deflate", "zlevel": DEFLATE_LEVEL, "predictor": pred}
    if compress.lower() == "zstd":
        return {"compress": "zstd", "zstd_level": ZSTD_LEVEL, "predictor": pred}
    return {"compress": compress}


def cog_options(blocksize: int = 512, compress: str = "deflate",
                overview_resampling: str = "average") -> dict:
    """The creation options of GDAL's COG driver for swathflow's COGs."""
    levels = {"deflate": DEFLATE_LEVEL, "zstd": ZSTD_LEVEL}
    opts = dict(driver="COG", COMPRESS=compress.upper(), BLOCKSIZE=blocksize,
                OVERVIEW_RESAMPLING=overview_resampling.upper(), BIGTIFF=BIGTIFF,
                NUM_THREADS=NUM_THREADS)
    if compress.lower() in levels:
        opts.update(PREDICTOR="YES", LEVEL=levels[compress.lower()])
    return opts


def build_overviews(dst, blocksize: int = 512, overview_resampling: str = "average") -> None:
    """GDAL's overviews (``gdaladdo``: :func:`overview_factors`, each level ``ceil(size /
    factor)`` pixels, nodata-aware, the mask band's too) inside the open tiled GeoTIFF
    ``dst``, computed on :data:`NUM_THREADS`."""
    import rasterio
    from rasterio.enums import Resampling
    factors = overview_factors(dst.height, dst.width, blocksize)
    if factors:
        with rasterio.Env(GDAL_NUM_THREADS=NUM_THREADS):
            dst.build_overviews(factors, Resampling[overview_resampling.lower()])


def copy_to_cog(part, final: str, blocksize: int = 512, compress: str = "deflate",
                overview_resampling: str = "average") -> None:
    """Copy the tiled GeoTIFF ``part`` (a path) with its overviews (:func:`build_overviews`)
    into the COG ``final`` with GDAL's COG driver, every tile compressed once."""
    import rasterio
    from rasterio.shutil import copy as rio_copy
    opts = cog_options(blocksize, compress, overview_resampling)
    with warnings.catch_warnings(), _cache_env():
        warnings.simplefilter("ignore", rasterio.errors.NotGeoreferencedWarning)
        rio_copy(part, final, OVERVIEWS="FORCE_USE_EXISTING", **opts)


def _cache_env():
    """GDAL's block cache while writing: :data:`GDAL_CACHE_MB`, not 5 % of the machine."""
    import rasterio
    return rasterio.Env(GDAL_CACHEMAX=GDAL_CACHE_MB, GDAL_TIFF_INTERNAL_MASK=True)


def _prepared(o, blocksize: int):
    """(dask array, dtype, whether it holds bands) of an output's ``array``."""
    import dask.array as da
    arr = o["array"]
    if not hasattr(arr, "chunks"):
        # name=False: not hashed (sha1 of every pixel: 3 ns/px, a sixth of the write)
        arr = da.from_array(np.asarray(arr), chunks=blocksize, name=False)
    dtype = np.dtype(o.get("dtype") or arr.dtype)
    if dtype != arr.dtype:
        arr = arr.astype(dtype)
    if arr.ndim == 3 and len(arr.chunks[0]) > 1:
        arr = arr.rechunk({0: -1})         # a window is written with all its bands
    if arr.ndim == 3 and arr.shape[0] == 1 and not o.get("mask"):
        arr = arr[0]
    return arr, dtype


def write_cogs(outputs, blocksize: int = 512, compress: str = "deflate",
               overview_resampling: str = "average", scheduler=None) -> None:
    """Write several rasters computed in ONE dask graph (shared tiles computed once).

    Each output is a dict: ``path``, ``array`` (dask or numpy, 2-D or bands x rows x cols),
    ``grid`` (None: ungeoreferenced, raw geometry), ``nodata``, ``tags``, ``dtype``, and
    optionally ``mask`` (the last plane is an internal mask band), ``bands`` (the raw
    bands' :class:`~.rawimage.BandInfo`), ``descriptions`` (one per band) and ``valid``,
    a (rows, cols) uint8 array filled with the written data's valid mask
    (:func:`valid_mask`) as the windows are written. Each is streamed into a tiled
    GeoTIFF beside its target (memory bounded by the blocks in flight), then copied into a
    COG with internal overviews by GDAL's COG driver (:func:`copy_to_cog`), atomically."""
    import rasterio
    with contextlib.ExitStack() as stack:
        sources, targets, parts = [], [], []
        for o in outputs:
            arr, dtype = _prepared(o, blocksize)
            mask = bool(o.get("mask"))
            count = (arr.shape[0] if arr.ndim == 3 else 1) - (1 if mask else 0)
            profile = part_profile(arr.shape[-2:], count, dtype, blocksize, compress,
                                   o.get("grid"), o.get("nodata"))
            final = stack.enter_context(atomic_path(o["path"], suffix=".part.tif"))
            in_memory = not mask and arr.nbytes <= PART_RAM_BYTES
            part = stack.enter_context(rasterio.MemoryFile() if in_memory
                                       else scratch_path(os.fspath(o["path"]), "stream.tif"))
            with warnings.catch_warnings(), rasterio.Env(GDAL_TIFF_INTERNAL_MASK=True):
                warnings.simplefilter("ignore", rasterio.errors.NotGeoreferencedWarning)
                dst = stack.enter_context(part.open(**profile) if in_memory
                                          else rasterio.open(part, "w", **profile))
            dst.update_tags(**product_tags(o.get("tags")))
            infos = o.get("bands") or ()
            _band_metadata(dst, infos, band_descriptions(count, infos, o.get("descriptions")))
            sources.append(arr)
            targets.append(_WindowWriter(dst, mask, o.get("valid"), o.get("nodata")))
            parts.append((dst, part.name if in_memory else part, final))
        with _cache_env():
            store_here(sources, targets, scheduler)
        for dst, part, final in parts:
            with _cache_env():
                build_overviews(dst, blocksize, overview_resampling)
            dst.close()
            copy_to_cog(part, final, blocksize, compress, overview_resampling)


def overview_factors(height: int, width: int, blocksize: int) -> list[int]:
    """The overview levels GDAL builds (as its COG driver by default): halve while the last level,
    counted as ``size // factor``, exceeds one block (1400 x 1354 with 512 blocks: factors
    2 and 4; 8200 x 2600: 2 to 16)."""
    f, out = 1, []
    while max(height // f, width // f) > blocksize:
        f *= 2
        out.append(f)
    return out
