"""Calibration without surveyed control: automatic control points from a reference
orthophoto (swathflow.calibration.reference / autocontrol).

Truth: missions simulated from the real Autzen orthophoto (``simulate --texture``), whose
truth (truth/calibration.json, truth/ortho.tif) the calibration never sees. The reference
is the truth ortho degraded as a real reference is (coarser pixels, blur, gamma, 8-bit
noise, patches changed since the flight): swathflow.simulation.reference. The mission's
gcp.csv is removed: no hand-measured point enters.
"""
from __future__ import annotations

import json
import re
import shutil
from pathlib import Path

import numpy as np
import pytest

from spec_vectors import DATA as REAL
AUTZEN = REAL / "autzen" / "autzen.jpg"


def _mission(tmp, seed=3, preset="tiny", factor=2, ref_seed=1, **overrides):
    """A simulated mission without gcp.csv, and its degraded reference (ref.tif)."""
    from swathflow.simulation import simulate
    from swathflow.simulation.reference import degrade_reference
    out = Path(tmp) / f"m{seed}"
    simulate(out, preset, seed=seed, texture=str(AUTZEN), **overrides)
    info = degrade_reference(out / "truth" / "ortho.tif", out / "ref.tif", factor=factor,
                             seed=ref_seed)
    (out / "gcp.csv").unlink()
    toml = out / "mission.toml"
    toml.write_text(re.sub(r"\[gcp\]\n[^\[]*", "", toml.read_text()))
    return out, info


def _truth(mission):
    doc = json.loads((mission / "truth" / "calibration.json").read_text())
    return {k: np.array(v["value"]) for k, v in doc["parameters"].items()}


def _z_scores(params, truth):
    z = {}
    for b in params.blocks:
        z[b.name] = (np.array(b.value) - truth[b.name]) / np.array(b.sigma)
    return z


def _rectified_shift(mission, calibration, out):
    """Shift (px) of each swing rectified with ``calibration`` against truth/ortho.tif,
    with the simulator's noise-free trajectory (the truth ortho has no POS noise)."""
    import rasterio
    from swathflow.formats.raster import read_raster
    from swathflow.rectification.mission import rectify_mission
    from shifts import shift_report
    from truth_ortho import overlap_with_truth
    toml = mission / "mission.toml"
    text = re.sub(r'\[pos\]\nfile = "[^"]*"\nformat = "[^"]*"',
                  '[pos]\nfile = "truth/pos.csv"\nformat = "csv"', toml.read_text())
    toml.write_text(text)
    rectify_mission(mission, out, calibration=str(calibration))
    truth = read_raster(mission / "truth" / "ortho.tif", masked_to_nan=True)
    reports = {}
    for tif in sorted(Path(out).glob("*.tif")):
        if tif.name.count(".") > 1:
            continue
        with rasterio.open(tif) as src:
            rect, t = src.read(1), src.transform
        sub_r, sub_t = overlap_with_truth(rect, t, truth)
        reports[tif.stem] = shift_report(sub_r, sub_t, tile=32, margin=8)
    return reports


@pytest.fixture(scope="module")
def tiny_result(tmp_path_factory):
    from swathflow.calibration.strategy import CalibrationOptions, calibrate_mission
    from swathflow.ingest.mission import load_mission
    mission, info = _mission(tmp_path_factory.mktemp("ref"))
    m = load_mission(mission)
    assert m.gcps is None or len(m.gcps) == 0          # no hand-measured point
    rc = calibrate_mission(m, CalibrationOptions(reference=str(mission / "ref.tif"),
                                                 max_rounds=3))
    paths = rc.write(mission / "cal")
    return mission, info, rc, paths


def test_reference_calibration_recovers_truth_within_3_sigma(tiny_result):
    mission, info, rc, _ = tiny_result
    # the reference really is degraded: pixels 2x the nominal raw ground size
    nadir = json.loads((mission / "truth" / "truth.json").read_text())["nadir_gsd_m"]
    assert info["res"] >= 2 * nadir
    z = _z_scores(rc.parameters, _truth(mission))
    print({k: np.round(v, 2) for k, v in z.items()})
    for name, zz in z.items():
        assert np.all(np.abs(zz) < 3.0), (name, zz)
    # the boresight angles are determined by the automatic points, not by the priors
    # (prior 5 deg; the truth's roll is 2.7 deg away from it)
    for name in ("opk_pos_L", "opk_pos_R"):
        assert rc.parameters.block(name).sigma[0] < 1.0
    assert len(rc.points) >= 20
    assert 0.5 < rc.sigma0 < 2.0


def test_reference_points_agree_with_truth_geometry(tiny_result):
    """Each automatic point's raw (line, element) against the true model's projection of
    its ground coordinates: the accepted points agree to within their sigmas."""
    from swathflow.ingest.mission import load_mission
    mission, _, rc, _ = tiny_result
    m = load_mission(mission)
    truth = _truth(mission)
    tp = m.priors.updated({k: {"value": list(v)} for k, v in truth.items()})
    p = rc.points[~rc.points["rejected"]]
    for iid, g in p.groupby("image_id"):
        ij = m.model(iid, tp).ground_to_image(g[["X", "Y", "Z"]].to_numpy(), clip=False)
        dl = (g["line"].to_numpy() - ij[:, 0]) / g["sigma_line"].to_numpy()
        de = (g["element"].to_numpy() - ij[:, 1]) / g["sigma_element"].to_numpy()
        # normalised errors (POS noise adds to the match error: a factor of 2 headroom)
        assert np.median(np.abs(dl)) < 2 * 0.6745 * 2, (iid, np.median(np.abs(dl)))
        assert np.median(np.abs(de)) < 2 * 0.6745 * 2, (iid, np.median(np.abs(de)))


