"""The flow rectifies every band of a multi-band mission (or those of ``[rectify] bands``),
each band checked against its own truth: band 1 the simulator's texture (truth ortho),
band 2 the raw line index and band 3 the raw element index, whose rectified values must be
the raw coordinates the true sensor model gives each output pixel centre."""
from __future__ import annotations

import shutil

import numpy as np
import pytest
import rasterio

pytestmark = pytest.mark.usefixtures("prefect_harness")


def _multiband_mission(src, dst):
    """A copy of ``src`` whose images are 3-band float32 GeoTIFFs (DN, line, element)."""
    shutil.copytree(src, dst)
    for img in sorted((dst / "images").glob("*.tif")):
        with rasterio.open(img) as s:
            dn, prof = s.read(1).astype(np.float32), s.profile
        li, ei = np.indices(dn.shape, dtype=np.float32)
        prof.update(count=3, dtype="float32", nodata=None)
        img.unlink()
        with rasterio.open(img, "w", **prof) as d:
            d.write(np.stack([dn, li, ei]))
            d.set_band_description(2, "line")
            d.set_band_description(3, "element")
    return dst


def _coordinate_errors(mission, path, band, axis):
    """|rectified value - true raw coordinate| of ``band`` (a raw index ramp along
    ``axis``) at the interior pixels of a rectified swing."""
    from swathflow.formats.calibfile import calibration_priors, read_calibration
    from swathflow.geometry.grid import Grid
    from swathflow.ingest.mission import load_mission
    m = load_mission(mission)
    with rasterio.open(path) as src:
        vals = src.read(band).astype(float)
        grid = Grid(m.crs, src.transform, (src.height, src.width))
        iid = src.tags()["image_id"]
    params = m.priors.updated(calibration_priors(read_calibration(
        mission / "truth" / "calibration.json")))
    model = m.model(iid, params)
    x, y = grid.centres()
    truth = model.ground_to_image(grid.to_ecef(x, y, m.terrain))[..., axis]
    nl, ne = model.shape
    n = (nl, ne)[axis]
    ok = np.isfinite(vals) & np.isfinite(truth) & (truth >= 0) & (truth <= n - 1)
    assert ok.mean() > 0.3
    return np.abs(vals[ok] - truth[ok])


def _assert_coordinates(err, where):
    """Bilinear reproduces a ramp exactly, so the error is the lattice's: its bound
    (0.05 raw px) is tested at cell centres and edge midpoints; measured on this mission:
    median 0.0003, 99th percentile 0.028, worst 0.17 px (0.5 % of pixels above 0.05)."""
    assert np.median(err) < 0.005 and np.percentile(err, 99) < 0.05 and err.max() < 0.25, \
        (where, np.median(err), np.percentile(err, 99), err.max())


def test_flow_rectifies_every_band_each_against_its_truth(tiny_mission, tmp_path):
    from swathflow.flows.mission import run
    from test_flow import _check_against_truth
    mission = _multiband_mission(tiny_mission, tmp_path / "mission")
    result = run(mission, tmp_path / "out", calibration=str(mission / "truth" /
                                                                 "calibration.json"))
    _check_against_truth(mission, result)           # band 1, and the mosaic of band 1
    for path in result["rectified"]:
        with rasterio.open(path) as src:
            assert src.count == 3 and src.dtypes == ("float32",) * 3
            assert src.descriptions[1:] == ("line", "element")
        for band, axis in ((2, 0), (3, 1)):
            err = _coordinate_errors(mission, path, band, axis)
            _assert_coordinates(err, (path, band))


def test_mission_bands_option_selects_bands_and_names_bad_ones(tiny_mission, tmp_path):
    from swathflow.errors import FormatError
    from swathflow.rectification.mission import rectify_mission
    mission = _multiband_mission(tiny_mission, tmp_path / "mission")
    toml = mission / "mission.toml"
    text = toml.read_text()
    toml.write_text(text + '\n[rectify]\nbands = "3"\n')
    out = tmp_path / "rect"
    cal = str(mission / "truth" / "calibration.json")
    s = rectify_mission(mission, out, cal, images=["L1"])
    with rasterio.open(s[0]["path"]) as src:
        assert src.count == 1 and src.descriptions == ("element",)
    _assert_coordinates(_coordinate_errors(mission, s[0]["path"], 1, 1), "L1 band 3")
    toml.write_text(text + '\n[rectify]\nbands = "2-5"\n')
    with pytest.raises(FormatError, match=r"mission.toml: \[rectify\] bands = '2-5'.*bands 1-3"):
        rectify_mission(mission, out, cal, images=["L1"])
    # a typo of the key is an error naming it, not silently every band
    from swathflow.ingest.mission import validate_mission
    toml.write_text(text + '\n[rectify]\nband = "3"\n')
    probs = validate_mission(mission)
    assert any(p.where == "[rectify].band" and p.level == "error" and "bands" in p.fix
               for p in probs), probs
