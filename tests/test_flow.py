"""The mission flow for real: a Prefect flow run, a local Dask cluster (worker processes),
COG outputs through rasterio, checked against the simulator's truth."""
import os
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import rasterio

pytestmark = pytest.mark.usefixtures("prefect_harness")


def _outputs(out: Path) -> dict:
    files = sorted(p for p in out.rglob("*") if p.is_file() and not p.name.endswith(".json"))
    return {str(p.relative_to(out)): p.stat().st_mtime_ns for p in files}


def _check_against_truth(mission: Path, result: dict, tol_px: float = 0.25):
    from swathflow.ingest.mission import load_mission
    from shifts import phase_shift
    m = load_mission(mission)
    with rasterio.open(mission / "truth" / "ortho.tif") as t:
        truth = t.read(1, masked=True).astype(float).filled(np.nan)
        t_tr, t_crs = t.transform, t.crs
    assert len(result["rectified"]) == len(m.images)
    for path in result["rectified"]:
        with rasterio.open(path) as src:
            assert src.crs == t_crs == rasterio.crs.CRS.from_user_input(m.crs)
            assert src.tags(ns="IMAGE_STRUCTURE").get("LAYOUT") == "COG"
            if max(src.width, src.height) > 512:
                assert src.overviews(1), "no internal overviews"
            assert src.tags().get("image_id") in m.images
            img = src.read(1, masked=True).astype(float).filled(np.nan)
            # the same window of the truth ortho (grids share pixel size and alignment)
            col0 = round((src.transform.c - t_tr.c) / t_tr.a)
            row0 = round((src.transform.f - t_tr.f) / t_tr.e)
            assert abs(src.transform.a - t_tr.a) < 1e-9
        win = truth[row0:row0 + img.shape[0], col0:col0 + img.shape[1]]
        assert win.shape == img.shape, "rectified grid falls outside the truth ortho"
        ok = np.isfinite(img) & np.isfinite(win)
        assert ok.mean() > 0.3
        dy, dx = phase_shift(np.where(ok, img, np.nanmean(img[ok])),
                             np.where(ok, win, np.nanmean(win[ok])))
        assert abs(dx) < tol_px and abs(dy) < tol_px, (path, dx, dy)
    if "mosaic" not in result:          # the swings alone (a batch of the rectify stage)
        return
    with rasterio.open(result["mosaic"]) as mos:
        assert mos.crs == t_crs and mos.width > 0


def _check_catalog(result: dict):
    """The run's STAC catalogue: an item per swing and the mosaic, STAC core valid, each
    footprint's area the area of the file's valid pixels (counted, not traced)."""
    import pystac
    from pyproj import Transformer
    from pystac.validation import validate_dict
    from shapely.geometry import shape
    import shapely
    from stac_schemas import validate_extensions
    cat = pystac.Catalog.from_file(result["catalog"])
    items = {i.properties["swathflow:image_id"]: i for i in cat.get_items(recursive=True)}
    products = {Path(p).stem: p for p in result["rectified"]} | {"mosaic": result["mosaic"]}
    assert set(items) == set(products)
    for iid, path in products.items():
        validate_dict(items[iid].to_dict(), extensions=[])
        validate_extensions(items[iid].to_dict())     # extension schemas, held offline
        with rasterio.open(path) as src:
            valid = float((src.dataset_mask() > 0).sum()) * abs(src.transform.a * src.transform.e)
            to = Transformer.from_crs("EPSG:4326", src.crs, always_xy=True)
        area = shapely.transform(shape(items[iid].geometry),
                                 lambda xy, t=to: np.column_stack(t.transform(*xy.T))).area
        assert abs(area - valid) < 0.03 * valid, (iid, area, valid)
        # acquired on the simulated flight's date (GPS seconds of week from Wednesday noon)
        start = items[iid].common_metadata.start_datetime
        assert start.date().isoformat() == "2024-06-05" and start.hour in (11, 12), start


def _check_same_as_cli_and_api(mission: Path, result: dict, cal: str, out: Path):
    """The flow's rectified swings are the pixels of 'swathflow rectify' and of the lazy
    swathflow.rectify (one function under all three)."""
    import swathflow
    from swathflow.flows.cli import main
    assert main(["rectify", str(mission), "--calibration", cal, "--out", str(out), "-q"]) == 0
    for path in result["rectified"]:
        iid = Path(path).stem
        api = swathflow.rectify(mission, iid, cal, dtype=None).values
        with rasterio.open(path) as f, rasterio.open(out / f"{iid}.tif") as c:
            assert f.dtypes == c.dtypes == (str(api.dtype),) and f.nodata == c.nodata
            assert np.array_equal(f.read(1), c.read(1)) and np.array_equal(f.read(1), api)


