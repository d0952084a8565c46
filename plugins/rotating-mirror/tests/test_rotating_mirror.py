"""The rotating-mirror plugin: swathflow's contract suite, closed forms, per-pixel time."""
from importlib.metadata import entry_points

import numpy as np
import pytest
import xarray as xr

from swathflow.errors import FormatError
from swathflow.formats.pos import Trajectory
from swathflow.geometry.rotations import r_en
from swathflow.testing import check_model
from swathflow_rotating_mirror import RotatingMirrorModel

SPEED = 60.0


def _level_north(height=1000.0, seconds=6.0):
    """Level flight due north along the meridian of lon 0 at SPEED m/s."""
    t = np.arange(-1.0, seconds + 1.0, 0.005)
    lat = np.degrees(SPEED * t / 6_335_439.0)     # meridian radius of curvature at lat 0
    z = np.zeros_like(t)
    ds = xr.Dataset({"lat": ("time", lat), "lon": ("time", z), "h": ("time", z + height),
                     "roll": ("time", z), "pitch": ("time", z), "heading": ("time", z)},
                    coords={"time": t})
    return Trajectory.from_dataset(ds)


def _model(dwell=0.0, params=None, rows=200, row_period=0.02, **sensor):
    s = {"n_elements": 600, "ifov_deg": 0.05, "dwell": dwell, **sensor}
    lines = {"time": np.arange(rows) * row_period}
    return RotatingMirrorModel.build(s, lines, _level_north(), params)


def _ned(model, img):
    """Ground point (on height 0) minus the antenna at the pixel's time, north/east/down."""
    img = np.asarray(img, float)
    g = model.image_to_ground(img, 0.0)
    pos = model.trajectory.interpolate(model.image_time(img))
    ren = r_en(np.radians(pos["lat"]), np.radians(pos["lon"]))
    return np.einsum("...ji,...j->...i", ren, g - pos["ecef"])


def test_contract_suite():
    check_model(RotatingMirrorModel.example_model())


def test_contract_suite_with_slow_mirror():
    """The suite also passes when pixels of one row are far apart in time."""
    m = _model(dwell=0.02 / 600 * 0.5, params={"opk_mount": [0.3, -0.5, 1.0],
                                               "u_gps": [0.5, 0.2, 1.0]})
    check_model(m)


def test_scan_angle_closed_form():
    m = _model()
    center = 299.5
    d = _ned(m, [[50, center], [50, center + 100], [50, center - 200]])
    assert np.abs(d[0, :2]).max() < 1e-6                                    # nadir
    # +100 pixels of 0.05 deg = 5 deg to the LEFT (west); -200 = 10 deg right
    assert d[1, 1] == pytest.approx(-1000 * np.tan(np.radians(5.0)), abs=0.02)
    assert d[2, 1] == pytest.approx(1000 * np.tan(np.radians(10.0)), abs=0.05)
    assert np.abs(d[:, 0]).max() < 1e-6                                     # no along-track
    m = _model(params={"scan_offset": [1.0]})
    assert _ned(m, [[50, center]])[0, 1] == pytest.approx(-1000 * np.tan(np.radians(1.0)),
                                                           abs=5e-3)


def test_every_pixel_has_its_own_time():
    dwell = 1e-4                                         # 600 pixels = 60 ms per sweep
    m = _model(dwell=dwell, row_period=0.1, rows=50)
    img = np.array([[10.0, 0.0], [10.0, 299.5], [10.0, 599.0]])
    assert np.allclose(m.image_time(img), 1.0 + img[:, 1] * dwell)
    g = m.image_to_ground(img, 0.0)
    p0 = m.trajectory.interpolate(np.array([1.0]))
    # north of the ground points from the antenna at the row's start = ground speed * e * dwell
    ned = (g - p0["ecef"][0]) @ r_en(np.radians(p0["lat"][0]), 0.0)
    ground_speed = SPEED * 6_335_439.0 / (6_335_439.0 + 1000.0)
    assert ned[:, 0] == pytest.approx(ground_speed * img[:, 1] * dwell, abs=1e-3)


