"""Mosaic inputs: the rectified swings' headers placed on one common grid, windowed
reading with per-thread dataset handles, and finding the inputs of a run.

Image ids come from the tag ``image_id`` (else the file name), strips from mission.toml,
else the tag ``strip``, else the file order.
"""
from __future__ import annotations

import contextlib
import math
import os
import threading
from dataclasses import dataclass, field

import numpy as np

from swathflow.errors import FormatError, SwathflowError

__all__ = ["Swing", "Layout", "scan_inputs", "read_window", "find_inputs", "mission_strips",
           "TAG_IMAGE", "TAG_STRIP", "TAG_DIRECTION"]

# plain tag names: GDAL splits "a:b=c" metadata at the colon, so no namespaced keys
TAG_IMAGE = "image_id"
TAG_STRIP = "strip"
TAG_DIRECTION = "direction"


@dataclass(frozen=True)
class Swing:
    """One rectified swing: its file and its place on the common grid (pixel offsets)."""
    path: str
    image_id: str
    strip: int
    row: int          # grid row of the file's first row
    col: int
    height: int
    width: int
    nodata: float | None
    dtype: str
    direction: str = ""

    @property
    def extent(self):
        return self.row, self.col, self.row + self.height, self.col + self.width


@dataclass
class Layout:
    """The common grid and the swings on it."""
    crs: object                 # rasterio CRS
    transform: object           # affine.Affine of the grid's top-left corner
    shape: tuple[int, int]
    swings: list[Swing] = field(default_factory=list)

    @property
    def res(self) -> float:
        return abs(self.transform.a)


def _tag(tags: dict, *names, default=None):
    for n in names:
        if n in tags and str(tags[n]).strip() != "":
            return tags[n]
    return default


def _read_heads(paths, handles=None):
    """(path, crs, transform, height, width, nodata, dtype, tags, count) per input. With
    ``handles`` (a :class:`_Handles`), each dataset stays open in it for the decoding
    (:meth:`_Handles.keep_open`) instead of being opened a second time."""
    import rasterio
    heads = []
    for p in paths:
        try:
            ds = rasterio.open(p, NUM_THREADS=1)
            with contextlib.ExitStack() as stack:
                if handles is None or not handles.keep_open(p, ds):
                    stack.enter_context(ds)
                t = ds.transform
                if t.b != 0 or t.d != 0:
                    raise FormatError(f"{p}: rotated transforms are not supported; rectify "
                                      f"to a north-up grid")
                heads.append((p, ds.crs, t, ds.height, ds.width, ds.nodata, ds.dtypes[0],
                              ds.tags(), ds.count))
        except rasterio.errors.RasterioIOError as exc:
            raise FormatError(f"{p}: cannot read raster: {exc}") from None
    return heads


def _grid_places(heads):
    """Rows and columns of every input's first pixel on the common grid (checked: one
    CRS, one pixel size, aligned to whole pixels) and the grid's origin (x0, y0)."""
    p0, crs0, t0 = heads[0][0], heads[0][1], heads[0][2]
    for p, crs, t, *_ in heads[1:]:
        if crs != crs0:
            raise FormatError(f"{p}: CRS differs from {p0}; rectify every swing to one grid")
        if not (math.isclose(t.a, t0.a, rel_tol=1e-9) and math.isclose(t.e, t0.e, rel_tol=1e-9)):
            raise FormatError(f"{p}: pixel size ({t.a}, {t.e}) differs from {p0} "
                              f"({t0.a}, {t0.e}); rectify every swing to one grid")
    xs = np.array([h[2].c for h in heads])
    ys = np.array([h[2].f for h in heads])
    x0, y0 = xs.min(), ys.max()
    cols = (xs - x0) / t0.a
    rows = (ys - y0) / t0.e
    for (p, *_), r, c in zip(heads, rows, cols):
        if abs(r - round(r)) > 1e-3 or abs(c - round(c)) > 1e-3:
            raise FormatError(f"{p}: not aligned with {p0} (offset of {r:.3f}, {c:.3f} "
                              f"pixels); rectify every swing to one aligned grid")
    return rows, cols, float(x0), float(y0)


