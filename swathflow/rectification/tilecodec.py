"""DEFLATE tiles of a COG compressed here, by ISA-L, instead of by GDAL's libdeflate.

The COG writer (:mod:`.writing`) streams each output into a tiled ``.part`` GeoTIFF, then
:mod:`.tifflayout` copies the compressed tiles into the COG layout. When GDAL compressed
them, DEFLATE level 1 was about 40 % of every worker's CPU time on the rectify command's
0.05 m job. ISA-L's level 1 (Intel's Intelligent Storage Acceleration Library, through
the ``isal`` wheel) compressed the same predicted uint16 tiles 2.1x faster than
libdeflate's level 1, 4 % larger (44 against 95 ms for a 12 Mpx swing). Its stream is
plain zlib, which every TIFF reader decodes: only the compressed bytes differ, never the
pixels.

A :class:`TileSink` takes an output level's tiles as they are computed, applies the TIFF
predictor (2, horizontal differencing, for integers; 3, the floating-point one, for
floats), compresses them and appends them to a binary file (in memory, or a scratch file
for a large output), recording each tile's offset and size; GDAL still writes the level's
tags (its ``.part`` GeoTIFF, with no tile written). :func:`with_tiles` joins the two into
what :func:`.tifflayout.write_cog_layout` copies. A tile of nothing but nodata is left out,
as GDAL's ``SPARSE_OK`` leaves it out (the layout writes its nodata tile). Without the
``isal`` module, or for another codec, :func:`can_encode` says no and GDAL compresses.
"""
from __future__ import annotations

import math
import threading

import numpy as np

try:
    from isal import isal_zlib
except ImportError:     # pragma: no cover - a dependency; a platform without its wheel
    isal_zlib = None    # (or a build without it) has GDAL compress

#: ISA-L's compression level (0-3; 1: 2.1x libdeflate's level 1 on predicted uint16 tiles,
#: 4 % larger; 0 only 8 % faster than 1 and 11 % larger)
LEVEL = 1


def can_encode(compression: dict, dtype) -> bool:
    """Whether tiles with these GDAL creation options (``compress``, ``predictor``) and
    ``dtype`` are compressed here: DEFLATE with predictor 1, 2 (integers) or 3 (floats),
    and the ``isal`` module present."""
    dt = np.dtype(dtype)
    pred = int(compression.get("predictor", 1) or 1)
    return (isal_zlib is not None and str(compression.get("compress", "")).lower() == "deflate"
            and (pred == 1 or (pred == 2 and dt.kind in "ui") or (pred == 3 and dt.kind == "f")))


def encode(block: np.ndarray, blocksize: int, predictor: int) -> bytes:
    """One tile of a TIFF as DEFLATE (zlib) bytes: ``block`` (rows, cols), at most
    ``blocksize`` a side (an edge tile), padded with zeros to the whole tile, the
    predictor applied to each row."""
    dt = np.dtype(block.dtype).newbyteorder("<")
    rows, cols = block.shape
    tile = np.zeros((blocksize, blocksize), dt)
    tile[:rows, :cols] = block
    if predictor == 2:                  # horizontal differencing, modulo the type
        tile[:, 1:] = tile[:, 1:] - tile[:, :-1]
    elif predictor == 3:                # bytes to planes (most significant first), then
        planes = tile.view(np.uint8).reshape(blocksize, blocksize, dt.itemsize)
        tile = np.ascontiguousarray(planes[:, :, ::-1].transpose(0, 2, 1)).reshape(
            blocksize, -1)              # byte differencing along the whole row
        tile[:, 1:] = tile[:, 1:] - tile[:, :-1]
    return isal_zlib.compress(tile.data, LEVEL)


class TileSink:
    """The compressed tiles of one level of an output (``bands`` planes of ``height`` x
    ``width`` pixels in tiles of ``blocksize``, band-interleaved: tile ``j`` of band ``b``
    is entry ``b * tiles + j``), appended to ``file`` as they come: :meth:`put` takes a
    window on the tile grid (whole tiles; the right and bottom ones cut by the edge).
    Thread-safe (the mosaic's render threads); compression runs outside the lock."""

    def __init__(self, file, bands: int, height: int, width: int, blocksize: int,
                 predictor: int | None, nodata=None):
        self.file, self.blocksize, self.predictor = file, blocksize, int(predictor or 1)
        self.height, self.width = height, width
        self.across, self.down = -(-width // blocksize), -(-height // blocksize)
        n = bands * self.across * self.down
        self.offsets = np.zeros(n, np.uint64)
        self.counts = np.zeros(n, np.uint64)
        self.nodata = nodata
        self._lock = threading.Lock()

    def put(self, row: int, col: int, value: np.ndarray) -> None:
        """The window of ``value`` ((rows, cols), or (bands, rows, cols)) whose first pixel
        is (``row``, ``col``): on tile boundaries, whole tiles but at the edges."""
        bs = self.blocksize
        planes = value if value.ndim == 3 else value[None]
        rows, cols = planes.shape[-2:]
        if row % bs or col % bs or (rows % bs and row + rows != self.height) \
                or (cols % bs and col + cols != self.width):
            raise ValueError(f"window at ({row}, {col}) of {rows} x {cols} is not on the "
                             f"{bs}-pixel tile grid")
        for b in range(planes.shape[0]):
            for r in range(0, rows, bs):
                for c in range(0, cols, bs):
                    block = planes[b, r:r + bs, c:c + bs]
                    if self._empty(block):
                        continue
                    j = (b * self.down + (row + r) // bs) * self.across + (col + c) // bs
                    data = encode(block, bs, self.predictor)
                    with self._lock:
                        self.offsets[j] = self.file.tell()
                        self.file.write(data)
                        self.counts[j] = len(data)

    def _empty(self, block) -> bool:
        """A tile GDAL's ``SPARSE_OK`` leaves out: every pixel nodata (0 without one)."""
        nd = 0 if self.nodata is None else self.nodata
        if isinstance(nd, float) and math.isnan(nd):
            return bool(np.isnan(block).all())
        return bool((block == nd).all())


def with_tiles(ifd, sink: TileSink):
    """(the level's IFD as GDAL wrote it, with the sink's tile offsets and sizes; the file
    holding them): a level for :func:`.tifflayout.write_cog_layout`."""
    from swathflow.rectification.tifflayout import Ifd
    if ifd.counts.size != sink.counts.size:
        raise ValueError(f"the level's TIFF has {ifd.counts.size} tiles, the sink "
                         f"{sink.counts.size}")
    return Ifd(ifd.tags, sink.offsets, sink.counts, ifd.at), sink.file
