"""Issue 44, hostile missions: a result that is not a result is an error, "OK" from
``validate`` means the mission runs, every argument and size is bounded before memory is
allocated, and every message names the file, row or key and the real cause.

Each case breaks one thing of a simulated ``tiny`` mission (geometry only: its images are
a constant 1000, its control points exact) the way a user would, and runs the real
command line (or the public Python API)."""
from __future__ import annotations

import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import rasterio
from faultkit import bad, pos_csv, run, toml
from swathflow.flows.cli import main

pytestmark = pytest.mark.filterwarnings("ignore::rasterio.errors.NotGeoreferencedWarning")


def _argv_refused(capsys, argv, *words) -> str:
    with pytest.raises(SystemExit) as e:
        main([str(a) for a in argv])
    assert e.value.code == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err and all(w in err for w in words), err
    return err


def _gcps_moved(m, **change) -> None:
    p = m / "gcp.csv"
    d = pd.read_csv(p, dtype={"gcp_id": str, "image_id": str})
    for col, fn in change.items():
        d[col] = fn(d)
    d.to_csv(p, index=False, float_format="%.9f")


# ------------------------------------------------------------------------------------------
# a calibration that estimated nothing is an error; each dropped observation is named

def test_calibration_from_no_usable_observation_is_an_error(fault_base):
    """GCP heights 30 km off: every observation unprojectable; calibrate wrote the priors
    as the calibration ("sigma0 nan, 0 iterations", converged) and exited 0."""
    import dataclasses

    from swathflow.calibration.strategy import calibrate_mission
    from swathflow.calibration.unknowns import CalibrationError
    from swathflow.geometry.geodesy import geodetic_to_ecef
    from swathflow.ingest.mission import load_mission
    mission = load_mission(fault_base)
    g = mission.gcps.copy()
    xyz = geodetic_to_ecef(np.stack([g["lat"], g["lon"], g["h"] + 30000.0], -1))
    g["X"], g["Y"], g["Z"] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    with pytest.warns(UserWarning, match="G0001"), \
            pytest.raises(CalibrationError, match="nothing estimated"):
        calibrate_mission(dataclasses.replace(mission, gcps=g))


def test_gcp_heights_above_the_aircraft_fail_validation(m, capsys):
    """validate said OK for GCP heights off by 30 km (or in millimetres)."""
    _gcps_moved(m, z=lambda d: d.z + 30000.0)
    bad(capsys, m, "gcp.csv", "column z", "above the aircraft")


def test_a_control_point_the_adjustment_cannot_use_is_named_everywhere(m, tmp_path,
                                                                        capsys):
    """A GCP 9 km off was dropped without a word: now it is in the calibration's rejected
    list (phase "dropped", with the reason), in the report and in one warning naming its
    image (the calibration still runs on the others)."""
    import json
    d = pd.read_csv(m / "gcp.csv", dtype={"gcp_id": str, "image_id": str})
    moved = d.gcp_id.iloc[0]
    image = d.image_id.iloc[0]
    _gcps_moved(m, x=lambda d: np.where(d.gcp_id == moved, d.x + 0.096, d.x))  # ~9 km east
    code, text = run(capsys, "calibrate", m, "--out", tmp_path / "cal")
    assert code == 0, text
    warned = [ln for ln in text.splitlines() if moved in ln]
    assert len(warned) == 1 and "warning:" in warned[0] and image in warned[0], text
    assert "does not project into the image" in warned[0]
    assert "1 dropped" in text
    doc = json.loads((tmp_path / "cal" / "calibration.json").read_text())
    rows = [r for r in doc["rejected"] if r["gcp_id"] == moved]
    assert rows == [{**rows[0], "name": f"{moved}@{image}", "phase": "dropped",
                     "image_id": image}]
    assert "does not project into the image" in rows[0]["reason"]
    html = (tmp_path / "cal" / "report.html").read_text()
    assert f"{moved}@{image}" in html and "1 dropped" in html


