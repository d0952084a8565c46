"""Calibration from a reference orthophoto for the push-broom plugin: the same generic code
(only the SensorModel interface), no push-broom name in it.

Truth: a push-broom mission (three views F, N, B) rendered from the real Autzen orthophoto;
the reference is its truth ortho degraded (2x coarser, blur, gamma, noise, changed
patches); no gcp.csv and no tie file enter. One segment per view and two orientation fixes
(42 parameters) keep the generic dense adjustment to minutes.
"""
from __future__ import annotations

import re

import numpy as np
import pandas as pd
import pytest

from test_reference_calibration import _mission, _truth, _z_scores


@pytest.mark.slow
def test_pushbroom_reference_calibration_within_3_sigma(tmp_path):
    from swathflow.calibration.strategy import CalibrationOptions, calibrate_mission
    from swathflow.ingest.mission import load_mission
    mission, info = _mission(tmp_path, seed=3, preset="pushbroom", factor=2, n_segments=1,
                             fix_interval=20.0)
    # no simulated tie measurements either: only the reference enters
    toml = mission / "mission.toml"
    toml.write_text(re.sub(r"\[ties\]\n[^\[]*", "", toml.read_text()))
    (mission / "ties.csv").unlink(missing_ok=True)
    m = load_mission(mission)
    assert m.gcps is None or len(m.gcps) == 0
    rc = calibrate_mission(m, CalibrationOptions(reference=str(mission / "ref.tif"),
                                                 max_rounds=3))
    truth = _truth(mission)
    z = _z_scores(rc.parameters, truth)
    print({k: np.round(v, 2) for k, v in z.items()}, rc.rounds)
    for name, zz in z.items():
        assert np.all(np.abs(zz) < 3.0), (name, zz)
    # the points determine the boresight's omega and phi beyond their priors (1 deg); its
    # kappa stays near the prior (0.8 deg): the APs, 10 px a priori, absorb most of it
    prior = {b.name: np.array(b.sigma, float) for b in m.priors.blocks}
    assert np.all(np.array(rc.parameters.block("opk_cam").sigma)[:2]
                  < 0.6 * prior["opk_cam"][:2])
    assert {"F1", "N1", "B1"} <= set(rc.points["image_id"])
    # false matches (the reference's changed patches) rejected and listed
    assert rc.points["rejected"].sum() == len(rc.result.rejected)
    paths = rc.write(tmp_path / "cal")
    pts = pd.read_csv(paths["points"])
    assert int(pts["rejected"].sum()) == int(rc.points["rejected"].sum())
