"""Tie points between left and right swings in the reference calibration
(swathflow.calibration.ties).

Truth: a mission simulated from the real Autzen orthophoto (4 swings L R L R, consecutive
swings overlapping by half their width at nadir) whose truth (truth/calibration.json) the
calibration never sees; the reference is the truth ortho degraded 3x (about 3.2 raw nadir
pixels, blur, gamma, noise, changed patches), so coarse that the reference alone leaves the
left/right boresight difference poorly known.
"""
from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from test_reference_calibration import AUTZEN, _mission, _truth, _z_scores


@pytest.fixture(scope="module")
def overlap_mission(tmp_path_factory):
    if not AUTZEN.exists():
        pytest.skip("real Autzen ortho not available")
    mission, info = _mission(tmp_path_factory.mktemp("ties"), seed=6, factor=3,
                             swings_per_strip=4, along_overlap=0.5)
    return mission, info


def _setup(mission, truth_params: bool):
    from swathflow.calibration.reference import open_reference
    from swathflow.ingest.mission import load_mission
    from swathflow.rectification.rectify import RawSource
    m = load_mission(mission)
    tp = m.priors.updated({k: {"value": list(v)} for k, v in _truth(mission).items()})
    models = {i: m.model(i, tp if truth_params else None) for i in m.image_ids}
    srcs = {i: RawSource(m.image(i).load()) for i in m.image_ids}
    return m, tp, models, srcs, open_reference(mission / "ref.tif")


def _true_transfer_error(ties, true_models, terrain):
    """Per tie point: its second observation minus the true model's projection of the
    ground under its first observation (true model, true terrain), raw pixels."""
    out = []
    for _, g in ties.groupby("tie_id", sort=False):
        a, b = g.iloc[0], g.iloc[1]
        ground = true_models[a.image_id].image_to_ground(np.array([[a.line, a.element]]),
                                                         terrain)
        ij = true_models[b.image_id].ground_to_image(ground, clip=False)[0]
        out.append((b.line - ij[0], b.element - ij[1]))
    return np.array(out)


def test_tie_points_agree_with_truth_geometry(overlap_mission):
    """Ties matched with the PRIOR parameters (boresight 2.7 deg off): each pair of
    opposite-direction swings gives tie points, and they agree with the true geometry."""
    from swathflow.calibration.reference import DEFAULT_SETTINGS
    from swathflow.calibration.ties import match_ties
    mission, _ = overlap_mission
    m, tp, models, srcs, ref = _setup(mission, truth_params=False)
    stats: list = []
    ties = match_ties(models, srcs, m.terrain, ref, DEFAULT_SETTINGS, m.gsd, stats)
    print(stats)
    kept = {s["pair"]: s["kept"] for s in stats}
    for pair in ("L1-R1", "R1-L2", "L2-R2"):            # consecutive swings overlap
        assert kept[pair] >= 8, stats
    assert ties.groupby("tie_id")["image_id"].nunique().eq(2).all()
    true_models = {i: m.model(i, tp) for i in m.image_ids}
    d = _true_transfer_error(ties, true_models, m.terrain)
    err = np.hypot(d[:, 0], d[:, 1])
    print(np.round(np.sort(err), 3))
    assert np.median(err) < 0.25                # raw pixels (0.4 m); reference pixel 1.2 m
    assert np.percentile(err, 90) < 0.6


@pytest.mark.slow
def test_false_tie_point_is_rejected_and_reported(overlap_mission):
    """A tie point moved by 4 px in one swing (a false match) is rejected by the robust
    adjustment and listed; the others are kept."""
    from swathflow.calibration.autocontrol import _ties_with_residuals
    from swathflow.calibration.control import calibrate
    from swathflow.calibration.reference import DEFAULT_SETTINGS, match_swing
    from swathflow.calibration.ties import match_ties
    mission, _ = overlap_mission
    m, tp, models, srcs, ref = _setup(mission, truth_params=True)
    ties = match_ties(models, srcs, m.terrain, ref, DEFAULT_SETTINGS, m.gsd)
    bad = ties["tie_id"].iloc[10]
    row = ties.index[(ties["tie_id"] == bad)][1]
    ties.loc[row, "element"] += 4.0
    obs = pd.concat([match_swing(i, models[i], srcs[i], m.terrain, ref, DEFAULT_SETTINGS,
                                 m.gsd)[0] for i in m.image_ids], ignore_index=True)
    res = calibrate(models, obs, m.priors, ties=ties, check_design=False)
    assert res.options["ties"]["rejected_names"] == [bad]
    table = _ties_with_residuals(ties, res)
    assert set(table.loc[table["rejected"], "tie_id"]) == {bad}
    assert abs(table.loc[row, "x"]) > 3.0                  # its residual shows the 4 px


