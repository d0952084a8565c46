"""What numba's on-disk cache holds for a compiled kernel, read through public means only.

swathflow's kernels are ``numba.njit(cache=True)`` functions: the first run on a new
machine (a new install or clone, numba's cache empty) compiles them, later runs load them
from the cache. numba names the cache folder of a kernel (``kernel.stats.cache_path``:
``__pycache__`` beside its module where that is writable, else ``NUMBA_CACHE_DIR`` or the
user's cache folder) and keeps one index file a kernel there,
``<module>.<function>-<line>.pyXY.nbi`` (numba's documented cache layout,
"Notes on caching"). Nothing here loads or changes numba's cache: it only looks at files.
"""
from __future__ import annotations

import contextlib
import glob
import os
import socket
import time

__all__ = ["cache_folder", "cached", "compiling_alone"]


def cache_folder(kernel) -> str | None:
    """The folder numba caches ``kernel`` (a dispatcher with ``cache=True``) in; None
    where this numba does not say."""
    try:
        return os.fspath(kernel.stats.cache_path)
    except (AttributeError, TypeError):
        return None


def cached(kernel) -> bool:
    """Whether numba's on-disk cache holds ``kernel``'s index file: False on the first run
    after an install or a clone, when numba compiles the kernels (about a minute more for
    a whole run on 2 cores; later runs load them). True where this numba does not say
    where it caches."""
    folder = cache_folder(kernel)
    if folder is None:
        return True
    fn = kernel.py_func
    line = fn.__code__.co_firstlineno
    return bool(glob.glob(os.path.join(glob.escape(folder),
                                       f"*.{glob.escape(fn.__qualname__)}-{line}.py*.nbi")))


@contextlib.contextmanager
def compiling_alone(kernel, timeout: float = 600.0):
    """While numba's cache lacks ``kernel`` (a new install): hold an exclusive lock on a
    file of this host in the folder numba caches it in, so that the processes running the
    same block on this machine (a local cluster's workers) take turns: the first compiles
    and caches the kernels, the others wait, then load them instead of compiling them
    again side by side (each the same 25-50 CPU-s). With the cache full, or no lock to be
    had (no such folder, no ``fcntl``), the block runs at once; after ``timeout`` s of
    waiting too. The system drops the lock of a process that dies. Yields whether the
    cache lacked ``kernel`` on entry."""
    fd = None
    cold = not cached(kernel)
    folder = cache_folder(kernel)
    if cold and folder is not None:
        with contextlib.suppress(ImportError, OSError):    # no lock: compile alongside
            import fcntl
            os.makedirs(folder, exist_ok=True)
            # one lock a host: the processes of one machine (one CPU, one entry of numba's
            # cache) take turns; those of other hosts sharing the folder do not wait
            path = os.path.join(folder, f"swathflow-compile.{socket.gethostname()}.lock")
            fd = os.open(path, os.O_CREAT | os.O_RDWR, 0o666)
            _lock(fd, fcntl, timeout)
    try:
        yield cold
    finally:
        if fd is not None:
            os.close(fd)                            # the lock goes with the descriptor


def _lock(fd: int, fcntl, timeout: float) -> None:
    """``flock(fd, LOCK_EX)``, given up after ``timeout`` s (polled)."""
    end = time.monotonic() + timeout
    while True:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            return
        except BlockingIOError:
            if time.monotonic() > end:
                return
            time.sleep(0.1)