# ------------------------------------------------------------------------------------------
# prior sigmas: negative, NaN, infinite refused; 0 holds the parameter at its value

@pytest.mark.parametrize("sigma", ["-1.0", "nan", "inf"])
def test_bad_prior_sigma_refused(m, capsys, sigma):
    toml(m, "opk_sen = { value = [0.0, 0.0, 0.0], sigma = [1.0, 1.0, 1.0] }",
          f"opk_sen = {{ value = [0.0, 0.0, 0.0], sigma = [1.0, {sigma}, 1.0] }}")
    bad(capsys, m, "[calibration].opk_sen.sigma", ">= 0")


def test_prior_sigma_zero_holds_the_parameter_at_its_value(m, tmp_path, capsys):
    """sigma 0 means "fixed": the calibration keeps exactly the value given (0.3 deg, the
    truth being another), while the other parameters are estimated."""
    import json
    toml(m, "opk_sen = { value = [0.0, 0.0, 0.0], sigma = [1.0, 1.0, 1.0] }",
          "opk_sen = { value = [0.3, 0.0, 0.0], sigma = [0.0, 1.0, 1.0] }")
    code, text = run(capsys, "calibrate", m, "--out", tmp_path / "cal")
    assert code == 0, text
    doc = json.loads((tmp_path / "cal" / "calibration.json").read_text())
    assert doc["parameters"]["opk_sen"]["value"][0] == 0.3
    assert doc["parameters"]["opk_sen"]["value"][1] != 0.0      # estimated


def test_absurd_prior_angle_is_named_as_such(m, capsys):
    """An ``opk_sen`` prior of 1e308 degrees was reported as a DEM not covering the ground."""
    toml(m, "opk_sen = { value = [0.0, 0.0, 0.0]", "opk_sen = { value = [1e308, 0.0, 0.0]")
    line = bad(capsys, m, "[calibration].opk_sen", "degrees")
    assert "DEM" not in line


def test_calibration_without_parameters_is_refused():
    """A calibration document with no parameters silently meant the priors."""
    from swathflow.errors import FormatError
    from swathflow.formats.calibfile import FORMAT, calibration_priors
    with pytest.raises(FormatError, match="no parameters"):
        calibration_priors({"format": FORMAT, "sensor": "pendulum", "parameters": {}})


def test_rectify_api_refuses_a_calibration_without_parameters(fault_base):
    import swathflow
    from swathflow.errors import FormatError
    from swathflow.formats.calibfile import FORMAT
    with pytest.raises(FormatError, match="no parameters"):
        swathflow.rectify(fault_base, "L1", {"format": FORMAT, "sensor": "pendulum"})


@pytest.mark.parametrize("rounds", ["0", "-3"])
def test_rounds_below_one_refused(fault_base, tmp_path, capsys, rounds):
    """``--rounds 0`` and ``-3`` ran one round."""
    _argv_refused(capsys, ["calibrate", fault_base, "--out", tmp_path / "c", "--rounds", rounds],
                  "--rounds")


# ------------------------------------------------------------------------------------------
# raw images: empty, complex, an ENVI file larger than its header says

@pytest.mark.parametrize("fill, nodata", [(np.nan, None), (1000.0, 1000.0)])
def test_image_without_a_valid_pixel_refused(m, capsys, fill, nodata):
    """All-NaN or all-nodata raw images gave empty products, exit 0, and STAC footprints
    claiming full coverage."""
    p = m / "images" / "L1.tif"
    with rasterio.open(p) as src:
        prof = src.profile
    prof.update(dtype="float32", nodata=nodata)
    with rasterio.open(p, "w", **prof) as dst:
        dst.write(np.full((1, prof["height"], prof["width"]), fill, np.float32))
    bad(capsys, m, "L1.tif", "no valid pixel")


