"""Multi-band and integer rectification against known truth.

The scene of test_rectify (a pendulum swing over an analytic texture) with a cube of
bands, each its own pattern: band k is the texture moved by its own offset and scaled,
T_k(E, N) = a_k + s_k * T(E + dx_k, N + dy_k). The truth ortho of band k is T_k at the
output pixel centres; every band must match its own truth (a band swap or a mapping
computed for one band only would fail)."""
from __future__ import annotations

import math

import numpy as np
import pytest
from swathflow.geometry.grid import ecef_to_map, footprint_grid
from swathflow.geometry.terrain import ConstantHeight
from shifts import shift_report
from swathflow.rectification import tiles as T
from test_rectify import rectify_to_files, scene_model, texture

BANDS = [(0.0, 1.0, 0.0, 0.0), (400.0, -1.0, 7.0, -3.0), (200.0, 0.5, -11.0, 5.0)]


def band_truth(k, x, y):
    a, s, dx, dy = BANDS[k]
    return a + s * texture(np.asarray(x) + dx, np.asarray(y) + dy)


@pytest.fixture(scope="module")
def scene():
    model = scene_model(n_lines=500, n_elements=160)
    terrain = ConstantHeight(5.0)
    grid = footprint_grid(model, terrain, 1.5)
    nl, ne = model.shape
    ll, ee = np.meshgrid(np.arange(nl, dtype=float), np.arange(ne, dtype=float), indexing="ij")
    x, y, _ = ecef_to_map(model.image_to_ground(np.stack([ll, ee], axis=-1), terrain), grid.crs)
    cube = np.stack([band_truth(k, x, y) for k in range(len(BANDS))])
    gx, gy = grid.centres()
    truth = np.stack([band_truth(k, gx, gy) for k in range(len(BANDS))])
    return {"model": model, "terrain": terrain, "grid": grid, "cube": cube, "truth": truth}


def _as(kind, cube):
    if kind == "numpy":
        return cube
    import dask.array as da
    import xarray as xr
    return xr.DataArray(da.from_array(cube, chunks=(1, 128, cube.shape[2])),
                        dims=("band", "line", "element"),
                        coords={"wavelength": ("band", [450.0, 550.0, 650.0][:cube.shape[0]])})


def _check_bands(out, truth, limit=0.1):
    for k in range(truth.shape[0]):
        rep = shift_report(out[k], truth[k], tile=64, margin=16)
        assert rep["tiles"] >= 4, (k, rep)
        assert rep["whole_px"] < limit and rep["worst_tile_px"] < limit, (k, rep)
        # and not another band's truth: the bands differ by far more than the kernel's own
        # smoothing (bilinear, raw pixels coarser than the output: rms 1.6 DN measured)
        ok = np.isfinite(out[k])
        err = np.sqrt(np.mean((out[k][ok] - truth[k][ok]) ** 2))
        assert err < 2.5, (k, err)
        if truth.shape[0] > 1:
            other = np.sqrt(np.mean((out[k][ok] - truth[(k + 1) % truth.shape[0]][ok]) ** 2))
            assert other > 25, (k, other)


@pytest.mark.parametrize("kind", ["numpy", "dask"])
def test_float_cube_every_band_matches_its_truth(scene, kind):
    out = T.rectify(scene["model"], _as(kind, scene["cube"].astype(np.float32)), scene["grid"],
                    scene["terrain"], "bilinear", tile=256).compute()
    assert out.shape == (3,) + scene["grid"].shape and out.dtype == np.float32
    _check_bands(out.astype(float), scene["truth"])
    # band selection by wavelength and index reads those bands only
    sub = T.rectify(scene["model"], _as("dask", scene["cube"].astype(np.float32)),
                    scene["grid"], scene["terrain"], "bilinear", tile=256, bands="3").compute()
    assert sub.shape == (1,) + scene["grid"].shape
    _check_bands(sub.astype(float), scene["truth"][[2]])


@pytest.mark.parametrize("kind", ["numpy", "dask"])
@pytest.mark.parametrize("dtype,lo,hi", [(np.uint16, 1000, 60000), (np.int16, -15000, 15000),
                                         (np.uint8, 2, 253)])
