"""Feathered blending, one swing at a time: every swing is shifted by its offset and given
its feather weight once (whole-swing arrays: the cubic shift and the distance transform
are compiled scipy.ndimage passes), kept in a small memory-bounded cache, and a tile is
the weighted sum of the cached swings that reach it (vectorised numpy).

Weight of a swing: its distance to the nearest pixel outside its own corrected footprint,
capped at ``feather`` pixels, which is the paper's ``G = (Rl*Gr + Rr*Gl)/(Rl + Rr)`` for a
straight overlap and works for any overlap shape. Because a swing's shifted values and
weights do not depend on the tile, the mosaic is the same pixel for pixel however it is
cut into tiles (or into separate runs over parts of the area).
"""
from __future__ import annotations

import mmap
import threading
import weakref
from collections import OrderedDict
from dataclasses import dataclass

import numpy as np

__all__ = ["Corrected", "corrected_swing", "shift_cubic", "Scratch", "SwingCache",
           "blend_tile"]


@dataclass
class Corrected:
    """A swing moved by its offset: values (radiometric offset removed) and feather
    weights (0 outside its valid footprint) on grid rows ``row..``, cols ``col..``."""
    row: int
    col: int
    values: np.ndarray      # float32
    weight: np.ndarray      # float32, 0 where invalid

    @property
    def nbytes(self) -> int:
        return self.values.nbytes + self.weight.nbytes


def _b3(x):
    x = np.abs(x)
    return np.where(x < 1, 2 / 3 - x ** 2 + x ** 3 / 2, np.where(x < 2, (2 - x) ** 3 / 6, 0.0))


def shift_cubic(img, f, pad: int = 12):
    """``out[x] = img(x + f)`` by cubic B-spline for one shift ``f`` (row, col) of the
    whole image: the prefilter, then one 4-tap correlation per axis (the same weights at
    every pixel). Equals ``ndimage.shift(img, -f, order=3, mode="nearest")`` (which pads
    by 12 edge pixels the same way) for ``|f| < pad - 2``, at about 4x less cost."""
    from scipy import ndimage
    f = np.asarray(f, float)
    a = np.floor(f).astype(int)
    if np.any(np.abs(a) > pad - 3):
        return ndimage.shift(img, -f, order=3, mode="nearest")
    c = ndimage.spline_filter(np.pad(img, pad, mode="edge"), order=3, mode="mirror")
    for axis in (0, 1):
        w = _b3(float(f[axis] - a[axis]) - (np.arange(4) - 1))
        c = ndimage.correlate1d(c, w, axis=axis, mode="mirror", origin=-1)
    h, wd = img.shape
    return c[pad + a[0]:pad + a[0] + h, pad + a[1]:pad + a[1] + wd]


def corrected_swing(val, ok, row: int, col: int, offset, radiometric: float,
                    feather: float, empty=None, scratch=None) -> Corrected:
    """``val``/``ok``: the whole swing (grid origin ``row, col``). Returns it corrected by
    ``offset`` ``t``: ``out[x] = image[x + t] - radiometric`` (cubic spline), valid where
    every pixel the interpolation leans on was valid, weighted by the capped distance to
    the nearest invalid pixel (compiled kernels, swathflow.mosaicking.kernels).

    ``empty(shape, dtype)`` makes the result's two arrays (default ``np.empty``), and
    ``scratch(name, shape, dtype)`` the arrays used only inside (default: new ones; a
    :class:`Scratch`'s ``get`` reuses them from one swing to the next)."""
    from swathflow.mosaicking import kernels as K
    empty = empty or np.empty
    scratch = scratch or _new
    t = np.asarray(offset, float)
    a = np.floor(t).astype(int)
    f = t - a
    ok = np.ascontiguousarray(ok, bool)
    vals = empty(ok.shape, np.float32)
    if f[0] < 1e-6 and f[1] < 1e-6:
        m = ok
        vals[...] = 0.0
        np.subtract(val, radiometric, out=vals, where=ok, casting="unsafe")
    else:
        pad = 12
        val = np.ascontiguousarray(val, float)
        filled = val
        if not (ok.all() or not ok.any()):
            filled = scratch("filled", ok.shape, np.float64)
            K.fill_rows_into(val, ok, filled)
        coef = scratch("coef", (ok.shape[0] + 2 * pad, ok.shape[1] + 2 * pad), np.float64)
        K.prefilter_into(filled, pad, coef)                  # scipy's, compiled
        # a cubic spline rings at steps (the outer edge of a swing, saturated targets): each
        # pixel is kept within the values of its 4 x 4 spline support (issue 13)
        m = scratch("valid", ok.shape, np.bool_)
        K.sample_clip_into(coef, filled, ok, pad, float(f[0]), float(f[1]),
                           float(radiometric), vals, m)
    wt = empty(ok.shape, np.float32)
    if feather > 0:
        K.capped_distance_into(m, float(feather), wt, scratch("distance", ok.shape,
                                                               np.float64))
    else:
        wt[...] = m
    return Corrected(int(row - a[0]), int(col - a[1]), vals, wt)


def _new(name, shape, dtype):
    return np.empty(shape, dtype)


