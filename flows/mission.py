"""The mission flow: ingest -> POS interpolation -> calibration -> rectification -> mosaic.

Composition only: every stage is a task in :mod:`swathflow.tasks.stages`. Embedded defaults
need nothing set up by hand: Prefect's local (ephemeral) mode, unless ``PREFECT_API_URL``
names a server, and a local Dask cluster sized to the machine, unless ``dask_address``
names a scheduler. The Dask cluster runs the heavy work inside the tasks (DESIGN.md: a
DaskTaskRunner would start a Prefect server in every worker in local mode).
"""
from __future__ import annotations

import contextlib
import functools
import math
import os
import sys
from pathlib import Path

from swathflow.flows import standby  # noqa: E402  (no Prefect there)

standby.quiet_defaults()
if "dask" in sys.modules:   # dask read the environment before these defaults (the mission
    import dask             # check imports it): read it again, or distributed, imported
    dask.config.refresh()   # later, logs its INFO lines (the cluster's start and close)
# raw scanner images have no geotransform by nature (see flows/cli.py)
import warnings  # noqa: E402
warnings.filterwarnings("ignore", message="Dataset has no geotransform")

from prefect import flow  # noqa: E402

from swathflow.cluster import dask_client, local_cluster  # noqa: E402
from swathflow.flows.progress import Progress  # noqa: E402
from swathflow.tasks import stages, swings  # noqa: E402

#: most swings per Dask task of the rectify stage
BATCH = 16


@flow(name="swathflow-mission", log_prints=False)
def mission_flow(mission: str, out: str, calibration: str | None = None,
                 dask_address: str | None = None, cluster: str = "local",
                 jobs: int | None = None, workers: int | None = None) -> dict:
    """Process one mission folder into ``out``; returns the paths of every product and the
    stage timings. Finished outputs whose inputs are unchanged are reused. The Dask work
    runs on ``dask_address``, or on ``jobs`` SLURM worker jobs (``cluster="slurm"``), or on
    a local cluster (``workers`` processes; default: one per core, at most 4)."""
    mission = str(Path(mission).resolve())
    out = str(Path(out).resolve())
    with Progress() as prog, dask_client(dask_address, cluster=cluster, jobs=jobs,
                                            n_workers=workers) as client, \
            _task_stream(client, prog):
        warm = [client.submit(swings.warm, workers=[w], pure=False)
                for w in client.scheduler_info()["workers"]]
        # the loaded mission sent to the workers (0.5-0.7 s for the survey's 48 MB, load
        # 7) while this process starts the flow run and its first stages
        handing = _beside(hand_mission, client, mission, stages._load(mission))
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
        futures = submit_swings(client, mission, ids, cal, out)
        prog.start("interpolate-pos")
        eo = stages.interpolate_pos(mission, out)
        prog.finish("interpolate-pos")
        # the mosaic's control offsets, while the workers rectify (a failure: the mosaic
        # stage meets it again and reports)
        _quietly(stages.prepare_mosaic, mission, cal)
        rectified = gather_swings(futures, lambda done: prog.update("rectify", done, len(ids)))
        prog.finish("rectify", len(ids))
        del warm
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
    worker that does not hold it yet (a worker of an earlier run may): no task depends on
    it, a worker started later loads and validates the mission itself."""
    have = client.run(swings.loaded, mission, on_error="return")
    need = [w for w, ok in have.items() if ok is not True]
    if need:
        client.run(swings.remember, mission, loaded, workers=need, on_error="ignore")


def submit_swings(client, mission: str, ids: list, calibration: str, out: str,
                  loaded=None) -> list:
    """Every swing handed to the Dask workers, several per Dask task
    (:func:`swathflow.tasks.swings.rectify_batch`, :func:`swing_batches`: at most
    :data:`BATCH` swings, smaller and smaller towards the end so the workers finish
    together; a lost worker's task is run
    again by Dask on another, a failed one retried once, its finished swings kept).
    ``loaded``: the client's loaded Mission, handed to the workers first
    (:func:`hand_mission`). The futures, in ``ids`` order (:func:`gather_swings` waits
    for them)."""
    batches = swing_batches(list(ids), max(len(client.scheduler_info()["workers"]), 1))
    if loaded is not None:
        hand_mission(client, mission, loaded)
    return client.map(swings.rectify_batch, batches, mission_path=mission,
                      calibration=calibration, out_dir=out, pure=False, retries=1)


def swing_batches(ids: list, n_workers: int) -> list[list]:
    """``ids`` cut into the rectify stage's tasks, in order, each at most :data:`BATCH`
    swings and about a quarter of the remaining swings per worker (guided scheduling): the
    first tasks large (little overhead), the last ones single swings, so no worker waits
    long for the others at the end of the stage (Dask starts tasks in submission order).
    With equal batches of 16, a worker of the survey idled one batch's time at the end."""
    batches, k = [], 0
    while k < len(ids):
        size = max(1, min(BATCH, math.ceil((len(ids) - k) / (4 * n_workers))))
        batches.append(ids[k:k + size])
        k += size
    return batches


