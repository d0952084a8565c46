"""POS readers (real SBET, CSV) and interpolation against an analytic trajectory."""
import numpy as np
import pytest
import xarray as xr

from spec_vectors import DATA
from swathflow import FormatError, OutOfRangeError, read_pos
from swathflow.formats.pos import (SBET_DTYPE, Trajectory, interpolate_pos, read_sbet, write_pos_csv,
                           write_sbet)

SBET = DATA / "pdal-sbet" / "2-points.sbet"
BAD = DATA / "pdal-sbet" / "badfile.sbet"


def test_real_sbet_first_record():
    ds = read_pos(SBET)
    assert ds.sizes["time"] == 2
    first = ds.isel(time=0)
    assert float(first.time) == pytest.approx(151631.00284, abs=1e-5)
    assert float(first.lat) == pytest.approx(32.5452166, abs=1e-7)
    assert float(first.lon) == pytest.approx(-116.9781799, abs=1e-7)
    assert float(first.h) == pytest.approx(107.715, abs=1e-3)
    # true heading = platform heading - wander angle, from the raw record
    raw = np.fromfile(SBET, dtype=SBET_DTYPE)
    exp = (np.degrees(raw["platform_heading"] - raw["wander"]) + 180) % 360 - 180
    assert np.allclose(ds["heading"].values, exp)


def test_truncated_sbet_is_rejected_clearly():
    with pytest.raises(FormatError) as exc:
        read_pos(BAD)
    msg = str(exc.value)
    assert "badfile.sbet" in msg and "271 bytes" in msg and "truncated" in msg


def test_wander_angle_gives_true_heading(tmp_path):
    rec = np.zeros(3, dtype=SBET_DTYPE)
    rec["time"] = [1.0, 2.0, 3.0]
    rec["lat"] = np.radians(45.0)
    rec["platform_heading"] = np.radians([100.0, 100.0, 10.0])
    rec["wander"] = np.radians([30.0, -50.0, 20.0])
    p = tmp_path / "w.sbet"
    rec.tofile(p)
    ds = read_sbet(p)
    assert np.allclose(ds["heading"].values, [70.0, 150.0, -10.0])


def _analytic(t):
    """A circling, climbing aircraft: closed-form position and attitude."""
    w = 2 * np.pi / 120.0
    lat = 40.0 + 0.01 * np.sin(w * t)
    lon = 10.0 + 0.01 * np.cos(w * t)
    h = 1000.0 + 5.0 * t
    heading = (np.degrees(w * t) * 3 + 180) % 360 - 180   # wraps several times
    roll = 20.0 * np.sin(0.1 * t)
    pitch = 2.0 * np.cos(0.05 * t)
    return lat, lon, h, roll, pitch, heading


def test_interpolation_matches_analytic_trajectory():
    t = np.arange(0.0, 240.0, 1 / 200)
    lat, lon, h, roll, pitch, heading = _analytic(t)
    ds = xr.Dataset({k: ("time", v) for k, v in zip(
        ("lat", "lon", "h", "roll", "pitch", "heading"), (lat, lon, h, roll, pitch, heading))},
        coords={"time": t})
    tq = np.random.default_rng(0).uniform(0, 239.99, 5000)
    out = interpolate_pos(ds, tq)
    elat, elon, eh, eroll, epitch, eheading = _analytic(tq)
    assert np.abs(out["lat"].values - elat).max() < 1e-8
    assert np.abs(out["lon"].values - elon).max() < 1e-8
    assert np.abs(out["h"].values - eh).max() < 1e-3
    assert np.abs(out["roll"].values - eroll).max() < 1e-4
    dh = (out["heading"].values - eheading + 180) % 360 - 180
    assert np.abs(dh).max() < 1e-9


def test_no_extrapolation_and_gap_limit():
    t = np.array([0.0, 1.0, 2.0, 10.0, 11.0])
    ds = xr.Dataset({k: ("time", np.zeros(5) + (1000.0 if k == "h" else 0.0))
                     for k in ("lat", "lon", "h", "roll", "pitch", "heading")},
                    coords={"time": t})
    traj = Trajectory.from_dataset(ds, max_gap=2.0)
    traj.interpolate([0.5, 10.5])
    with pytest.raises(OutOfRangeError, match="outside the trajectory"):
        traj.interpolate([11.5])
    with pytest.raises(OutOfRangeError, match="gaps longer"):
        traj.interpolate([5.0])


def test_csv_and_sbet_writers_round_trip(tmp_path):
    t = np.arange(0.0, 5.0, 0.005)
    lat, lon, h, roll, pitch, heading = _analytic(t)
    ds = xr.Dataset({k: ("time", v) for k, v in zip(
        ("lat", "lon", "h", "roll", "pitch", "heading"), (lat, lon, h, roll, pitch, heading))},
        coords={"time": t})
    write_pos_csv(ds, tmp_path / "p.csv")
    write_sbet(ds, tmp_path / "p.sbet")
    for f in ("p.csv", "p.sbet"):
        back = read_pos(tmp_path / f)
        for k in ("lat", "lon", "roll", "pitch"):
            assert np.allclose(back[k].values, ds[k].values, atol=1e-9)
        dh = (back["heading"].values - heading + 180) % 360 - 180
        assert np.abs(dh).max() < 1e-9


@pytest.mark.parametrize("text, match", [
    ("time,lat,lon,h,roll,pitch\n0,1,2,3,4,5\n", "missing column"),
    ("time,lat,lon,h,roll,pitch,heading\n0,1,2,3,4,5,6\n0,1,2,3,4,5,6\n", "increase strictly"),
    ("time,lat,lon,h,roll,pitch,heading\n0,1,2,3,4,5,6\n1,1,x,3,4,5,6\n", "non-numeric"),
    ("time,lat,lon,h,roll,pitch,heading\n0,1,2,3,4,5,6\n1,1,,3,4,5,6\n", "not finite"),
])
def test_bad_csv_names_the_problem(tmp_path, text, match):
    p = tmp_path / "pos.csv"
    p.write_text(text)
    with pytest.raises(FormatError, match=match) as exc:
        read_pos(p)
    assert "pos.csv" in str(exc.value)