def test_integer_cube_keeps_its_dtype_and_matches_truth(scene, kind, dtype, lo, hi):
    cmin, cmax = scene["cube"].min(), scene["cube"].max()
    scale = (hi - lo) / (cmax - cmin)
    offset = lo - cmin * scale
    raw = np.floor(scene["cube"] * scale + offset + 0.5)
    info = np.iinfo(dtype)
    out = T.rectify(scene["model"], _as(kind, raw.astype(dtype)), scene["grid"],
                    scene["terrain"], "bilinear", tile=256).compute()
    assert out.dtype == dtype
    # nodata: the geometric footprint (the float rectification's) is the valid area
    ref = T.rectify(scene["model"], scene["cube"][:1], scene["grid"], scene["terrain"],
                    "bilinear", tile=256).compute()[0]
    valid = np.isfinite(ref)
    assert (out[:, ~valid] == info.min).all()          # nodata: the type's lowest value
    assert (out[:, valid] != info.min).all()           # which no valid pixel holds
    vals = np.where(valid, (out.astype(float) - offset) / scale, np.nan)
    _check_bands(vals, scene["truth"], limit=0.1 if dtype != np.uint8 else 0.15)


def test_cubic_integer_output_is_clamped_not_wrapped(scene):
    # a cube at the edges of the uint8 range: cubic overshoots must clamp to 0 / 255
    raw = np.where(scene["cube"][0] > 100, 255, 0).astype(np.uint8)
    out = T.rectify(scene["model"], raw, scene["grid"], scene["terrain"], "cubic",
                    tile=256).compute()
    f = T.rectify(scene["model"], raw.astype(np.float32), scene["grid"], scene["terrain"],
                  "cubic", tile=256).compute()
    ok = np.isfinite(f)
    assert np.nanmin(f) < -1 and np.nanmax(f) > 256             # the float result rings
    want = np.clip(np.floor(f[ok] + 0.5), 0, 255).astype(np.uint8)
    want[want == 0] = 1                        # 0 is the nodata value: valid zeros move to 1
    assert np.array_equal(out[ok], want)
    assert (out[~ok] == 0).all()


def test_envi_cube_to_cog_with_band_metadata_and_mask(scene, tmp_path):
    import rasterio
    raw = np.floor(scene["cube"] * 40 + 4000.5)
    assert raw.min() > 0 and raw.max() < 65535
    raw = raw.astype(np.uint16)
    nb, nl, ne = raw.shape
    data = tmp_path / "swing.bil"
    data.write_bytes(np.ascontiguousarray(raw.transpose(1, 0, 2)).astype("<u2").tobytes())
    (tmp_path / "swing.hdr").write_text(
        "ENVI\n" f"samples = {ne}\nlines = {nl}\nbands = {nb}\nheader offset = 0\n"
        "data type = 12\ninterleave = bil\nbyte order = 0\n"
        "band names = {blue, green, red}\nwavelength units = Nanometers\n"
        "wavelength = {450.0, 550.0, 650.0}\nfwhm = {20.0, 20.0, 20.0}\n")
    out = tmp_path / "swing.tif"
    s = rectify_to_files(scene["model"], data, scene["terrain"], out, grid=scene["grid"],
                        tile=256, bands="650nm,1", mask_band=True)
    assert s["dtype"] == "uint16" and s["bands"] == 2 and s["nodata"] == "mask band"
    with rasterio.open(out) as src:
        assert src.count == 2 and src.dtypes == ("uint16", "uint16")
        assert src.tags(ns="IMAGE_STRUCTURE").get("LAYOUT") == "COG"
        assert src.descriptions == ("red", "blue")
        assert float(src.tags(1)["wavelength"]) == 650.0
        assert src.tags(1)["wavelength_units"] == "Nanometers"
        assert math.isclose(float(src.tags(2, ns="IMAGERY")["CENTRAL_WAVELENGTH_UM"]), 0.45)
        img = src.read(masked=True)
    vals = np.where(~img.mask, (img.data - 4000.0) / 40.0, np.nan)
    _check_bands(vals, scene["truth"][[2, 0]])