def test_image_with_a_few_valid_pixels_passes(m, capsys):
    """The check reads a sample of lines first: an image valid on one line only is fine."""
    p = m / "images" / "L1.tif"
    with rasterio.open(p) as src:
        prof = src.profile
    a = np.full((1, prof["height"], prof["width"]), np.nan, np.float32)
    a[0, 7, 3] = 5.0                              # on no sampled line
    prof.update(dtype="float32", nodata=None)
    with rasterio.open(p, "w", **prof) as dst:
        dst.write(a)
    code, text = run(capsys, "validate", m)
    assert code == 0, text


def test_complex_image_refused(m, capsys):
    p = m / "images" / "L1.tif"
    with rasterio.open(p) as src:
        prof, a = src.profile, src.read()
    prof.update(dtype="complex64")
    with rasterio.open(p, "w", **prof) as dst:
        dst.write(a.astype(np.complex64) * (1 + 1j))
    bad(capsys, m, "L1.tif", "complex")


def test_envi_data_larger_than_its_header_refused(m_envi, capsys):
    """A 5-band BIL read as 3 came out scrambled: the data file is larger than the header
    accounts for."""
    img = next(p for p in (m_envi / "images").glob("L1*") if p.suffix not in (".hdr", ".csv"))
    img.write_bytes(img.read_bytes() * 2)
    bad(capsys, m_envi, "L1", "header")


def test_envi_wavelength_list_of_the_wrong_length_fails_validation(m_envi, capsys):
    """validate said OK, rectify then refused the header."""
    hdr = next((m_envi / "images").glob("L1*.hdr"))
    hdr.write_text(hdr.read_text() + "wavelength = {500, 600}\nfwhm = {10}\n")
    bad(capsys, m_envi, "L1", "wavelength")


@pytest.mark.parametrize("bands", ['"4"', '"550nm"', '"x-y"', "[0]"])
def test_rectify_bands_that_do_not_fit_fail_validation(m, capsys, bands):
    toml(m, "[calibration]", f"[rectify]\nbands = {bands}\n\n[calibration]")
    bad(capsys, m, "[rectify].bands")


def test_reference_table_is_validated(m, capsys):
    toml(m, "[calibration]", '[reference]\northo = "nowhere.tif"\n\n[calibration]')
    bad(capsys, m, "nowhere.tif", "not found")


def _ortho(path, crs, transform, shape=(64, 64)):
    from swathflow.formats.raster import write_geotiff
    a = np.random.default_rng(0).random(shape).astype(np.float32)
    write_geotiff(path, a, crs, transform, nodata=np.nan)


def test_reference_in_degrees_fails_validation_and_never_allocates(m, capsys):
    """A reference orthophoto in EPSG:4326 was a 2.55 PiB MemoryError (the 40 m margin
    divided by a pixel size in degrees)."""
    from swathflow.calibration.reference import open_reference
    from swathflow.errors import FormatError
    _ortho(m / "ref.tif", "EPSG:4326", (4e-6, 0, 120.44, 0, -4e-6, 32.54))
    toml(m, "[calibration]", '[reference]\northo = "ref.tif"\n\n[calibration]')
    bad(capsys, m, "ref.tif", "not projected")
    with pytest.raises(FormatError, match="not projected"):
        open_reference(m / "ref.tif")


def test_a_reference_finer_than_the_swing_is_matched_on_coarser_pixels():
    """A 0.02 m reference for 0.4 m pixels ran for minutes at 4.9 GB: matched on pixels no
    finer than half the swing's (0.2 m), each the mean of the 10 x 10 it covers."""
    from affine import Affine
    from swathflow.calibration.reference import Reference, coarsened
    from swathflow.geometry.grid import Grid
    img = np.arange(100 * 60, dtype=float).reshape(100, 60)
    ref = Reference("r.tif", img, Grid("EPSG:32651", Affine(0.02, 0, 5e5, 0, -0.02, 3.6e6),
                                       img.shape))
    c = coarsened(ref, 0.4)
    assert c.res == pytest.approx(0.2) and c.image.shape == (10, 6)
    assert c.image[1, 2] == pytest.approx(img[10:20, 20:30].mean())
    assert coarsened(ref, 0.04) is ref                    # not finer than half: as is