def _swing(k, head, r, c, strips) -> Swing:
    p, _, _, h, w, nod, dt, tags, _count = head     # multi-band swings: band 1 is mosaicked
    iid = str(_tag(tags, TAG_IMAGE, "IMAGE_ID",
                   default=os.path.splitext(os.path.basename(p))[0]))
    strip = strips.get(iid) if strips else None
    if strip is None:
        strip = _tag(tags, TAG_STRIP, "STRIP", default=None)
    try:
        strip = int(float(strip)) if strip is not None else k
    except ValueError:
        raise FormatError(f"{p}: tag {TAG_STRIP}={strip!r} is not a strip number") from None
    direction = str(_tag(tags, TAG_DIRECTION, "DIRECTION", default=""))
    return Swing(p, iid, strip, int(round(r)), int(round(c)), h, w, nod, dt, direction)


def scan_inputs(paths, strips: dict | None = None, handles=None) -> Layout:
    """Read the headers of rectified swings and place them on their common grid.

    All inputs must share the CRS and pixel size and be aligned to whole pixels; the grid is
    the union of their extents. Image ids come from the tag ``image_id`` (else the file
    name), strips from ``strips`` (image id -> strip, e.g. from mission.toml), else the tag
    ``strip``, else the file order (every file its own strip). ``handles``: a
    :class:`_Handles` keeping whole swings, which then decodes them from the datasets
    opened here (each file opened once).
    """
    from affine import Affine
    paths = [os.fspath(p) for p in paths]
    if not paths:
        raise FormatError("no rectified swings given (expected single-band GeoTIFFs)")
    heads = _read_heads(paths, handles)
    rows, cols, x0, y0 = _grid_places(heads)
    swings = [_swing(k, hd, r, c, strips) for k, (hd, r, c) in enumerate(zip(heads, rows, cols))]
    seen: dict = {}
    for s in swings:
        seen[s.image_id] = seen.get(s.image_id, 0) + 1
    dup = sorted(i for i, n in seen.items() if n > 1)
    if dup:
        raise FormatError(f"image ids used by more than one file: {dup}; give every "
                          f"swing a unique {TAG_IMAGE} tag")
    height = max(s.row + s.height for s in swings)
    width = max(s.col + s.width for s in swings)
    t0 = heads[0][2]
    transform = Affine(t0.a, 0.0, x0, 0.0, t0.e, y0)
    return Layout(heads[0][1], transform, (height, width), swings)


#: at most this many datasets of a scan stay open for the decoding (file descriptors)
KEEP_OPEN = 256


