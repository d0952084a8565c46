"""The push-broom simulator (swathflow.sensors.pushbroom.simulate): bundles that validate, truth
that reproduces the measurements, and the unchanged rectifier on a rendered mission."""
from __future__ import annotations

import json
import re

import numpy as np
import pandas as pd

from swathflow.formats.calibfile import calibration_priors, read_calibration
from swathflow.ingest.mission import load_mission, validate_mission
from swathflow.sensors.pushbroom import continuity_residuals
from swathflow.sensors.pushbroom.simulate import simulate as simulate_pushbroom
from truth_ortho import overlap_with_truth


def _truth_pos(mission):
    """Point the mission at the noise-free POS (truth/pos.csv)."""
    toml = mission / "mission.toml"
    text = re.sub(r'\[pos\]\nfile = "[^"]*"\nformat = "[^"]*"',
                  '[pos]\nfile = "truth/pos.csv"\nformat = "csv"', toml.read_text())
    assert "truth/pos.csv" in text
    toml.write_text(text)


def test_geometry_only_bundle_and_truth(tmp_path):
    out = tmp_path / "m"
    truth = simulate_pushbroom(out, "pushbroom-calib", seed=1, n_strips=1, fix_interval=10.0,
                               n_ties=15, n_control=8, n_check=4)
    assert validate_mission(out) == []
    m = load_mission(out)
    assert {e.attrs["view"] for e in m.images.values()} == {"forward", "nadir", "backward"}
    assert len(m.sensor["fixes"]["time"]) == len(truth["fix_times"]) >= 2
    # truth: C0/C1-consistent APs, not all zero, within the priors
    params = m.priors.updated(calibration_priors(read_calibration(
        out / "truth" / "calibration.json")))
    assert np.abs(continuity_residuals(m.sensor, params)).max() < 1e-15
    ap = np.array([v for b in params.blocks if b.name.startswith("ax_") for v in b.value])
    assert np.abs(ap).max() > 1e-4
    # the noise-free GCP image coordinates are where the truth model (rebuilt from the
    # bundle: truth POS, truth calibration) sees the surveyed ground
    _truth_pos(out)
    m = load_mission(out)
    g = pd.read_csv(out / "truth" / "gcp.csv")
    for iid, grp in g.groupby("image_id"):
        ij = m.model(iid, params).ground_to_image(grp[["X", "Y", "Z"]].to_numpy())
        assert np.abs(ij - grp[["line", "element"]].to_numpy()).max() < 2e-3
    # measured = truth + noise of the stated size
    meas = m.gcps.merge(g, on=["gcp_id", "image_id"], suffixes=("", "_t"))
    d = np.concatenate([meas["line"] - meas["line_t"], meas["element"] - meas["element_t"]])
    assert 0.15 < d.std() < 0.45                       # gcp_noise 0.3 px, ~70 values
    # ties: every tie seen in two or more images; the truth ground projects onto them
    t = pd.read_csv(out / "ties.csv")
    assert list(t.columns) == ["tie_id", "image_id", "line", "element"]
    assert t.groupby("tie_id").size().min() >= 2 and t.tie_id.nunique() == 15
    tt = pd.read_csv(out / "truth" / "ties.csv")
    for iid, grp in tt.groupby("image_id"):
        ij = m.model(iid, params).ground_to_image(grp[["X", "Y", "Z"]].to_numpy())
        assert np.abs(ij - grp[["line", "element"]].to_numpy()).max() < 2e-3


def test_cli_simulate_validate_rectify_nadir_against_truth(tmp_path):
    from swathflow.flows.cli import main
    from swathflow.formats.raster import read_raster
    from shifts import phase_shift
    import rasterio
    mission = tmp_path / "mission"
    assert main(["simulate", str(mission), "--preset", "pushbroom", "--seed", "3"]) == 0
    assert main(["validate", str(mission)]) == 0
    _truth_pos(mission)
    out = tmp_path / "rect"
    assert main(["rectify", str(mission), "--calibration",
                 str(mission / "truth" / "calibration.json"), "--out", str(out),
                 "--images", "N1"]) == 0
    truth = read_raster(mission / "truth" / "ortho.tif", masked_to_nan=True)
    with rasterio.open(out / "N1.tif") as src:
        rect = src.read(1).astype(float)
        t = src.transform
        if src.nodata is not None:
            rect[rect == src.nodata] = np.nan
    sr, st = overlap_with_truth(rect, t, truth)
    assert np.isfinite(sr).mean() > 0.3          # a slanted strip in a north-up box
    shift = phase_shift(sr, st)
    assert np.hypot(*shift) < 0.05, shift                  # measured 0.004 px
    # a wrong boresight moves the image: the comparison can fail
    doc = json.loads((mission / "truth" / "calibration.json").read_text())
    doc["parameters"]["opk_cam"]["value"][0] += 0.03        # deg, ~0.9 px at 300 m
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps(doc))
    out2 = tmp_path / "rect2"
    assert main(["rectify", str(mission), "--calibration", str(bad), "--out", str(out2),
                 "--images", "N1"]) == 0
    with rasterio.open(out2 / "N1.tif") as src:
        rect2 = src.read(1).astype(float)
        if src.nodata is not None:
            rect2[rect2 == src.nodata] = np.nan
        t2 = src.transform
    rc, cc = (int(round((t2.f - truth.transform.f) / truth.transform.e)),
              int(round((t2.c - truth.transform.c) / truth.transform.a)))
    sub = truth.data[rc:rc + rect2.shape[0], cc:cc + rect2.shape[1]]
    r2 = rect2[:sub.shape[0], :sub.shape[1]]
    r2 = np.where(np.isfinite(sub), r2, np.nan)
    assert np.hypot(*phase_shift(r2, np.where(np.isfinite(sub), sub, np.nanmean(sub)))) > 0.3
