"""The mission flow: ingest -> POS interpolation -> calibration -> rectification -> mosaic.

Composition only: every stage is a task in :mod:`swathflow.tasks.stages`. Nothing needs
setting up by hand: Prefect starts its own temporary server unless ``PREFECT_API_URL``
names one, and a local Dask cluster sized to the machine does the heavy work unless
``dask_address`` names a scheduler (or ``cluster="slurm"`` asks for SLURM worker jobs).
Each swing's rectification is a Prefect task run of the flow (``rectify``) whose work
runs on the Dask cluster; the Dask workers need no Prefect server of their own.
Importing this module changes no setting of Prefect, Dask or logging.
"""
from __future__ import annotations

import contextlib
import os
from pathlib import Path
from typing import Literal

from prefect import flow, unmapped
from prefect.futures import as_completed

from swathflow.cluster import dask_client
from swathflow.flows.progress import Progress
from swathflow.tasks import stages, swings


@flow(name="swathflow-mission", log_prints=False)
def mission_flow(mission: str, out: str, calibration: str | None = None,
                 dask_address: str | None = None, cluster: Literal["local", "slurm"] = "local",
                 jobs: int | None = None, workers: int | None = None) -> dict:
    """Process one mission folder into ``out``; returns the paths of every product and the
    stage timings. Finished outputs whose inputs are unchanged are reused.

    Args:
        mission: The mission folder (with its mission.toml).
        out: The folder the products are written into (never one of the mission's inputs).
        calibration: A calibration.json to use instead of calibrating the mission.
        dask_address: The address of a running Dask scheduler to do the heavy work on.
        cluster: Without dask_address: "local" (a Dask LocalCluster on this machine) or
            "slurm" (Dask workers submitted as SLURM jobs through dask-jobqueue).
        jobs: The number of SLURM worker jobs (cluster "slurm").
        workers: The number of local Dask worker processes (default: one per core).
    """
    mission = str(Path(mission).resolve())
    out = str(Path(out).resolve())
    with Progress() as prog, dask_client(dask_address, cluster=cluster, jobs=jobs,
                                            n_workers=workers,
                                            preload=(swings.__name__,)) as client, \
            _task_stream(client, prog):
        # the loaded mission sent to the workers while this process runs the first stages
        handing = _beside(hand_mission, client, mission, swings.load(mission))
        prog.start("ingest")
        info = stages.ingest(mission)
        prog.finish("ingest")
        ids = info["images"]
        prog.start("calibrate")
        cal = stages.calibrate(mission, out, calibration)
        prog.finish("calibrate")
        # the workers rectify while this process writes the POS products (no swing needs
        # them; the mission check already found the POS covering every line)
        prog.start("rectify", len(ids))
        handing.join()
        futures = stages.rectify.map(image_id=ids, mission_path=unmapped(mission),
                                     calibration=unmapped(cal), out_dir=unmapped(out))
        prog.start("interpolate-pos")
        eo = stages.interpolate_pos(mission, out)
        prog.finish("interpolate-pos")
        # the mosaic's control offsets, while the workers rectify (a failure: the mosaic
        # stage meets it again and reports)
        _quietly(stages.prepare_mosaic, mission, cal)
        for done, _ in enumerate(as_completed(futures), 1):
            prog.update("rectify", done, len(ids))
        rectified = [f.result() for f in futures]
        prog.finish("rectify", len(ids))
        prog.start("mosaic")
        mos = stages.mosaic(rectified, out, mission, cal)
        prog.finish("mosaic")
        prog.start("catalog")
        stac = stages.catalog(mission, rectified, mos, cal, out)
        prog.finish("catalog")
    report = str(Path(cal).parent / "report.html")
    return {"mission": info["name"], "eo": eo, "calibration": cal,
            "report": report if os.path.exists(report) else None,
            "rectified": rectified, "mosaic": mos, "catalog": stac, "timings": prog.timings}


def _beside(fn, *args):
    """``fn(*args)`` run in a thread of this process (its failure ignored: the stage that
    needs its work does it again and reports); the started thread."""
    import threading
    t = threading.Thread(target=_quietly, args=(fn, *args), daemon=True)
    t.start()
    return t


