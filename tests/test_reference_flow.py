"""The mission flow with ``[reference]`` in mission.toml and no gcp.csv: a real Prefect flow
run (local Dask cluster) calibrates from the reference orthophoto, and its outputs are
checked against the simulator's truth (truth/calibration.json, truth/ortho.tif), which the
flow never sees."""
from __future__ import annotations

import json

import numpy as np
import pytest
import rasterio

from test_reference_calibration import _mission, _truth

pytestmark = pytest.mark.usefixtures("prefect_harness")


@pytest.mark.slow
def test_flow_calibrates_from_mission_reference(tmp_path):
    from swathflow.flows.mission import run
    from swathflow.ingest.mission import load_mission
    from shifts import phase_shift
    mission, info = _mission(tmp_path)                 # tiny seed 3, reference 2x coarser
    toml = mission / "mission.toml"
    toml.write_text(toml.read_text() + '\n[reference]\northo = "ref.tif"\n')
    m = load_mission(mission)
    assert m.gcps is None or len(m.gcps) == 0
    assert not (mission / "gcp.csv").exists()
    result = run(mission, tmp_path / "out")
    doc = json.loads(open(result["calibration"]).read())
    assert doc["reference"]["points"] >= 20                    # automatic control was used
    assert doc["reference"]["ortho"].endswith("ref.tif")
    truth = _truth(mission)
    for name, p in doc["parameters"].items():
        z = (np.array(p["value"]) - truth[name]) / np.array(p["sigma"])
        print(name, np.round(z, 2))
        assert np.all(np.abs(z) < 3.0), (name, z)
    assert result["report"] and "Automatic control from the reference" in open(
        result["report"]).read()
    # every rectified swing against the truth ortho (same pixel lattice): whole-swing shift
    with rasterio.open(mission / "truth" / "ortho.tif") as t:
        ortho = t.read(1, masked=True).astype(float).filled(np.nan)
        t_tr = t.transform
    assert len(result["rectified"]) == len(m.images)
    for path in result["rectified"]:
        with rasterio.open(path) as src:
            img = src.read(1, masked=True).astype(float).filled(np.nan)
            col0 = round((src.transform.c - t_tr.c) / t_tr.a)
            row0 = round((src.transform.f - t_tr.f) / t_tr.e)
        win = ortho[row0:row0 + img.shape[0], col0:col0 + img.shape[1]]
        assert win.shape == img.shape
        ok = np.isfinite(img) & np.isfinite(win)
        assert ok.mean() > 0.3
        dy, dx = phase_shift(np.where(ok, img, np.nanmean(img[ok])),
                             np.where(ok, win, np.nanmean(win[ok])))
        print(path, round(dx, 3), round(dy, 3))
        assert np.hypot(dx, dy) < 0.3, (path, dx, dy)
