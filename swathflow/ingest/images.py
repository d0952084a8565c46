"""A mission's raw images: their ``[[images]]`` entry, a raster checked whole before
anything reads it (a truncated ENVI or GeoTIFF file is refused), and lazy, windowed
reading of band 1 as a dask array (GeoTIFF, ENVI, anything rasterio reads).
"""
from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from swathflow.errors import SwathflowError


@dataclass(frozen=True)
class ImageEntry:
    """One ``[[images]]`` entry of mission.toml, its paths resolved in the mission folder;
    ``attrs``: its other keys, handed to the sensor model."""

    id: str
    file: Path
    lines_file: Path
    direction: str
    strip: int
    attrs: dict = field(default_factory=dict)


class _RasterBand:
    """An array-like over band 1 of a raster file that reads only the requested window."""

    def __init__(self, path: str, shape: tuple[int, int], dtype: str):
        self.path = path
        self.shape = shape
        self.dtype = np.dtype(dtype)
        self.ndim = 2

    def __getitem__(self, key):
        from rasterio.windows import Window
        if not isinstance(key, tuple):
            key = (key,)
        key = key + (slice(None),) * (2 - len(key))
        sl = []
        for k, n in zip(key, self.shape):
            if not isinstance(k, slice) or (k.step not in (None, 1)):
                with open_raw(self.path) as src:
                    return src.read(1)[key]
            start, stop, _ = k.indices(n)
            sl.append((start, max(stop, start)))
        (r0, r1), (c0, c1) = sl
        if r1 == r0 or c1 == c0:
            return np.empty((r1 - r0, c1 - c0), self.dtype)
        with open_raw(self.path) as src:
            return src.read(1, window=Window(c0, r0, c1 - c0, r1 - r0))


def open_raw(path):
    """rasterio.open for raw (non-georeferenced) images, without the warning."""
    import warnings

    import rasterio
    from rasterio.errors import NotGeoreferencedWarning
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", NotGeoreferencedWarning)
        return rasterio.open(os.fspath(path))


def raster_info(path) -> tuple[int, int, int, str]:
    """(rows, cols, bands, dtype) of a raster; raises SwathflowError when unreadable."""
    import rasterio
    try:
        with open_raw(path) as src:
            return src.height, src.width, src.count, src.dtypes[0]
    except (rasterio.errors.RasterioError, OSError, ValueError) as exc:
        raise SwathflowError(f"{path}: cannot read image: {exc}") from None


def raster_check(path) -> tuple[int, int, int, str]:
    """(rows, cols, bands, note) of a raw image after checking that all of its pixels
    are there: a raw (ENVI) data file shorter than its header says, or a GeoTIFF whose
    last line cannot be read, is refused. ``note`` says which band is used when there
    are several (empty otherwise)."""
    import rasterio
    from rasterio.windows import Window
    try:
        with open_raw(path) as src:
            rows, cols, bands = src.height, src.width, src.count
            if np.dtype(src.dtypes[0]).kind == "c":
                raise SwathflowError(f"{path}: complex-valued pixels ({src.dtypes[0]}); a "
                                     f"raw image holds real numbers: write its magnitude "
                                     f"(or the real part) as the image")
            need = rows * cols * bands * np.dtype(src.dtypes[0]).itemsize
            if src.driver == "ENVI":
                _envi_size(src, path, need)
            from swathflow.ingest.pixels import has_data
            has_data(src, path)
            end = _tiff_blocks_end(src) if src.driver == "GTiff" else None
            if end is None:              # not told: read the last line (0.003 s each)
                src.read(1, window=Window(0, rows - 1, cols, 1))
            elif end > os.path.getsize(path):
                raise SwathflowError(
                    f"{path}: truncated: {os.path.getsize(path):,} bytes where its image "
                    f"blocks end at byte {end:,}; re-copy or re-export the image")
    except rasterio.errors.RasterioError as exc:
        raise SwathflowError(f"{path}: cannot read image (truncated or damaged?): "
                             f"{str(exc).splitlines()[0][:200]}") from None
    except (OSError, ValueError) as exc:
        raise SwathflowError(f"{path}: cannot read image: {exc}") from None
    note = (f"the image has {bands} bands; every band is rectified, the mosaic uses band 1"
            if bands > 1 else "")
    return rows, cols, bands, note


def _envi_size(src, path, need: int) -> None:
    """An ENVI data file must hold exactly what its header says: shorter is truncated;
    longer means the header does not describe it (a 5-band BIL read as 3 comes out
    scrambled)."""
    from swathflow.ingest.pixels import envi_offset
    data = _envi_data_file(src, path)
    have = os.path.getsize(data)
    offset = envi_offset(src)
    shape = (f"{src.height} lines x {src.width} samples x {src.count} band(s), "
             f"{src.dtypes[0]}")
    if have < need + offset:
        raise SwathflowError(f"{data}: truncated: {have:,} bytes where the header ({shape}) "
                             f"needs {need + offset:,}; re-copy or re-export the image")
    if have > need + offset:
        raise SwathflowError(
            f"{data}: {have:,} bytes where the header ({shape}, header offset {offset}) "
            f"accounts for {need + offset:,}: the header does not describe the file (its "
            f"bands, samples, lines or data type are wrong, and the pixels would be read "
            f"scrambled); correct the .hdr")


def _tiff_blocks_end(src) -> int | None:
    """The byte where the last image block of an open GeoTIFF ends (from its block
    offsets and sizes, without decompressing anything), or None when GDAL does not say."""
    pixel = str(getattr(src.interleaving, "name", "")).upper() == "PIXEL"
    bands = (1,) if pixel else range(1, src.count + 1)   # pixel-interleaved: shared blocks
    bh, bw = src.block_shapes[0]
    end = 0
    for b in bands:
        for y in range(-(-src.height // bh)):
            for x in range(-(-src.width // bw)):
                off = src.get_tag_item(f"BLOCK_OFFSET_{x}_{y}", "TIFF", bidx=b)
                size = src.get_tag_item(f"BLOCK_SIZE_{x}_{y}", "TIFF", bidx=b)
                if off is None or size is None:
                    return None
                end = max(end, int(off) + int(size))
    return end


def _envi_data_file(src, path) -> str:
    """The binary file of an ENVI image (the path itself, or the one beside its header)."""
    path = os.fspath(path)
    if not path.lower().endswith(".hdr"):
        return path
    for f in src.files:
        if not f.lower().endswith(".hdr"):
            return f
    return path


def lazy_image(path, chunk_lines: int = 2048):
    """A dask array over band 1 of a raster, chunked in blocks of whole lines."""
    import dask.array as da
    rows, cols, _, dtype = raster_info(path)
    arr = _RasterBand(os.fspath(path), (rows, cols), dtype)
    return da.from_array(arr, chunks=(min(chunk_lines, rows), cols), lock=False,
                         asarray=True, name=f"raw-{os.fspath(path)}-{os.path.getmtime(path)}")
