"""The Python API in xarray terms: open_mission against the mission's own files, rectify
and mosaic against the simulator's truth ortho (georeferencing through rioxarray), and the
README's examples run as doctests."""
import doctest
import shutil
from pathlib import Path

import dask.array as da
import numpy as np
import pandas as pd
import rasterio

import swathflow
from swathflow.formats.pos import SBET_DTYPE

ROOT = Path(__file__).resolve().parents[1]


def test_open_mission_is_lazy_and_matches_the_files(tiny_mission):
    tree = swathflow.open_mission(tiny_mission)
    assert tree.attrs["crs"] == "EPSG:32651" and tree.attrs["sensor"] == "pendulum"
    rec = np.fromfile(tiny_mission / "pos.sbet", dtype=SBET_DTYPE)
    pos = tree["pos"].to_dataset()
    assert np.allclose(pos["time"], rec["time"])
    assert np.allclose(pos["lat"], np.degrees(rec["lat"]))
    for iid in ("L1", "R1"):
        ds = tree[f"images/{iid}"].to_dataset()
        assert ds["dn"].dims == ("band", "line", "element")
        assert isinstance(ds["dn"].data, da.Array)                  # nothing read yet
        with rasterio.open(tiny_mission / "images" / f"{iid}.tif") as src:
            assert np.array_equal(ds["dn"].values, src.read())
        lines = pd.read_csv(tiny_mission / "images" / f"{iid}.lines.csv")
        assert np.allclose(ds["time"], lines["time"]) and np.allclose(ds["swing"], lines["swing"])
        assert ds.attrs["direction"] == iid[0]


def test_open_mission_band_and_wavelength_coordinates(tiny_mission, tmp_path):
    """A three-band ENVI image whose header gives wavelengths."""
    m = tmp_path / "m"
    shutil.copytree(tiny_mission, m)
    with rasterio.open(m / "images" / "L1.tif") as src:
        band = src.read(1)
    (m / "images" / "L1.bil").write_bytes(np.stack([band, band + 1, band + 2], axis=1)
                                          .astype("<u2").tobytes())
    (m / "images" / "L1.hdr").write_text(
        "ENVI\nsamples = %d\nlines = %d\nbands = 3\nheader offset = 0\nfile type = ENVI "
        "Standard\ndata type = 12\ninterleave = bil\nbyte order = 0\n"
        "wavelength units = Micrometers\nwavelength = {8.6, 10.4, 11.2}\n" % band.shape[::-1])
    toml = (m / "mission.toml").read_text().replace('file = "images/L1.tif"',
                                                    'file = "images/L1.bil"')
    (m / "mission.toml").write_text(toml)
    ds = swathflow.open_mission(m)["images/L1"].to_dataset()
    assert list(ds["band"].values) == [1, 2, 3]
    assert np.allclose(ds["wavelength"], [8.6, 10.4, 11.2])
    assert np.array_equal(ds["dn"].sel(band=3).values, band + 2)


def _against_truth(arr, mission, tol_px=0.25):
    """Phase shift of a georeferenced DataArray against the truth ortho's same window."""
    from swathflow.rectification.rectify import phase_shift
    with rasterio.open(mission / "truth" / "ortho.tif") as t:
        truth = t.read(1, masked=True).astype(float).filled(np.nan)
        tt, tcrs = t.transform, t.crs
    tr = arr.rio.transform()
    assert arr.rio.crs == tcrs and abs(tr.a - tt.a) < 1e-9
    col0, row0 = round((tr.c - tt.c) / tt.a), round((tr.f - tt.f) / tt.e)
    img = np.asarray(arr.values, float)
    win = truth[row0:row0 + img.shape[0], col0:col0 + img.shape[1]]
    assert win.shape == img.shape
    ok = np.isfinite(img) & np.isfinite(win)
    assert ok.mean() > 0.3
    dy, dx = phase_shift(np.where(ok, img, np.nanmean(img[ok])),
                         np.where(ok, win, np.nanmean(win[ok])))
    assert abs(dx) < tol_px and abs(dy) < tol_px, (dx, dy)


def test_rectify_and_mosaic_are_georeferenced_dataarrays(tiny_mission, tmp_path):
    cal = tiny_mission / "truth" / "calibration.json"
    swings = [swathflow.rectify(tiny_mission, iid, cal) for iid in ("L1", "R1")]
    for s in swings:
        assert isinstance(s.data, da.Array) and s.dtype == np.float32
        assert np.isnan(s.rio.nodata)
    # written by rioxarray, read back by rasterio: on the truth ortho's grid
    swings[0].rio.to_raster(tmp_path / "L1.tif")
    with rasterio.open(tmp_path / "L1.tif") as src:
        assert src.crs.to_string() == "EPSG:32651"
        assert src.transform.almost_equals(swings[0].rio.transform(), precision=1e-9)
    _against_truth(swings[0], tiny_mission)
    mos = swathflow.mosaic(swings, tmp_path / "mosaic.tif")
    assert mos.dims == ("y", "x") and (tmp_path / "mosaic.tif").exists()
    assert mos.attrs["report"]["inputs"] == 2
    _against_truth(mos, tiny_mission)


def test_readme_examples_run(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    result = doctest.testfile(str(ROOT / "README.md"), module_relative=False,
                              optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE)
    assert result.attempted >= 8, result
    assert result.failed == 0, result
