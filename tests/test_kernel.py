"""The compiled pixel kernels (swathflow.rectification.kernel) and the multi-band raw
reader (swathflow.rectification.rawimage) against closed forms and hand-written files."""
from __future__ import annotations

import numpy as np
import pytest
from swathflow.errors import FormatError
from swathflow.rectification import kernel as K
from swathflow.rectification.rawimage import open_raw_image, parse_bands

RNG = np.random.default_rng(7)
PL = RNG.uniform(2, 17, 200)
PE = RNG.uniform(2, 27, 200)


def _coords(pl, pe):
    return np.stack([pl, pe]).astype(np.float32).reshape(2, 1, -1)


def _closed_forms():
    li, ei = np.mgrid[0:20, 0:30].astype(float)
    return li, ei


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_bilinear_reproduces_planes_and_cubic_quadratics(dtype):
    li, ei = _closed_forms()
    lin = 3 + 0.7 * li - 1.3 * ei
    quad = 0.05 * li ** 2 - 0.03 * ei ** 2 + 0.02 * li * ei + li
    co = _coords(PL, PE)
    pl, pe = co[0, 0].astype(float), co[1, 0].astype(float)
    v, ok = K.resample_window(lin.astype(dtype), co, "bilinear", None, np.float64, np.nan)
    assert ok.all() and np.allclose(v[0, 0], 3 + 0.7 * pl - 1.3 * pe, atol=1e-4)
    v, _ = K.resample_window(quad.astype(dtype), co, "cubic", None, np.float64, np.nan)
    assert np.allclose(v[0, 0], 0.05 * pl ** 2 - 0.03 * pe ** 2 + 0.02 * pl * pe + pl,
                       atol=1e-4)
    v, _ = K.resample_window(lin.astype(dtype), co, "nearest", None, np.float64, np.nan)
    assert np.allclose(v[0, 0], 3 + 0.7 * np.round(pl) - 1.3 * np.round(pe), atol=1e-4)


def test_nodata_aware_and_off_image():
    img = np.arange(100.0).reshape(10, 10)
    img[4, 4] = np.nan
    co = _coords(np.array([4.0, 4.5, 3.0, 4.0, np.nan]), np.array([5.0, 5.0, 3.0, 3.4, 2.0]))
    v, ok = K.resample_window(img, co, "bilinear", None, np.float64, np.nan)
    v = v[0, 0]
    assert v[0] == img[4, 5]                      # a NaN tap with zero weight does not count
    assert v[1] == pytest.approx((img[4, 5] + img[5, 5]) / 2)
    assert v[2] == img[3, 3]
    assert np.isnan(v[3]) and np.isnan(v[4])      # weight 0.6 on the NaN tap; no coordinate
    assert ok[0].tolist() == [True, True, True, False, False]
    # an integer nodata value is nodata too
    u = np.full((10, 10), 500, np.uint16)
    u[4, 4] = 9
    v, ok = K.resample_window(u, co, "bilinear", 9, np.uint16, 9)
    assert v[0, 0].tolist()[:4] == [500, 500, 500, 9] and ok[0].tolist()[:4] == [True] * 3 + [False]


def test_integer_output_rounds_clamps_and_avoids_nodata():
    li, ei = _closed_forms()
    ramp = (1000 + 37 * li + 11 * ei).astype(np.uint16)
    co = _coords(PL, PE)
    pl, pe = co[0, 0].astype(float), co[1, 0].astype(float)
    v, ok = K.resample_window(ramp, co, "bilinear", None, np.uint16, None)
    assert v.dtype == np.uint16 and ok.all()
    assert np.array_equal(v[0, 0], np.floor(1000 + 37 * pl + 11 * pe + 0.5).astype(np.uint16))
    # cubic over a 0 -> 255 step overshoots: clamped to the uint8 range, not wrapped
    step = np.where(ei >= 15, 255, 0).astype(np.uint8)
    xs = np.linspace(12.5, 17.5, 41)
    c = _coords(np.full(41, 10.0), xs)
    v, _ = K.resample_window(step, c, "cubic", None, np.uint8, None)
    f, _ = K.resample_window(step.astype(np.float64), c, "cubic", None, np.float64, np.nan)
    assert f.min() < -5 and f.max() > 260                      # the float kernel rings
    assert np.array_equal(v[0, 0], np.clip(np.floor(f[0, 0] + 0.5), 0, 255).astype(np.uint8))
    # a valid value that lands on the output nodata moves one unit
    flat = np.full((10, 10), 7, np.int16)
    v, ok = K.resample_window(flat, _coords(np.array([5.0]), np.array([5.0])), "nearest",
                              None, np.int16, 7)
    assert v[0, 0, 0] == 8 and ok.all()


def test_multiband_each_band_its_own_pattern():
    li, ei = _closed_forms()
    cube = np.stack([3 + 0.7 * li - 1.3 * ei, -2 * li + 0.5 * ei, 10 + 0 * li]).astype(np.float32)
    co = _coords(PL, PE)
    pl, pe = co[0, 0].astype(float), co[1, 0].astype(float)
    v, ok = K.resample_window(cube, co, "bilinear", None, np.float32, np.nan)
    assert v.shape == (3, 1, 200) and ok.all()
    assert np.allclose(v[0, 0], 3 + 0.7 * pl - 1.3 * pe, atol=1e-3)
    assert np.allclose(v[1, 0], -2 * pl + 0.5 * pe, atol=1e-3)
    assert np.allclose(v[2, 0], 10)


