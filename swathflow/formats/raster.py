"""Small raster helpers: GeoTIFF writing with CRS, transform and nodata (atomic), and
reading a raster with its georeferencing. Cloud-Optimized GeoTIFFs have one writer,
:func:`swathflow.rectification.writing.write_cog` (streamed, our own overviews): this layer
sits below it and lays none out itself.

Conventions: ``transform`` is a :class:`affine.Affine` (or its 6 numbers ``a, b, c, d, e, f``)
mapping (col, row) of the pixel's top-left CORNER to map coordinates (rasterio / GDAL).
Arrays are ``(rows, cols)`` or ``(bands, rows, cols)``.
"""
from __future__ import annotations

import os
from dataclasses import dataclass, field

from affine import Affine

import numpy as np

from swathflow.errors import FormatError
from swathflow.io import atomic_path


def _affine(transform):
    if isinstance(transform, Affine):
        return transform
    t = tuple(transform)
    if len(t) == 9:
        t = t[:6]
    if len(t) != 6:
        raise ValueError(f"a transform needs 6 numbers (a, b, c, d, e, f), got {len(t)}")
    return Affine(*t)


def _crs(crs):
    from rasterio.crs import CRS
    if crs is None:
        return None
    if isinstance(crs, CRS):
        return crs
    import pyproj
    return CRS.from_wkt(pyproj.CRS.from_user_input(crs).to_wkt())


def _as_bands(array) -> np.ndarray:
    """A (bands, rows, cols) array of a type GeoTIFF holds."""
    arr = np.asarray(array)
    if arr.ndim == 2:
        arr = arr[None]
    if arr.ndim != 3:
        raise ValueError(f"write_geotiff needs a 2-D or 3-D array, got shape {arr.shape}")
    if arr.dtype == np.float16:
        return arr.astype(np.float32)
    if arr.dtype == bool:
        return arr.astype(np.uint8)
    return arr


def _profile(arr, crs, transform, nodata, compress, blocksize) -> dict:
    count, height, width = arr.shape
    profile = dict(driver="GTiff", width=width, height=height, count=count,
                   dtype=arr.dtype.name, crs=_crs(crs), transform=_affine(transform),
                   compress=compress)
    if nodata is not None:
        profile["nodata"] = nodata
    if compress == "deflate" and arr.dtype.kind in "fui":
        profile["predictor"] = 3 if arr.dtype.kind == "f" else 2
    if height >= blocksize and width >= blocksize:
        profile.update(tiled=True, blockxsize=blocksize, blockysize=blocksize)
    if arr.size * arr.itemsize > 3.5e9:
        profile["BIGTIFF"] = "YES"
    return profile


def write_geotiff(path, array, crs, transform, nodata=None, tags: dict | None = None,
                  compress: str = "deflate", blocksize: int = 256) -> None:
    """Write ``array`` (2-D or bands x rows x cols) as a GeoTIFF, atomically (tiled when it
    spans a block both ways; a Cloud-Optimized GeoTIFF: ``rectification.writing.write_cog``).

    ``crs``: anything pyproj accepts ("EPSG:32633", WKT, a CRS).
    ``tags``: dataset-level metadata (values are stored as strings).
    """
    import rasterio
    arr = _as_bands(array)
    profile = _profile(arr, crs, transform, nodata, compress, blocksize)
    tags = {k: str(v) for k, v in (tags or {}).items()}
    with atomic_path(path, suffix=".tif") as tmp:
        with rasterio.open(tmp, "w", **profile) as dst:
            dst.write(arr)
            if tags:
                dst.update_tags(**tags)


@dataclass(frozen=True, eq=False)
class Raster:
    """A raster read into memory: ``data`` (rows, cols) or (bands, rows, cols)."""

    data: np.ndarray = field(repr=False)
    crs: str | None           # WKT, or None when the file has no CRS
    transform: Affine
    nodata: float | None
    tags: dict
    path: str = ""

    @property
    def shape(self) -> tuple[int, ...]:
        return self.data.shape

    def xy(self, row, col):
        """Map coordinates of (fractional) pixel-centre indices ``row, col``."""
        t = self.transform
        row = np.asarray(row, float) + 0.5
        col = np.asarray(col, float) + 0.5
        return t.c + col * t.a + row * t.b, t.f + col * t.d + row * t.e

    def rowcol(self, x, y):
        """Fractional pixel-centre indices of map coordinates ``x, y``."""
        t = ~self.transform
        x = np.asarray(x, float)
        y = np.asarray(y, float)
        col = t.c + x * t.a + y * t.b - 0.5
        row = t.f + x * t.d + y * t.e - 0.5
        return row, col

    def bounds(self) -> tuple[float, float, float, float]:
        """(xmin, ymin, xmax, ymax) of the raster's outer edges."""
        rows, cols = self.data.shape[-2:]
        xs, ys = self.xy(np.array([-0.5, -0.5, rows - 0.5, rows - 0.5]),
                         np.array([-0.5, cols - 0.5, -0.5, cols - 0.5]))
        return float(xs.min()), float(ys.min()), float(xs.max()), float(ys.max())


def read_raster(path, band: int | None = 1, masked_to_nan: bool = False) -> Raster:
    """Read a raster (GeoTIFF, ENVI, JPEG + world file...) with CRS, transform and nodata.

    ``band``: 1-based band to read as 2-D, or None for all bands (3-D). ``masked_to_nan``:
    return float data with nodata cells as NaN. A JPEG/PNG with a world file but no CRS
    takes its CRS from a ``.wkt`` / ``-srs.wkt`` / ``.prj`` file beside it if present.
    """
    import rasterio
    path = os.fspath(path)
    if not os.path.exists(path):
        raise FormatError(f"{path}: raster file not found")
    try:
        with rasterio.open(path) as src:
            data = src.read(band) if band is not None else src.read()
            crs = src.crs.to_wkt() if src.crs else None
            tr = src.transform
            nodata = src.nodata
            tags = dict(src.tags())
    except rasterio.errors.RasterioIOError as exc:
        raise FormatError(f"{path}: cannot read raster: {exc}") from None
    if crs is None:
        crs = _sidecar_crs(path)
    if masked_to_nan:
        data = data.astype(np.float64 if data.dtype.itemsize > 4 else np.float32)
        if nodata is not None:
            data[data == nodata] = np.nan
    return Raster(data, crs, tr, nodata, tags, path)


def _sidecar_crs(path: str) -> str | None:
    import pyproj
    stem = os.path.splitext(path)[0]
    for cand in (stem + ".wkt", stem + "-srs.wkt", stem + ".prj", path + ".wkt"):
        if os.path.exists(cand):
            with open(cand, encoding="utf-8") as f:
                text = f.read().strip()
            try:
                return pyproj.CRS.from_user_input(text).to_wkt()
            except pyproj.exceptions.CRSError:
                raise FormatError(f"{cand}: not a CRS pyproj understands") from None
    return None
