"""Freed heap memory kept in the process for the next tile (glibc's ``mallopt``).

Every output tile allocates and frees the same few buffers of 0.5-4 MB (the lattice's
values, the painted coordinates, the tile, GDAL's blocks). glibc gives each block of more
than its mmap threshold its own mapping, and returns freed memory at the heap's top to the
system past its trim threshold (both adjusted on the way, at most 32 and 64 MB): the
rectify workers took about 25 000 page faults (fresh, zeroed pages) over the demo's 8
swings at 0.05 m. With the thresholds set once, the heap keeps up to :data:`TRIM_BYTES`
of freed memory: about 1 400 faults, the same peak memory."""
from __future__ import annotations

import ctypes
import platform
import sys

#: freed memory at the heap's top kept, not returned to the system, up to this size
TRIM_BYTES = 64 << 20
#: blocks of this size or more get their own mapping (glibc's ceiling for its own
#: threshold, which setting :data:`TRIM_BYTES` would otherwise freeze at 128 KB)
MMAP_BYTES = 32 << 20

_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3


def keep_freed_memory() -> bool:
    """Set glibc's trim and mmap thresholds of this process (and of the processes it forks
    afterwards) to :data:`TRIM_BYTES` and :data:`MMAP_BYTES`. False, changing nothing,
    where the C library is not glibc."""
    if not sys.platform.startswith("linux") or platform.libc_ver()[0] != "glibc":
        return False
    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes = (ctypes.c_int, ctypes.c_int)
    return bool(mallopt(_M_TRIM_THRESHOLD, TRIM_BYTES)) and \
        bool(mallopt(_M_MMAP_THRESHOLD, MMAP_BYTES))