def gather_swings(futures, progress=None) -> list[str]:
    """The rectified swings' paths of :func:`submit_swings`'s futures, in order;
    ``progress(done)`` is told the number of swings finished as batches finish."""
    from distributed import as_completed
    done = 0
    for f in as_completed(futures):
        done += len(f.result())
        if progress is not None:
            progress(done)
    return [p for f in futures for p in f.result()]


def run(mission, out, calibration=None, dask_address=None, cluster="local", jobs=None,
        workers=None) -> dict:
    """Run the flow without the heartbeat overhead (DESIGN.md) and return its result;
    when nothing is to be recomputed (:mod:`swathflow.flows.fresh`), the recorded result
    at once (``result["fresh"]``), without starting Prefect or Dask."""
    from swathflow.flows import fresh
    hit = fresh.fresh_result(mission, out, calibration)
    if hit is not None:
        return hit
    fresh.forget(out)
    from prefect.settings import (PREFECT_API_URL, PREFECT_FLOWS_HEARTBEAT_FREQUENCY,
                                  temporary_settings)
    with _started(mission, dask_address, cluster, workers) as (address, api_url):
        settings = {PREFECT_FLOWS_HEARTBEAT_FREQUENCY: None}
        if api_url:
            settings[PREFECT_API_URL] = api_url
        with temporary_settings(settings):
            result = mission_flow(str(mission), str(out), calibration, address,
                                  "local" if address else cluster, jobs, workers)
    fresh.record(mission, out, calibration, result)
    return result


def _quietly(fn, *args) -> None:
    try:
        fn(*args)
    except Exception:  # noqa: BLE001 - the flow does it again and reports the failure
        pass


def _engine_modules() -> None:
    """What Prefect imports when a flow is first called (its flow engine, FastAPI's JSON
    encoder for the parameters, Starlette, graphviz: 0.5-0.9 CPU-s here), imported while
    the temporary server starts instead of between the flow run's first requests, where
    the workers wait for it."""
    import fastapi.encoders  # noqa: F401
    import prefect.flow_engine  # noqa: F401
    import prefect.utilities.visualization  # noqa: F401  (Flow.__call__: graphviz)


@contextlib.contextmanager
def _started(mission, dask_address, cluster, workers):
    """Prefect's temporary server (when no server is configured: started first, it takes
    longest), the local Dask cluster (when no other is asked for; its workers forked from
    this process first, while only its main thread runs, so they inherit the mission the
    check loaded) and the mission's loading (when no check loaded it), side by side: each
    mostly waits on its own processes, so together they take about the longest of them
    rather than their sum. Yields the Dask scheduler's address
    for the flow (None: the flow connects as asked) and the temporary server's API url
    (None: Prefect's configured one). A failure here other than the server's is left to
    the flow to report."""
    own_server = standby.serve()     # launched already when `swathflow run` checked
    root = str(Path(mission).resolve())
    with contextlib.ExitStack() as stack:
        address = dask_address
        if not dask_address and cluster == "local":
            # the workers forked from this process while it runs one thread (the engine
            # imported here once; the checked mission inherited; each worker loads the
            # kernels on the mission's first swing while this process starts the
            # scheduler and the flow run), else spawned by Dask
            address = stack.enter_context(local_cluster(
                workers, preload=(swings.__name__,), fork_setup=swings.warm,
                worker_setup=functools.partial(swings.warm, root))).scheduler_address
        loader = None if swings.loaded(root) else _beside(swings.load, root)
        _engine_modules()
        url = standby.ready() if own_server else None
        if loader is not None:
            loader.join()
        yield address, url
