"""The pages of memory-mapped raw windows: which :class:`numpy.memmap` a window is a view
of, and dropping the window's pages from the process once a tile is done with them, so
that the resident memory of a rectification grows with the tile, not with the swing.
"""
from __future__ import annotations

import mmap

import numpy as np


def memmap_of(a):
    """The :class:`numpy.memmap` an array is a view of: the one made over the open mmap
    (its ``base``), whose data start ``offset % ALLOCATIONGRANULARITY`` bytes into the
    mapping (views of a memmap are memmaps too, but start elsewhere); or None."""
    while a is not None:
        if isinstance(a, np.memmap) and isinstance(a.base, mmap.mmap):
            return a
        a = a.base
    return None


def release_pages(window: np.ndarray) -> None:
    """Drop the pages of a memory-mapped window from the process (``madvise`` with
    ``MADV_DONTNEED``; the file's data stay in the page cache and a later read maps them
    again). Without it every page a tile touched stays mapped, so the resident memory of
    a rectification grows with the swing (an 8 GB ENVI cube: 8 GB), not with the tile."""
    mm = memmap_of(window)
    if mm is None or not hasattr(mmap, "MADV_DONTNEED") or window.size == 0 or \
            min(window.strides) < 0:
        return
    nbytes = window.itemsize + sum((n - 1) * st for n, st in zip(window.shape, window.strides))
    base = mm.ctypes.data - (mm.offset % mmap.ALLOCATIONGRANULARITY)
    start = window.__array_interface__["data"][0] - base
    mm = mm.base
    page = mmap.PAGESIZE
    lo = max(start // page * page, 0)
    hi = min(-(-(start + nbytes) // page) * page, len(mm))
    if hi > lo:
        mm.madvise(mmap.MADV_DONTNEED, lo, hi - lo)