class _Handles:
    """Open datasets, one small LRU set per thread (GDAL handles must not be shared across
    threads; an open dataset costs memory, so at most ``per_thread`` stay open).

    ``keep_bytes > 0``: whole swings read at full resolution are also kept decoded, shared
    by every thread, in an LRU of at most ``keep_bytes`` (each swing is then decoded once
    for the footprints' neighbours, the matching and the blending, instead of once per
    overlap window and again for the blend)."""

    def __init__(self, per_thread: int = 16, keep_bytes: int = 0):
        from collections import OrderedDict
        self._local = threading.local()
        self._all = set()
        self._lock = threading.Lock()
        self.per_thread = per_thread
        self.keep_bytes = int(keep_bytes)
        self._whole: OrderedDict = OrderedDict()
        self._whole_bytes = 0
        self._opened: dict = {}     # datasets of the scan, each until its swing is decoded

    def get(self, path):
        import rasterio
        from collections import OrderedDict
        cache = getattr(self._local, "cache", None)
        if cache is None:
            cache = self._local.cache = OrderedDict()
        ds = cache.get(path)
        if ds is not None:
            cache.move_to_end(path)
            return ds
        # one decoding thread per file: the swings are read on this run's own threads
        # (GDAL_NUM_THREADS=2 decoded each small swing's strips on a pool beside them:
        # 0.22 against 0.14 CPU-s to decode the 48-swing benchmark's swings)
        ds = cache[path] = rasterio.open(path, NUM_THREADS=1)
        with self._lock:
            self._all.add(ds)
        while len(cache) > self.per_thread:
            _, old = cache.popitem(last=False)
            with self._lock:
                self._all.discard(old)
            old.close()
        return ds

    def keep_open(self, path, ds) -> bool:
        """Keep the scan's open dataset ``ds`` of ``path`` for :meth:`whole` (the decoding
        threads take it over, one at a time, and close it), when whole swings are kept
        and at most :data:`KEEP_OPEN` are open; False (the caller closes it) otherwise.
        Opening a swing costs about 0.9 ms of CPU (48-swing benchmark: 0.04 s)."""
        with self._lock:
            if self.keep_bytes <= 0 or len(self._opened) >= KEEP_OPEN or path in self._opened:
                return False
            self._opened[path] = ds
            return True

    def _take_opened(self, path):
        with self._lock:
            return self._opened.pop(path, None)

    def whole(self, sw: Swing):
        """Band 1 of swing ``sw`` in its own type and its valid mask, decoded once while it
        stays in the shared LRU; None without ``keep_bytes``."""
        if self.keep_bytes <= 0:
            return None
        with self._lock:
            hit = self._whole.get(sw.path)
            if hit is not None:
                self._whole.move_to_end(sw.path)
                return hit
        ds = self._take_opened(sw.path)
        if ds is None:
            data = self.get(sw.path).read(1)
        else:
            with ds:
                data = ds.read(1)
        hit = (data, _valid(data, sw.nodata))
        with self._lock:
            if sw.path not in self._whole:
                self._whole[sw.path] = hit
                self._whole_bytes += data.nbytes + hit[1].nbytes
            while self._whole_bytes > self.keep_bytes and len(self._whole) > 1:
                _, (d, o) = self._whole.popitem(last=False)
                self._whole_bytes -= d.nbytes + o.nbytes
        return hit

    def keep_if_fits(self, swings) -> None:
        """Keep whole decoded swings only when all of ``swings`` fit in ``keep_bytes``: an
        LRU too small for the run's working set would decode whole swings again and again
        where windows of them are needed."""
        need = sum(s.height * s.width * (np.dtype(s.dtype).itemsize + 1) for s in swings)
        if need > self.keep_bytes:
            self.keep_bytes = 0
            self._close_opened()

    def prefetch(self, swings, workers: int | None = None) -> None:
        """Decode all of ``swings`` into the store now, on ``workers`` threads (GDAL
        releases the GIL while it decodes), when they are kept (:meth:`keep_if_fits`)."""
        if self.keep_bytes <= 0 or not swings:
            return
        from concurrent.futures import ThreadPoolExecutor
        n = max(1, int(workers or os.cpu_count() or 1))
        with ThreadPoolExecutor(n) as ex:
            list(ex.map(self.whole, swings))

    def _close_opened(self):
        with self._lock:
            opened, self._opened = list(self._opened.values()), {}
        for ds in opened:
            ds.close()

    def close(self):
        self._close_opened()
        with self._lock:
            for ds in self._all:
                ds.close()
            self._all.clear()
            self._whole.clear()
            self._whole_bytes = 0


def _valid(a, nodata):
    ok = np.isfinite(a) if a.dtype.kind == "f" else np.ones(a.shape, bool)
    if nodata is not None and not (isinstance(nodata, float) and math.isnan(nodata)):
        ok &= a != nodata
    return ok


