"""Rectify every (or some) image of a mission with a calibration: one COG per image and a
``rectify.json`` summary. Each image is ``to_cog(rectify(...))`` of the Python API
(:mod:`swathflow.rectification.api`), as the flow's rectify task writes it; the images run
side by side as Dask tasks, one image each: on a Dask cluster (``--dask-address``, or the
active client's), else on Dask's threaded scheduler in this process."""
from __future__ import annotations

import contextlib
import json
import os
import time
from collections.abc import Callable, Sequence

from swathflow.errors import FormatError
from swathflow.ingest.mission import load_mission
from swathflow.io import write_text
from swathflow.rectification.api import geolocation, rectify, to_cog
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
                    workers: int | None = None, compress: str = "deflate",
                    dask_address: str | None = None) -> list[dict]:
    """Rectify the mission's images into ``out_dir/<id>.tif`` with ``calibration`` (a
    calibration.json; default: the mission's priors). Every band of each raw image is
    rectified (``bands``: a subset by 1-based index or wavelength, see
    :func:`~swathflow.rectification.rawimage.parse_bands`; default: ``[rectify] bands``
    of mission.toml, see :func:`mission_bands`), in the raw dtype unless
    ``dtype`` says otherwise (integer nodata, or a mask band with ``mask_band``);
    ``products`` adds ``<id>.glt.tif`` / ``<id>.igm.tif``; ``compress`` is the COGs' codec
    (``deflate``, or ``zstd``: see :data:`~.writing.CODECS`). Returns one summary per
    image.

    The images are rectified side by side, one Dask task each (its tiles on the task's
    own thread): on the scheduler at ``dask_address`` (the loaded mission sent to its
    workers once); else on the active Dask client's cluster (e.g. inside the mission
    flow); else on Dask's threaded scheduler in this process (``workers`` threads,
    default one per core, see :func:`_run`)."""
    unknown = set(products) - {"glt", "igm"}
    if unknown:
        raise FormatError(f"unknown product(s) {', '.join(sorted(unknown))}; use glt, igm")
    if compress not in CODECS:
        raise FormatError(f"unknown COG compression {compress!r}; use one of "
                          f"{', '.join(CODECS)}")
    if workers is not None and workers < 1:
        raise FormatError(f"workers must be at least 1, not {workers}")
    with _cluster(dask_address) as client:
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
        jobs = [(iid, dict(options, bands=bands if bands not in (None, "") else
                           mission_bands(mission, iid)))
                for iid in ids]
        summaries, cal_tag = [], ""
        for s, tag, shape in _run(client, mission, jobs, calibration, out_dir,
                                  tuple(products), workers):
            summaries.append(s)
            cal_tag = tag
            if progress:
                progress(f"{s['image_id']}: {shape[0]} x {shape[1]} px -> {s['path']} "
                         f"({s['seconds']:.1f} s)")
    write_text(os.path.join(out_dir, "rectify.json"),
               json.dumps({"images": summaries, "calibration": cal_tag}, indent=2) + "\n")
    return summaries


@contextlib.contextmanager
def _cluster(address: str | None):
    """The Dask client to rectify on: the one at ``address``; else the active client;
    else None (Dask's threaded scheduler in this process, :func:`_run`)."""
    from swathflow.cluster import connect
    if address:
        with connect(address) as client:
            yield client
        return
    yield _active_client()


def _active_client():
    """The Dask client active in this process or task (None: none; distributed not
    imported yet: none can be, and importing it costs 0.2-0.3 s)."""
    import sys
    if "distributed" not in sys.modules:
        return None
    try:
        from distributed import get_client
        return get_client()
    except ValueError:
        return None


def _one(mission, iid: str, calibration, out_dir: str, products: tuple, o: dict):
    """Rectify image ``iid`` of the loaded ``mission``, its tiles on this thread: (summary,
    calibration tag, (rows, cols))."""
    import dask
    o = dict(o)
    compress = o.pop("compress")
    out = os.path.join(out_dir, f"{iid}.tif")
    t0 = time.perf_counter()
    with dask.config.set(scheduler="sync"):     # the cluster's processes are the parallelism
        arr = rectify(mission, iid, calibration, **o)
        s = to_cog(arr, out, blocksize=o["tile"], compress=compress)
        for p in products:
            to_cog(geolocation(mission, iid, calibration, p, kernel=o["kernel"],
                               tile=o["tile"], tol=o["tol"]),
                   os.path.join(out_dir, f"{iid}.{p}.tif"), blocksize=o["tile"],
                   compress=compress)
    s.update(image_id=iid, method=o["method"], kernel=o["kernel"],
             seconds=round(time.perf_counter() - t0, 3))
    return s, arr.attrs["calibration"], (arr.rio.height, arr.rio.width)


def _run(client, mission, jobs, calibration, out_dir: str, products: tuple,
         workers: int | None = None):
    """The results of :func:`_one` for every job, in the jobs' order: on the cluster of
    ``client`` (the mission sent to every worker once), or, without one, on Dask's
    threaded scheduler in this process (``workers`` threads, default one per core: the
    engine's compiled kernels release the GIL; the imports, the mission and the loaded
    kernels are this process's, where worker processes would each pay them, about
    2 CPU-s each)."""
    if client is None:
        import dask
        import dask.threaded
        from swathflow.cluster import default_workers
        n = min(workers or default_workers(), len(jobs)) or 1
        # the threaded scheduler's function itself: named by a string, Dask would import
        # distributed to look for a client first (0.2-0.3 s)
        yield from dask.compute(*[dask.delayed(_one, pure=False)(
            mission, iid, calibration, os.fspath(out_dir), products, o) for iid, o in jobs],
            scheduler=dask.threaded.get, num_workers=n)
        return
    [loaded] = client.scatter([mission], broadcast=True, hash=False)
    futures = [client.submit(_one, loaded, iid, calibration, os.fspath(out_dir), products,
                             o, key=f"rectify-{iid}-{os.urandom(4).hex()}")
               for iid, o in jobs]
    try:
        for f in futures:
            yield f.result()
    finally:
        client.cancel(futures + [loaded])


def warm_engine() -> None:
    """Import the rectification engine and load the compiled kernels every swing calls
    (numba's on-disk cache) in this process."""
    import numpy as np

    import swathflow.rectification.kernel  # noqa: F401
    from swathflow.rectification.paint import paint_pixels, paint_window
    paint_window(np.ones((1, 4), np.int64), np.zeros((1, 4, 2)), 2, 2, 0, 0, 4, 4)
    paint_pixels(np.zeros((2, 2, 2)), 0, 0, 4, 4)
