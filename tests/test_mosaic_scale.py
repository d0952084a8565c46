"""Coarse-to-fine matching, per-swing blending, the overlap sweep and control-point
anchoring, each against a known truth (exactly shifted procedural texture, scipy's own
definitions, brute force, simulated offsets)."""
import json
import os

import numpy as np
import pytest
from scipy import ndimage

from mosaic_synth import make_swings, random_shifts, texture
from swathflow.mosaicking import mosaic as M
from swathflow.mosaicking.blend import blend_tile, corrected_swing, shift_cubic
from swathflow.mosaicking.coarse import coarse_shift, match_overlap
from swathflow.mosaicking.matching import OverlapMatch, combine_blocks
from swathflow.mosaicking.network import solve_network
from swathflow.mosaicking.overlaps import _bbox_pairs

SHIFTS = [(0.3, -2.7), (1.45, 3.2), (-4.1, 0.6), (2.5, 2.5), (-0.8, -4.9), (7.6, -9.3),
          (-11.2, 10.4)]


def _overlap(d, shape=(480, 40), margin=0, wavy=True, noise=0.5, seed=0, tex=texture):
    """A narrow overlap strip (as between two flight strips) of a known texture; ``mov``
    is the truth displaced by ``d`` and read with ``margin``; wavy valid edges."""
    rng = np.random.default_rng(seed)
    rr, cc = np.mgrid[0:shape[0], 0:shape[1]].astype(float)
    ref = tex(rr, cc) + rng.normal(0, noise, shape)
    r2, c2 = np.mgrid[-margin:shape[0] + margin, -margin:shape[1] + margin].astype(float)
    mov = tex(r2 - d[0], c2 - d[1]) + 9.0 + rng.normal(0, noise, r2.shape)
    rok = np.ones(shape, bool)
    mok = np.ones(r2.shape, bool)
    if wavy:
        rok &= cc < shape[1] - 3 + 2 * np.sin(rr / 23.0)
        mok &= c2 > 2 + 2 * np.sin(r2 / 17.0)
    return ref, rok, mov, mok


@pytest.mark.parametrize("d", SHIFTS)
def test_coarse_shift_lands_near_the_truth(d):
    S = 12
    ref, rok, mov, mok = _overlap(d, margin=S)
    c, contrast = coarse_shift(ref, rok, mov, mok, S, factor=3)
    assert c is not None and contrast > 0.15
    assert max(abs(c[0] - d[0]), abs(c[1] - d[1])) <= 2.0, (c, d)


@pytest.mark.parametrize("d", SHIFTS)
def test_coarse_to_fine_offsets_within_0_05_px(d):
    S = 12
    M_ = S + 3 // 2 + 2
    ref, rok, mov, mok = _overlap(d, margin=M_, seed=3)
    blocks, c = match_overlap(ref, rok, mov, mok, M_, S, block=128, max_blocks=16)
    assert c is not None                      # the overview path was taken
    res = combine_blocks(blocks)
    assert res.ok, res.status
    assert np.allclose(res.offset, d, atol=0.05), (res.offset, d)
    assert abs(res.radiometric - 9.0) < 0.5


def test_coarse_to_fine_refuses_a_flat_overlap():
    flat = lambda r, c: 100.0 + 0 * np.asarray(r, float) * np.asarray(c, float)  # noqa: E731
    ref, rok, mov, mok = _overlap((1.5, 2.0), margin=17, tex=flat, noise=1.0)
    blocks, c = match_overlap(ref, rok, mov, mok, 17, 12)
    assert c is None                          # no overview answer: the full search ran
    res = combine_blocks(blocks)
    assert not res.ok and res.status == "low_texture"


@pytest.mark.parametrize("f", [(0.3, 0.7), (0.0, 0.45), (0.6, 0.0), (0.999, 0.001),
                               (-1.37, 2.2), (3.5, -4.05), (-0.2, -0.9), (15.3, 0.5)])
def test_shift_cubic_is_scipys_spline_shift(f):
    a = np.random.default_rng(1).normal(size=(70, 45))
    want = ndimage.shift(a, -np.asarray(f), order=3, mode="nearest")
    assert np.abs(shift_cubic(a, np.asarray(f)) - want).max() < 1e-9