def test_reference_report_and_files(tiny_result):
    mission, _, rc, paths = tiny_result
    doc = json.loads(Path(paths["calibration"]).read_text())
    assert doc["reference"]["points"] == len(rc.points)
    assert doc["reference"]["rounds"][0]["round"] == 1
    html = Path(paths["report"]).read_text()
    assert "Automatic control from the reference" in html
    assert "data:image/png;base64," in html                       # the map over the reference
    # one mark a point on the map, each with its tooltip: "name: x .. y .. px" or "name rejected"
    assert html.count(" px</title>") + html.count(" rejected</title>") == len(rc.points)
    import pandas as pd
    pts = pd.read_csv(paths["points"])
    assert {"line", "element", "E", "N", "x", "y", "rejected"} <= set(pts.columns)


def test_rectified_with_reference_calibration_matches_truth(tiny_result, tmp_path):
    mission, _, _, paths = tiny_result
    work = tmp_path / "m"
    shutil.copytree(mission, work)
    reports = _rectified_shift(work, paths["calibration"], tmp_path / "rect")
    assert reports
    for iid, rep in reports.items():
        print(iid, rep["whole"], rep["median_tile_px"], rep["tiles"])
        assert rep["whole_px"] < 0.3, (iid, rep)


def test_mission_reference_table_selects_reference_calibration(tmp_path):
    """[reference] in mission.toml: chosen when the mission has no control points."""
    from swathflow.calibration.strategy import (CalibrationOptions, ReferenceCalibration,
                                                reference_strategy)
    from swathflow.simulation import simulate
    out = tmp_path / "m"
    simulate(out, "tiny", seed=1, render=False)
    from swathflow.ingest.mission import load_mission
    assert reference_strategy(load_mission(out), CalibrationOptions()) is None
    toml = out / "mission.toml"
    (out / "gcp.csv").unlink()
    text = re.sub(r"\[gcp\]\n[^\[]*", "", toml.read_text())
    toml.write_text(text + '\n[reference]\northo = "ortho.tif"\ndem = "dem.tif"\n')
    from swathflow.formats.raster import write_geotiff     # validate opens the reference
    write_geotiff(out / "ortho.tif", np.ones((32, 32), np.float32), "EPSG:32651",
                  (0.4, 0, 500000, 0, -0.4, 3600000))
    s = reference_strategy(load_mission(out), CalibrationOptions())
    assert isinstance(s, ReferenceCalibration)
    assert s.ortho == str(out / "ortho.tif") and s.dem == str(out / "dem.tif")


def test_cli_reference_missing_file_exits_2(tmp_path, capsys):
    from swathflow.flows.cli import main
    from swathflow.simulation import simulate
    out = tmp_path / "m"
    simulate(out, "tiny", seed=1, render=False)
    rc = main(["calibrate", str(out), "--reference", str(tmp_path / "nope.tif"),
               "--out", str(tmp_path / "cal")])
    assert rc == 2
    err = capsys.readouterr().err
    assert "nope.tif" in err and "Traceback" not in err


@pytest.mark.slow
def test_reference_calibration_sigmas_are_honest(tmp_path):
    """NEES over several seeds: sum over missions of (x - truth)' C^-1 (x - truth) of the
    data-determined parameters is chi-square with (their number, summed) degrees of freedom
    when the sigmas are honest; too small means sigmas too large, too large too small."""
    from scipy import stats
    from swathflow.calibration.autocontrol import calibrate_mission_from_reference
    from swathflow.ingest.mission import load_mission
    nees, dof = 0.0, 0
    for seed in (11, 12, 13, 14):
        mission, _ = _mission(tmp_path, seed=seed, ref_seed=seed)
        m = load_mission(mission)
        rc = calibrate_mission_from_reference(m, str(mission / "ref.tif"), max_rounds=3)
        truth = _truth(mission)
        err = np.concatenate([np.array(b.value) - truth[b.name] for b in rc.parameters.blocks])
        cov = rc.model_cov
        # the combinations of parameters the automatic points determine: the directions v
        # of cov v = lam P v (P the prior covariance) with lam < 0.25 (the posterior
        # variance below a quarter of the prior's). Prior-dominated directions only repeat
        # the simulator's truth-near-prior choice (its truth is not drawn from the prior),
        # which would pull the NEES down.
        from scipy.linalg import eigh
        prior_sigma = np.concatenate([np.array(b.sigma, float) for b in m.priors.blocks])
        free = np.diag(cov) > 0
        lam, vec = eigh(cov[np.ix_(free, free)], np.diag(prior_sigma[free] ** 2))
        data = lam < 0.25
        proj = vec[:, data].T @ err[free]
        nees += float(np.sum(proj ** 2 / lam[data]))
        dof += int(data.sum())
        print(seed, nees, dof)
    lo, hi = stats.chi2.ppf([0.001, 0.999], dof)
    assert lo < nees < hi, (nees, dof, lo, hi)