def read_window(handles: _Handles, sw: Swing, r0: int, c0: int, r1: int, c1: int,
                step: int = 1, scratch=None):
    """Values (float64) and valid mask of grid window ``[r0, r1) x [c0, c1)`` of one swing
    (outside the file: invalid). ``step > 1`` reads a decimated window (nearest).
    ``scratch``: a :meth:`swathflow.mosaicking.blend.Scratch.get` whose arrays the
    window is read into (valid until the thread reads the next), instead of new ones."""
    h, w = (r1 - r0 + step - 1) // step, (c1 - c0 + step - 1) // step
    if scratch is None:
        val, ok = np.zeros((h, w)), np.zeros((h, w), bool)
    else:
        val, ok = scratch("window", (h, w), np.float64), scratch("window ok", (h, w), bool)
        val[...], ok[...] = 0.0, False
    # the part of the window inside the file, aligned to the decimation lattice
    a0 = max(r0, sw.row)
    b0 = max(c0, sw.col)
    a0 = r0 + -(-(a0 - r0) // step) * step
    b0 = c0 + -(-(b0 - c0) // step) * step
    a1, b1 = min(r1, sw.row + sw.height), min(c1, sw.col + sw.width)
    if a1 <= a0 or b1 <= b0:
        return val, ok
    from rasterio.windows import Window
    i0, j0 = (a0 - r0) // step, (b0 - c0) // step
    whole = handles.whole(sw)
    if whole is not None:
        # a decimated window takes the pixels on the lattice (GDAL's decimated read picks
        # the pixel nearest each output cell's centre instead)
        data, good = whole
        rows = slice(a0 - sw.row, a1 - sw.row, step)
        cols = slice(b0 - sw.col, b1 - sw.col, step)
        g = good[rows, cols]
        hh, ww = g.shape
        np.copyto(val[i0:i0 + hh, j0:j0 + ww], data[rows, cols], where=g)
        ok[i0:i0 + hh, j0:j0 + ww] = g
        return val, ok
    ds = handles.get(sw.path)
    win = Window(b0 - sw.col, a0 - sw.row, b1 - b0, a1 - a0)
    shape = ((a1 - a0 + step - 1) // step, (b1 - b0 + step - 1) // step)
    if scratch is None:
        data = ds.read(1, window=win, out_shape=shape if step > 1 else None)
    else:
        data = ds.read(1, window=win, out=scratch("window raw", shape, ds.dtypes[0]))
    hh, ww = data.shape
    good = ok[i0:i0 + hh, j0:j0 + ww]
    good[...] = _valid(data, sw.nodata)
    np.copyto(val[i0:i0 + hh, j0:j0 + ww], data, where=good)
    return val, ok


def find_inputs(source):
    """Rectified swings under ``source``: a folder of GeoTIFFs, or a mission/run folder
    with a ``rectified/`` subfolder. Earlier mosaics (tag ``product=mosaic``) and an
    image's extra products (``<id>.glt.tif``, ``<id>.igm.tif``) in the folder are not
    swings and are left out; swings of more than one mission (tag ``mission``) are
    refused: they would be blended into one mosaic."""
    source = os.fspath(source)
    if os.path.isfile(source):
        return [source]
    if not os.path.isdir(source):
        raise SwathflowError(f"{source}: no such folder; give a folder of rectified swings "
                             f"(GeoTIFF) or a mission folder with a rectified/ subfolder")
    for sub in ("rectified", os.path.join("out", "rectified"), ""):
        d = os.path.join(source, sub)
        if os.path.isdir(d):
            tifs = sorted(os.path.join(d, f) for f in os.listdir(d)
                          if f.lower().endswith((".tif", ".tiff")) and not f.startswith(".")
                          and not f.lower().endswith(_PRODUCT_FILES))
            tifs = _swings_only(d, tifs)
            if tifs:
                return tifs
    raise SwathflowError(f"{source}: no rectified swings found (looked for *.tif in "
                         f"{source}/rectified and {source}); run 'swathflow rectify' first")


#: the files of an image's extra products (``swathflow rectify --products``)
_PRODUCT_FILES = (".glt.tif", ".igm.tif")


def _swings_only(folder: str, tifs: list[str]) -> list[str]:
    """``tifs`` without earlier mosaics; refused when the swings name several missions."""
    import rasterio
    keep, missions = [], {}
    for p in tifs:
        try:
            with rasterio.open(p) as src:
                tags = src.tags()
        except (rasterio.errors.RasterioError, OSError):
            keep.append(p)          # reported when read, with the file named
            continue
        if tags.get("product") == "mosaic":
            continue
        keep.append(p)
        if tags.get("mission"):
            missions.setdefault(tags["mission"], os.path.basename(p))
    if len(missions) > 1:
        names = ", ".join(f"{k!r} ({v})" for k, v in list(missions.items())[:4])
        raise SwathflowError(f"{folder}: holds swings of {len(missions)} missions ({names}); "
                             f"a mosaic blends one mission's swings: move the others to "
                             f"their own folder")
    return keep


def mission_strips(path) -> dict:
    """Image id -> strip number from a mission folder's ``mission.toml`` ([[images]])."""
    import tomllib

    from swathflow.ingest.tomlfile import load
    path = os.fspath(path)
    toml = os.path.join(path, "mission.toml") if os.path.isdir(path) else path
    try:
        cfg = load(toml)
    except (OSError, tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise FormatError(f"{toml}: cannot read mission file: {exc}") from None
    out = {}
    for k, e in enumerate(cfg.get("images", [])):
        if "id" in e and "strip" in e:
            try:
                out[str(e["id"])] = int(e["strip"])
            except (TypeError, ValueError):
                raise FormatError(f"{toml}: images[{k}].strip must be an integer, got "
                                  f"{e['strip']!r}") from None
    return out
