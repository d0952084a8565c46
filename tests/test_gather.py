"""The multi-band gather kernels (swathflow.rectification.gather) against closed forms, for
every memory interleave (BSQ, BIL, BIP windows, read without a transposing copy), integer
rounding, nodata, clamping and ENVI files of each interleave."""
from __future__ import annotations

import numpy as np
import pytest
from swathflow.rectification import kernel as K
from swathflow.rectification.rawimage import open_raw_image

NB, NL, NE = 7, 23, 31
LAYOUTS = {"bsq": (0, 1, 2), "bil": (1, 0, 2), "bip": (1, 2, 0)}
RNG = np.random.default_rng(11)


def _plane(b, li, ei):
    """Band b's known pattern: a plane (bilinear reproduces it exactly), its own per band."""
    return 1000 + 150 * b + (3 + b) * li + (7 - b) * 0.5 * ei


def _cube(layout, dtype=np.uint16):
    b, li, ei = np.ogrid[0:NB, 0:NL, 0:NE]
    cube = np.round(_plane(b, li, ei)).astype(dtype)
    native = np.ascontiguousarray(cube.transpose(LAYOUTS[layout]))
    return cube, native.transpose(np.argsort(LAYOUTS[layout]))   # (b, l, e) view


def _coords(h=9, w=40):
    pl = RNG.uniform(-0.5, NL - 0.5, (h, w))
    pe = RNG.uniform(-0.5, NE - 0.5, (h, w))
    pl[0, :3] = np.nan                          # pixels off the image
    return np.stack([pl, pe]).astype(np.float32)


def _truth_bilinear(cube, co, nl=NL, ne=NE):
    """Bilinear by the textbook formula (taps clamped to the image), float64."""
    pl = np.clip(np.nan_to_num(co[0].astype(float)), 0, nl - 1)
    pe = np.clip(np.nan_to_num(co[1].astype(float)), 0, ne - 1)
    i0 = np.minimum(np.floor(pl).astype(int), nl - 2)
    j0 = np.minimum(np.floor(pe).astype(int), ne - 2)
    p, q = pl - i0, pe - j0
    c = cube.astype(float)
    return ((1 - p) * (1 - q) * c[:, i0, j0] + (1 - p) * q * c[:, i0, j0 + 1]
            + p * (1 - q) * c[:, i0 + 1, j0] + p * q * c[:, i0 + 1, j0 + 1])


@pytest.mark.parametrize("layout", sorted(LAYOUTS))
def test_bilinear_uint16_every_interleave_matches_closed_form(layout):
    cube, raw = _cube(layout)
    assert raw.flags.c_contiguous == (layout == "bsq")
    co = _coords()
    v, ok = K.resample_window(raw, co, "bilinear", None, np.uint16, 0)
    assert v.dtype == np.uint16 and v.shape == (NB, 9, 40)
    nan = np.isnan(co[0])
    assert (ok == ~nan).all() and (v[:, nan] == 0).all()
    truth = _truth_bilinear(cube, co)
    # rounding half up of the exact bilinear value: at most 0.5 DN off (plus float noise)
    assert np.abs(v[:, ~nan] - truth[:, ~nan]).max() <= 0.5 + 1e-6
    # and against each band's own plane (the raw values are rounded planes: 0.5 + 0.5 DN)
    pl, pe = np.clip(co[0], 0, NL - 1), np.clip(co[1], 0, NE - 1)
    for b in range(NB):
        assert np.abs(v[b][~nan] - _plane(b, pl, pe)[~nan]).max() <= 1.0 + 1e-6


@pytest.mark.parametrize("layout", sorted(LAYOUTS))
def test_nearest_and_float_output_every_interleave(layout):
    cube, raw = _cube(layout)
    co = _coords()
    nan = np.isnan(co[0])
    v, ok = K.resample_window(raw, co, "nearest", None, np.uint16, 0)
    il = np.clip(np.floor(co[0] + 0.5), 0, NL - 1)
    ie = np.clip(np.floor(co[1] + 0.5), 0, NE - 1)
    il, ie = np.where(nan, 0, il).astype(int), np.where(nan, 0, ie).astype(int)
    assert (v[:, ~nan] == cube[:, il, ie][:, ~nan]).all()
    f, ok = K.resample_window(raw, co, "bilinear", None, np.float32, np.nan)
    assert np.isnan(f[:, nan]).all()
    assert np.abs(f[:, ~nan] - _truth_bilinear(cube, co)[:, ~nan]).max() < 1e-2


