"""Rectify every (or some) image of a mission with a calibration: one COG per image and a
``rectify.json`` summary. Each image is ``to_cog(rectify(...))`` of the Python API
(:mod:`swathflow.rectification.api`), as the flow's rectify task writes it; the images run
side by side in forked worker processes."""
from __future__ import annotations

import contextlib
import gc
import json
import os
import sys
import threading
import time
from collections.abc import Callable, Sequence

from swathflow.errors import FormatError
from swathflow.ingest.mission import load_mission
from swathflow.io import write_text
from swathflow.rectification.api import geolocation, rectify, to_cog, warm_up
from swathflow.rectification.lattice import TOLERANCE_PX
from swathflow.rectification.rawimage import open_raw_image
from swathflow.rectification.writing import CODECS


def mission_bands(mission, image_id: str | None = None):
    """The band selection of ``[rectify] bands`` in the mission's ``mission.toml`` (the
    syntax of ``--bands``: ``"1,4-6"``, ``"550nm"``, or a list of 1-based indices), None
    (every band) when absent. With ``image_id`` the selection is checked against that
    image's bands (a :class:`FormatError` naming mission.toml and the key)."""
    spec = (mission.config.get("rectify") or {}).get("bands")
    if spec in (None, "", []):
        return None
    if not isinstance(spec, (str, list)) or (isinstance(spec, list) and not all(
            isinstance(b, int) and not isinstance(b, bool) for b in spec)):
        raise FormatError(f"{mission.path / 'mission.toml'}: [rectify] bands = {spec!r} is "
                          f"neither a string such as \"1,4-6\" or \"550nm\" nor a list of "
                          f"1-based band numbers")
    if image_id is not None:
        img = open_raw_image(mission.images[image_id].file)
        try:
            img.select(spec)
        except FormatError as exc:
            raise FormatError(f"{mission.path / 'mission.toml'}: [rectify] bands = {spec!r} "
                              f"does not fit image {image_id!r}: "
                              f"{str(exc).split(': ', 1)[-1]}") from None
    return spec


def rectify_mission(mission_path, out_dir, calibration: str | None = None,
                    images: Sequence[str] | None = None, method: str = "exact",
                    kernel: str = "bilinear", tol: float = TOLERANCE_PX, tile: int = 512,
                    products: Sequence[str] = (),
                    progress: Callable[[str], None] | None = None, bands=None,
                    dtype: str | None = None, mask_band: bool = False,
                    workers: int | None = None, compress: str = "deflate") -> list[dict]:
    """Rectify the mission's images into ``out_dir/<id>.tif`` with ``calibration`` (a
    calibration.json; default: the mission's priors). Every band of each raw image is
    rectified (``bands``: a subset by 1-based index or wavelength, see
    :func:`~swathflow.rectification.rawimage.parse_bands`; default: ``[rectify] bands``
    of mission.toml, see :func:`mission_bands`), in the raw dtype unless
    ``dtype`` says otherwise (integer nodata, or a mask band with ``mask_band``);
    ``products`` adds ``<id>.glt.tif`` / ``<id>.igm.tif``; ``compress`` is the COGs' codec
    (``deflate``, or ``zstd``: see :data:`~.writing.CODECS`). Returns one summary per
    image.

    ``workers`` processes rectify the images side by side (default: one per CPU, at most
    one per image; forked, so nothing is imported or pickled again), each with one
    thread; with one worker, one image, an active Dask client, other threads alive or no
    ``fork`` on the platform, the images go one after the other, each on the current Dask
    scheduler (threads over tiles)."""
    unknown = set(products) - {"glt", "igm"}
    if unknown:
        raise FormatError(f"unknown product(s) {', '.join(sorted(unknown))}; use glt, igm")
    if compress not in CODECS:
        raise FormatError(f"unknown COG compression {compress!r}; use one of "
                          f"{', '.join(CODECS)}")
    with _start_up():
        mission = load_mission(mission_path)
        ids = mission.image_ids
        if images:
            missing = [i for i in images if i not in ids]
            if missing:
                raise FormatError(f"{mission_path}: no image(s) {', '.join(missing)}; the "
                                  f"mission has {', '.join(ids)}")
            ids = list(images)
        os.makedirs(out_dir, exist_ok=True)
        options = dict(kernel=kernel, tile=tile, method=method, tol=tol, bands=bands,
                       dtype=dtype, mask_band=mask_band, compress=compress)
        jobs = [(mission, iid, calibration, out_dir, tuple(products),
                 dict(options, bands=bands if bands not in (None, "") else
                      mission_bands(mission, iid)))
                for iid in ids]
        processes = _processes(workers, len(jobs))
        if processes > 1:
            _warm(jobs[0])
            # shared with the forked workers: no collector passes over these objects there
            gc.freeze()     # (nor copies of their pages); _run unfreezes them at its end
    summaries, cal_tag = [], ""
    for s, tag, shape in _run(jobs, processes):
        summaries.append(s)
        cal_tag = tag
        if progress:
            progress(f"{s['image_id']}: {shape[0]} x {shape[1]} px -> {s['path']} "
                     f"({s['seconds']:.1f} s)")
    write_text(os.path.join(out_dir, "rectify.json"),
               json.dumps({"images": summaries, "calibration": cal_tag}, indent=2) + "\n")
    return summaries


