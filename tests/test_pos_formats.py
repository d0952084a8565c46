"""Navigation formats as plugins: synthetic round trips against known values for every
built-in reader, and the registry with a real installed plugin package (no patching)."""
import json
import os
import subprocess
import sys
from importlib.metadata import entry_points
from pathlib import Path

import numpy as np
import pytest
from swathflow import FormatError, Trajectory, read_pos
from swathflow.formats.navigation import GROUP, list_formats
from swathflow.formats.navigation.registry import BUILTINS

ROOT = Path(__file__).resolve().parents[1]
PLUGIN = ROOT / "tests" / "plugins" / "posformat"


def _truth(n=50):
    """Known epochs: a turning, climbing aircraft whose heading crosses north and south."""
    t = 345600.0 + 0.1 * np.arange(n)            # GPS seconds of week
    lat = 47.5 + 1e-4 * np.arange(n)
    lon = -122.3 - 2e-4 * np.arange(n)
    h = 812.25 + 0.5 * np.arange(n)
    roll = 3.0 * np.sin(0.3 * np.arange(n))
    pitch = -1.5 + 0.01 * np.arange(n)
    heading = np.linspace(150.0, 225.0, n)       # through 180: stored -180..180 after reading
    return {"time": t, "lat": lat, "lon": lon, "h": h, "roll": roll, "pitch": pitch,
            "heading": heading}


def _check(ds, truth, keep=slice(None)):
    assert np.allclose(ds["time"].values, truth["time"][keep], rtol=0, atol=1e-9)
    for k in ("lat", "lon"):
        assert np.allclose(ds[k].values, truth[k][keep], rtol=0, atol=1e-10), k
    assert np.allclose(ds["h"].values, truth["h"][keep], rtol=0, atol=1e-6)
    for k in ("roll", "pitch"):
        assert np.allclose(ds[k].values, truth[k][keep], rtol=0, atol=1e-9), k
    wrapped = (truth["heading"][keep] + 180.0) % 360.0 - 180.0
    assert np.allclose(ds["heading"].values, wrapped, rtol=0, atol=1e-9)
    assert ds["heading"].min() < -170 and ds["heading"].max() > 170   # crossed south


# ---- Resonon LCF --------------------------------------------------------------------------

def _write_lcf(path, tr, use):
    cols = [tr["time"], np.radians(tr["roll"]), np.radians(tr["pitch"]),
            np.radians(tr["heading"]), tr["lon"], tr["lat"], tr["h"],
            np.full(tr["time"].size, -1.0), np.full(tr["time"].size, 7.0), use]
    np.savetxt(path, np.column_stack(cols), fmt="%.12f", delimiter=" ")


def test_lcf_round_trip_with_times_file(tmp_path):
    tr = _truth()
    use = np.ones(tr["time"].size)
    use[[3, 17]] = 0                                   # records the logger marked unusable
    _write_lcf(tmp_path / "raw_0.lcf", tr, use)
    line_times = tr["time"][0] + 0.0125 * np.arange(300) + 0.003
    np.savetxt(tmp_path / "raw_0.times", line_times, fmt="%.6f")
    ds = read_pos(tmp_path / "raw_0.lcf")              # format from the suffix
    _check(ds, tr, use == 1)
    assert ds.sizes["time"] == 48
    assert np.allclose(ds["line_time"].values, line_times, rtol=0, atol=1e-6)
    # the line times are on the trajectory's clock: interpolation at them works
    r = Trajectory.from_dataset(ds).interpolate(ds["line_time"].values)
    assert np.all(np.abs(r["lat"] - (47.5 + 1e-4 * (line_times - tr["time"][0]) / 0.1)) < 1e-9)


def test_lcf_times_option_and_short_record(tmp_path):
    tr = _truth(10)
    _write_lcf(tmp_path / "nav.lcf", tr, np.ones(10))
    np.savetxt(tmp_path / "image.bil.times", tr["time"][:4] + 0.05)
    ds = read_pos(tmp_path / "nav.lcf", "resonon", times=tmp_path / "image.bil.times")
    assert np.allclose(ds["line_time"].values, tr["time"][:4] + 0.05)
    with open(tmp_path / "nav.lcf", "a") as f:
        f.write("345601.0 0.1 0.2 0.3 -122.3 47.5\n")
    with pytest.raises(FormatError, match=r"nav.lcf: line 11 has 6 field\(s\)"):
        read_pos(tmp_path / "nav.lcf")


# ---- NovAtel Inertial Explorer / Applanix POSPac text exports ------------------------------

