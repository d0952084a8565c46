"""Absolute offsets from control points (swathflow.mosaicking.control) on a simulated mission: with the
true calibration the rectified swings sit where they belong (offsets near zero within their
sigmas); control points surveyed 10 m further east make every image read 10 m / GSD
columns to the west."""
import dataclasses

import numpy as np

from swathflow.formats.calibfile import calibration_priors, read_calibration
from swathflow.geometry.geodesy import ecef_to_geodetic, geodetic_to_ecef, transformer
from swathflow.ingest.mission import load_mission
from swathflow.mosaicking.control import control_offsets


def _truth_params(m, mission_path):
    cal = read_calibration(mission_path / "truth" / "calibration.json")
    return m.priors.updated(calibration_priors(cal))


def test_true_calibration_gives_zero_offsets(tiny_mission):
    m = load_mission(tiny_mission)
    off = control_offsets(m, _truth_params(m, tiny_mission))
    assert set(off) == set(m.gcps[m.gcps["role"] == "control"]["image_id"])
    for iid, (d, s, n) in off.items():
        assert n >= 3
        # the GCPs' image measurements carry 1 px of noise: the mean is near zero
        assert (np.abs(d) < 4 * np.array(s) + 0.05).all(), (iid, d, s)


def test_moved_control_points_move_the_offsets(tiny_mission):
    m = load_mission(tiny_mission)
    p = _truth_params(m, tiny_mission)
    base = control_offsets(m, p)
    to_map = transformer("EPSG:4978", m.crs)
    to_ecef = transformer(m.crs, "EPSG:4978")
    g = m.gcps.copy()
    e, n, h = to_map.transform(g["X"].to_numpy(), g["Y"].to_numpy(), g["Z"].to_numpy())
    x, y, z = to_ecef.transform(np.asarray(e) + 10.0, n, h)
    g["X"], g["Y"], g["Z"] = x, y, z
    llh = ecef_to_geodetic(np.c_[x, y, z])
    g["lat"], g["lon"], g["h"] = llh[:, 0], llh[:, 1], llh[:, 2]
    assert np.allclose(geodetic_to_ecef(llh), np.c_[x, y, z], atol=1e-3)
    moved = control_offsets(dataclasses.replace(m, gcps=g), p)
    for iid in base:
        dr = moved[iid][0][0] - base[iid][0][0]
        dc = moved[iid][0][1] - base[iid][0][1]
        assert abs(dc + 10.0 / m.gsd) < 0.05 and abs(dr) < 0.05, (iid, dr, dc)
