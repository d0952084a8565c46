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
    from shifts import phase_shift
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


class _Count:
    """A dask callback counting the tasks the local schedulers run (by key prefix)."""

    def __init__(self):
        from dask.callbacks import Callback
        self.keys = []
        self.cb = Callback(pretask=lambda key, dsk, state: self.keys.append(key))

    def __enter__(self):
        self.cb.__enter__()
        return self

    def __exit__(self, *exc):
        self.cb.__exit__(*exc)

    def named(self, prefix):
        return sum(1 for k in self.keys if str(k[0] if isinstance(k, tuple) else k)
                   .startswith(prefix))


def test_rectify_is_lazy_and_to_cog_is_what_the_cli_writes(tiny_mission, tmp_path):
    """Building the DataArray computes no task; computing it and streaming it with
    to_cog give the pixels 'swathflow rectify' writes (native dtype, nodata, band
    metadata, tags), which match the truth ortho."""
    from swathflow.flows.cli import main
    from swathflow.rectification.api import to_cog
    cal = tiny_mission / "truth" / "calibration.json"
    with _Count() as built:
        arr = swathflow.rectify(tiny_mission, "L1", cal, dtype=None, tile=128)
    assert built.keys == [] and isinstance(arr.data, da.Array)
    with _Count() as computed:
        values = arr.values
    assert computed.named("rectify-") == arr.data.npartitions > 1
    assert main(["rectify", str(tiny_mission), "--calibration", str(cal), "--images", "L1",
                 "--tile", "128", "--out", str(tmp_path / "cli"), "-q"]) == 0
    to_cog(arr, tmp_path / "api.tif", blocksize=128)
    with rasterio.open(tmp_path / "cli" / "L1.tif") as c, \
            rasterio.open(tmp_path / "api.tif") as a:
        assert a.dtypes == c.dtypes == (str(values.dtype),) and values.dtype.kind == "u"
        assert a.nodata == c.nodata == arr.rio.nodata
        assert np.array_equal(a.read(1), c.read(1)) and np.array_equal(a.read(1), values)
        assert a.transform == c.transform and a.crs == c.crs
        assert a.tags()["image_id"] == c.tags()["image_id"] == "L1"
        assert a.tags()["calibration"] == c.tags()["calibration"]
        assert a.tags(1)["source_band"] == "1"
    _against_truth(arr.where(arr != arr.rio.nodata), tiny_mission)


def test_mask_band_rides_along_as_a_lazy_coordinate(tiny_mission, tmp_path):
    from swathflow.rectification.api import to_cog
    cal = tiny_mission / "truth" / "calibration.json"
    arr = swathflow.rectify(tiny_mission, "R1", cal, dtype=None, mask_band=True, tile=128)
    assert arr.rio.nodata is None and isinstance(arr["mask"].data, da.Array)
    to_cog(arr, tmp_path / "m.tif", blocksize=128)
    ref = swathflow.rectify(tiny_mission, "R1", cal, tile=128).values    # float32, NaN
    with rasterio.open(tmp_path / "m.tif") as src:
        assert src.nodata is None and src.count == 1
        mask = src.read_masks(1)
        assert np.array_equal(mask > 0, np.isfinite(ref))
        # the native-dtype pixels are the float result rounded (bilinear of integers)
        v = src.read(1).astype(float)
        ok = np.isfinite(ref)
        assert np.abs(v[ok] - ref[ok]).max() <= 0.5 + 1e-3


def test_mosaic_is_lazy_and_is_the_file_the_cli_writes(tiny_mission, tmp_path):
    """The lazy mosaic blends no tile until computed; computed on a real Dask cluster
    (worker processes) it is the COG 'swathflow mosaic' writes, and it sits on the truth."""
    from distributed import Client, LocalCluster

    from swathflow.flows.cli import main
    from swathflow.rectification.api import to_cog
    cal = tiny_mission / "truth" / "calibration.json"
    paths = []
    for iid in ("L1", "R1"):
        paths.append(tmp_path / f"{iid}.tif")
        to_cog(swathflow.rectify(tiny_mission, iid, cal), paths[-1])
    with _Count() as built:
        mos = swathflow.mosaic(paths, tile=128)
    assert built.named("mosaic-") == 0 and isinstance(mos.data, da.Array)
    with _Count() as local:
        on_threads = mos.values
    assert local.named("mosaic-") == mos.data.npartitions > 1    # each tile blended once
    assert mos.attrs["report"]["inputs"] == 2 and "nodes" in mos.attrs["report"]
    assert main(["mosaic", str(tmp_path), "--out", str(tmp_path / "out" / "mosaic.tif"),
                 "--workers", "1", "-q"]) == 0
    with LocalCluster(n_workers=1, threads_per_worker=2, processes=True,
                      dashboard_address=None) as cluster, Client(cluster):
        on_cluster = mos.values
    with rasterio.open(tmp_path / "out" / "mosaic.tif") as src:
        written = src.read(1, masked=True).astype(float).filled(np.nan)
        assert src.transform == mos.rio.transform()
    assert np.array_equal(np.isnan(written), np.isnan(on_cluster))
    ok = np.isfinite(written)
    assert np.abs(written[ok] - on_cluster[ok]).max() < 1e-3
    assert np.array_equal(on_threads, on_cluster, equal_nan=True)
    _against_truth(mos, tiny_mission)


def test_grid_dataarray_is_what_rioxarray_writes():
    """grid_dataarray writes the CRS, transform and nodata from a template made once per
    CRS, type and nodata: the same DataArray (coordinates, attributes, encoding, what
    ``.rio`` reads back) as rioxarray's own write_crs / write_transform / write_nodata."""
    import rioxarray  # noqa: F401
    import xarray as xr
    from affine import Affine

    from swathflow.geometry.grid import Grid
    from swathflow.rectification.api import grid_dataarray

    def by_rioxarray(data, grid, nodata):
        t = grid.transform
        coords = {"y": t.f + t.e * (np.arange(grid.shape[0]) + 0.5),
                  "x": t.c + t.a * (np.arange(grid.shape[1]) + 0.5)}
        dims = ("y", "x")
        if data.ndim == 3:
            dims = ("band", "y", "x")
            coords["band"] = np.arange(1, data.shape[0] + 1)
        out = xr.DataArray(data, dims=dims, coords=coords, name="n", attrs={"k": "v"})
        out = out.rio.write_crs(grid.crs).rio.write_transform(t)
        return out.rio.write_nodata(nodata, encoded=False) if nodata is not None else out

    for crs, t in (("EPSG:32651", Affine(0.05, 0, 257420.0, 0, -0.05, 3604966.0)),
                   ("EPSG:4326", Affine(1e-5, 0, 123.1, 0, -1e-5, 31.2))):
        grid = Grid(crs, t, (30, 40))
        for dtype, nodata in ((np.float32, np.nan), (np.uint16, 0), (np.int16, -32768),
                              (np.uint8, None), (np.float64, -9999.0)):
            for shape in ((30, 40), (3, 30, 40)):
                for _ in range(2):                  # the second from the template
                    data = da.zeros(shape, dtype=dtype, chunks=16)
                    got = grid_dataarray(data, grid, "n", {"k": "v"}, nodata)
                    want = by_rioxarray(data, grid, nodata)
                    xr.testing.assert_identical(got, want)
                    assert got.encoding == want.encoding
                    assert got.rio.crs == want.rio.crs
                    assert got.rio.transform() == want.rio.transform() == t
                    assert repr(got.rio.nodata) == repr(want.rio.nodata)
                    assert type(got.attrs.get("_FillValue")) is type(want.attrs.get("_FillValue"))