@pytest.mark.parametrize("dwell", [0.0, 1e-5, 1.6e-4])
def test_ground_to_image_round_trip_with_pixel_time(dwell):
    m = _model(dwell=dwell, row_period=0.1, rows=50,
               params={"opk_mount": [1.0, -2.0, 3.0], "u_gps": [0.2, 0.3, 1.5]})
    rng = np.random.default_rng(0)
    img = np.stack([rng.uniform(0, 49, 300), rng.uniform(0, 599, 300)], axis=-1)
    back = m.ground_to_image(m.image_to_ground(img, 30.0))
    assert np.abs(back - img).max() < 1e-6


def test_bad_sensor_table():
    with pytest.raises(FormatError, match="missing key 'dwell'"):
        RotatingMirrorModel.build({"n_elements": 10, "ifov_deg": 0.1},
                                  {"time": [0.0, 1.0]}, _level_north())


def test_registered_through_the_entry_point():
    eps = {ep.name: ep.value for ep in entry_points(group="swathflow.sensors")}
    if "rotating-mirror" not in eps:
        pytest.skip("plugin not pip-installed (pip install ./plugins/rotating-mirror)")
    from swathflow.sensormodel import get_sensor
    assert eps["rotating-mirror"] == "swathflow_rotating_mirror:RotatingMirrorModel"
    assert get_sensor("rotating-mirror").__name__ == "RotatingMirrorModel"


# --- the plugin's own line-table column: scan_start ------------------------------------------
def test_scan_start_column_turns_the_scan_closed_form():
    """Rows that start 1 degree further left put the centre pixel 1 degree left of nadir:
    H tan(1 deg) west in level northward flight; the model without the column is nominal."""
    rows, center = 200, 299.5
    nominal = -center * 0.05
    m0 = _model()
    m1 = RotatingMirrorModel.build({"n_elements": 600, "ifov_deg": 0.05, "dwell": 0.0},
                                   {"time": np.arange(rows) * 0.02,
                                    "scan_start": np.full(rows, nominal + 1.0)},
                                   _level_north())
    assert np.abs(_ned(m0, [[50, center]])[0, :2]).max() < 1e-6
    d = _ned(m1, [[50, center]])[0]
    assert d[1] == pytest.approx(-1000 * np.tan(np.radians(1.0)), abs=5e-3)
    assert abs(d[0]) < 1e-6


def test_scan_start_varies_along_the_image():
    """A start angle changing linearly with the row: the centre pixel of row k looks
    k * 0.01 degree further left."""
    rows, center = 100, 299.5
    start = -center * 0.05 + 0.01 * np.arange(rows)
    m = RotatingMirrorModel.build({"n_elements": 600, "ifov_deg": 0.05, "dwell": 0.0},
                                  {"time": np.arange(rows) * 0.02, "scan_start": start},
                                  _level_north())
    k = np.array([0.0, 30.0, 75.5])
    d = _ned(m, np.stack([k, np.full(3, center)], -1))
    assert d[:, 1] == pytest.approx(-1000 * np.tan(np.radians(0.01 * k)), abs=5e-3)


@pytest.mark.parametrize("dwell", [0.0, 1.6e-4])
def test_round_trip_with_wandering_scan_start(dwell):
    """ground_to_image inverts image_to_ground when the start angle wanders by a pixel
    and, with a slow mirror, pixels of one row are 96 ms apart (line and element coupled)."""
    rows = 50
    start = -299.5 * 0.05 + 0.05 * np.sin(np.arange(rows) / 6.0)
    m = RotatingMirrorModel.build({"n_elements": 600, "ifov_deg": 0.05, "dwell": dwell},
                                  {"time": np.arange(rows) * 0.1, "scan_start": start},
                                  _level_north(), {"opk_mount": [1.0, -2.0, 3.0]})
    rng = np.random.default_rng(1)
    img = np.stack([rng.uniform(0, rows - 1, 300), rng.uniform(0, 599, 300)], axis=-1)
    back = m.ground_to_image(m.image_to_ground(img, 30.0))
    assert np.abs(back - img).max() < 1e-6


