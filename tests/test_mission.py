"""Loading mission bundles: the Mission API on a tiny simulated mission (GeoTIFF, ENVI,
CSV POS, calibration file priors, auto-utm)."""
from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import rasterio

from swathflow import load_mission
from swathflow.errors import SwathflowError
from swathflow.geometry.geodesy import geodetic_to_ecef
from swathflow.ingest.mission import ImageEntry, Mission
from swathflow.sensors.pendulum.simulate import PRIORS, simulate

pytestmark = pytest.mark.filterwarnings("ignore::rasterio.errors.NotGeoreferencedWarning")


@pytest.fixture(scope="module")
def tiny(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("m") / "tiny"
    simulate(out, "tiny", seed=3)
    return out


@pytest.fixture()
def copy(tiny, tmp_path) -> Path:
    dst = tmp_path / "mission"
    shutil.copytree(tiny, dst)
    return dst


def _edit_toml(path: Path, old: str, new: str) -> None:
    t = (path / "mission.toml").read_text()
    assert old in t
    (path / "mission.toml").write_text(t.replace(old, new))


def test_load_tiny(tiny):
    m = load_mission(tiny)
    assert isinstance(m, Mission)
    assert m.name == "sim-tiny"
    # 32.53 N, 120.45 E is in UTM zone floor((120.45 + 180) / 6) + 1 = 51 north
    assert m.crs == "EPSG:32651"
    assert m.gsd == 0.4
    assert m.sensor["model"] == "pendulum" and m.sensor["n_elements"] == 64
    assert list(m.images) == ["L1", "R1"]
    e = m.images["L1"]
    assert isinstance(e, ImageEntry)
    assert e.file == tiny / "images" / "L1.tif" and e.lines_file.name == "L1.lines.csv"
    assert (e.direction, e.strip) == ("L", 1)
    assert m.images["R1"].direction == "R"
    assert set(m.pos.data_vars) >= {"lat", "lon", "h", "roll", "pitch", "heading"}
    assert m.trajectory.time.size == m.pos.sizes["time"]
    assert type(m.terrain).__name__ == "DEM"


def test_priors_from_calibration_table(tiny):
    m = load_mission(tiny)
    for name, (value, sigma) in PRIORS.items():
        np.testing.assert_allclose(m.priors[name], value)
        np.testing.assert_allclose(m.priors.block(name).sigma, sigma)


def test_priors_from_calibration_file(copy):
    text = (copy / "mission.toml").read_text()
    start = text.index("[calibration]")
    end = text.index("[[images]]")
    (copy / "mission.toml").write_text(text[:start] + '[calibration]\nfile = '
                                       '"truth/calibration.json"\n\n' + text[end:])
    m = load_mission(copy)
    truth = json.loads((copy / "truth" / "truth.json").read_text())["parameters"]
    for name, v in truth.items():
        np.testing.assert_allclose(m.priors[name], v)


def test_lines_and_image(tiny):
    m = load_mission(tiny)
    lt = m.lines("L1")
    df = pd.read_csv(tiny / "images" / "L1.lines.csv")
    assert set(lt) >= {"line", "time", "swing", "pitch_comp"}
    np.testing.assert_array_equal(lt["time"], df["time"].to_numpy())
    ds = m.image("L1", chunk_lines=100)
    assert ds["dn"].dims == ("line", "element")
    assert ds["dn"].chunks is not None and ds["dn"].chunks[0][0] == 100   # lazy, dask
    for k in ("time", "swing", "pitch_comp"):
        assert ds[k].dims == ("line",)
    assert ds.attrs["image_id"] == "L1" and ds.attrs["direction"] == "L"
    assert ds.attrs["strip"] == 1 and ds.attrs["sensor"] == "pendulum"
    with rasterio.open(tiny / "images" / "L1.tif") as src:
        raw = src.read(1)
    np.testing.assert_array_equal(ds["dn"].values, raw)
    np.testing.assert_array_equal(ds["dn"][123:140, 5:9].values, raw[123:140, 5:9])


def test_gcps_columns_and_coordinates(tiny):
    m = load_mission(tiny)
    g = m.gcps
    for c in ("gcp_id", "image_id", "line", "element", "x", "y", "z", "role", "lat", "lon",
              "h", "X", "Y", "Z"):
        assert c in g.columns
    raw = pd.read_csv(tiny / "gcp.csv")
    assert len(g) == len(raw)
    # EPSG:4979 in the file: x = lon, y = lat, z = h
    np.testing.assert_allclose(g["lon"], raw["x"])
    np.testing.assert_allclose(g["lat"], raw["y"])
    xyz = geodetic_to_ecef(np.stack([raw["y"], raw["x"], raw["z"]], -1))
    np.testing.assert_allclose(g[["X", "Y", "Z"]].to_numpy(), xyz, atol=1e-6)
    assert set(g["role"]) == {"control", "check"}


def test_model_reproduces_truth_gcps(tiny):
    """With the TRUE parameters the mission's model (built on the NOISY POS) puts the true
    ground points at their true image coordinates to a fraction of a pixel; with the
    priors (no calibration) it is off by many pixels."""
    from swathflow.formats.calibfile import calibration_priors, read_calibration
    m = load_mission(tiny)
    truth = m.priors.updated(calibration_priors(read_calibration(
        tiny / "truth" / "calibration.json")))
    tg = pd.read_csv(tiny / "truth" / "gcp.csv")
    for iid in m.images:
        sel = tg[tg.image_id == iid]
        xyz = geodetic_to_ecef(np.stack([sel.y, sel.x, sel.z], -1))
        ij = m.model(iid, truth).ground_to_image(xyz)
        err = ij - sel[["line", "element"]].to_numpy()
        assert np.nanmax(np.abs(err)) < 0.6, err
        ij0 = m.model(iid).ground_to_image(xyz, clip=False)
        assert np.nanmedian(np.abs(ij0 - sel[["line", "element"]].to_numpy())) > 5


def test_envi_images(copy):
    """Raw images as ENVI (.img + .hdr, rasterio's ENVI driver) load like GeoTIFF."""
    for iid in ("L1", "R1"):
        with rasterio.open(copy / "images" / f"{iid}.tif") as src:
            a = src.read(1)
        with rasterio.open(copy / "images" / f"{iid}.img", "w", driver="ENVI", width=a.shape[1],
                           height=a.shape[0], count=1, dtype=a.dtype) as dst:
            dst.write(a, 1)
        (copy / "images" / f"{iid}.tif").unlink()
        _edit_toml(copy, f"images/{iid}.tif", f"images/{iid}.img")
    assert (copy / "images" / "L1.hdr").exists()
    m = load_mission(copy)
    with rasterio.open(copy / "images" / "R1.img") as src:
        np.testing.assert_array_equal(m.image("R1")["dn"].values, src.read(1))


def test_simulator_envi_option(tmp_path):
    simulate(tmp_path / "e", "tiny", seed=1, image_format="envi", write_ortho=False)
    m = load_mission(tmp_path / "e")
    assert m.images["L1"].file.suffix == ".img"
    assert m.image("L1")["dn"].values.max() > 0


def test_csv_pos_and_auto_utm(copy):
    from swathflow.formats.pos import read_pos, write_pos_csv
    write_pos_csv(read_pos(copy / "pos.sbet"), copy / "pos.csv")
    (copy / "pos.sbet").unlink()
    _edit_toml(copy, 'file = "pos.sbet"\nformat = "sbet"', 'file = "pos.csv"\nformat = "csv"')
    _edit_toml(copy, 'crs = "EPSG:32651"', 'crs = "auto-utm"')
    m = load_mission(copy)
    assert m.crs == "EPSG:32651"
    assert abs(float(m.pos["lat"].mean()) - 32.53) < 0.05


def test_load_raises_listing_all_problems(copy):
    (copy / "images" / "R1.tif").unlink()
    _edit_toml(copy, 'model = "pendulum"', 'model = "no-such-scanner"')
    with pytest.raises(SwathflowError) as exc:
        load_mission(copy)
    msg = str(exc.value)
    assert "2 problem(s)" in msg and "R1.tif" in msg and "no-such-scanner" in msg


def test_gcps_in_a_projected_crs(copy, tiny):
    """[gcp].crs may be projected (x, y) with ellipsoidal z: lat/lon come back the same."""
    from swathflow.geometry.geodesy import transformer
    g = pd.read_csv(copy / "gcp.csv")
    e, n = transformer("EPSG:4326", "EPSG:32651").transform(g["x"].to_numpy(), g["y"].to_numpy())
    g["x"], g["y"] = e, n
    g.to_csv(copy / "gcp.csv", index=False, float_format="%.4f")
    _edit_toml(copy, 'crs = "EPSG:4979"', 'crs = "EPSG:32651"')
    ref = load_mission(tiny).gcps
    got = load_mission(copy).gcps
    np.testing.assert_allclose(got["lat"], ref["lat"], atol=1e-8)
    np.testing.assert_allclose(got["lon"], ref["lon"], atol=1e-8)
    np.testing.assert_allclose(got[["X", "Y", "Z"]].to_numpy(), ref[["X", "Y", "Z"]].to_numpy(),
                               atol=1e-3)
