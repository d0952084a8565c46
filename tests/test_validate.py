"""``swathflow validate``: every kind of problem is found in a broken copy of a good
(tiny simulated) mission, reported with its file and row/key, never as a traceback."""
from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from swathflow.ingest.mission import Problem, validate_mission
from swathflow.sensors.pendulum.simulate import simulate

pytestmark = pytest.mark.filterwarnings("ignore::rasterio.errors.NotGeoreferencedWarning")


@pytest.fixture(scope="module")
def good(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("v") / "good"
    simulate(out, "tiny", seed=5, write_ortho=False)
    return out


@pytest.fixture()
def m(good, tmp_path) -> Path:
    dst = tmp_path / "broken"
    shutil.copytree(good, dst)
    return dst


def _toml(m: Path, old: str, new: str) -> None:
    t = (m / "mission.toml").read_text()
    assert old in t, old
    (m / "mission.toml").write_text(t.replace(old, new, 1))


def _csv(path: Path, fn) -> None:
    df = pd.read_csv(path, dtype={"gcp_id": str, "image_id": str})
    df = fn(df)
    df.to_csv(path, index=False)


def _one(problems: list[Problem], *words: str) -> Problem:
    """The single problem whose text contains all ``words`` (case-insensitive)."""
    hits = [p for p in problems if all(w.lower() in str(p).lower() for w in words)]
    assert hits, f"no problem with {words} in:\n" + "\n".join(map(str, problems))
    p = hits[0]
    assert p.fix, f"no fix given for {p}"
    return p


def test_good_mission_has_no_problems(good):
    assert validate_mission(good) == []


def test_missing_image_file(m):
    (m / "images" / "R1.tif").unlink()
    p = _one(validate_mission(m), "R1.tif", "not found")
    assert p.file.endswith("R1.tif") and "R1" in p.where


def test_missing_lines_file(m):
    (m / "images" / "L1.lines.csv").unlink()
    _one(validate_mission(m), "L1.lines.csv", "not found")


def test_missing_pos_dem_gcp_toml(m):
    (m / "pos.sbet").unlink()
    (m / "dem.tif").unlink()
    (m / "gcp.csv").unlink()
    probs = validate_mission(m)
    _one(probs, "pos.sbet", "not found")
    _one(probs, "dem.tif", "not found")
    _one(probs, "gcp.csv", "not found")
    (m / "mission.toml").unlink()
    _one(validate_mission(m), "mission.toml", "not found")


def test_bad_toml_syntax(m):
    _toml(m, "[mission]", "[mission")
    _one(validate_mission(m), "mission.toml", "TOML")


def test_wrong_line_table_columns(m):
    _csv(m / "images" / "L1.lines.csv", lambda d: d.drop(columns=["swing"]))
    p = _one(validate_mission(m), "L1.lines.csv", "missing column", "swing")
    assert p.where == "header"


def test_wrong_gcp_columns(m):
    _csv(m / "gcp.csv", lambda d: d.rename(columns={"element": "sample"}))
    _one(validate_mission(m), "gcp.csv", "missing column", "element")


def test_non_increasing_line_times(m):
    def swap(d):
        t = d["time"].to_numpy().copy()
        t[10], t[11] = t[11], t[10]
        d["time"] = t
        return d
    _csv(m / "images" / "R1.lines.csv", swap)
    p = _one(validate_mission(m), "R1.lines.csv", "increase")
    assert "12" in p.where or "13" in p.where          # file row of line 10/11


def test_non_increasing_pos_times(m):
    from swathflow.formats.pos import read_pos, write_pos_csv
    ds = read_pos(m / "pos.sbet")
    write_pos_csv(ds, m / "pos.csv")
    (m / "pos.sbet").unlink()
    _toml(m, 'file = "pos.sbet"\nformat = "sbet"', 'file = "pos.csv"\nformat = "csv"')
    assert validate_mission(m) == []

    def dup(d):
        d.loc[50, "time"] = d.loc[49, "time"]
        return d
    _csv(m / "pos.csv", dup)
    _one(validate_mission(m), "pos.csv", "increase")


def test_image_lines_outside_pos_span(m):
    _csv(m / "images" / "L1.lines.csv", lambda d: d.assign(time=d["time"] + 500.0))
    p = _one(validate_mission(m), "L1.lines.csv", "outside the POS time span")
    assert "time" in p.where


def test_line_table_length_mismatch(m):
    _csv(m / "images" / "L1.lines.csv", lambda d: d.iloc[:-3])
    _one(validate_mission(m), "L1.lines.csv", "rows", "lines")


def test_gcp_outside_image(m):
    def move(d):
        d.loc[2, "line"] = 1.0e5
        d.loc[4, "element"] = -7.0
        return d
    _csv(m / "gcp.csv", move)
    p = _one(validate_mission(m), "gcp.csv", "outside image")
    assert "4" in p.where and "6" in p.where           # file rows of data rows 2 and 4


def test_gcp_unknown_image_and_role(m):
    def bad(d):
        d.loc[0, "image_id"] = "X9"
        d.loc[1, "role"] = "tie"
        return d
    _csv(m / "gcp.csv", bad)
    probs = validate_mission(m)
    _one(probs, "gcp.csv", "unknown image", "X9")
    _one(probs, "gcp.csv", "role")


def test_unknown_sensor_plugin(m):
    _toml(m, 'model = "pendulum"', 'model = "whiskbroom-9000"')
    p = _one(validate_mission(m), "unknown sensor plugin", "whiskbroom-9000")
    assert p.where == "[sensor].model" and "pendulum" in p.fix


def test_sensor_keys_checked_by_plugin(m):
    _toml(m, "focal_length = 0.02", "focal_length = -0.02")
    _one(validate_mission(m), "[sensor]", "focal_length")


@pytest.mark.parametrize("old,new,key", [
    ('crs = "EPSG:32651"', 'crs = "EPSG:999999"', "[mission].crs"),
    ('crs = "EPSG:32651"', 'crs = "+proj=nonsense"', "[mission].crs"),
    ('crs = "EPSG:4979"', 'crs = "not a crs"', "[gcp].crs"),
])
def test_crs_rejected_by_pyproj(m, old, new, key):
    _toml(m, old, new)
    p = _one(validate_mission(m), "pyproj rejects")
    assert p.where == key


def test_dem_not_covering_images(m):
    from swathflow.formats.raster import read_raster, write_geotiff
    r = read_raster(m / "dem.tif")
    rows, cols = r.data.shape
    t = r.transform
    # keep only the north-west quarter of the DEM
    write_geotiff(m / "dem.tif", r.data[: rows // 4, : cols // 4], r.crs,
                  (t.a, t.b, t.c, t.d, t.e, t.f), nodata=r.nodata)
    p = _one(validate_mission(m), "dem.tif", "does not cover")
    assert "L1" in p.where or "R1" in p.where


def test_dem_hole_under_images_is_found(m):
    from swathflow.formats.raster import read_raster, write_geotiff
    r = read_raster(m / "dem.tif")
    d = r.data.copy()
    d[:, :] = r.nodata   # all nodata
    d[:3, :3] = 10.0
    t = r.transform
    write_geotiff(m / "dem.tif", d, r.crs, (t.a, t.b, t.c, t.d, t.e, t.f), nodata=r.nodata)
    _one(validate_mission(m), "dem.tif", "does not cover")


def test_nans(m):
    def nan_swing(d):
        d.loc[7, "swing"] = np.nan
        return d

    def nan_gcp(d):
        d.loc[3, "z"] = np.nan
        return d
    _csv(m / "images" / "R1.lines.csv", nan_swing)
    _csv(m / "gcp.csv", nan_gcp)
    probs = validate_mission(m)
    p = _one(probs, "R1.lines.csv", "NaN")
    assert "swing" in p.where and "9" in p.where
    p = _one(probs, "gcp.csv", "NaN")
    assert "column z" in p.where and "5" in p.where


def test_nan_in_pos(m):
    from swathflow.formats.pos import read_pos, write_pos_csv
    write_pos_csv(read_pos(m / "pos.sbet"), m / "pos.csv")
    _toml(m, 'file = "pos.sbet"\nformat = "sbet"', 'file = "pos.csv"\nformat = "csv"')

    def nan(d):
        d.loc[100, "roll"] = np.nan
        return d
    _csv(m / "pos.csv", nan)
    _one(validate_mission(m), "pos.csv", "roll", "not finite")


def test_bad_calibration_and_gsd(m):
    _toml(m, "gsd = 0.4", "gsd = -1")
    _toml(m, "opk_pos_R = {", "opk_bogus = {")
    probs = validate_mission(m)
    _one(probs, "[mission].gsd", "positive")
    _one(probs, "[calibration]", "opk_bogus")


def test_every_problem_listed_at_once(m):
    (m / "images" / "R1.tif").unlink()
    _csv(m / "images" / "L1.lines.csv", lambda d: d.iloc[:-1])
    _toml(m, 'crs = "EPSG:4979"', 'crs = "nope"')
    probs = validate_mission(m)
    assert len(probs) >= 3
    _one(probs, "R1.tif")
    _one(probs, "L1.lines.csv")
    _one(probs, "[gcp].crs")


def test_cli_exit_codes_and_no_traceback(good, m):
    from swathflow.flows.cli import main
    assert main(["validate", str(good)]) == 0
    _csv(m / "images" / "L1.lines.csv", lambda d: d.assign(time=d["time"] + 500.0))
    (m / "gcp.csv").write_bytes(b"\x00\xff garbage,\n\x01")
    assert main(["validate", str(m)]) == 2       # one rule for bad input: exit code 2
    r = subprocess.run([sys.executable, "-m", "swathflow.flows.cli", "validate", str(m)],
                       capture_output=True, text=True)
    assert r.returncode == 2
    assert "Traceback" not in r.stdout + r.stderr
    assert "L1.lines.csv" in r.stdout
    r = subprocess.run([sys.executable, "-m", "swathflow.flows.cli", "validate",
                        str(m / "no-such-folder")], capture_output=True, text=True)
    assert r.returncode != 0 and "Traceback" not in r.stdout + r.stderr


def test_orthometric_dem_without_geoid(m):
    _toml(m, 'vertical = "ellipsoidal"', 'vertical = "orthometric"')
    p = _one(validate_mission(m), "dem.tif", "orthometric")
    assert "undulation" in p.message or "geoid" in p.message
    _toml(m, 'vertical = "orthometric"', 'vertical = "orthometric"\nundulation = 10.0')
    assert validate_mission(m) == []


def test_reference_table_is_known_and_its_keys_checked(m):
    """[reference] (calibration from a reference orthophoto) is read by swathflow: no
    'unknown key' warning for it; a misspelt key inside it is an error naming the fix."""
    from swathflow.formats.raster import write_geotiff
    # a real reference (validate checks that it exists, opens and is north-up in metres)
    write_geotiff(m / "ref.tif", np.ones((32, 32), np.float32), "EPSG:32651",
                  (0.4, 0, 500000, 0, -0.4, 3600000))
    with open(m / "mission.toml", "a") as f:
        f.write('\n[reference]\northo = "ref.tif"\nties = true\n')
    assert not [p for p in validate_mission(m) if "reference" in p.message]
    with open(m / "mission.toml", "a") as f:
        f.write('ortoh = "x.tif"\n')
    p = _one(validate_mission(m), "ortoh")
    assert p.level == "error" and "ortho" in p.fix and "[reference]" in p.where