@contextlib.contextmanager
def _start_up():
    """No collector passes while the mission loads and the engine warms up (0.1-0.2 CPU-s
    on the demo): what is made then (the modules imported on the way, the mission, the
    loaded kernels) lives to the end anyway. The collector's state is restored after."""
    on = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if on:
            gc.enable()


#: the jobs of the running :func:`rectify_mission`, read by its forked workers
_JOBS: list = []


def _one(k: int):
    """Rectify job ``k`` of :data:`_JOBS`: (summary, calibration tag, (rows, cols))."""
    mission, iid, calibration, out_dir, products, o = _JOBS[k]
    o = dict(o)
    compress = o.pop("compress")
    out = os.path.join(out_dir, f"{iid}.tif")
    t0 = time.perf_counter()
    arr = rectify(mission, iid, calibration, **o)
    s = to_cog(arr, out, blocksize=o["tile"], compress=compress)
    for p in products:
        to_cog(geolocation(mission, iid, calibration, p, kernel=o["kernel"], tile=o["tile"],
                           tol=o["tol"]),
               os.path.join(out_dir, f"{iid}.{p}.tif"), blocksize=o["tile"], compress=compress)
    s.update(image_id=iid, method=o["method"], kernel=o["kernel"],
             seconds=round(time.perf_counter() - t0, 3))
    return s, arr.attrs["calibration"], (arr.rio.height, arr.rio.width)


def _one_synchronous(k: int):
    import dask
    with dask.config.set(scheduler="synchronous"):      # the processes are the parallelism
        return _one(k)


def _processes(workers: int | None, n_jobs: int) -> int:
    """Worker processes to use (1: in this process)."""
    import multiprocessing as mp
    if workers is not None and workers < 1:
        raise FormatError(f"workers must be at least 1, not {workers}")
    n = min(workers or os.cpu_count() or 1, n_jobs)
    if n < 2 or "fork" not in mp.get_all_start_methods() or threading.active_count() > 1:
        return 1                  # forking beside other threads may copy a held lock
    if "distributed" not in sys.modules:     # not imported: no client can be active (and
        return n                             # importing it costs 0.2-0.3 s)
    try:
        from distributed import default_client
        default_client()
        return 1                                  # a cluster is there: use it
    except ValueError:
        return n


def _run(jobs, processes: int):
    """The results of :func:`_one` for every job, in the jobs' order."""
    global _JOBS
    _JOBS = jobs
    try:
        if processes < 2:
            for k in range(len(jobs)):
                yield _one(k)
            return
        import multiprocessing as mp
        try:
            with mp.get_context("fork").Pool(processes, initializer=_worker_signals) as pool:
                yield from pool.imap(_one_synchronous, range(len(jobs)))
                pool.close()                     # the workers end on their own (no SIGTERM)
                pool.join()
        finally:
            gc.unfreeze()
    finally:
        _JOBS = []


def _worker_signals() -> None:
    """A forked worker ends quietly on SIGTERM (the pool's terminate, or the command's
    process group stopped) and leaves Ctrl-C to the parent, which stops the pool."""
    import signal
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    signal.signal(signal.SIGINT, signal.SIG_IGN)


def _warm(job) -> None:
    """Import the engine and load every compiled kernel the jobs call (numba's on-disk
    cache) once, before the workers fork (each would otherwise load them again):
    :func:`~swathflow.rectification.api.warm_up` on the first job's swing."""
    mission, iid, calibration, _, _, o = job
    if o["method"] != "exact":
        return
    warm_up(mission, iid, calibration, kernel=o["kernel"], tile=o["tile"], tol=o["tol"],
            bands=o["bands"], dtype=o["dtype"], mask_band=o["mask_band"],
            compress=o["compress"])