@pytest.mark.parametrize("layout", sorted(LAYOUTS))
def test_nodata_taps_and_collision_step(layout):
    cube, raw = _cube(layout)
    raw = raw.copy(order="K")
    raw[2, 10, 10] = 0                          # band 3 has a nodata pixel
    co = np.array([[[10.0, 10.5, 12.0, 10.0]], [[10.0, 10.5, 12.0, 11.0]]], np.float32)
    v, ok = K.resample_window(raw, co, "bilinear", 0, np.uint16, 0)
    assert list(ok[0]) == [False, False, True, True]
    assert v[2, 0, 0] == 0 and v[2, 0, 1] == 0          # taps on the nodata pixel
    assert v[1, 0, 0] == cube[1, 10, 10]                 # other bands keep their values
    assert v[2, 0, 3] == cube[2, 10, 11]                 # zero-weight tap ignored
    # a valid value landing on the output nodata moves one unit up
    flat = np.zeros((NB, NL, NE), np.uint16).transpose(0, 1, 2)
    v, ok = K.resample_window(flat, co, "bilinear", None, np.uint16, 0)
    assert ok.all() and (v == 1).all()
    v, ok = K.resample_window(flat + 65535, co, "bilinear", None, np.uint16, 65535)
    assert ok.all() and (v == 65534).all()


def test_narrower_output_type_is_clamped():
    cube, raw = _cube("bil")
    co = _coords()
    nan = np.isnan(co[0])
    v, _ = K.resample_window(raw, co, "bilinear", None, np.uint8, 0)
    truth = np.clip(np.floor(_truth_bilinear(cube, co) + 0.5), 1, 255)
    assert np.abs(v[:, ~nan].astype(float) - truth[:, ~nan]).max() <= 1


@pytest.mark.parametrize("layout", sorted(LAYOUTS))
def test_envi_window_read_keeps_interleave_and_selects_bands(layout, tmp_path):
    cube, _ = _cube(layout)
    path = tmp_path / f"cube.{layout}"
    np.ascontiguousarray(cube.transpose(LAYOUTS[layout])).astype(">u2").tofile(path)
    (tmp_path / f"cube.{layout}.hdr").write_text(
        f"ENVI\nsamples = {NE}\nlines = {NL}\nbands = {NB}\nheader offset = 0\n"
        f"data type = 12\ninterleave = {layout}\nbyte order = 1\n")
    img = open_raw_image(path)
    w = img.read(3, 17, 5, 29)
    assert w.shape == (NB, 14, 24) and w.dtype == np.dtype("=u2")
    assert (w == cube[:, 3:17, 5:29]).all()
    sub = img.select("2,5-6").read(3, 17, 5, 29)
    assert (sub == cube[[1, 4, 5], 3:17, 5:29]).all()
    # little-endian files: consecutive bands are a view of the memory map, no copy
    path.write_bytes(np.ascontiguousarray(cube.transpose(LAYOUTS[layout])).astype("<u2")
                     .tobytes())
    (tmp_path / f"cube.{layout}.hdr").write_text(
        (tmp_path / f"cube.{layout}.hdr").read_text().replace("byte order = 1", "byte order = 0"))
    img = open_raw_image(path)
    w = img.select("3-5").read(3, 17, 5, 29)
    assert np.shares_memory(w, img.data) and (w == cube[2:5, 3:17, 5:29]).all()
    co = np.stack(np.meshgrid(np.arange(14.0), np.arange(24.0), indexing="ij")).astype(np.float32)
    v, ok = K.resample_window(w, co + 0.25, "bilinear", None, np.float64, np.nan)
    assert ok.all() and np.abs(v - _truth_bilinear(cube[2:5, 3:17, 5:29], co + 0.25,
                                                   14, 24)).max() < 1e-9


def _rss_file_mb() -> float:
    with open("/proc/self/status") as f:
        return next(int(ln.split()[1]) for ln in f if ln.startswith("RssFile")) / 1024