def test_flow_end_to_end_and_rerun_reuses_outputs(tiny_mission, tmp_path):
    from swathflow.flows.mission import run
    out = tmp_path / "out"
    cal = str(tiny_mission / "truth" / "calibration.json")
    result = run(tiny_mission, out, calibration=cal)
    _check_against_truth(tiny_mission, result)
    _check_catalog(result)
    _check_same_as_cli_and_api(tiny_mission, result, cal, tmp_path / "cli")
    eo = result["eo"][0]
    assert Path(eo).exists() and sum(1 for _ in open(eo)) > 10
    before = _outputs(out)
    again = run(tiny_mission, out, calibration=cal)
    assert again["rectified"] == result["rectified"]
    assert _outputs(out) == before, "a re-run with unchanged inputs recomputed outputs"


def test_changed_calibration_recomputes_only_what_depends_on_it(tiny_mission, tmp_path):
    from swathflow.formats.calibfile import read_calibration, write_calibration
    from swathflow.flows.mission import run
    out = tmp_path / "out"
    cal = tmp_path / "cal.json"
    shutil.copy(tiny_mission / "truth" / "calibration.json", cal)
    run(tiny_mission, out, calibration=str(cal))
    before = _outputs(out)
    doc = read_calibration(cal)
    doc["parameters"]["u_gps"]["value"][0] += 0.01
    write_calibration(cal, doc["sensor"], doc["parameters"])
    run(tiny_mission, out, calibration=str(cal))
    after = _outputs(out)
    eo = [k for k in before if k.startswith("pos/")]
    assert eo and all(after[k] == before[k] for k in eo), "POS products were redone"
    rect = [k for k in before if k.startswith("rectified/")]
    assert rect and all(after[k] != before[k] for k in rect), "rectified swings were reused"


def test_interrupted_run_resumes_without_redoing_finished_images(tiny_mission, tmp_path):
    """Kill the run once the first swing is rectified; the re-run keeps that swing."""
    out = tmp_path / "out"
    cal = str(tiny_mission / "truth" / "calibration.json")
    env = dict(os.environ)
    proc = subprocess.Popen([sys.executable, "-m", "swathflow.flows.cli", "run",
                             str(tiny_mission), "--out", str(out), "--calibration", cal],
                            env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            start_new_session=True)
    deadline = time.time() + 240
    first = None
    while time.time() < deadline and proc.poll() is None:
        done = sorted((out / "rectified").glob("*.tif.swathflow.json"))
        if done:
            first = done[0]
            break
        time.sleep(0.05)
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    if first is None:
        pytest.fail("the run finished or failed before any swing was rectified: "
                    + proc.stdout.read().decode()[-2000:])
    finished = {p.name: p.stat().st_mtime_ns for p in (out / "rectified").glob("*.tif")
                if Path(str(p) + ".swathflow.json").exists()}
    from swathflow.flows.mission import run
    result = run(tiny_mission, out, calibration=cal)
    for name, mtime in finished.items():
        assert (out / "rectified" / name).stat().st_mtime_ns == mtime, f"{name} was redone"
    assert len(result["rectified"]) >= len(finished)
    _check_against_truth(tiny_mission, result)
    leftovers = [p for p in out.rglob("*") if ".tmp" in p.name or p.name.endswith(".part")]
    assert not leftovers, f"half-written files left: {leftovers}"


def test_killed_dask_worker_does_not_break_rectification(tiny_mission, tmp_path):
    from distributed import Client, LocalCluster
    from swathflow.flows.mission import run
    out = tmp_path / "out"
    cal = str(tiny_mission / "truth" / "calibration.json")
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                      dashboard_address=None, silence_logs=40) as cluster, \
            Client(cluster) as client:
        killed = {}

        def killer():
            deadline = time.time() + 240
            while time.time() < deadline and not killed:
                busy = [w for w, tasks in client.processing().items() if tasks]
                if busy:
                    pids = client.run(os.getpid, workers=[busy[0]])
                    os.kill(pids[busy[0]], signal.SIGKILL)
                    killed["worker"] = busy[0]
                    return
                time.sleep(0.01)

        t = threading.Thread(target=killer, daemon=True)
        t.start()
        result = run(tiny_mission, out, calibration=cal, dask_address=cluster.scheduler_address)
        t.join(5)
    assert killed, "no Dask work was seen to kill a worker in"
    _check_against_truth(tiny_mission, result)


