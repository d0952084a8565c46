"""The mosaic's kernels compiled ahead, on the core a first run leaves idle.

On a new install numba compiles every kernel the first time a process calls it; the
mosaic stage's kernels (matching, network, blending: about 33 s on this 2-core machine)
would be compiled in the mosaic stage, the last of the flow, by one process while the
other core waits. ``swathflow demo`` and ``swathflow run`` start :func:`in_background`
instead when numba's cache has none of them: a child process mosaics a few small
synthetic swings (:func:`synthetic_swings`, the demo's uint16 raw type, procedural
texture) so that numba compiles and caches those kernels while the simulation (one core)
or the first stages run, at a lower priority (``nice`` 10: the simulation evaluates its
texture on two threads, which the child slowed at the command's own priority: cold demos
of 126-128 s against 73-80 s with it); the mosaic stage waits for it while it runs
(:func:`wait`: not on a child starved by other work on a loaded machine) and loads them.
It writes nothing but numba's cache (its swings and mosaic go to a temporary folder,
removed afterwards) and is stopped, by its PID, when the command ends.

``python -m swathflow.tasks.ahead FOLDER`` is the child's command.
"""
from __future__ import annotations

import contextlib
import os
import shutil
import subprocess
import sys
import tempfile
import time

import numpy as np

#: the synthetic swings: strips x swings a strip, each ROWS x SWATH px at RES m
STRIPS, SWINGS, ROWS, SWATH, RES = 3, 2, 340, 180, 0.3


def synthetic_swings(folder: str) -> tuple[list[str], dict]:
    """Write ``STRIPS * SWINGS`` overlapping uint16 swings (nodata 0, wavy edges, each
    strip shifted by a pixel or two) into ``folder``: ``(paths, image id -> strip)``."""
    from affine import Affine

    from swathflow.formats.raster import write_geotiff
    from swathflow.simulation.texture import ProceduralTexture, area_average
    texture = ProceduralTexture(seed=7, scale=0.5)
    step = int(SWATH * 0.6)
    paths, strips = [], {}
    for k in range(STRIPS):
        for s in range(SWINGS):
            r0, c0 = s * (ROWS - 40), k * step
            # the texture averaged over each pixel, strip k displaced by (0.8 k, -1.3 k) px
            seen = Affine(RES, 0, 500000.0 + (c0 + 1.3 * k) * RES,
                          0, -RES, 4000000.0 - (r0 - 0.8 * k) * RES)
            value = 1000.0 + 30000.0 * area_average(texture, seen, (ROWS, SWATH))
            rr, cc = np.mgrid[r0:r0 + ROWS, c0:c0 + SWATH]
            edge = 6.0 + 4.0 * np.sin(rr / 23.0 + k)
            inside = (cc - c0 >= edge) & (c0 + SWATH - cc > edge)
            iid = f"S{k}_{s}"
            path = os.path.join(folder, f"{iid}.tif")
            write_geotiff(path, np.where(inside, value, 0).astype(np.uint16), "EPSG:32633",
                          Affine(RES, 0, 500000.0 + c0 * RES, 0, -RES, 4000000.0 - r0 * RES),
                          nodata=0, tags={"image_id": iid, "strip": k})
            paths.append(path)
            strips[iid] = k
    return paths, strips


def compile_mosaic_kernels(folder: str) -> dict:
    """Mosaic the synthetic swings in ``folder`` (matched, feathered, written as the
    mosaic stage does): numba compiles and caches the kernels on the way. The report."""
    from swathflow.mosaicking.api import write_mosaic
    paths, strips = synthetic_swings(folder)
    return write_mosaic(paths, os.path.join(folder, "mosaic.tif"), strips=strips)


def cold() -> bool:
    """Whether numba's cache lacks the mosaic's kernels (a new install)."""
    from swathflow.jit import cached
    from swathflow.mosaicking.match_kernels import polish
    return not cached(polish)


#: the child of :func:`in_background` while its block runs
_CHILDREN: list = []


def wait(timeout: float = 300.0, starved: float = 0.25) -> None:
    """Let a running child of :func:`in_background` finish (at most ``timeout`` s) while
    it gets a share of a core: the mosaic stage calls it first, to load what the child is
    compiling rather than compile it a second time beside it. A child given less than
    ``starved`` CPU-s in a second (its low priority on a machine loaded by other work) is
    not waited for: the stage compiles what is not cached yet."""
    import psutil               # dask.distributed's own dependency
    for child in list(_CHILDREN):
        end = time.monotonic() + timeout
        try:
            proc = psutil.Process(child.pid)
            used = sum(proc.cpu_times()[:2])
            while time.monotonic() < end:
                try:
                    child.wait(1.0)
                    break
                except subprocess.TimeoutExpired:
                    now = sum(proc.cpu_times()[:2])
                    if now - used < starved:
                        break
                    used = now
        except psutil.Error:        # ended meanwhile
            continue


@contextlib.contextmanager
def in_background():
    """When :func:`cold`: the child compiling the mosaic's kernels, running while the
    block runs (``None`` otherwise); stopped (SIGTERM, then SIGKILL after 5 s) if still
    running at the block's end, its temporary folder removed. numba writes each cache
    entry to a temporary file renamed into place, so a stopped child leaves no half entry,
    and a kernel the parent needs before the child has cached it is compiled by the
    parent as usual."""
    if not cold():
        yield None
        return
    folder = tempfile.mkdtemp(prefix="swathflow-ahead-")
    child = None
    try:
        with contextlib.suppress(OSError):      # not started: compiled where needed
            child = subprocess.Popen([sys.executable, "-m", __name__, folder],
                                     stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                                     stderr=subprocess.DEVNULL)
            _CHILDREN.append(child)
        yield child
    finally:
        if child in _CHILDREN:
            _CHILDREN.remove(child)
        if child is not None and child.poll() is None:
            child.terminate()
            try:
                child.wait(5)
            except subprocess.TimeoutExpired:
                child.kill()
                child.wait()
        shutil.rmtree(folder, ignore_errors=True)


if __name__ == "__main__":          # the child: its failure only leaves the cache cold
    with contextlib.suppress(OSError):
        os.nice(10)             # the command's own processes first (the simulation's threads)
    compile_mosaic_kernels(sys.argv[1])