def test_large_tiles_reuse_only_memory_nothing_refers_to(monkeypatch):
    """Output tiles of 16 MB or more come from a pool (no fresh pages to zero): a tile in
    use is never handed out again, a freed one is, and a tile resampled into the dirty
    memory of an earlier one holds its own closed form in every pixel."""
    monkeypatch.setattr(K, "_POOL", [])                 # no tiles of earlier tests
    li, ei = np.mgrid[0:24, 0:24].astype(float)
    co = np.stack(np.meshgrid(np.linspace(1, 21, 512), np.linspace(2, 20, 512),
                              indexing="ij")).astype(np.float32)
    pl, pe = co[0].astype(float), co[1].astype(float)
    nb = 40                                             # 40 x 512 x 512 uint16: 21 MB
    first, _ = K.resample_window(np.stack([1000 + 0 * li] * nb).astype(np.uint16), co,
                                 "bilinear", None, np.uint16, 0)
    other = K.tile_buffer(first.shape, np.uint16)
    assert not np.shares_memory(first, other)           # the first tile is in use
    where = first.__array_interface__["data"][0]
    del first, other
    cube = np.stack([100 + 7 * b + 3 * li + 2 * ei for b in range(nb)]).astype(np.uint16)
    v, ok = K.resample_window(cube, co, "bilinear", None, np.uint16, 0)
    assert v.__array_interface__["data"][0] == where    # the freed memory, reused
    truth = np.stack([100 + 7 * b + 3 * pl + 2 * pe for b in range(nb)])
    assert ok.all() and np.abs(v - truth).max() <= 0.5 + 1e-6


# ----------------------------------------------------------------------------------------
# raw images: ENVI BSQ / BIL / BIP with headers, multi-band GeoTIFF, band selection
# ----------------------------------------------------------------------------------------
def _cube(nb=4, nl=13, ne=17):
    b, li, ei = np.mgrid[0:nb, 0:nl, 0:ne]
    return (1000 * (b + 1) + 10 * li + ei).astype(np.uint16)     # each band its own offset


def _write_envi(path, cube, interleave, byte_order=0, wavelengths=True):
    nb, nl, ne = cube.shape
    arr = {"bsq": cube, "bil": cube.transpose(1, 0, 2), "bip": cube.transpose(1, 2, 0)}[interleave]
    arr = arr.astype(">u2" if byte_order else "<u2")
    path.write_bytes(b"\0" * 16 + np.ascontiguousarray(arr).tobytes())
    hdr = ["ENVI", "description = {test cube}", f"samples = {ne}", f"lines = {nl}",
           f"bands = {nb}", "header offset = 16", "file type = ENVI Standard",
           "data type = 12", f"interleave = {interleave}", f"byte order = {byte_order}",
           "band names = {" + ", ".join(f"B{i + 1}" for i in range(nb)) + "}",
           "data ignore value = 0"]
    if wavelengths:
        hdr += ["wavelength units = Nanometers",
                "wavelength = {\n " + ",\n ".join(f"{450 + 100 * i}.0" for i in range(nb)) + "}",
                "fwhm = {" + ", ".join("10.0" for _ in range(nb)) + "}"]
    path.with_suffix(".hdr").write_text("\n".join(hdr) + "\n")
    return path


@pytest.mark.parametrize("interleave", ["bsq", "bil", "bip"])
@pytest.mark.parametrize("byte_order", [0, 1])
def test_envi_interleaves_read_the_same_cube(tmp_path, interleave, byte_order):
    cube = _cube()
    img = open_raw_image(_write_envi(tmp_path / f"c.{interleave}", cube, interleave, byte_order))
    assert img.shape == (13, 17) and img.count == 4 and img.nodata == 0
    assert np.array_equal(img.read(2, 9, 3, 11), cube[:, 2:9, 3:11])
    assert [b.description for b in img.band_info] == ["B1", "B2", "B3", "B4"]
    assert [b.wavelength for b in img.band_info] == [450.0, 550.0, 650.0, 750.0]
    sub = img.select("650nm,1")
    assert np.array_equal(sub.read(0, 13, 0, 17), cube[[2, 0]])
    assert [b.index for b in sub.band_info] == [3, 1]


def test_band_selection_by_wavelength_and_errors(tmp_path):
    img = open_raw_image(_write_envi(tmp_path / "c.bil", _cube(), "bil"))
    assert parse_bands("0.555um,2-3", img.bands) == [1, 1, 2]
    with pytest.raises(FormatError, match="no band at 600nm"):
        parse_bands("600nm", img.bands)                # 50 nm from both: beyond the FWHM
    with pytest.raises(FormatError, match="out of range"):
        parse_bands("5", img.bands)
    plain = open_raw_image(_write_envi(tmp_path / "d.bsq", _cube(), "bsq", wavelengths=False))
    with pytest.raises(FormatError, match="no band wavelengths"):
        plain.select("550nm")


def test_envi_header_size_mismatch_is_one_clear_line(tmp_path):
    p = _write_envi(tmp_path / "c.bil", _cube(), "bil")
    p.write_bytes(p.read_bytes()[:-10])
    with pytest.raises(FormatError, match="fix the header or the file"):
        open_raw_image(p)


def test_multiband_geotiff_with_band_metadata(tmp_path):
    import rasterio
    cube = _cube(3)
    path = tmp_path / "raw.tif"
    with rasterio.open(path, "w", driver="GTiff", width=17, height=13, count=3,
                       dtype="uint16") as dst:
        dst.write(cube)
        for i in range(3):
            dst.set_band_description(i + 1, f"thermal {i + 1}")
            dst.update_tags(i + 1, wavelength=str(8.5 + i), wavelength_units="um")
    img = open_raw_image(path, bands="9.5um,3")
    assert img.count == 2 and img.dtype == np.uint16
    assert np.array_equal(img.read(0, 13, 0, 17), cube[[1, 2]])
    assert img.band_info[0].description == "thermal 2"