#: environment variable naming a JSON file for the run's timeline (:func:`_task_stream`)
TASK_STREAM = "SWATHFLOW_TASK_STREAM"


@contextlib.contextmanager
def _task_stream(client, prog):
    """With ``SWATHFLOW_TASK_STREAM=path`` set: the run's timeline written to ``path``
    (JSON): every Dask task's compute span per worker (Dask's task stream) and every
    stage's span, in wall-clock seconds, to see whether the workers idle
    (``benchmarks/bench_flow.py --timeline``). Otherwise nothing."""
    path = os.environ.get(TASK_STREAM)
    if not path:
        yield
        return
    import json
    import time

    from distributed import get_task_stream

    from swathflow.io import write_text
    t0 = time.time()
    with get_task_stream(client) as ts:
        yield
    tasks = [{"worker": t.get("worker"), "key": str(t.get("key")),
              "start": s["start"], "stop": s["stop"]}
             for t in ts.data for s in t.get("startstops", ()) if s.get("action") == "compute"]
    write_text(path, json.dumps({"flow_start": t0, "stages": prog.spans, "tasks": tasks,
                                 "workers": sorted(client.scheduler_info()["workers"])}))


def hand_mission(client, mission: str, loaded) -> None:
    """The client's ``loaded`` Mission of ``mission`` handed once to the memo of every
    worker that does not hold it yet (a worker of an earlier run may), through Dask's
    ``Client.run``: no task depends on it, a worker started later loads and validates
    the mission itself."""
    have = client.run(swings.loaded, mission, on_error="return")
    need = [w for w, ok in have.items() if ok is not True]
    if need:
        client.run(swings.remember, mission, loaded, workers=need, on_error="ignore")


def run(mission, out, calibration=None, dask_address=None, cluster="local", jobs=None,
        workers=None) -> dict:
    """Run the flow and return its result; when nothing is to be recomputed
    (:mod:`swathflow.flows.fresh`), the recorded result at once (``result["fresh"]``),
    without starting Prefect or Dask. Otherwise the services are checked or started
    first, side by side (:func:`services`): a named Dask scheduler or Prefect server that
    does not answer is a :class:`~swathflow.errors.SwathflowError` within seconds."""
    from swathflow.flows import fresh
    hit = fresh.fresh_result(mission, out, calibration)
    if hit is not None:
        return hit
    fresh.forget(out)
    with services(dask_address, cluster, workers) as address:
        result = mission_flow(str(mission), str(out), calibration, address,
                              "local" if address else cluster, jobs, workers)
    fresh.record(mission, out, calibration, result)
    return result


@contextlib.contextmanager
def services(dask_address=None, cluster: str = "local", workers: int | None = None):
    """The run's services, started or checked side by side: the local Dask cluster (when
    no other is asked for; Dask's ``LocalCluster``, started in a thread and closed on
    exit) while Prefect's API is reached (:func:`swathflow.flows.services.prefect_ready`:
    Prefect starts its own temporary server when no ``PREFECT_API_URL`` is set), and a
    named scheduler checked (:func:`swathflow.cluster.connect`). Yields the scheduler's
    address for the flow (None: the flow starts its SLURM cluster itself)."""
    import concurrent.futures

    from swathflow.cluster import connect, local_cluster
    from swathflow.flows.services import prefect_ready
    if dask_address:
        connect(dask_address).close()       # unreachable: told now, before Prefect
        prefect_ready()
        yield dask_address
        return
    if cluster != "local":
        prefect_ready()
        yield None
        return
    from prefect.settings import PREFECT_API_URL
    if PREFECT_API_URL.value():     # a named server: checked within seconds, first
        prefect_ready()
    pool = concurrent.futures.ThreadPoolExecutor(1)
    starting = pool.submit(local_cluster, workers, (swings.__name__,))
    pool.shutdown(wait=False)
    try:
        prefect_ready()             # Prefect's temporary server starts meanwhile
    except BaseException:
        with contextlib.suppress(Exception):
            starting.result().close()
        raise
    with starting.result() as local:
        yield local.scheduler_address


def _quietly(fn, *args) -> None:
    try:
        fn(*args)
    except Exception:  # noqa: BLE001 - the flow does it again and reports the failure
        pass