@pytest.mark.skipif(not __import__("os").path.exists("/proc/self/status"), reason="Linux")
def test_mapped_window_pages_are_released_after_resampling(tmp_path):
    """Resident memory bounded by the tile: the pages of a memory-mapped ENVI window that
    the kernel touched are dropped from the process afterwards (the swing's file is not
    kept resident as tiles go by)."""
    from swathflow.rectification.pages import release_pages
    nb, nl, ne = 16, 1024, 1024                     # 32 MB of uint16, BIL
    path = tmp_path / "big.bil"
    b, li, ei = np.ogrid[0:nb, 0:nl, 0:ne]
    np.ascontiguousarray(np.broadcast_to(((b * 7 + li + 2 * ei) % 60000).astype("<u2"),
                                         (nb, nl, ne)).transpose(1, 0, 2)).tofile(path)
    (tmp_path / "big.bil.hdr").write_text(
        f"ENVI\nsamples = {ne}\nlines = {nl}\nbands = {nb}\nheader offset = 0\n"
        "data type = 12\ninterleave = bil\nbyte order = 0\n")
    img = open_raw_image(path)
    w = img.read(0, nl, 0, ne)
    r0 = _rss_file_mb()
    assert int(w[:, ::4, ::512].sum()) > 0          # touch every page of the window
    r1 = _rss_file_mb()
    release_pages(w)
    r2 = _rss_file_mb()
    assert r1 - r0 > 24 and r1 - r2 > 24, (r0, r1, r2)
    # through the kernel: every pixel resampled, nothing left resident
    co = np.stack(np.meshgrid(np.arange(nl - 1.0) + 0.5, np.arange(0, ne - 1.0, 2) + 0.5,
                              indexing="ij")).astype(np.float32)
    K.resample_window(w, co[:, :2, :2], "bilinear", None, np.uint16, 0)  # compiled code
    release_pages(w)
    r2 = _rss_file_mb()
    v, ok = K.resample_window(w, co, "bilinear", None, np.uint16, 0)
    r3 = _rss_file_mb()
    assert ok.all() and r3 - r2 < 4, (r2, r3)
    assert v[3, 10, 7] == np.floor(3 * 7 + 10.5 + 2 * 14.5 + 0.5)      # round half up


@pytest.mark.parametrize("dtype,out_nodata", [(np.uint16, 0), (np.int16, -32768),
                                              (np.uint8, 0)])
def test_single_band_integer_one_pass_equals_row_form(dtype, out_nodata, monkeypatch):
    """One integer band without nodata (a single-band swing) goes through
    :func:`.gather1.gather_int_one`, one pass a pixel: the same values as the row form of
    :func:`gather_bands` (taps off the image's edges clamped, NaN coordinates, a value
    landing on the nodata value moved up), and within 1 DN of the closed form (rounding,
    and the step off the nodata value)."""
    from swathflow.rectification import gather as G
    from swathflow.rectification import gather1
    cube, _ = _cube("bsq", dtype)
    raw = np.ascontiguousarray(cube[2:3])
    raw[0, 5:8, 4:9] = out_nodata + 1 if dtype != np.int16 else -32767
    raw[0, 6, 6] = out_nodata                   # data equal to the output's nodata
    co = _coords(40, 57)
    co[:, 1, :5] = [[-0.5, -0.2, NL - 0.5, NL - 0.7, 3.0], [NE - 0.5, -0.5, 0.0, NE - 1, -0.4]]
    co[:, 2, :4] = [[6.0, 6.2, 6.0, 5.9], [6.0, 6.1, 5.8, 6.3]]      # onto the nodata value
    called = []
    one = gather1.gather_int_one

    def spy(*a):
        called.append(1)
        return one(*a)

    monkeypatch.setattr(gather1, "gather_int_one", spy)
    v, ok = K.resample_window(raw, co, "bilinear", None, dtype, out_nodata)
    assert called
    info = np.iinfo(dtype)
    out = np.empty((1, 40, 57), dtype)
    valid = np.empty((40, 57), np.uint8)
    flat, (sb, sl, se) = G.storage_view(raw)
    G.gather_bands(flat, sb, sl, se, 1, NL, NE, co, False, False, False, 0.0, out,
                   float(out_nodata), float(info.min), float(info.max), True, False, True,
                   valid, False)
    assert np.array_equal(v, out) and np.array_equal(ok, valid.view(bool))
    nan = np.isnan(co[0])
    assert (ok == ~nan).all() and (v[0, nan] == out_nodata).all()
    assert not (v[0, ~nan] == out_nodata).any()
    assert (v[0, 2, :4] == out_nodata + 1).all()
    truth = _truth_bilinear(raw, co)
    assert np.abs(v[:, ~nan] - truth[:, ~nan]).max() <= 1.0 + 1e-6