class Scratch:
    """Arrays reused from one call to the next, one set per thread: ``get(name, shape,
    dtype)`` is an array of that shape on the thread's buffer called ``name``, grown when
    too small, in a memory mapping of its own (outside the C heap). Its contents are
    undefined; it stays valid until the same thread asks for ``name`` again.

    A swing's reading and correction make some 40 bytes a pixel of short-lived arrays
    (the window read, the filled values, the spline's coefficients, the distance pass);
    made new for each swing, each was mapped and faulted in page by page: 45-50 s of
    system CPU in the 1.06 Gpx regional run, 9-11 s with this."""

    def __init__(self):
        self._local = threading.local()

    def get(self, name: str, shape, dtype) -> np.ndarray:
        dtype = np.dtype(dtype)
        n = int(np.prod(shape)) * dtype.itemsize
        bufs = self._local.__dict__.setdefault("bufs", {})
        mm = bufs.get(name)
        if mm is None or len(mm) < n:
            if mm is not None:
                del bufs[name]
            mm = bufs[name] = mmap.mmap(-1, max(n, 1))
        return np.frombuffer(mm, dtype, int(np.prod(shape))).reshape(shape)


class Mappings:
    """Arrays in anonymous memory mappings of their own, outside the C heap, each mapping
    reused once the array made on it is gone (at most ``spare`` unused mappings are kept;
    others are unmapped).

    The swing cache's corrected swings live long and are freed out of order among the
    builds' short-lived arrays of the same sizes (16-33 MB): in glibc's heap (it takes
    blocks up to 32 MB once one is freed) the freed ones left holes that other sizes could
    not reuse; the 0.27 Gpx regional mosaic peaked at 1.7-1.9 GB RSS, 1.2 GB with its
    cached swings in mappings. Reusing the mappings saves their page faults (a fresh
    mapping per swing cost about 6 CPU-s of faults on that run)."""

    def __init__(self, spare: int = 4):
        self.spare = int(spare)
        self._free: dict = {}       # size in bytes -> unused mappings
        self._lock = threading.Lock()

    def empty(self, shape, dtype) -> np.ndarray:
        """A new array (contents undefined) on a mapping of its own."""
        dtype = np.dtype(dtype)
        size = int(np.prod(shape))
        n = max(size * dtype.itemsize, 1)
        with self._lock:
            free = self._free.get(n)
            mm = free.pop() if free else None
        if mm is None:
            mm = mmap.mmap(-1, n)
        b = np.frombuffer(mm, dtype, size).reshape(shape)
        weakref.finalize(b, self._release, mm).atexit = False
        return b

    def _release(self, mm) -> None:
        # called as the array is freed (its buffer may still hold the mapping: a mapping
        # not kept is unmapped when its last reference goes)
        with self._lock:
            free = self._free.setdefault(len(mm), [])
            if len(free) < self.spare:
                free.append(mm)

    def clear(self) -> None:
        """Let the unused mappings go (unmapped)."""
        with self._lock:
            self._free = {}


class SwingCache:
    """Thread-safe LRU of corrected swings, bounded by ``max_bytes``; ``make(k, empty)``
    builds swing ``k`` with its arrays made by ``empty(shape, dtype)`` (each swing is built
    once at a time: other threads wait for it): :meth:`Mappings.empty`, outside the C
    heap."""

    def __init__(self, make, max_bytes: int = 512 * 2 ** 20):
        self.make = make
        self.max_bytes = int(max_bytes)
        self.mappings = Mappings()
        self._data: OrderedDict = OrderedDict()
        self._bytes = 0
        self._lock = threading.Lock()
        self._building: dict = {}

    def get(self, k) -> Corrected:
        while True:
            with self._lock:
                if k in self._data:
                    self._data.move_to_end(k)
                    return self._data[k]
                ev = self._building.get(k)
                if ev is None:
                    ev = self._building[k] = threading.Event()
                    break
            ev.wait()
        try:
            c = self.make(k, self.mappings.empty)
            with self._lock:
                self._data[k] = c
                self._bytes += c.nbytes
                while self._bytes > self.max_bytes and len(self._data) > 1:
                    _, old = self._data.popitem(last=False)
                    self._bytes -= old.nbytes
            return c
        finally:
            with self._lock:
                self._building.pop(k, None)
            ev.set()


def blend_tile(swings, r0: int, c0: int, r1: int, c1: int, mode: str = "feather"):
    """Blend corrected swings (:class:`Corrected`, in input order) on grid window
    ``[r0, r1) x [c0, c1)``. ``mode``: ``"feather"`` (weighted mean, compiled, float32),
    ``"cut"`` (each pixel from the swing with the largest weight: hard seams) or
    ``"first"`` (first valid swing wins, like rasterio.merge). Returns ``(values float32
    with NaN, valid)``."""
    from swathflow.mosaicking import kernels as K
    h, w = r1 - r0, c1 - c0
    acc = np.zeros((h, w), np.float32)
    wsum = np.zeros((h, w), np.float32)
    best = np.zeros((h, w), np.float32)
    for s in swings:
        hh, ww = s.values.shape
        i0, j0 = max(r0, s.row), max(c0, s.col)
        i1, j1 = min(r1, s.row + hh), min(c1, s.col + ww)
        if i1 <= i0 or j1 <= j0:
            continue
        if mode == "feather":
            K.accumulate(acc, wsum, s.values, s.weight, i0 - r0, j0 - c0, i0 - s.row,
                         j0 - s.col, i1 - i0, j1 - j0)
            continue
        v = s.values[i0 - s.row:i1 - s.row, j0 - s.col:j1 - s.col]
        wt = s.weight[i0 - s.row:i1 - s.row, j0 - s.col:j1 - s.col]
        ta, tb = slice(i0 - r0, i1 - r0), slice(j0 - c0, j1 - c0)
        if mode == "first":
            take = (wt > 0) & (wsum[ta, tb] == 0)
        else:
            take = wt > best[ta, tb]
            best[ta, tb][take] = wt[take]
        acc[ta, tb][take] = v[take]
        wsum[ta, tb][take] = 1.0
    valid = wsum > 0
    return K.normalise(acc, wsum), valid