def test_flow_calibrates_and_maps_a_pushbroom_mission(tmp_path):
    """The same flow on a three-line push-broom mission: its own calibration (tie points,
    C0/C1), rectification and mosaic, unchanged; every view lands on the truth ortho."""
    from swathflow.formats.calibfile import read_calibration
    from swathflow.flows.mission import run
    from swathflow.sensors.pushbroom.simulate import simulate as simulate_pushbroom
    mission = tmp_path / "pb"
    simulate_pushbroom(mission, preset="pushbroom", seed=1)
    result = run(mission, tmp_path / "out")
    doc = read_calibration(result["calibration"])
    assert doc["sensor"] == "pushbroom" and result["report"]
    _check_against_truth(mission, result, tol_px=0.5)


def _files(out: Path) -> dict:
    """Every file of a run's output folder (the lock aside): bytes and modification time."""
    return {str(p.relative_to(out)): (p.read_bytes(), p.stat().st_mtime_ns)
            for p in sorted(out.rglob("*")) if p.is_file() and p.name != ".swathflow.lock"}


def test_nothing_to_recompute_exits_before_prefect_and_dask(tiny_mission, tmp_path):
    """A second `swathflow run` on unchanged inputs says so and exits 0 without importing
    Prefect or Dask (fresh interpreter); every output keeps its bytes and its mtime. A
    touched but unchanged input is still fresh (its content is compared)."""
    from swathflow.flows.mission import run
    mission = tmp_path / "mission"
    shutil.copytree(tiny_mission, mission)
    out = tmp_path / "out"
    cal = str(mission / "truth" / "calibration.json")
    first = run(mission, out, calibration=cal)
    assert not first.get("fresh")
    os.utime(mission / "pos.sbet")         # same content, new stamp
    before = _files(out)
    code = ("import sys\nfrom swathflow.flows.cli import main\n"
            f"rc = main(['run', {str(mission)!r}, '--out', {str(out)!r}, '--calibration', "
            f"{cal!r}])\n"
            "print('RC', rc, 'prefect' if 'prefect' in sys.modules else '-', "
            "'dask' if 'distributed' in sys.modules else '-')\n")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                       timeout=300)
    assert "RC 0 - -" in r.stdout, r.stdout + r.stderr
    assert "nothing to recompute" in r.stdout
    assert _files(out) == before, "a run with nothing to recompute changed its outputs"
    again = run(mission, out, calibration=cal)
    assert again["fresh"] and again["rectified"] == first["rectified"]
    assert again["mosaic"] == first["mosaic"]


def test_changed_image_recomputes_exactly_what_depends_on_it(tiny_mission, tmp_path):
    """One raw image changed: its swing, the mosaic and the catalogue are redone; the other
    swing and every POS product (they do not read pixels) keep their bytes and mtimes;
    a deleted output is written again; then the run is fresh again."""
    from swathflow.flows.mission import run
    mission = tmp_path / "mission"
    shutil.copytree(tiny_mission, mission)
    out = tmp_path / "out"
    cal = str(mission / "truth" / "calibration.json")
    first = run(mission, out, calibration=cal)
    before = _files(out)
    changed = Path(first["rectified"][0]).stem
    with rasterio.open(mission / "images" / f"{changed}.tif", "r+") as src:
        block = src.read(1, window=((0, 8), (0, 8)))
        src.write(block + 1, 1, window=((0, 8), (0, 8)))
    second = run(mission, out, calibration=cal)
    assert not second.get("fresh")
    after = _files(out)
    redone = {k for k in before if after.get(k) != before[k]}
    rect = {k for k in before if k.startswith("rectified/") and k.endswith(".tif")}
    assert f"rectified/{changed}.tif" in redone
    assert rect - {f"rectified/{changed}.tif"} and not (rect - {f"rectified/{changed}.tif"}) & redone
    assert "mosaic.tif" in redone
    assert not {k for k in redone if k.startswith("pos/")}, "POS products were redone"
    assert run(mission, out, calibration=cal)["fresh"]
    os.remove(out / "mosaic.tif")
    third = run(mission, out, calibration=cal)
    assert not third.get("fresh") and (out / "mosaic.tif").exists()
    kept = _files(out)
    assert all(kept[k] == after[k] for k in rect), "swings redone for a lost mosaic"


