"""The rectify stage's work, importable without Prefect: the Dask workers run it (a worker
that unpickled a function from a module importing Prefect would import Prefect, about
1 CPU-s, for nothing), and :mod:`.stages` wraps it in its Prefect task.

The mission is loaded once per process (:func:`load`, memoised on the folder's file
stamps) or handed over already loaded (:func:`remember`: the flow sends the client's
Mission to its workers once, instead of each worker validating the mission again);
:func:`rectify_one` rectifies one swing, a Dask task of the flow's rectify stage.
"""
from __future__ import annotations

import os
import threading
import time
from pathlib import Path

from swathflow.cache import is_fresh, mark_done, stage_key

_MISSIONS: dict = {}
_MISSIONS_LOCK = threading.Lock()


def _key(mission_path) -> tuple[Path, tuple]:
    root = Path(mission_path).resolve()
    return root, (str(root), hash(tuple(sorted(_file_stamps(str(root))))))


def _file_stamps(folder: str):
    """(path, mtime_ns, size) of every file under ``folder``, as ``Path.rglob("*")`` with
    ``is_file()`` finds them (symbolic links to files followed, to folders not entered),
    one ``stat`` a file (a survey's 490 files: 3 ms, 16 through pathlib)."""
    stack = [folder]
    while stack:
        try:
            entries = os.scandir(stack.pop())
        except (PermissionError, FileNotFoundError, NotADirectoryError):
            continue        # as rglob: nothing there (the mission's check then says why)
        with entries:
            for e in entries:
                if e.is_dir(follow_symlinks=False):
                    stack.append(e.path)
                elif e.is_file():
                    st = e.stat()
                    yield e.path, st.st_mtime_ns, st.st_size


def mission_stamp(mission_path) -> tuple:
    """The mission folder's identity and its files' stamps (path, modification time,
    size), as :func:`load` memoises on them."""
    return _key(mission_path)[1]


def load(mission_path):
    """load_mission, memoised per process on the mission folder's file stamps: every task
    of a run needs the mission, and loading it (POS, DEM, GCPs, checks) costs seconds."""
    from swathflow.ingest.mission import load_mission
    root, key = _key(mission_path)
    with _MISSIONS_LOCK:
        if key not in _MISSIONS:
            if len(_MISSIONS) > 8:
                _MISSIONS.clear()
            _MISSIONS[key] = load_mission(root)
        return _MISSIONS[key]


def loaded(mission_path) -> bool:
    """True when :func:`load` has ``mission_path`` memoised with its files' stamps."""
    _, key = _key(mission_path)
    with _MISSIONS_LOCK:
        return key in _MISSIONS


def remember(mission_path, mission) -> None:
    """Memoise an already loaded Mission of ``mission_path``: :func:`load` returns it
    while the folder's files keep their stamps."""
    _, key = _key(mission_path)
    with _MISSIONS_LOCK:
        if key not in _MISSIONS and len(_MISSIONS) > 8:
            _MISSIONS.clear()
        _MISSIONS[key] = mission


def mission_files(mission) -> list:
    """The files every stage of a mission depends on (configuration, POS, terrain)."""
    files = [mission.path / "mission.toml", mission.path / mission.config["pos"]["file"]]
    dem = mission.config.get("terrain", {}).get("dem")
    if dem:
        files.append(mission.path / dem)
    return files


def image_files(mission, iid) -> list:
    e = mission.images[iid]
    return [e.file, e.lines_file]


