"""Compiled pixel kernels of the rectifier (numba, ``cache=True``).

Two passes per output tile, no ``(rows, cols, 2)`` float64 temporary:

1. :func:`.paint.paint_window` fills the tile's raw coordinates from the leaf cells of the
   adaptive lattice (:mod:`.lattice`), interpolating each leaf's corners with
   :func:`_bil`, as float32 relative to the raw window read for the tile (a few hundred
   pixels: 3e-5 px resolution), NaN off the raw image.
2. :func:`resample_window` resamples every band of the raw window at those coordinates
   (nearest, bilinear, Keys cubic), nodata-aware, into the output dtype: the mapping is
   computed once per tile and applied to every band. Nearest and bilinear go through the
   gather kernels of :mod:`.gather` (taps once per output block, the window in its file's
   interleave); cubic through :func:`resample_bands`.

Why numba: it installs as a wheel (no compiler on the machine), compiles plain loops over
numpy arrays for any dtype, and caches the machine code on disk (``cache=True``) so the
command's start-up pays the compilation once per installation, not once per run.
"""
from __future__ import annotations

import math
import sys
import threading

import numpy as np
from numba import njit

#: kernel codes
NEAREST, BILINEAR, CUBIC = 0, 1, 2
KERNEL_CODES = {"nearest": NEAREST, "bilinear": BILINEAR, "cubic": CUBIC}


@njit(cache=True, nogil=True, inline="always")
def _bil(wr, wc, q00, q01, q10, q11):
    """Bilinear interpolation of four corners; terms of zero weight are left out, so a
    NaN corner does not spoil the exact values at the other corners."""
    v = 0.0
    a = (1 - wr) * (1 - wc)
    if a != 0.0:
        v += a * q00
    a = (1 - wr) * wc
    if a != 0.0:
        v += a * q01
    a = wr * (1 - wc)
    if a != 0.0:
        v += a * q10
    a = wr * wc
    if a != 0.0:
        v += a * q11
    return v


@njit(cache=True, nogil=True, inline="always")
def _keys(t):
    a = -0.5
    t = abs(t)
    if t <= 1.0:
        return (a + 2) * t * t * t - (a + 3) * t * t + 1
    if t < 2.0:
        return a * t * t * t - 5 * a * t * t + 8 * a * t - 4 * a
    return 0.0


@njit(cache=True, nogil=True, inline="always")
def _weights(x, n, kernel, idx, wts):
    """Tap indices (clamped to [0, n - 1]) and weights of a coordinate; returns the tap
    count."""
    if kernel == NEAREST:
        i = math.floor(x + 0.5)
        idx[0] = min(max(i, 0), n - 1)
        wts[0] = 1.0
        return 1
    i0 = math.floor(x)
    f = x - i0
    if kernel == BILINEAR:
        idx[0] = min(max(i0, 0), n - 1)
        idx[1] = min(max(i0 + 1, 0), n - 1)
        wts[0] = 1.0 - f
        wts[1] = f
        return 2
    for k in range(4):
        idx[k] = min(max(i0 - 1 + k, 0), n - 1)
        wts[k] = _keys(f - (k - 1))
    return 4


@njit(cache=True, nogil=True, inline="always")
def _sample(raw, b, il, wl, na, ie, we, nq, has_nodata, nodata):
    """Weighted sum of a pixel's taps in band ``b``; NaN where a tap of non-zero weight
    is nodata."""
    acc = 0.0
    for p in range(na):
        if wl[p] == 0.0:
            continue
        for q in range(nq):
            wgt = wl[p] * we[q]
            if wgt == 0.0:
                continue
            v = raw[b, il[p], ie[q]]
            if math.isnan(v) or (has_nodata and v == nodata):
                return np.nan
            acc += wgt * v
    return acc


@njit(cache=True, nogil=True, inline="always")
def _to_int(acc, lo, hi, avoid, out_nodata):
    """Round half up, clamp to [lo, hi], and step off the nodata value with ``avoid``."""
    acc = math.floor(acc + 0.5)
    if acc < lo:
        acc = lo
    elif acc > hi:
        acc = hi
    if avoid and acc == out_nodata:
        acc = acc + 1 if acc < hi else acc - 1
    return acc