# ------------------------------------------------------------------------------------------
# arguments and sizes bounded before memory is allocated

@pytest.mark.parametrize("argv, words", [
    (["rectify", "SRC", "--out", "OUT", "--tile", "1"], ("--tile", "16")),
    (["rectify", "SRC", "--out", "OUT", "--tile", "100000000"], ("--tile", "4096")),
    (["mosaic", "SRC", "--out", "OUT.tif", "--tile", "1"], ("--tile", "16")),
    (["mosaic", "SRC", "--out", "OUT.tif", "--tile", "100000000"], ("--tile", "4096")),
    (["mosaic", "SRC", "--out", "OUT.tif", "--max-shift", "100000"], ("--max-shift", "256")),
    (["simulate", "OUT", "--seed", "-5"], ("--seed",)),
    (["run", "SRC", "--out", "OUT", "--jobs", "0"], ("--jobs",)),
    (["simulate", "OUT", "--gcp-noise", "nan"], ("--gcp-noise", "finite")),
])
def test_out_of_range_arguments_refused(fault_base, tmp_path, capsys, argv, words):
    argv = [str(fault_base) if a == "SRC" else str(tmp_path / "o") + a[3:] if a.startswith("OUT")
            else a for a in argv]
    _argv_refused(capsys, argv, *words)
    assert not (tmp_path / "o").exists()


def test_max_pixels_of_1e300_refused(m, capsys):
    toml(m, "gsd = 0.4", "gsd = 0.4\nmax_pixels = 1e300")
    bad(capsys, m, "[mission].max_pixels")


@pytest.mark.parametrize("name, kind", [("gcp.csv", "fifo"), ("gcp.csv", "device"),
                                        ("pos.sbet", "fifo")])
def test_mission_file_that_is_a_fifo_or_a_device_refused(m, name, kind):
    """A GCP file that is a FIFO hung validate; /dev/zero filled memory. Run in a child
    with a time limit: a hang fails the test instead of stalling the suite."""
    (m / name).unlink()
    if kind == "fifo":
        os.mkfifo(m / name)
    else:
        os.symlink("/dev/zero", m / name)
    r = subprocess.run([sys.executable, "-m", "swathflow.flows.cli", "validate", str(m)],
                       capture_output=True, text=True, timeout=240)
    assert r.returncode == 2, r.stdout + r.stderr
    assert name in r.stdout and "not a regular file" in r.stdout, r.stdout


def test_read_pos_with_a_number_as_format_is_a_clear_error(fault_base):
    from swathflow.errors import FormatError
    from swathflow.formats.pos import read_pos
    with pytest.raises(FormatError, match="format"):
        read_pos(fault_base / "pos.sbet", format=5)


# ------------------------------------------------------------------------------------------
# messages name the file, row or key and the real cause

def _pos_with_nan_time(m: Path, fmt: str) -> Path:
    """The mission's POS written in format ``fmt`` (mission.toml pointed at it) with a NaN
    time at epoch 7 (after t of epoch 6, which the message names): the written file."""
    from swathflow.formats.navigation.lcf import write_lcf
    from swathflow.formats.pos import read_pos, write_pos_csv, write_sbet
    ds = read_pos(m / "pos.sbet")
    t = ds.time.values.copy()
    t[7] = np.nan
    ds = ds.assign_coords(time=t)
    path = m / f"nav.{fmt}"
    if fmt == "sbet":
        write_sbet(ds, path)
    elif fmt == "csv":
        write_pos_csv(ds, path)
    elif fmt == "lcf":
        write_lcf(ds, path)
    else:                               # an Inertial Explorer export, "nan" as exported
        pd.DataFrame({"GPSTime": t, "Latitude": ds.lat.values, "Longitude": ds.lon.values,
                      "H-Ell": ds.h.values, "Roll": ds["roll"].values,
                      "Pitch": ds["pitch"].values, "Heading": ds["heading"].values}
                     ).to_csv(path, index=False, na_rep="nan", float_format="%.10f")
    (m / "pos.sbet").unlink()
    toml(m, 'file = "pos.sbet"\nformat = "sbet"', f'file = "nav.{fmt}"\nformat = "{fmt}"')
    return path