def test_corrected_swing_weights_are_the_capped_distance():
    rng = np.random.default_rng(2)
    val = rng.normal(size=(60, 50))
    ok = np.zeros((60, 50), bool)
    ok[5:55, 8:40] = True
    ok[20:30, 8:12] = False
    c = corrected_swing(val, ok, 100, 200, (2.0, -3.0), 4.0, feather=6)
    assert (c.row, c.col) == (98, 203)        # out[x] = image[x + t]: integer part
    want = np.minimum(ndimage.distance_transform_edt(np.pad(ok, 1))[1:-1, 1:-1], 6)
    assert np.allclose(c.weight, want)
    assert np.allclose(c.values[ok], val[ok] - 4.0, atol=1e-5)
    # a fractional shift: valid only where both neighbours along each shifted axis were
    c = corrected_swing(val, ok, 0, 0, (0.5, 0.0), 0.0, feather=6)
    m = ok.copy()
    m[:-1] &= ok[1:]
    m[-1] = False
    assert np.array_equal(c.weight > 0, m)


def test_blend_tile_is_the_weighted_mean():
    from swathflow.mosaicking.blend import Corrected
    a = Corrected(0, 0, np.full((10, 10), 10.0, np.float32), np.full((10, 10), 1.0, np.float32))
    b = Corrected(5, 5, np.full((10, 10), 20.0, np.float32), np.full((10, 10), 3.0, np.float32))
    v, ok = blend_tile([a, b], 0, 0, 15, 15)
    assert v[0, 0] == 10.0 and v[14, 14] == 20.0 and v[7, 7] == pytest.approx(17.5)
    assert not ok[0, 14] and np.isnan(v[0, 14])
    v, _ = blend_tile([a, b], 0, 0, 15, 15, mode="first")
    assert v[7, 7] == 10.0
    v, _ = blend_tile([a, b], 0, 0, 15, 15, mode="cut")
    assert v[7, 7] == 20.0


def _mapping(a):
    """The memory mapping an array's memory belongs to, or None (the C heap)."""
    import mmap
    while isinstance(a, np.ndarray):
        a = a.base
    return a.obj if isinstance(a, memoryview) and isinstance(a.obj, mmap.mmap) else None


def test_swing_cache_keeps_its_swings_in_reused_mappings():
    from swathflow.mosaicking.blend import Corrected, SwingCache
    rng = np.random.default_rng(0)
    made = {k: Corrected(k, 0, rng.random((30, 20), dtype=np.float32),
                         rng.random((30, 20), dtype=np.float32)) for k in range(6)}

    def make(k, empty):                 # as corrected_swing makes its arrays
        v, w = empty((30, 20), np.float32), empty((30, 20), np.float32)
        v[...], w[...] = made[k].values, made[k].weight
        return Corrected(k, 0, v, w)
    cache = SwingCache(make, max_bytes=2 * made[0].nbytes)
    first = cache.get(0)
    assert np.array_equal(first.values, made[0].values)
    assert np.array_equal(first.weight, made[0].weight)
    maps = {id(_mapping(first.values)), id(_mapping(first.weight))}
    assert None not in {_mapping(first.values), _mapping(first.weight)}
    del first
    for k in range(1, 4):           # 0 is evicted as 2 comes in, its mappings freed
        c = cache.get(k)
        assert np.array_equal(c.values, made[k].values) and c.row == k
        assert cache._bytes <= cache.max_bytes
    # 3 was made on the mappings 0 left
    assert {id(_mapping(c.values)), id(_mapping(c.weight))} == maps


def test_mappings_keep_at_most_spare_unused():
    from swathflow.mosaicking.blend import Mappings
    m = Mappings(spare=2)
    arrays = [m.empty((4, 4), np.float64) for k in range(5)]
    for k, a in enumerate(arrays):
        a[...] = k
    assert [a[0, 0] for a in arrays] == [0, 1, 2, 3, 4]
    del arrays
    assert [len(v) for v in m._free.values()] == [2]
    m.clear()
    assert m._free == {}


def test_tiles_go_down_bands_a_swing_wide():
    from types import SimpleNamespace as NS

    from swathflow.mosaicking.output import _tile_order
    tall = NS(shape=(2500, 5000), swings=[NS(height=3000, width=2100)] * 3)
    order = _tile_order(tall, 1000)
    grid = {(r, c, min(2500, r + 1000), min(5000, c + 1000))
            for r in range(0, 2500, 1000) for c in range(0, 5000, 1000)}
    assert len(order) == len(grid) and set(order) == grid
    # bands of 3 tile columns (a swing is 2.1 tiles wide), row by row down each band
    assert [(r, c) for r, c, _, _ in order[:9]] == [(r, c) for r in (0, 1000, 2000)
                                                   for c in (0, 1000, 2000)]
    assert order[9][:2] == (0, 3000)
    wide = NS(shape=(5000, 2500), swings=[NS(height=900, width=2000)] * 3)
    assert [t[:2] for t in _tile_order(wide, 1000)[:4]] == [(0, 0), (0, 1000), (0, 2000),
                                                            (1000, 0)]