@pytest.mark.slow
def test_ties_separate_direction_dependent_boresight(overlap_mission, tmp_path):
    """With a 3x coarser reference: the sigmas of the left-minus-right boresight are much
    smaller with tie points, and every parameter (and the L-R difference) is within 3 sigma
    of the truth; the report lists the tie points and the rejected ones."""
    from swathflow.calibration.autocontrol import calibrate_mission_from_reference
    from swathflow.ingest.mission import load_mission
    mission, info = overlap_mission
    nadir = json.loads((mission / "truth" / "truth.json").read_text())["nadir_gsd_m"]
    assert info["res"] >= 3 * nadir
    m = load_mission(mission)
    truth = _truth(mission)
    out = {}
    for ties in (False, True):
        rc = calibrate_mission_from_reference(m, str(mission / "ref.tif"), max_rounds=3,
                                              ties=ties)
        names = [b.name for b in rc.parameters.blocks]
        off = dict(zip(names, np.cumsum([0] + [len(b.value) for b in
                                               rc.parameters.blocks][:-1])))
        iL, iR, C = off["opk_pos_L"], off["opk_pos_R"], rc.model_cov
        sd = np.sqrt([C[iL + k, iL + k] + C[iR + k, iR + k] - 2 * C[iL + k, iR + k]
                      for k in range(3)])
        diff = (np.array(rc.parameters.block("opk_pos_L").value)
                - np.array(rc.parameters.block("opk_pos_R").value))
        z_diff = (diff - (truth["opk_pos_L"] - truth["opk_pos_R"])) / sd
        out[ties] = (rc, sd, z_diff)
        print(ties, np.round(sd, 4), np.round(z_diff, 2),
              {k: np.round(v, 2) for k, v in _z_scores(rc.parameters, truth).items()})
    rc, sd, z_diff = out[True]
    assert np.all(sd < 0.5 * out[False][1]), (sd, out[False][1])
    assert np.all(np.abs(z_diff) < 3.0), z_diff
    for name, zz in _z_scores(rc.parameters, truth).items():
        assert np.all(np.abs(zz) < 3.0), (name, zz)
    assert rc.ties is not None and rc.ties["tie_id"].nunique() >= 24
    paths = rc.write(tmp_path / "cal")
    html = Path(paths["report"]).read_text()
    assert "Tie points between left and right swings" in html
    doc = json.loads(Path(paths["calibration"]).read_text())
    assert doc["reference"]["ties"]["points"] == rc.ties["tie_id"].nunique()
    assert doc["reference"]["ties"]["rejected"] == len(
        set(rc.ties.loc[rc.ties["rejected"], "tie_id"]))
    assert "tie_x" in doc["variance_components"]


def test_reference_table_ties_must_be_boolean(tmp_path):
    from swathflow.calibration.strategy import CalibrationOptions, reference_strategy
    from swathflow.errors import SwathflowError
    from swathflow.ingest.mission import load_mission
    from swathflow.simulation import simulate
    out = tmp_path / "m"
    simulate(out, "tiny", seed=1, render=False)
    (out / "gcp.csv").unlink()
    toml = out / "mission.toml"
    text = re.sub(r"\[gcp\]\n[^\[]*", "", toml.read_text())
    toml.write_text(text + '\n[reference]\northo = "ortho.tif"\nties = true\n')
    from swathflow.formats.raster import write_geotiff     # validate opens the reference
    write_geotiff(out / "ortho.tif", np.ones((32, 32), np.float32), "EPSG:32651",
                  (0.4, 0, 500000, 0, -0.4, 3600000))
    s = reference_strategy(load_mission(out), CalibrationOptions())
    assert s is not None and s.ties is True
    toml.write_text(text + '\n[reference]\northo = "ortho.tif"\nties = "yes"\n')
    # refused by the mission's validation now (issue 44: validate checks [reference])
    with pytest.raises(SwathflowError, match=r"mission.toml: \[reference\]\.ties"):
        reference_strategy(load_mission(out), CalibrationOptions())
