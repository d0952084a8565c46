"""Rectify every (or some) image of a mission with a calibration: one COG per image and a
``rectify.json`` summary."""
from __future__ import annotations

import hashlib
import json
import os
import threading
import time
from collections.abc import Callable, Sequence

from swathflow.errors import FormatError
from swathflow.formats.calibfile import calibration_priors, read_calibration
from swathflow.geometry.grid import footprint_grid
from swathflow.ingest.mission import load_mission
from swathflow.io import write_text
from swathflow.rectification.rawimage import open_raw_image
from swathflow.rectification.rectify import TOLERANCE_PX, rectify_image


def rectify_mission(mission_path, out_dir, calibration: str | None = None,
                    images: Sequence[str] | None = None, method: str = "exact",
                    kernel: str = "bilinear", tol: float = TOLERANCE_PX, tile: int = 512,
                    products: Sequence[str] = (),
                    progress: Callable[[str], None] | None = None, bands=None,
                    dtype: str | None = None, mask_band: bool = False,
                    workers: int | None = None) -> list[dict]:
    """Rectify the mission's images into ``out_dir/<id>.tif`` with ``calibration`` (a
    calibration.json; default: the mission's priors). Every band of each raw image is
    rectified (``bands``: a subset by 1-based index or wavelength, see
    :func:`~swathflow.rectification.rawimage.parse_bands`), in the raw dtype unless
    ``dtype`` says otherwise (integer nodata, or a mask band with ``mask_band``). Returns
    one summary per image.

    ``workers`` processes rectify the images side by side (default: one per CPU, at most
    one per image; forked, so nothing is imported or pickled again), each with one
    thread; with one worker, one image, an active Dask client or no ``fork`` on the
    platform, the images go one after the other, each on the current Dask scheduler
    (threads over tiles)."""
    mission = load_mission(mission_path)
    params, cal_tag = mission.priors, "none: mission priors (mission.toml [calibration])"
    if calibration:
        doc = read_calibration(calibration)
        if doc.get("sensor") and doc["sensor"] != mission.sensor.get("model"):
            raise FormatError(f"{calibration}: calibration is for sensor "
                              f"{doc['sensor']!r}, the mission uses "
                              f"{mission.sensor.get('model')!r}")
        params = mission.priors.updated(calibration_priors(doc))
        with open(calibration, "rb") as f:
            digest = hashlib.sha256(f.read()).hexdigest()[:16]
        cal_tag = f"{os.path.abspath(calibration)} (sha256 {digest})"
    ids = mission.image_ids
    if images:
        missing = [i for i in images if i not in ids]
        if missing:
            raise FormatError(f"{mission_path}: no image(s) {', '.join(missing)}; the mission "
                              f"has {', '.join(ids)}")
        ids = list(images)
    os.makedirs(out_dir, exist_ok=True)
    jobs = []
    for iid in ids:
        model = mission.model(iid, params)
        kw = dict(gsd=mission.gsd, crs=mission.crs, method=method, kernel=kernel, tol=tol, tile=tile,
                  products=tuple(products), bands=bands, dtype=dtype, mask_band=mask_band,
                  tags={"image_id": iid, "calibration": cal_tag, "mission": mission.name,
                        "parameters": json.dumps(model.parameters.values_dict())})
        jobs.append((iid, model, mission.images[iid].file, mission.terrain,
                     os.path.join(out_dir, f"{iid}.tif"), kw))
    summaries = []
    for s, seconds in _run(jobs, _processes(workers, len(jobs))):
        summaries.append(s)
        if progress:
            rows, cols = s["grid"]["shape"]
            progress(f"{s['image_id']}: {rows} x {cols} px -> {s['path']} ({seconds:.1f} s)")
    write_text(os.path.join(out_dir, "rectify.json"),
               json.dumps({"images": summaries, "calibration": cal_tag}, indent=2) + "\n")
    return summaries


#: the jobs of the running :func:`rectify_mission`, read by its forked workers
_JOBS: list = []


def _one(k: int):
    """Rectify job ``k`` of :data:`_JOBS`: (summary, seconds)."""
    iid, model, image, terrain, out, kw = _JOBS[k]
    t0 = time.perf_counter()
    kw = dict(kw)
    kw["grid"] = footprint_grid(model, terrain, kw.pop("gsd"), kw.pop("crs"))
    s = rectify_image(model, open_raw_image(image), terrain, out, **kw)
    s["image_id"] = iid
    return s, time.perf_counter() - t0


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
    try:
        from distributed import default_client
        default_client()
        return 1                                  # a cluster is there: use it
    except (ImportError, ValueError):
        return n


def _run(jobs, processes: int):
    """(summary, seconds) of every job, in the jobs' order."""
    global _JOBS
    _JOBS = jobs
    try:
        if processes < 2:
            for k in range(len(jobs)):
                yield _one(k)
            return
        import multiprocessing as mp
        _warm(jobs[0])
        with mp.get_context("fork").Pool(processes) as pool:
            yield from pool.imap(_one_synchronous, range(len(jobs)))
    finally:
        _JOBS = []


def _warm(job) -> None:
    """Import the engine and load its compiled kernels for the first job's types once,
    before the workers fork (each would otherwise load them again)."""
    import dask.array  # noqa: F401
    import numpy as np
    import rasterio  # noqa: F401
    from swathflow.rectification.kernel import resample_window
    from swathflow.rectification.paint import paint_window
    from swathflow.rectification.tiles import output_plan
    _, _, image, _, _, kw = job
    if kw["method"] != "exact":
        return
    src = open_raw_image(image, bands=kw["bands"])
    dt, ond, _ = output_plan(src, kw["dtype"], kw["mask_band"])
    paint_window(np.ones((1, 4), np.int64), np.zeros((1, 4, 2)), 2, 2, 0, 0, 4, 4)
    resample_window(np.zeros((src.count, 4, 4), src.dtype), np.zeros((2, 2, 2), np.float32),
                    kw["kernel"], src.nodata, dt, ond)
