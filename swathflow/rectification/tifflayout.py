"""A Cloud-Optimized GeoTIFF laid out from tiled GeoTIFFs that GDAL already compressed.

The COG writer (:mod:`.writing`) lets GDAL's GTiff driver compress every tile once, as it
streams the full resolution and each overview level into tiled GeoTIFFs. This module then
copies those compressed tiles, unchanged, into the COG layout of GDAL's COG driver: the
header, GDAL's structural metadata ("ghost area"), every IFD before any data, the tile
data from the smallest overview to the full resolution, each tile with its size before
it and its last four bytes repeated after it (``BLOCK_LEADER=SIZE_AS_UINT4``,
``BLOCK_TRAILER=LAST_4_BYTES_REPEATED``). The tags (georeferencing, nodata, metadata,
compression, predictor) are those GDAL wrote; only the tile offsets and byte counts, and
the overviews' ``NewSubfileType``, are ours. Classic TIFF, or BigTIFF when the file could
pass 4 GB. Little-endian only (what GDAL writes on every platform it runs on here).
"""
from __future__ import annotations

import struct
from dataclasses import dataclass

import numpy as np

#: bytes per value of each TIFF field type
TYPE_SIZE = {1: 1, 2: 1, 3: 2, 4: 4, 5: 8, 6: 1, 7: 1, 8: 2, 9: 4, 10: 8, 11: 4, 12: 8,
             13: 4, 16: 8, 17: 8, 18: 8}
#: a COG that could be larger than this is written as a BigTIFF
BIGTIFF_BYTES = 2 ** 32 - 1
NEW_SUBFILE_TYPE, TILE_OFFSETS, TILE_BYTE_COUNTS = 254, 324, 325
#: tags GDAL's COG driver leaves out of an overview's IFD (GeoTIFF keys, GDAL metadata)
NOT_IN_OVERVIEWS = {33550, 33922, 34264, 34735, 34736, 34737, 42112}
#: GDAL's structural metadata: what makes GDAL (and the COG validators) see a COG
GHOST = (b"GDAL_STRUCTURAL_METADATA_SIZE=000140 bytes\n"
         b"LAYOUT=IFDS_BEFORE_DATA\nBLOCK_ORDER=ROW_MAJOR\nBLOCK_LEADER=SIZE_AS_UINT4\n"
         b"BLOCK_TRAILER=LAST_4_BYTES_REPEATED\nKNOWN_INCOMPATIBLE_EDITION=NO\n ")


@dataclass
class Ifd:
    """The first IFD of a TIFF: ``tags`` maps a tag to (type, count, little-endian value
    bytes); ``offsets`` and ``counts`` are its tiles' data offsets and byte counts."""

    tags: dict
    offsets: np.ndarray
    counts: np.ndarray
    at: int = 0


def _values(typ: int, count: int, raw: bytes) -> np.ndarray:
    fmt = {3: "<u2", 4: "<u4", 16: "<u8"}[typ]
    return np.frombuffer(raw, fmt, count).astype(np.uint64)


def read_first_ifd(f) -> Ifd:
    """The first IFD of the tiled TIFF open in ``f`` (a binary file object)."""
    return read_ifds(f, 1)[0]


def read_ifds(f, most: int | None = None) -> list[Ifd]:
    """The IFDs of the tiled TIFF open in ``f`` (the first ``most``), in file order of the
    chain; each also records its own offset (``at``)."""
    f.seek(0)
    head = f.read(16)
    if head[:2] != b"II":
        raise ValueError("not a little-endian TIFF")
    magic = struct.unpack_from("<H", head, 2)[0]
    if magic == 42:
        big, (pos,) = False, struct.unpack_from("<I", head, 4)
    elif magic == 43:
        big, (pos,) = True, struct.unpack_from("<Q", head, 8)
    else:
        raise ValueError("not a TIFF")
    out: list[Ifd] = []
    while pos and (most is None or len(out) < most):
        ifd, pos = _read_ifd(f, pos, big)
        out.append(ifd)
    return out


def _read_ifd(f, pos: int, big: bool):
    f.seek(pos)
    n = struct.unpack("<Q" if big else "<H", f.read(8 if big else 2))[0]
    esz, inline = (20, 8) if big else (12, 4)
    table = f.read(n * esz)
    (nxt,) = struct.unpack("<Q" if big else "<I", f.read(8 if big else 4))
    tags = {}
    for k in range(n):
        e = table[k * esz:(k + 1) * esz]
        tag, typ = struct.unpack_from("<HH", e, 0)
        count = struct.unpack_from("<Q" if big else "<I", e, 4)[0]
        size = TYPE_SIZE.get(typ, 1) * count
        val = e[esz - inline:esz]
        if size > inline:
            (off,) = struct.unpack("<Q" if big else "<I", val)
            f.seek(off)
            val = f.read(size)
        tags[tag] = (typ, count, bytes(val[:size]))
    if TILE_OFFSETS not in tags or TILE_BYTE_COUNTS not in tags:
        raise ValueError("not a tiled TIFF")
    return Ifd(tags, _values(*tags[TILE_OFFSETS]), _values(*tags[TILE_BYTE_COUNTS]),
               pos), nxt