IE_PREAMBLE = """Project:     flight_0612
Program:     Inertial Explorer Version 8.90
Profile:     swathflow (custom)
Datum:       WGS84, (processing datum)
Master 1:    Name BASE, Status ENABLED

"""


def test_inertial_explorer_export(tmp_path):
    tr = _truth()
    rows = "\n".join(
        f"{tr['time'][i]:.3f} {i % 7:d} {tr['lat'][i]:.11f} {tr['lon'][i]:.11f} "
        f"{tr['h'][i]:.4f} {tr['h'][i] - 20:.4f} {tr['roll'][i]:.10f} {tr['pitch'][i]:.10f} "
        f"{tr['heading'][i] % 360:.10f}" for i in range(tr["time"].size))
    text = (IE_PREAMBLE + "     GPSTime  Q   Latitude   Longitude     H-Ell    H-MSL   Roll   "
            "Pitch    Heading\n       (sec)  ()      (deg)       (deg)       (m)      (m)  "
            "(deg)   (deg)      (deg)\n" + rows + "\n")
    (tmp_path / "flight.txt").write_text(text)
    _check(read_pos(tmp_path / "flight.txt", "novatel"), tr)


def test_pospac_export_comma_radians_other_order(tmp_path):
    tr = _truth()
    head = ("TIME, DISTANCE, EASTING, NORTHING, ELLIPSOID HEIGHT, LATITUDE, LONGITUDE, "
            "ELLIPSOID HEIGHT, ROLL, PITCH, HEADING, EAST VELOCITY")
    rows = "\n".join(
        f"{tr['time'][i]:.4f}, {i * 3.1:.2f}, 500000.0, 5260000.0, {tr['h'][i]:.4f}, "
        f"{np.radians(tr['lat'][i]):.15f}, {np.radians(tr['lon'][i]):.15f}, {tr['h'][i]:.4f}, "
        f"{np.radians(tr['roll'][i]):.15f}, {np.radians(tr['pitch'][i]):.15f}, "
        f"{np.radians(tr['heading'][i]):.15f}, 55.0" for i in range(tr["time"].size))
    (tmp_path / "sbet_export.asc").write_text("POSPac MMS export\n" + head + "\n" + rows + "\n")
    ds = read_pos(tmp_path / "sbet_export.asc", angle_units="rad", latlon_units="rad")
    _check(ds, tr)


def test_ascii_configurable_header(tmp_path):
    tr = _truth(20)
    rows = [f"{tr['heading'][i]:.10f}\t{tr['time'][i]:.3f}\t{tr['lat'][i]:.11f}\t"
            f"{tr['lon'][i]:.11f}\t{tr['h'][i]:.4f}\t{tr['roll'][i]:.10f}\t{tr['pitch'][i]:.10f}"
            for i in range(20)]
    # no header at all: the columns named in order
    (tmp_path / "bare.txt").write_text("\n".join(rows) + "\n")
    cols = ["heading", "time", "lat", "lon", "h", "roll", "pitch"]
    _check(read_pos(tmp_path / "bare.txt", "ascii", columns=cols), tr)
    # site-specific names mapped by a dictionary, header on a given line
    (tmp_path / "named.txt").write_text(
        "x\ny\nHdgT\tT_gps\tPhi\tLambda\tAlt_e\tR\tP\n" + "\n".join(rows) + "\n")
    names = {"heading": "HdgT", "time": "T_gps", "lat": "Phi", "lon": "Lambda",
             "h": "Alt_e", "roll": "R", "pitch": "P"}
    _check(read_pos(tmp_path / "named.txt", "ascii", columns=names, header_line=3), tr)
    with pytest.raises(FormatError, match="no column for h, roll"):
        read_pos(tmp_path / "named.txt", "ascii",
                 columns={"heading": "HdgT", "time": "T_gps", "lat": "Phi", "lon": "Lambda"})
    # a broken record after the data started is named by its line
    (tmp_path / "named.txt").write_text(
        "HdgT\tT_gps\tPhi\tLambda\tAlt_e\tR\tP\n" + "\n".join(rows[:5]) + "\nnan?\n")
    with pytest.raises(FormatError, match="line 7 is not a record"):
        read_pos(tmp_path / "named.txt", "ascii", columns=names)


def test_unknown_option_and_format_are_clear(tmp_path):
    tr = _truth(5)
    _write_lcf(tmp_path / "a.lcf", tr, np.ones(5))
    with pytest.raises(FormatError, match="option.*columns.*'lcf'.*accepts: times"):
        read_pos(tmp_path / "a.lcf", columns=["time"])
    with pytest.raises(FormatError, match="unknown POS format 'xyz'.*'sbet', 'csv', 'lcf'"):
        read_pos(tmp_path / "a.lcf", "xyz")