@pytest.mark.parametrize("fmt", ["sbet", "csv", "lcf", "ascii"])
def test_nan_time_in_every_pos_format_names_the_file_and_epoch(m, capsys, fmt):
    """A NaN time gave "unexpected content (ValueError: cannot convert float NaN to
    integer) ... report as a bug" with no file or epoch."""
    path = _pos_with_nan_time(m, fmt)
    line = bad(capsys, m, path.name, "column time", "epoch 7", "nan")
    assert "after t=" in line


@pytest.mark.parametrize("fmt", ["sbet", "csv", "lcf", "ascii"])
def test_read_pos_refuses_a_nan_time(m, fmt):
    """The Python API too: read_pos let a NaN time through (the times' order was tested
    with NaN comparing false), to fail later far from the file."""
    from swathflow.errors import FormatError
    from swathflow.formats.pos import read_pos
    path = _pos_with_nan_time(m, fmt)
    with pytest.raises(FormatError) as e:
        read_pos(path, fmt)
    assert str(path) in str(e.value) and "epoch 7" in str(e.value) and "time" in str(e.value)


def test_a_plugin_pos_format_with_a_nan_time_names_the_file_and_epoch(tmp_path,
                                                                       monkeypatch):
    """A third-party reader (tests/plugins/posformat, which leaves the checks to the
    registry) returning a NaN time: the registry's check names the file and epoch."""
    from swathflow.errors import FormatError
    from swathflow.formats.navigation import registry
    from swathflow.formats.pos import read_pos
    monkeypatch.syspath_prepend(str(Path(__file__).parent / "plugins" / "posformat"))
    from swathflow_sample_posformat import FORMAT
    formats = {**registry.list_formats(), FORMAT.name: FORMAT}
    monkeypatch.setattr(registry, "list_formats", lambda: formats)
    rows = [f"{100.0 + i};32.5;120.4;500;0;0;90" for i in range(10)]
    rows[4] = "nan;32.5;120.4;500;0;0;90"
    (tmp_path / "nav.semi").write_text("\n".join(rows) + "\n")
    with pytest.raises(FormatError, match=r"nav\.semi: column time, epoch 4 \(counted from 0, "
                                          r"after t=103\.000 s\): time is nan"):
        read_pos(tmp_path / "nav.semi")


def test_pos_times_in_minutes_are_not_called_a_jump(m, capsys):
    pos_csv(m, lambda d: d.assign(time=d.time / 60.0))
    line = bad(capsys, m, "pos.csv", "minutes")
    assert "jump" not in line


def test_mission_toml_with_a_utf8_bom_is_read(m, capsys):
    p = m / "mission.toml"
    p.write_bytes(b"\xef\xbb\xbf" + p.read_bytes())
    code, text = run(capsys, "validate", m)
    assert code == 0, text


def test_warnings_have_one_prefix_and_q_silences_them(m, tmp_path, capsys):
    """Mission warnings printed as ``warning: warning:``, and ``-q`` did not silence
    them."""
    toml(m, "gsd = 0.4", "gsd = 0.4\ncolour = 1")          # an unknown key: a warning
    cal = m / "truth" / "calibration.json"
    code, text = run(capsys, "rectify", m, "--out", tmp_path / "r", "--images", "L1",
                      "--calibration", cal)
    assert code == 0 and "colour" in text, text
    assert "warning: warning:" not in text
    code, text = run(capsys, "rectify", m, "--out", tmp_path / "r2", "--images", "L1",
                      "--calibration", cal, "-q")
    assert code == 0 and "warning" not in text, text