def _ifd_bytes(tags: dict, big: bool, at: int, next_ifd: int) -> bytes:
    """An IFD written at offset ``at``, its out-of-line values right after it."""
    esz, inline = (20, 8) if big else (12, 4)
    items = sorted(tags.items())
    head = struct.pack("<Q", len(items)) if big else struct.pack("<H", len(items))
    tail = struct.pack("<Q" if big else "<I", next_ifd)
    extra_at = at + len(head) + esz * len(items) + len(tail)
    entries, extra = [], []
    for tag, (typ, count, val) in items:
        e = struct.pack("<HHQ" if big else "<HHI", tag, typ, count)
        if len(val) <= inline:
            e += val + bytes(inline - len(val))
        else:
            if extra_at % 2:
                extra.append(b"\0")
                extra_at += 1
            e += struct.pack("<Q" if big else "<I", extra_at)
            extra.append(val)
            extra_at += len(val)
        entries.append(e)
    return head + b"".join(entries) + tail + b"".join(extra)


def _with_tiles(tags: dict, offsets, counts, big: bool) -> dict:
    out = dict(tags)
    typ, fmt = (16, "<u8") if big else (4, "<u4")
    out[TILE_OFFSETS] = (typ, len(offsets), np.asarray(offsets, fmt).tobytes())
    out[TILE_BYTE_COUNTS] = (typ, len(counts), np.asarray(counts, fmt).tobytes())
    return out


def _level_tags(ifd: Ifd, overview: bool) -> dict:
    tags = {t: v for t, v in ifd.tags.items() if t not in (TILE_OFFSETS, TILE_BYTE_COUNTS)}
    if overview:
        tags = {t: v for t, v in tags.items() if t not in NOT_IN_OVERVIEWS}
        tags[NEW_SUBFILE_TYPE] = (4, 1, struct.pack("<I", 1))
    else:
        tags.pop(NEW_SUBFILE_TYPE, None)
    return tags


def write_cog_layout(out, levels, empty=None) -> None:
    """Write the COG into the binary file ``out`` from ``levels``: (IFD, source file
    object) pairs of the full resolution then each overview, largest first (each a tiled
    TIFF with the same compression, read by :func:`read_first_ifd`). ``empty(rows,
    cols)``: the compressed bytes of a tile of nodata with ``rows`` x ``cols`` pixels
    inside the image, written for every tile a source left out (a sparse GeoTIFF's byte
    count 0), so the COG has every tile, as GDAL's COG driver writes it."""
    if empty is not None:
        levels = [_filled(i, f, empty) for i, f in levels]
    data_size = sum(int(i.counts.sum()) + 8 * int((i.counts > 0).sum()) for i, _ in levels)
    tag_size = sum(sum(len(v[2]) + 24 for v in i.tags.values()) + 16 * i.offsets.size + 64
                   for i, _ in levels)
    big = data_size + tag_size + 4096 > BIGTIFF_BYTES
    tags = [_level_tags(i, k > 0) for k, (i, _) in enumerate(levels)]
    head_len = 16 if big else 8
    start = head_len + len(GHOST)
    start += start % 2
    # IFD sizes do not depend on the offsets they hold: lay them out with zeros first
    ifd_at, at = [], start
    for t, (i, _) in zip(tags, levels):
        ifd_at.append(at)
        at += len(_ifd_bytes(_with_tiles(t, i.offsets * 0, i.counts, big), big, at, 0))
        at += at % 2
    # the tile data: the smallest overview first, full resolution last
    offsets = [None] * len(levels)
    for k in range(len(levels) - 1, -1, -1):
        counts = levels[k][0].counts
        offs = np.zeros(counts.size, np.uint64)
        for j, c in enumerate(counts.tolist()):
            if c:
                offs[j] = at + 4
                at += c + 8
        offsets[k] = offs
    if big:
        out.write(b"II+\0" + struct.pack("<HHQ", 8, 0, ifd_at[0]))
    else:
        out.write(b"II*\0" + struct.pack("<I", ifd_at[0]))
    out.write(GHOST)
    pos = head_len + len(GHOST)
    for k, (t, (i, _)) in enumerate(zip(tags, levels)):
        out.write(bytes(ifd_at[k] - pos))
        nxt = ifd_at[k + 1] if k + 1 < len(levels) else 0
        b = _ifd_bytes(_with_tiles(t, offsets[k], i.counts, big), big, ifd_at[k], nxt)
        out.write(b)
        pos = ifd_at[k] + len(b)
    first = min((int(o[o > 0].min()) - 4 for o in offsets if (o > 0).any()), default=pos)
    out.write(bytes(first - pos))
    for k in range(len(levels) - 1, -1, -1):
        _copy_tiles(out, *levels[k])