def test_workers_rectify_without_prefect(tiny_mission, tmp_path):
    """The rectify stage's worker code imports neither Prefect nor the flow (a worker
    would pay about a CPU second for it), and rectifies each swing with the mission
    handed over already loaded: each output against the truth."""
    code = ("import sys\nimport swathflow.tasks.swings\n"
            "print('prefect' if 'prefect' in sys.modules else '-')\n")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                       timeout=120)
    assert r.stdout.strip() == "-", r.stdout + r.stderr
    from swathflow.ingest.mission import load_mission
    from swathflow.tasks import swings
    m = load_mission(tiny_mission)
    swings.remember(tiny_mission, m)
    assert swings.load(tiny_mission) is m
    cal = str(tiny_mission / "truth" / "calibration.json")
    out = tmp_path / "out"
    ids = list(m.images)
    paths = [swings.rectify_one(i, str(tiny_mission), cal, str(out)) for i in ids]
    assert paths == [str(out / "rectified" / f"{i}.tif") for i in ids]
    _check_against_truth(tiny_mission, {"rectified": paths})


def test_mosaic_control_prepared_while_the_workers_rectify(tiny_mission, tmp_path):
    """The mosaic's control offsets are computed once per mission and calibration
    (``prepare_mosaic``, which the flow calls while the workers rectify; the mosaic stage
    then finds them), the same values as computed afresh, and again for a changed
    calibration file."""
    from swathflow.tasks import stages
    cal = tmp_path / "calibration.json"
    shutil.copy(tiny_mission / "truth" / "calibration.json", cal)
    stages._CONTROL.clear()
    stages.prepare_mosaic(str(tiny_mission), str(cal))
    assert len(stages._CONTROL) == 1
    (key, kept), = stages._CONTROL.items()
    again = stages.mosaic_control(str(tiny_mission), str(cal))
    assert list(stages._CONTROL) == [key] and again == kept and again is not kept
    stages._CONTROL.clear()
    fresh = stages.mosaic_control(str(tiny_mission), str(cal))
    assert fresh.keys() == again.keys() and all(
        np.array_equal(fresh[k][0], again[k][0]) and np.array_equal(fresh[k][1], again[k][1])
        for k in fresh)
    os.utime(cal, ns=(cal.stat().st_atime_ns, cal.stat().st_mtime_ns + 10**9))
    stages.mosaic_control(str(tiny_mission), str(cal))
    assert list(stages._CONTROL) != [key], "a changed calibration file used the old offsets"


def test_mission_memo_follows_every_file_of_the_folder(tmp_path):
    """The loaded mission's memo key stamps the files ``Path.rglob`` finds (files in
    subfolders, symbolic links to files; not links to folders, not broken links), and
    changes when any of them changes size or time."""
    import os

    from swathflow.tasks import swings
    (tmp_path / "images").mkdir()
    (tmp_path / "images" / "L1.tif").write_bytes(b"x")
    (tmp_path / "mission.toml").write_text("a")
    os.symlink(tmp_path / "mission.toml", tmp_path / "linked.toml")
    os.symlink(tmp_path / "images", tmp_path / "linked-folder")
    os.symlink(tmp_path / "missing", tmp_path / "broken")
    ref = sorted((str(p), p.stat().st_mtime_ns, p.stat().st_size)
                 for p in tmp_path.rglob("*") if p.is_file())
    assert sorted(swings._file_stamps(str(tmp_path))) == ref
    assert {os.path.basename(r[0]) for r in ref} == {"L1.tif", "mission.toml", "linked.toml"}
    before = swings.mission_stamp(tmp_path)
    assert swings.mission_stamp(tmp_path) == before
    (tmp_path / "images" / "L1.tif").write_bytes(b"xy")
    assert swings.mission_stamp(tmp_path) != before
    # no folder there: no files, and loading it says what is wrong
    from swathflow.errors import SwathflowError
    assert list(swings._file_stamps(str(tmp_path / "missing"))) == []
    with pytest.raises(SwathflowError, match="mission folder not found"):
        swings.load(tmp_path / "missing")
