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
    from swathflow.sensors import get_sensor
    assert eps["rotating-mirror"] == "swathflow_rotating_mirror:RotatingMirrorModel"
    assert get_sensor("rotating-mirror").__name__ == "RotatingMirrorModel"