def test_a_closed_pipe_ends_quietly(fault_base):
    """Output to a reader that went away (a killed parent, ``| head``): no traceback."""
    p = subprocess.Popen([sys.executable, "-m", "swathflow.flows.cli", "validate", str(fault_base)],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    p.stdout.close()
    err = p.stderr.read().decode()
    p.wait(timeout=240)
    assert "Traceback" not in err and "BrokenPipe" not in err, err
    assert not math.isnan(p.returncode)


def test_reference_dem_in_millimetres_fails_validation(m, capsys):
    """A reference DEM in millimetres: every automatic point unusable, calibrate exited 0
    with nothing estimated (and validate passed)."""
    with rasterio.open(m / "dem.tif") as src:
        prof, a = src.profile, src.read()
    with rasterio.open(m / "refdem.tif", "w", **prof) as dst:
        dst.write(a * 1000.0)
    _ortho(m / "ref.tif", "EPSG:32651", (0.4, 0, 500000, 0, -0.4, 3600000))
    toml(m, "[calibration]", '[reference]\northo = "ref.tif"\ndem = "refdem.tif"\n\n'
          '[calibration]')
    bad(capsys, m, "refdem.tif", "above the aircraft")


@pytest.mark.slow
def test_reference_dem_missing_the_swath_is_blamed_on_the_dem(tmp_path, capsys):
    """A reference DEM that misses the swath was reported as an orthophoto that does not
    cover the flight: now the DEM is named, with the cause."""
    mm = tmp_path / "r"
    assert main(["simulate", str(mm), "--preset", "tiny", "--seed", "3"]) == 0
    with rasterio.open(mm / "dem.tif") as src:
        prof, a = src.profile, src.read()
    t = prof["transform"]
    prof.update(transform=rasterio.Affine(t.a, t.b, t.c + 50000.0, t.d, t.e, t.f))
    with rasterio.open(tmp_path / "far.tif", "w", **prof) as dst:      # 50 km east
        dst.write(a)
    capsys.readouterr()
    code, text = run(capsys, "calibrate", mm, "--out", tmp_path / "cal", "--reference",
                      mm / "truth" / "ortho.tif", "--reference-dem", tmp_path / "far.tif",
                      "--rounds", "1")
    assert code == 2, text
    line = next(ln for ln in text.splitlines() if "error" in ln)
    assert "far.tif" in line and "misses the swath" in line, text


def test_validate_warnings_have_one_prefix_and_q_silences_them(m, capsys):
    """validate printed a usable mission's warnings as ``  - warning: ...`` lines of its
    own; now as every command does, and ``-q`` silences them."""
    toml(m, "gsd = 0.4", "gsd = 0.4\ncolour = 1")          # an unknown key: a warning
    code, text = run(capsys, "validate", m)
    lines = [ln for ln in text.splitlines() if "colour" in ln]
    assert code == 0 and len(lines) == 1, text
    assert lines[0].startswith("swathflow validate: warning: ") and "mission.toml" in lines[0]
    assert lines[0].count("warning:") == 1, lines[0]
    code, text = run(capsys, "validate", m, "-q")
    assert code == 0 and "warning" not in text and "colour" not in text, text


def test_q_silences_a_librarys_warnings_too(tmp_path):
    """``-q`` prints nothing but errors: a warning of a library the command calls (here
    a RuntimeWarning) is not printed either; without ``-q`` it is. In a fresh interpreter
    (pytest records warnings instead of printing them)."""
    code = ("import sys, warnings\n"
            "from swathflow.flows.cli import commands, main\n"
            "def validate(args):\n"
            "    warnings.warn('overflow in a library', RuntimeWarning, stacklevel=2)\n"
            "    return 0\n"
            "commands.validate = validate\n"
            "sys.exit(main(['validate', sys.argv[1], *sys.argv[2:]]))\n")
    quiet = subprocess.run([sys.executable, "-c", code, str(tmp_path), "-q"],
                           capture_output=True, text=True, timeout=120)
    loud = subprocess.run([sys.executable, "-c", code, str(tmp_path)],
                          capture_output=True, text=True, timeout=120)
    assert quiet.returncode == 0 and quiet.stdout + quiet.stderr == "", quiet.stderr
    assert loud.returncode == 0 and "overflow in a library" in loud.stderr, loud.stderr