@njit(cache=True, nogil=True)
def resample_bands(raw, coords, kernel, has_nodata, nodata, out, out_nodata, lo, hi,
                   is_int, avoid, valid):
    """Resample every band of ``raw`` ``(bands, lines, elements)`` (a window, any dtype)
    at ``coords`` ``(2, h, w)`` (window-relative, NaN = no data) into ``out``
    ``(bands, h, w)`` (any dtype).

    A pixel is nodata where its coordinate is NaN or a tap with non-zero weight is nodata
    (``has_nodata`` and equal to ``nodata``, or NaN). Nodata pixels get ``out_nodata``.
    Integer output (``is_int``) is rounded half up and clamped to ``[lo, hi]``; with
    ``avoid`` a valid value equal to ``out_nodata`` moves one unit towards the range's
    inside (GDAL's warper does the same), so it cannot be mistaken for nodata. ``valid``
    ``(h, w)`` uint8 receives 255 where every band is valid, else 0 (a mask band)."""
    nb, nl, ne = raw.shape
    _, h, w = coords.shape
    il = np.empty(4, np.int64)
    ie = np.empty(4, np.int64)
    wl = np.empty(4, np.float64)
    we = np.empty(4, np.float64)
    for r in range(h):
        for c in range(w):
            valid[r, c] = 255
    for b in range(nb):
        for r in range(h):
            for c in range(w):
                li = coords[0, r, c]
                ei = coords[1, r, c]
                if math.isnan(li) or math.isnan(ei):
                    out[b, r, c] = out_nodata
                    valid[r, c] = 0
                    continue
                na = _weights(li, nl, kernel, il, wl)
                nq = _weights(ei, ne, kernel, ie, we)
                acc = _sample(raw, b, il, wl, na, ie, we, nq, has_nodata, nodata)
                if math.isnan(acc):
                    out[b, r, c] = out_nodata
                    valid[r, c] = 0
                    continue
                if is_int:
                    acc = _to_int(acc, lo, hi, avoid, out_nodata)
                out[b, r, c] = acc
    return out


#: output tiles of at least this many bytes come from :func:`tile_buffer`'s pool
POOL_MIN_BYTES = 16 << 20
#: freed large output tiles kept for the next tiles of the same size (at most this many)
POOL_SIZE = 4
_POOL: list = []
_POOL_LOCK = threading.Lock()


def tile_buffer(shape, dtype) -> np.ndarray:
    """An uninitialised array for an output tile. A large one (a 100-band tile of 512 x
    512 uint16 is 52 MB) reuses the memory of an earlier tile of the same byte size that
    nothing refers to any more (only this pool: reference count 2), instead of fresh pages
    that the kernel must zero on first touch (9 ms for 52 MB: a tenth of that tile's
    work). At most :data:`POOL_SIZE` such buffers are kept."""
    dt = np.dtype(dtype)
    n = math.prod(shape) * dt.itemsize
    if n < POOL_MIN_BYTES:
        return np.empty(shape, dt)
    with _POOL_LOCK:
        for k in range(len(_POOL)):
            if _POOL[k].nbytes == n and sys.getrefcount(_POOL[k]) == 2:
                return _POOL[k].view(dt).reshape(shape)
        free = [k for k in range(len(_POOL)) if sys.getrefcount(_POOL[k]) == 2]
        if len(_POOL) >= POOL_SIZE and free:
            del _POOL[free[0]]                   # the oldest free one of another size
        buf = np.empty(n, np.uint8)
        if len(_POOL) < POOL_SIZE:
            _POOL.append(buf)
        return buf.view(dt).reshape(shape)


def resample_window(raw, coords, kernel: str, nodata, out_dtype, out_nodata):
    """Python front of :func:`resample_bands`: ``raw`` ``(bands, lines, elements)`` or 2-D,
    returns ``(values (bands, h, w) out_dtype, valid (h, w) bool)``."""
    raw = np.asarray(raw)
    if raw.ndim == 2:
        raw = raw[None]
    out_dtype = np.dtype(out_dtype)
    h, w = coords.shape[1:]
    out = tile_buffer((raw.shape[0], h, w), out_dtype)
    valid = np.empty((h, w), np.uint8)
    is_int = out_dtype.kind in "ui"
    if is_int:
        info = np.iinfo(out_dtype)
        lo, hi = float(info.min), float(info.max)
        if raw.dtype.kind in "ui":                # the source range too
            rinfo = np.iinfo(raw.dtype)
            lo, hi = max(lo, float(rinfo.min)), min(hi, float(rinfo.max))
    else:
        lo, hi = -np.inf, np.inf
    has_nodata = nodata is not None and not (isinstance(nodata, float) and math.isnan(nodata))
    nd = float(nodata) if has_nodata else 0.0
    if out_nodata is None or (isinstance(out_nodata, float) and math.isnan(out_nodata)):
        ond = np.nan if not is_int else 0.0
        avoid = False
    else:
        ond = float(out_nodata)
        avoid = is_int
    if kernel in ("nearest", "bilinear"):
        # taps and weights once per output row, applied to every band, reading the window
        # in its file's interleave (no transposing copy): see :mod:`.gather`
        from swathflow.rectification.gather import gather
        gather(raw, coords, kernel == "nearest", has_nodata, nd, out, ond, lo, hi, is_int,
               avoid, valid)
    else:
        from swathflow.rectification.pages import release_pages
        resample_bands(np.ascontiguousarray(raw), coords, KERNEL_CODES[kernel], has_nodata,
                       nd, out, ond, lo, hi, is_int, avoid, valid)
        release_pages(raw)
    return out, valid.view(bool)
