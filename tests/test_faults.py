"""The fault suite of issue 13: each bad input or fault ends as one clear line naming the
file or key and the fix (exit code 2, no traceback), or as correct behaviour.

Every case starts from a simulated ``tiny`` mission (geometry only) whose truth is known,
breaks one thing the way a user would, and runs the real command line.
"""
from __future__ import annotations

import contextlib
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import rasterio
from faultkit import bad, pos_csv, run, run_fresh, toml
from swathflow.flows.cli import main
from swathflow.formats.pos import read_pos


# ------------------------------------------------------------------------------------------
# silently wrong results

def test_pos_angles_in_radians(m, capsys):
    pos_csv(m, lambda d: d.assign(**{k: np.radians(d[k]) for k in ("roll", "pitch",
                                                                     "heading")}))
    bad(capsys, m, "pos.csv", "radians", "degrees")


def test_swing_column_in_radians(m, capsys):
    p = m / "images" / "L1.lines.csv"
    d = pd.read_csv(p)
    d.assign(swing=np.radians(d.swing)).to_csv(p, index=False)
    bad(capsys, m, "L1.lines.csv", "swing", "radians")


def test_truncated_envi_refused(m_envi, capsys):
    img = next((m_envi / "images").glob("L1*.img"))
    data = img.read_bytes()
    img.write_bytes(data[: len(data) // 2])
    bad(capsys, m_envi, "L1", "truncated")


def test_truncated_geotiff_refused(m, capsys):
    """A raw GeoTIFF cut short (a copy that stopped) is refused by the mission check, the
    file named: its image blocks end beyond the file."""
    p = m / "images" / "L1.tif"
    data = p.read_bytes()
    p.write_bytes(data[: len(data) - 200])
    bad(capsys, m, "L1.tif", "truncated")


def test_multiband_image_warned(m, capsys):
    p = m / "images" / "L1.tif"
    with rasterio.open(p) as src:
        a, prof = src.read(1), src.profile
    prof.update(count=3)
    with rasterio.open(p, "w", **prof) as dst:
        for b in (1, 2, 3):
            dst.write(a, b)
    code, text = run(capsys, "validate", m)
    assert code == 0 and "warning" in text and "every band is rectified" in text


def test_simulated_pos_is_continuous(fault_base):
    """The simulator's POS: no epoch left at the origin (was lat 0, lon 118.5)."""
    ds = read_pos(fault_base / "pos.sbet")
    lat = ds.lat.values
    assert np.ptp(lat) < 0.01 and np.abs(np.diff(ds["roll"].values)).max() < 1.0


def test_pos_position_jump(m, capsys):
    pos_csv(m, lambda d: d.assign(lat=np.r_[d.lat.values[:-1], 0.0]))
    bad(capsys, m, "pos.csv", "jump")


def test_pos_gap_inside_image_warned(m, capsys):
    t = pd.read_csv(m / "images" / "L1.lines.csv").time.values
    mid = 0.5 * (t[0] + t[-1])
    pos_csv(m, lambda d: d[(d.time < mid) | (d.time > mid + 0.3)])
    code, text = run(capsys, "validate", m)
    assert code == 0 and "warning" in text and "POS gap" in text and "L1.lines.csv" in text


def test_misspelt_terrain_key(m, capsys):
    toml(m, 'vertical = "ellipsoidal"', 'vertcal = "orthometric"')
    bad(capsys, m, "vertcal", "vertical")


def test_misspelt_sensor_key(m, capsys):
    toml(m, "focal_length =", "focal_lenght =")
    bad(capsys, m, "focal_lenght", "focal_length")


def test_sensor_model_not_a_name(m, capsys):
    """Found by the mission.toml fuzzer: a list as the model name was a TypeError."""
    toml(m, 'model = "pendulum"', 'model = []')
    bad(capsys, m, "[sensor].model", "swathflow sensors")


def test_fractional_n_elements(m, capsys):
    toml(m, "n_elements = 64", "n_elements = 64.5")
    bad(capsys, m, "n_elements", "whole number")


def test_two_images_on_one_file(m, capsys):
    toml(m, 'file = "images/R1.tif"', 'file = "images/L1.tif"')
    bad(capsys, m, "R1", "also the file")


# ------------------------------------------------------------------------------------------
# runaways

@pytest.mark.parametrize("gsd, words", [("1e-6", ("gsd", "max_pixels")),
                                        ("0.002", ("gsd", "max_pixels")),
                                        ("1e6", ("gsd", "footprint"))])
def test_gsd_out_of_proportion(m, capsys, gsd, words):
    toml(m, "gsd = 0.4", f"gsd = {gsd}")
    bad(capsys, m, *words)


def test_run_on_slurm_without_sbatch_is_refused_at_once(m, tmp_path, monkeypatch, capsys):
    """``run --cluster slurm`` on a machine without SLURM waited for a worker for good."""
    monkeypatch.setenv("PATH", str(tmp_path))           # no sbatch there
    t0 = time.monotonic()
    code, text = run(capsys, "run", m, "--out", tmp_path / "o", "--cluster", "slurm",
                     "--calibration", m / "truth" / "calibration.json")
    assert code == 2 and "sbatch" in text and "--cluster local" in text, text
    assert time.monotonic() - t0 < 300          # not the first worker's wait (600 s)


def test_waiting_for_the_first_worker_ends(tmp_path):
    """A SLURM job that never starts: the wait for its worker ends after its timeout with
    a message saying what to check (Dask's own wait ignored the timeout there)."""
    from swathflow.cluster import first_worker
    from swathflow.errors import SwathflowError

    class NoWorkers:                    # a scheduler no worker ever joins
        def scheduler_info(self):
            return {"workers": {}}
    with pytest.raises(SwathflowError, match="no SLURM worker job started within 1 s"):
        first_worker(NoWorkers(), 1.0)


def test_max_pixels_lifts_the_limit(m, capsys):
    toml(m, "gsd = 0.4", "gsd = 0.002\nmax_pixels = 1e12")
    code, text = run(capsys, "validate", m)
    assert code == 0, text


def test_run_validates_before_starting_prefect(m, tmp_path):
    """Bad input is reported before the flow (Prefect) or a Dask cluster is even imported:
    checked in a fresh interpreter, from the modules loaded when the command returns."""
    toml(m, "gsd = 0.4", "gsd = -1")
    status, text = run_fresh("run", m, "--out", tmp_path / "o")
    assert "[mission].gsd" in text
    assert status == "RC 2 - -", text


# ------------------------------------------------------------------------------------------
# data lost or half-written

def test_mosaic_never_writes_over_an_input(tmp_path, capsys):
    from swathflow.formats.raster import write_geotiff
    d = tmp_path / "r"
    a = np.arange(64, dtype=np.float32).reshape(8, 8)
    write_geotiff(d / "L1.tif", a, "EPSG:32651", (1, 0, 0, 0, -1, 8), nodata=-9999.0,
                  tags={"image_id": "L1"})
    before = (d / "L1.tif").read_bytes()
    code, text = run(capsys, "mosaic", d, "--out", d / "L1.tif", "--workers", "1")
    assert code == 2 and "input" in text
    assert (d / "L1.tif").read_bytes() == before


def test_simulate_into_existing_mission_needs_force(m, capsys):
    before = (m / "pos.sbet").read_bytes()
    code, text = run(capsys, "simulate", m, "--preset", "tiny", "--seed", "5",
                      "--geometry-only")
    assert code == 2 and "--force" in text
    assert (m / "pos.sbet").read_bytes() == before


def test_simulate_gross_errors_out_of_range(tmp_path, capsys):
    code, text = run(capsys, "simulate", tmp_path / "g", "--gross-errors", "2.0")
    assert code == 2 and "--gross-errors" in text
    assert not (tmp_path / "g").exists()


def test_stale_temporaries_of_a_killed_writer_are_cleared(tmp_path):
    from swathflow.io import write_text
    p = subprocess.Popen([sys.executable, "-c", "pass"])
    p.wait()                                   # a process id that no longer runs
    stale = tmp_path / f".out.txt.{p.pid}.abc.tmp.txt"
    stale.write_text("half")
    write_text(tmp_path / "out.txt", "whole")
    assert not stale.exists() and (tmp_path / "out.txt").read_text() == "whole"


def test_sigterm_exits_143_with_a_message(tmp_path):
    proc = subprocess.Popen([sys.executable, "-m", "swathflow.flows.cli", "simulate",
                             str(tmp_path / "d"), "--preset", "demo"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    # terminate once the run is writing (its output folder exists), not after a fixed
    # sleep: on a loaded machine the imports alone can take longer than any fixed delay
    for _ in range(600):
        if (tmp_path / "d").exists() or proc.poll() is not None:
            break
        time.sleep(0.1)
    time.sleep(1)
    proc.terminate()
    _out, err = proc.communicate(timeout=60)
    assert proc.returncode == 143, err
    assert "terminated" in err and "Traceback" not in err


@pytest.mark.parametrize("kind, code, word", [("sigterm", 143, "terminated"),
                                              ("ctrl-c", 130, "interrupted")])
def test_a_signal_raised_inside_compiled_code_still_ends_the_run_as_signalled(
        tmp_path, monkeypatch, capsys, kind, code, word):
    """A signal handler that raises inside Python code called by compiled code (numba's
    dispatcher unpickling a function) reaches the command as a SystemError whose cause is
    the signal's exception (CI of stop 26): still the signal's exit code and one line."""
    from swathflow.flows.cli import commands
    from swathflow.flows.guard import Terminated

    def simulate(args):
        try:
            raise Terminated() if kind == "sigterm" else KeyboardInterrupt()
        except BaseException as exc:
            raise SystemError("CPUDispatcher(<function hits>) returned a result with an "
                              "exception set") from exc
    monkeypatch.setattr(commands, "simulate", simulate)
    assert main(["simulate", str(tmp_path / "d"), "--preset", "demo"]) == code
    err = capsys.readouterr().err
    assert word in err and "Traceback" not in err and "SystemError" not in err


@pytest.mark.filterwarnings("ignore::pytest.PytestUnraisableExceptionWarning")  # expected
def test_a_sigterm_whose_exception_was_swallowed_still_ends_the_run_as_terminated(
        tmp_path, monkeypatch, capsys):
    """SIGTERM handled inside a ``__del__`` (or a callback of compiled code): Python only
    prints its exception as "Exception ignored" and the command goes on; when it returns,
    the run still ends as terminated (143), not as a success."""
    import gc
    import signal

    from swathflow.flows.cli import commands

    class Finaliser:
        def __del__(self):
            os.kill(os.getpid(), signal.SIGTERM)
            for _ in range(1000):        # the handler runs between these bytecodes
                pass

    def simulate(args):
        Finaliser()
        gc.collect()
        return 0
    monkeypatch.setattr(commands, "simulate", simulate)
    assert main(["simulate", str(tmp_path / "d"), "--preset", "demo"]) == 143
    err = capsys.readouterr().err
    assert "terminated" in err


# ------------------------------------------------------------------------------------------
# tracebacks

@pytest.mark.parametrize("argv", [["mosaic", "SRC", "--tile", "0", "--out", "x.tif"],
                                  ["rectify", "SRC", "--tile", "-5", "--out", "o"],
                                  ["mosaic", "SRC", "--feather", "0", "--out", "x.tif"],
                                  ["mosaic", "SRC", "--workers", "0", "--out", "x.tif"],
                                  ["mosaic", "SRC", "--max-shift", "-1", "--out", "x.tif"]])
def test_non_positive_arguments(fault_base, argv, capsys):
    argv = [str(fault_base) if a == "SRC" else a for a in argv]
    with pytest.raises(SystemExit) as e:
        main(argv)
    assert e.value.code == 2
    err = capsys.readouterr().err
    assert "must be 1 or more" in err and "Traceback" not in err


@pytest.mark.parametrize("cmd", ["calibrate", "rectify", "run"])
@pytest.mark.parametrize("where", ["file", "proc"])
def test_out_unusable(fault_base, tmp_path, capsys, cmd, where):
    out = tmp_path / "f" if where == "file" else Path("/proc/swathflow-out")
    if where == "file":
        out.write_text("x")
    code, text = run(capsys, cmd, fault_base, "--out", out)
    assert code == 2 and str(out) in text


def test_mosaic_out_under_proc(fault_base, capsys):
    code, text = run(capsys, "mosaic", fault_base, "--out", "/proc/x/m.tif")
    assert code == 2 and "/proc/x" in text


# ------------------------------------------------------------------------------------------
# misleading messages

def test_swapped_lat_lon(m, capsys):
    pos_csv(m, lambda d: d.rename(columns={"lat": "lon", "lon": "lat"}))
    bad(capsys, m, "pos.csv", "swap")


def test_latitude_out_of_range(m, capsys):
    pos_csv(m, lambda d: d.assign(lat=d.lat + 100.0))
    line = bad(capsys, m, "pos.csv", "lat", "outside")
    assert "DEM" not in line


def test_sbet_holding_degrees(m, capsys):
    from swathflow.formats.pos import write_sbet
    ds = read_pos(m / "pos.sbet")
    deg = ds.copy()
    for k in ("lat", "lon", "roll", "pitch", "heading"):
        deg[k] = np.degrees(ds[k])              # the file then stores degrees
    write_sbet(deg, m / "pos.sbet")
    line = bad(capsys, m, "pos.sbet", "degrees")
    assert "DEM" not in line


def test_dem_above_the_aircraft(m, capsys):
    p = m / "dem.tif"
    with rasterio.open(p) as src:
        a, prof = src.read(1), src.profile
    with rasterio.open(p, "w", **prof) as dst:
        dst.write(a + 5000.0, 1)
    bad(capsys, m, "dem.tif", "above the aircraft")


def test_gcp_x_y_swapped(m, capsys):
    p = m / "gcp.csv"
    d = pd.read_csv(p)
    d.rename(columns={"x": "y", "y": "x"}).to_csv(p, index=False)
    bad(capsys, m, "gcp.csv", "swap the x and y")


def test_readme_path_simulate_then_calibrate(fault_base, tmp_path, capsys):
    code, text = run(capsys, "calibrate", fault_base, "--out", tmp_path / "cal")
    assert code == 0, text
    assert (tmp_path / "cal" / "calibration.json").exists()


def test_rectify_without_calibration_says_so(fault_base, tmp_path, capsys):
    code, text = run(capsys, "rectify", fault_base, "--out", tmp_path / "r", "--images", "L1")
    assert code == 0 and "no --calibration" in text
    with rasterio.open(tmp_path / "r" / "L1.tif") as src:
        assert src.tags()["calibration"].startswith("none")


def _plugin(tmp_path, monkeypatch, body: str):
    from importlib.metadata import EntryPoint

    from swathflow.sensormodel import registry
    mod = tmp_path / "badplugin_mod.py"
    mod.write_text(body)
    monkeypatch.syspath_prepend(str(tmp_path))
    # the installed entry points (the built-in sensors among them) and one broken plugin
    eps = [*registry.entry_points(group=registry.GROUP),
           EntryPoint("broken", "badplugin_mod:Model", registry.GROUP)]
    monkeypatch.setattr(registry, "entry_points", lambda group: eps)
    registry.refresh()
    return registry


@pytest.mark.parametrize("body", [
    "import sys\nsys.exit('no licence')\n",
    "class Stop(BaseException):\n    pass\nraise Stop('bye')\n",
    "from swathflow.sensormodel import SensorModel\nclass Model(SensorModel):\n    pass\n",
])
def test_broken_plugin_warns_and_is_skipped(tmp_path, monkeypatch, capsys, body):
    sys.modules.pop("badplugin_mod", None)
    reg = _plugin(tmp_path, monkeypatch, body)
    try:
        code, text = run(capsys, "sensors")
        assert code == 0 and "pendulum" in text and "broken" in text and "skipped" in text
        assert "broken" not in reg.list_sensors()
    finally:
        monkeypatch.undo()
        reg.refresh()
        sys.modules.pop("badplugin_mod", None)


def test_mosaic_shift_stays_within_the_input_range():
    """A sub-pixel shift of a step (cubic spline) must not overshoot the inputs."""
    from swathflow.mosaicking.blend import corrected_swing
    step = np.where(np.arange(40)[None] < 20, 887.0, 13207.0) * np.ones((40, 1))
    ok = np.ones_like(step, bool)
    c = corrected_swing(step, ok, 0, 0, np.array([0.4, 0.45]), 0.0, feather=8)
    val = c.values[c.weight > 0]
    assert val.min() >= 887.0 and val.max() <= 13207.0


# ------------------------------------------------------------------------------------------
# resources: locks, full disks

def test_second_run_on_one_out_names_the_lock_holder(fault_base, tmp_path, capsys):
    out = tmp_path / "o"
    out.mkdir()
    holder = subprocess.Popen(
        [sys.executable, "-c",
         "import argparse, sys, time\n"
         "from swathflow.flows.guard import output_lock\n"
         "a = argparse.Namespace(command='rectify', out=sys.argv[1])\n"
         "with output_lock(a):\n"
         "    print('locked', flush=True)\n"
         "    time.sleep(60)\n", str(out)], stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "locked"
        code, text = run(capsys, "rectify", fault_base, "--out", out)
        assert code == 2 and f"process {holder.pid}" in text
    finally:
        holder.kill()
        holder.wait()
    assert not list(out.glob("*.tif"))      # the refused run did no work


def test_disk_full_is_one_clear_line(tmp_path):
    full = tmp_path / "full"
    full.mkdir()
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=300k", "tmpfs", str(full)],
                       capture_output=True)
    if r.returncode:
        pytest.skip("cannot mount a small tmpfs here (needs root)")
    try:
        p = subprocess.run([sys.executable, "-m", "swathflow.flows.cli", "simulate",
                            str(full / "m"), "--preset", "tiny", "--geometry-only"],
                           capture_output=True, text=True, timeout=120)
    finally:
        subprocess.run(["umount", str(full)], check=False)
    assert p.returncode == 2, p.stderr
    assert "disk is full" in p.stderr and "Traceback" not in p.stderr


@pytest.mark.slow
def test_readme_path_simulate_then_run(tmp_path):
    """The README's own example: simulate --preset tiny, then run (calibration included)."""
    m = tmp_path / "tiny"
    assert main(["simulate", str(m), "--preset", "tiny"]) == 0
    assert main(["run", str(m), "--out", str(tmp_path / "out")]) == 0
    assert (tmp_path / "out" / "mosaic.tif").exists()


@pytest.mark.slow
def test_sigterm_during_run_stops_the_prefect_server(fault_base, tmp_path):
    """SIGTERM while the flow runs: exit 143, and no server process of ours is left."""
    import signal
    proc = subprocess.Popen([sys.executable, "-m", "swathflow.flows.cli", "run", str(fault_base),
                             "--out", str(tmp_path / "o")], stderr=subprocess.PIPE, text=True,
                            start_new_session=True)
    children = []
    for _ in range(60):
        time.sleep(1)
        children = subprocess.run(["pgrep", "-P", str(proc.pid)], capture_output=True,
                                  text=True).stdout.split()
        if children:
            break
    assert children, "the run started no server or worker process"
    time.sleep(3)
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 143 and "terminated" in err
    time.sleep(5)
    alive = []
    for pid in children:
        try:
            os.kill(int(pid), 0)
            alive.append(pid)
        except ProcessLookupError:
            pass
    assert not alive, f"left running: {alive}"


@pytest.mark.parametrize("content, words", [
    ('{"format": "swathflow-calibration", "sensor": "another-scanner", '
     '"parameters": {"a": {"value": [1.0]}}}', ("another-scanner", "sensor")),
    ("{not json", ("not valid JSON",))])
def test_run_checks_the_calibration_before_starting_prefect(m, tmp_path, content, words):
    """A calibration file that is not JSON, or is for another sensor, is reported (file
    named, exit 2) before the flow (Prefect) or Dask is imported (fresh interpreter)."""
    from swathflow.formats.calibfile import FORMAT
    cal = tmp_path / "cal.json"
    cal.write_text(content.replace("swathflow-calibration", FORMAT))
    status, text = run_fresh("run", m, "--out", tmp_path / "o", "--calibration", cal)
    assert status == "RC 2 - -", text
    assert str(cal) in text and all(w in text for w in words), text
    assert "Traceback" not in text


def test_sigterm_while_the_workers_rectify_stops_everything(fault_base, tmp_path):
    """SIGTERM once the workers are rectifying (the calibration given): exit 143, one
    line, and no process of ours left (the cluster and the server closed on the way
    out), waited for by polling, not by fixed sleeps."""
    import signal
    out = tmp_path / "o"
    proc = subprocess.Popen([sys.executable, "-m", "swathflow.flows.cli", "run", str(fault_base),
                             "--out", str(out), "--calibration",
                             str(fault_base / "truth" / "calibration.json")],
                            stderr=subprocess.PIPE, text=True, start_new_session=True)
    deadline = time.monotonic() + 300
    while time.monotonic() < deadline and proc.poll() is None \
            and not list((out / "rectified").glob("*.swathflow.json")):
        time.sleep(0.02)
    children = subprocess.run(["pgrep", "-P", str(proc.pid)], capture_output=True,
                              text=True).stdout.split()
    assert proc.poll() is None and children, "the run ended before a swing was rectified"
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 143 and "terminated" in err and "Traceback" not in err, err
    alive = set(children)
    deadline = time.monotonic() + 60      # the children's own exit, polled
    while alive and time.monotonic() < deadline:
        for pid in list(alive):
            try:
                with open(f"/proc/{pid}/stat") as f:
                    if f.read().split(") ", 1)[1].startswith("Z"):
                        alive.discard(pid)
            except FileNotFoundError:
                alive.discard(pid)
        time.sleep(0.05)
    assert not alive, f"left running: {alive}"


def _run_until_rectifying(base, tmp_path):
    """``swathflow run`` of ``base`` started as a terminal's job would be (a process group
    of its own, stdout and stderr to one file), returned once its workers have rectified
    a swing: (the process, the processes it started, the file)."""
    import psutil
    out, err_file = tmp_path / "o", tmp_path / "stderr.txt"
    with open(err_file, "w") as err:
        proc = subprocess.Popen([sys.executable, "-m", "swathflow.flows.cli", "run",
                                 str(base), "--out", str(out), "--calibration",
                                 str(base / "truth" / "calibration.json")],
                                stdout=err, stderr=err, start_new_session=True)
    deadline = time.monotonic() + 300
    while time.monotonic() < deadline and proc.poll() is None \
            and not list((out / "rectified").glob("*.swathflow.json")):
        time.sleep(0.02)
    started = psutil.Process(proc.pid).children(recursive=True)
    assert proc.poll() is None and started, "the run ended before a swing was rectified"
    return proc, started, err_file


def _end(started) -> None:
    """End what a test's run left running, by process id."""
    import psutil
    for p in started:
        with contextlib.suppress(psutil.Error):
            p.kill()


@pytest.mark.slow
def test_kill_9_of_a_run_leaves_nothing_on_the_terminal(fault_base, tmp_path):
    """``kill -9`` of ``swathflow run`` while the workers rectify: what the run started
    goes on writing to the same terminal once the shell's prompt is back (Python's
    multiprocessing resource tracker reported the semaphores of Dask's nannies in a
    two-line UserWarning): nothing of that reaches it. Checked once the run's worker
    processes and its resource tracker have ended (polled); what is still serving is
    ended by process id after."""
    import signal

    import psutil
    proc, started, err_file = _run_until_rectifying(fault_base, tmp_path)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    try:
        multi = [p for p in started if "multiprocessing" in _cmdline(p)]
        assert multi, "no worker or resource tracker among the run's processes"
        _, alive = psutil.wait_procs(multi, timeout=90)
        assert not alive, f"still running 90 s after the kill: {[p.pid for p in alive]}"
        text = err_file.read_text()
        assert not [ln for ln in text.splitlines() if ln.strip()], text
    finally:
        _end(started)


@pytest.mark.slow
def test_ctrl_c_at_the_terminal_prints_one_line(fault_base, tmp_path):
    """Ctrl-C while the workers rectify: the terminal sends SIGINT to the whole job, the
    Dask workers and Prefect's temporary server too. Each worker printed a
    KeyboardInterrupt traceback, and Prefect's event and log workers an ERROR line and
    "--- Error logging to API ---" for each call that no longer reached the server: now
    the run's one line, exit 130, once everything it started has ended (polled)."""
    import signal

    import psutil
    proc, started, err_file = _run_until_rectifying(fault_base, tmp_path)
    os.killpg(proc.pid, signal.SIGINT)
    try:
        assert proc.wait(timeout=120) == 130
        _, alive = psutil.wait_procs(started, timeout=90)
        assert not alive, f"still running 90 s after: {[p.pid for p in alive]}"
        lines = [ln for ln in err_file.read_text().splitlines() if ln.strip()]
        assert len(lines) == 1 and lines[0].startswith("swathflow run: interrupted"), lines
    finally:
        _end(started)


def _cmdline(p) -> str:
    import psutil
    try:
        return " ".join(p.cmdline())
    except psutil.Error:
        return ""