def test_check_lines_refuses_non_physical_scan_start():
    good = {"time": np.arange(5.0), "scan_start": np.full(5, -15.0)}
    assert RotatingMirrorModel.check_lines(good) == []
    bad = {"time": np.arange(5.0), "scan_start": np.array([-15.0, -15.0, 95.0, -15.0, -261.8])}
    problems = RotatingMirrorModel.check_lines(bad)
    assert len(problems) == 1
    assert "scan_start" in problems[0] and "file row(s) 4, 6" in problems[0]
    assert "beyond +-80 deg" in problems[0] and "degrees" in problems[0]


def test_line_columns_include_the_plugins_own():
    assert RotatingMirrorModel.line_columns == ("time", "scan_start")


# --- the plugin's simulator --------------------------------------------------------------------
def test_simulator_hook_offers_the_preset():
    sim = RotatingMirrorModel.simulator()
    assert "rotating-mirror" in sim.PRESETS and callable(sim.simulate)


def test_simulated_bundle_geometry(tmp_path):
    """A geometry-only bundle: the line table carries the plugin's column as simulated
    (nominal + bias + wander), one mirror turn per row (dwell = row period * ifov / 360),
    and the control points lie on the DEM and where the true model sees them."""
    import pandas as pd
    import tomllib
    from swathflow.formats.calibfile import read_calibration
    from swathflow.formats.pos import read_pos
    from swathflow.geometry.geodesy import geodetic_to_ecef
    from swathflow.geometry.terrain import DEM
    sim = RotatingMirrorModel.simulator()
    out = tmp_path / "m"
    truth = sim.simulate(out, "rotating-mirror", seed=2, render=False, write_ortho=False)
    cfg = truth["config"]
    toml = tomllib.loads((out / "mission.toml").read_text())
    s = toml["sensor"]
    lt = pd.read_csv(out / "images" / "M1.lines.csv")
    assert list(lt.columns) == ["line", "time", "scan_start"]
    period = np.diff(lt["time"]).mean()
    assert period == pytest.approx(np.radians(cfg["ifov_deg"]) * cfg["agl"] / cfg["speed"])
    assert s["dwell"] == pytest.approx(period * s["ifov_deg"] / 360.0)
    nominal = -(s["n_elements"] - 1) / 2 * s["ifov_deg"]
    dev = lt["scan_start"] - nominal
    assert dev.mean() == pytest.approx(cfg["scan_start_bias_deg"],
                                       abs=cfg["scan_start_wander_deg"])
    assert dev.max() - dev.min() <= 2 * cfg["scan_start_wander_deg"] + 1e-9
    # control points: on the terrain, and seen by the true model where the truth says
    g = pd.read_csv(out / "truth" / "gcp.csv")
    dem = DEM.open(out / "dem.tif")
    assert np.abs(dem.height(g["y"].to_numpy(), g["x"].to_numpy()) - g["z"]).max() < 1e-3
    xyz = geodetic_to_ecef(g[["y", "x", "z"]].to_numpy())
    assert np.abs(xyz - g[["X", "Y", "Z"]].to_numpy()).max() < 1e-3
    doc = read_calibration(out / "truth" / "calibration.json")
    params = {k: v["value"] for k, v in doc["parameters"].items()}
    assert params == truth["parameters"]
    traj = Trajectory.from_dataset(read_pos(out / "truth" / "pos.csv"))
    m = RotatingMirrorModel.build(s, {k: lt[k].to_numpy() for k in ("time", "scan_start")},
                                  traj, params)
    ij = m.ground_to_image(xyz)
    assert np.abs(ij - g[["line", "element"]].to_numpy()).max() < 1e-4
    assert truth["gcp_counts"]["M1"]["control"] == cfg["n_control"]