def rectify_swing(mission, image_id: str, calibration: str, out_dir: str) -> str:
    """Orthorectify one swing of the loaded ``mission`` to ``OUT/rectified/<image>.tif``
    (COG) with the calibration: ``to_cog(rectify(...))`` of the Python API in the raw
    image's dtype, every band or those of ``[rectify] bands``; a finished output whose
    inputs are unchanged is kept."""
    import numpy as np

    from swathflow.formats.stac import traced_whole
    from swathflow.rectification.api import rectify as rectified, taking_turns, to_cog
    from swathflow.rectification.mission import mission_bands
    out = Path(out_dir) / "rectified" / f"{image_id}.tif"
    key = stage_key("rectify", mission_files(mission) + image_files(mission, image_id)
                    + [calibration])
    if is_fresh(out, key):
        return str(out)
    t0 = time.perf_counter()
    with taking_turns():        # a new install: one worker compiles the kernels at a time
        da = rectified(mission, image_id, calibration,
                       bands=mission_bands(mission, image_id), dtype=None)
        # the valid mask kept as the tiles are written: the footprint is traced from it
        # instead of read back from the file (3 of 13 ms a survey swing)
        valid = np.empty(da.shape[-2:], np.uint8) if traced_whole(*da.shape[-2:]) else None
        to_cog(da, out, valid=valid)
    seconds = round(time.perf_counter() - t0, 3)
    mark_done(out, key, seconds=seconds, **catalog_facts(out, valid))
    return str(out)


def catalog_facts(path, valid=None) -> dict:
    """What the run's STAC catalogue says of the swing just written to ``path`` (its
    footprint traced here, in the worker that wrote it, while the file is in the page
    cache: the catalogue stage would otherwise open and trace every swing again, one after
    the other, at the end of the run), with the file's stamp: ``{"stac": facts,
    "stac_stamp": [size, mtime_ns]}`` for the swing's stage manifest
    (:func:`recorded_facts` reads it back). ``valid``: the swing's valid mask as it was
    written (:func:`~swathflow.formats.stac.valid_footprint`)."""
    from swathflow.formats.stac import raster_facts
    st = Path(path).stat()
    return {"stac": raster_facts(path, valid), "stac_stamp": [st.st_size, st.st_mtime_ns]}


def recorded_facts(path) -> dict | None:
    """The catalogue facts :func:`catalog_facts` recorded for ``path``, when the file is
    still the one they describe (same size and modification time); else None."""
    import json

    from swathflow.cache import manifest_path
    try:
        with open(manifest_path(path), encoding="utf-8") as f:
            doc = json.load(f)
        st = Path(path).stat()
        if doc.get("stac_stamp") == [st.st_size, st.st_mtime_ns]:
            return doc["stac"]
    except (OSError, ValueError, KeyError, TypeError):
        pass
    return None


def rectify_one(image_id: str, mission_path: str, calibration: str, out_dir: str) -> str:
    """One swing in this process (a Dask worker: its tiles on its own thread, so no
    pixels or models cross processes), the mission loaded once a process (memoised, or
    handed over by :func:`remember`): :func:`rectify_swing`'s output path."""
    import dask
    m = load(mission_path)
    with dask.config.set(scheduler="sync"):
        return rectify_swing(m, image_id, calibration, out_dir)


def warm() -> None:
    """Import what a swing's rectification and its catalogue facts use and load the
    engine's compiled kernels (numba's cache), e.g. in a Dask worker as it starts."""
    import pystac.extensions.raster  # noqa: F401  (catalog_facts, after each swing)
    import rasterio.features  # noqa: F401
    import rasterio.warp  # noqa: F401
    import shapely  # noqa: F401

    import swathflow.rectification.api  # noqa: F401
    from swathflow.rectification.mission import warm_engine
    warm_engine()


def dask_setup(worker=None) -> None:
    """Dask's worker preload hook (``local_cluster(preload=("swathflow.tasks.swings",))``):
    :func:`warm` while the worker starts, so a local cluster's workers are ready to
    rectify when the flow begins."""
    warm()


def dask_teardown(worker=None) -> None:
    """Dask's worker preload hook at the worker's close: the process ends soon after
    (:func:`swathflow.cluster.leave_quickly`)."""
    from swathflow.cluster import leave_quickly
    leave_quickly()