def test_bbox_sweep_finds_every_intersecting_pair():
    rng = np.random.default_rng(4)
    r0 = rng.integers(0, 500, 300)
    c0 = rng.integers(0, 500, 300)
    ext = np.c_[r0, c0, r0 + rng.integers(1, 60, 300), c0 + rng.integers(1, 60, 300)]
    brute = [(i, j) for i in range(300) for j in range(i + 1, 300)
             if max(ext[i, 0], ext[j, 0]) < min(ext[i, 2], ext[j, 2])
             and max(ext[i, 1], ext[j, 1]) < min(ext[i, 3], ext[j, 3])]
    assert _bbox_pairs(ext) == brute and len(brute) > 50


def _obs(i, j, d, s=0.02):
    return (i, j, OverlapMatch(True, "ok", offset=tuple(d), sigma=(s, s), radiometric=0.0,
                               radiometric_sigma=0.1))


def test_network_tied_to_control_points():
    """Absolute offsets (control points, sigma 0.3 px per node) plus precise relative ones:
    every node lands within 3 sigma of its true absolute offset, and the reported sigmas
    are those of the least-squares solution (about 0.3 / sqrt(n) for the common shift)."""
    rng = np.random.default_rng(5)
    n = 8
    t = rng.uniform(-4, 4, (n, 2))
    obs = [_obs(i, i + 1, t[i + 1] - t[i] + rng.normal(0, 0.02, 2)) for i in range(n - 1)]
    sig = 0.3
    absolute = [(k, tuple(t[k] + rng.normal(0, sig, 2)), (sig, sig)) for k in range(n)]
    net = solve_network(list(range(n)), obs, absolute=absolute)
    assert not net.free_groups and not net.anchored
    err = np.abs(net.offsets - t)
    assert (err < 3 * net.sigmas).all(), (err, net.sigmas)
    assert np.allclose(net.sigmas, sig / np.sqrt(n), rtol=0.5)
    # without the control the network can only hold the mean: off by the mean offset
    free = solve_network(list(range(n)), obs)
    assert np.abs(free.offsets - t).max() > 0.5


@pytest.fixture(scope="module")
def shifted_scene(tmp_path_factory):
    d = tmp_path_factory.mktemp("gcpswings")
    shifts, rads = random_shifts(4, seed=11)
    shifts[0] = (1.2, -0.7)                   # no strip sits at the truth
    paths, _, shape = make_swings(d, n_strips=4, length=420, shifts=shifts, rads=rads,
                                  footprints=False)
    return dict(paths=paths, shifts=shifts, shape=shape, dir=d)


def test_mosaic_anchored_on_control_points(shifted_scene, tmp_path):
    """Control offsets (truth + 0.3 px noise, 2 images per strip) tie the mosaic to the
    ground: every strip's absolute offset within 3 sigma of the truth; mosaic.json holds
    them with their sigmas; the report picture is written."""
    sc = shifted_scene
    rng = np.random.default_rng(8)
    control = {}
    for k in range(4):
        for s in (0, 2):
            control[f"S{k}_{s}"] = (tuple(sc["shifts"][k] + rng.normal(0, 0.3, 2)), (0.3, 0.3))
    out = tmp_path / "g.tif"
    rep = M.mosaic(sc["paths"], out, control=control, png=False)
    doc = json.load(open(tmp_path / "g.json"))
    assert doc["anchor"] == "gcp" and len(doc["control"]) == 8 and not doc["free_groups"]
    for nd in doc["nodes"]:
        k = int(nd["node"])
        err = np.abs(np.array(nd["offset"]) - sc["shifts"][k])
        assert (err < 3 * np.array(nd["sigma"])).all() and err.max() < 0.45, (k, err, nd)
    assert os.path.getsize(tmp_path / "g.report.png") > 10_000
    assert rep["sigma0"] is not None