# ---- SBET and CSV through the registry ----------------------------------------------------

def test_sbet_and_csv_round_trip_through_their_writers(tmp_path):
    tr = _truth()
    tr["heading"] = (tr["heading"] + 180.0) % 360.0 - 180.0     # CSV keeps headings as given
    formats = list_formats()
    import xarray as xr
    ds = xr.Dataset({k: ("time", tr[k]) for k in ("lat", "lon", "h", "roll", "pitch",
                                                  "heading")}, coords={"time": tr["time"]})
    for name, suffix in (("sbet", "out"), ("csv", "csv"), ("lcf", "lcf")):
        formats[name].write(ds, tmp_path / f"x.{suffix}")
        _check(read_pos(tmp_path / f"x.{suffix}"), tr)


def test_builtins_declared_as_entry_points():
    declared = {ep.name: ep.value for ep in entry_points(group=GROUP)}
    for name, target in BUILTINS.items():
        assert declared.get(name) == target, (name, declared)
    assert {"sbet", "csv", "lcf", "ascii"} <= set(list_formats())


@pytest.fixture(scope="module")
def plugin_site(tmp_path_factory):
    target = tmp_path_factory.mktemp("site")
    subprocess.run([sys.executable, "-m", "pip", "install", "--quiet", "--no-deps",
                    "--no-build-isolation", "--no-index", "--target", str(target),
                    str(PLUGIN)], check=True, capture_output=True, text=True)
    return target


def test_installed_format_plugin_reads_and_broken_ones_warn(plugin_site, tmp_path):
    tr = _truth(6)
    rows = np.column_stack([tr[k] for k in ("time", "lat", "lon", "h", "roll", "pitch",
                                            "heading")])
    np.savetxt(tmp_path / "n.semi", rows, delimiter=";", fmt="%.12f")
    code = ("import json, sys; from swathflow import read_pos;"
            "from swathflow.formats.navigation import list_formats;"
            f"ds = read_pos({str(tmp_path / 'n.semi')!r}, scale=2.0);"
            "print(json.dumps({'formats': {k: v.read.__module__ for k, v in "
            "list_formats().items()}, 'h': ds['h'].values.tolist()}))")
    env = dict(os.environ, PYTHONPATH=str(plugin_site))
    r = subprocess.run([sys.executable, "-W", "always", "-c", code], env=env, check=False,
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout.strip().splitlines()[-1])
    assert out["formats"]["semicolon"] == "swathflow_sample_posformat"
    assert out["formats"]["sbet"].endswith("navigation.sbet")       # the clash lost
    assert "broken" not in out["formats"] and "notaformat" not in out["formats"]
    assert np.allclose(out["h"], 2.0 * tr["h"], atol=1e-6)
    assert "'broken'" in r.stderr and "failed to load" in r.stderr
    assert "not a PosFormat" in r.stderr and "clashes" in r.stderr


def test_mission_toml_passes_pos_options(tiny_mission, tmp_path):
    """[pos] format = "lcf" with a times file relative to the mission folder; an option the
    reader does not know is listed by validation with the key and the fix."""
    import shutil

    from swathflow.formats.navigation.lcf import write_lcf
    from swathflow.ingest.mission import inspect_mission, load_mission
    m = tmp_path / "m"
    shutil.copytree(tiny_mission, m)
    sbet = read_pos(m / "pos.sbet")
    write_lcf(sbet, m / "nav.lcf")
    (m / "extra").mkdir()
    np.savetxt(m / "extra" / "L1.times", sbet["time"].values[:5] + 0.01)
    toml = (m / "mission.toml").read_text()
    lcf = toml.replace('file = "pos.sbet"\nformat = "sbet"',
                       'file = "nav.lcf"\nformat = "lcf"\ntimes = "extra/L1.times"')
    (m / "mission.toml").write_text(lcf)
    pos = load_mission(m).pos
    assert np.allclose(pos["lat"], sbet["lat"], atol=1e-10)
    assert np.allclose(pos["line_time"], sbet["time"].values[:5] + 0.01)
    (m / "mission.toml").write_text(lcf.replace('times = "extra/L1.times"', 'colums = 3'))
    problems, _ = inspect_mission(m)
    text = "\n".join(map(str, problems))
    assert "[pos].colums" in text and "times" in text, text      # named, with the known keys