def _copy_tiles(out, ifd: Ifd, src) -> None:
    """A level's tiles from ``src``, each with its size before it and its last four bytes
    after it."""
    for j, (off, c) in enumerate(zip(ifd.offsets.tolist(), ifd.counts.tolist())):
        if not c:
            continue
        tile = src.tile(j, off, c) if isinstance(src, _Filled) else _read(src, off, c)
        if len(tile) != c:
            raise ValueError("a tile of the source TIFF is cut short")
        out.write(struct.pack("<I", c))
        out.write(tile)
        out.write(tile[-4:] if c >= 4 else tile + bytes(4 - c))


def _read(src, off: int, count: int) -> bytes:
    src.seek(off)
    return src.read(count)


def _tag_int(ifd: Ifd, tag: int) -> int:
    return int(_values(*ifd.tags[tag][:2], ifd.tags[tag][2])[0])


def _filled(ifd: Ifd, f, empty):
    """(the IFD with its left-out tiles' byte counts, a source reading them as
    ``empty(rows, cols)``)."""
    w, h = _tag_int(ifd, 256), _tag_int(ifd, 257)
    tw, th = _tag_int(ifd, 322), _tag_int(ifd, 323)
    across, down = -(-w // tw), -(-h // th)
    counts, tiles = ifd.counts.copy(), {}
    for j in np.flatnonzero(ifd.counts == 0).tolist():
        r, c = divmod(j % (across * down), across)
        tiles[j] = empty(min(th, h - r * th), min(tw, w - c * tw))
        counts[j] = len(tiles[j])
    return Ifd(ifd.tags, ifd.offsets, counts, ifd.at), _Filled(f, tiles)


class _Filled:
    """A source TIFF whose left-out tiles (byte count 0) read as given."""

    def __init__(self, f, tiles: dict):
        self.f, self.tiles = f, tiles

    def tile(self, j: int, off: int, count: int) -> bytes:
        t = self.tiles.get(j)
        return t if t is not None else _read(self.f, off, count)


#: compressed nodata tiles by (dtype, nodata, codec, block, rows, cols): :func:`nodata_tiles`
_NODATA_TILES: dict = {}


def nodata_tiles(dtype, nodata, codec: dict, blocksize: int):
    """``empty(rows, cols)``: the compressed bytes of a tile of ``nodata`` (0 when None) of
    ``rows`` x ``cols`` pixels inside the image (fewer at the right and bottom edges), as
    GDAL's GTiff driver writes it with ``codec`` (its creation options: compression, level,
    predictor), for :func:`write_cog_layout` to put in place of the tiles a sparse GeoTIFF
    left out. Each is made once a process (:data:`_NODATA_TILES`; a GeoTIFF in memory, 3-5
    ms). GDAL pads edge tiles with zeros: with a fill of zero bytes every shape's tile is
    the whole block's, made once (the demo's 8 swings at 0.05 m made 32 before: 0.15 CPU-s)."""
    import io
    import warnings

    from rasterio.errors import NotGeoreferencedWarning
    from rasterio.io import MemoryFile
    dt = np.dtype(dtype)
    fill = np.full(1, 0 if nodata is None else nodata, dt)
    zero = not fill.view(np.uint8).any()
    key = (dt.str, repr(nodata), repr(sorted(codec.items())), blocksize)  # repr: NaN == NaN

    def empty(rows: int, cols: int) -> bytes:
        rows, cols = (blocksize, blocksize) if zero else (rows, cols)
        if key + (rows, cols) not in _NODATA_TILES:
            with MemoryFile() as mem, warnings.catch_warnings():
                warnings.simplefilter("ignore", NotGeoreferencedWarning)
                with mem.open(driver="GTiff", width=cols, height=rows, count=1, dtype=dt.name,
                              nodata=nodata, tiled=True, blockxsize=blocksize,
                              blockysize=blocksize, **codec) as dst:
                    dst.write(np.full((1, rows, cols), fill[0], dt))
                f = io.BytesIO(mem.read())
            ifd = read_first_ifd(f)
            f.seek(int(ifd.offsets[0]))
            _NODATA_TILES[key + (rows, cols)] = f.read(int(ifd.counts[0]))
        return _NODATA_TILES[key + (rows, cols)]
    return empty