def test_parts_of_an_area_give_the_same_pixels(shifted_scene, tmp_path):
    """The area cut into four runs (each with the swings that reach its quarter) gives,
    inside each quarter, exactly the pixels of the whole run (same offsets)."""
    import rasterio
    from rasterio.windows import from_bounds
    sc = shifted_scene
    lay = M.scan_inputs(sc["paths"])
    off = np.repeat(sc["shifts"], 3, axis=0)
    rad = np.zeros(len(lay.swings))
    M.write_mosaic(lay, tmp_path / "all.tif", off, rad, tile=128, cog=False)
    H, W = lay.shape
    with rasterio.open(tmp_path / "all.tif") as ds:
        whole = ds.read(1)
        tr = ds.transform
    for q, (r0, c0) in enumerate([(0, 0), (0, W // 2), (H // 2, 0), (H // 2, W // 2)]):
        r1, c1 = (r0 + H // 2, c0 + W // 2)
        sel = [k for k, s in enumerate(lay.swings)
               if s.row - 12 < r1 and s.row + s.height + 12 > r0 and s.col - 12 < c1
               and s.col + s.width + 12 > c0]
        part = M.scan_inputs([lay.swings[k].path for k in sel])
        M.write_mosaic(part, tmp_path / f"q{q}.tif", off[sel], rad[sel], tile=256, cog=False)
        x0, y0 = tr.c + c0 * tr.a, tr.f + r0 * tr.e
        x1, y1 = tr.c + c1 * tr.a, tr.f + r1 * tr.e
        with rasterio.open(tmp_path / f"q{q}.tif") as ds:
            got = ds.read(1, window=from_bounds(x0, y1, x1, y0, ds.transform))
        assert np.array_equal(got, whole[r0:r1, c0:c1]), q


def test_cli_anchor_gcp_needs_the_mission_and_calibration(shifted_scene, tmp_path, capsys):
    from swathflow.flows.cli import main
    code = main(["mosaic", str(shifted_scene["dir"]), "--out", str(tmp_path / "x.tif"),
                 "--anchor", "gcp"])
    assert code == 2 and "--anchor gcp needs the mission" in capsys.readouterr().err
    assert not (tmp_path / "x.tif").exists()


def test_decoded_swings_give_the_windows_gdal_reads(shifted_scene):
    """Windows sliced from the kept decoded swings (inside, across and outside a swing's
    edges) are the values and validity of windowed reads (decimated ones: every third pixel
    of the window); a store too small for the run keeps nothing."""
    from swathflow.mosaicking.inputs import _Handles, read_window
    lay = M.scan_inputs(shifted_scene["paths"])
    kept, plain = M.swing_store(), _Handles()
    kept.keep_if_fits(lay.swings)
    assert kept.keep_bytes > 0
    try:
        for sw in lay.swings[:4]:
            for win in ((sw.row, sw.col, sw.row + sw.height, sw.col + sw.width),
                        (sw.row - 7, sw.col + 5, sw.row + 40, sw.col + sw.width + 9),
                        (sw.row + sw.height - 3, sw.col - 4, sw.row + sw.height + 5,
                         sw.col + 3)):
                a, b = read_window(kept, sw, *win), read_window(plain, sw, *win)
                assert np.array_equal(a[1], b[1]) and np.array_equal(a[0], b[0])
                # decimated: the pixels on the grid lattice of the window
                d = read_window(kept, sw, *win, step=3)
                assert np.array_equal(d[1], b[1][::3, ::3])
                assert np.array_equal(d[0], b[0][::3, ::3])
        assert len(kept._whole) == 4
    finally:
        kept.close()
        plain.close()
    small = M.swing_store(keep_mb=0)
    small.keep_if_fits(lay.swings)
    assert small.keep_bytes == 0


def test_corrections_on_reused_dirty_buffers_equal_fresh_ones():
    """A swing corrected in a thread's scratch buffers and on dirty result arrays (left by
    a larger swing, NaN-filled) equals the same swing corrected on new arrays: every
    element the kernels return is written, whatever the buffers held."""
    from swathflow.mosaicking.blend import Scratch, corrected_swing
    rng = np.random.default_rng(7)
    big = rng.normal(size=(90, 80))
    big_ok = ndimage.binary_opening(rng.random((90, 80)) > 0.1)
    val = rng.normal(size=(60, 50))
    ok = np.zeros((60, 50), bool)
    ok[5:55, 8:40] = True
    ok[20:30, 8:12] = False
    ok[0, :] = True                              # an edge row: the fill's borders

    def dirty(shape, dtype):
        a = np.empty(shape, dtype)
        a[...] = np.nan if np.dtype(dtype).kind == "f" else True
        return a

    scratch = Scratch()
    for offset in ((0.0, 0.0), (0.3, -1.6), (2.5, 0.25)):
        corrected_swing(big, big_ok, 0, 0, (0.7, 0.2), 1.0, 8, scratch=scratch.get)
        for buf in ("filled", "coef", "valid", "distance"):   # what the big swing left,
            b = scratch.get(buf, (90, 80), bool if buf == "valid" else float)  # soiled
            b[...] = True if buf == "valid" else np.nan
        got = corrected_swing(val, ok, 3, 4, offset, 2.0, 6, empty=dirty,
                              scratch=scratch.get)
        want = corrected_swing(val, ok, 3, 4, offset, 2.0, 6)
        assert (got.row, got.col) == (want.row, want.col)
        assert np.array_equal(got.values, want.values)
        assert np.array_equal(got.weight, want.weight)
