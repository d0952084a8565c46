"""Mosaic: strip offsets, network, feathering and output against a known truth.

Synthetic swings (tests/mosaic_synth.py) sample a known truth at exactly shifted positions,
so the true strip offsets (1-5 px, random directions) and radiometric offsets are known.
"""
import json
import os

import numpy as np
import pytest
import rasterio

from mosaic_synth import (ImageTruth, make_swings, random_shifts, truth_grid)
from swathflow.mosaicking import mosaic as M
from swathflow.errors import FormatError, SwathflowError
from swathflow.mosaicking.matching import OverlapMatch, gradient_refine

LAKE = (200, 400, 130, 200)         # a flat area covering part of the strip 0/1 overlap
N = 5


def _read(path):
    with rasterio.open(path) as ds:
        a = ds.read(1).astype(float)
        nd = ds.nodata
        ovr = ds.overviews(1)
        prof = ds.profile
    if nd is not None:
        a[a == nd] = np.nan
    return a, ovr, prof


def _tile_shifts(mosaic, truth, tile=64, skip=None):
    """Offset of the mosaic against the truth in every fully covered tile (px)."""
    out = []
    inner = np.zeros((tile, tile), bool)
    inner[4:-4, 4:-4] = True
    for r0 in range(0, mosaic.shape[0] - tile + 1, tile):
        for c0 in range(0, mosaic.shape[1] - tile + 1, tile):
            m = mosaic[r0:r0 + tile, c0:c0 + tile]
            if not np.isfinite(m).all() or (skip is not None and skip[r0:r0 + tile, c0:c0 + tile].any()):
                continue
            d, *_ = gradient_refine(truth[r0:r0 + tile, c0:c0 + tile], m, inner)
            out.append(np.hypot(*d))
    return np.array(out)


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    d = tmp_path_factory.mktemp("swings")
    shifts, rads = random_shifts(N, seed=1)
    paths, fps, shape = make_swings(d, n_strips=N, shifts=shifts, rads=rads, lake=LAKE)
    return dict(dir=d, paths=paths, fps=fps, shape=shape, shifts=shifts, rads=rads)


@pytest.fixture(scope="module")
def result(scene, tmp_path_factory):
    out = tmp_path_factory.mktemp("out") / "mosaic.tif"
    rep = M.mosaic(scene["paths"], out, anchors=["0"], tile=256)
    return out, rep


def test_scan_inputs(scene):
    lay = M.scan_inputs(scene["paths"])
    assert lay.shape == scene["shape"]
    assert [s.strip for s in lay.swings] == [k for k in range(N) for _ in range(3)]
    assert lay.swings[4].image_id == "S1_1" and lay.res == 2.0
    assert lay.swings[3].col == 144 and lay.swings[4].row == 192


def test_scan_inputs_rejects_misaligned(scene, tmp_path):
    from affine import Affine
    from swathflow.formats.raster import write_geotiff
    bad = tmp_path / "bad.tif"
    write_geotiff(bad, np.ones((10, 10), np.float32), "EPSG:32633",
                  Affine(2.0, 0, 500000.7, 0, -2.0, 4000000.0), nodata=-9999)
    with pytest.raises(FormatError, match="not aligned"):
        M.scan_inputs(scene["paths"][:2] + [bad])


def test_offsets_recovered_within_0_2_px(scene, result):
    _, rep = result
    nodes = {n["node"]: n for n in rep["nodes"]}
    for k in range(N):
        est = np.array(nodes[str(k)]["offset"])
        assert np.hypot(*(est - scene["shifts"][k])) < 0.2, (k, est, scene["shifts"][k])
        assert abs(nodes[str(k)]["radiometric"] - scene["rads"][k]) < 1.0
    assert rep["anchors"] == ["0"]
    assert rep["sigma0"] is not None and rep["sigma0"] < 3


def test_matching_on_a_dask_cluster(scene):
    """Inside a Dask distributed context (the mission flow's), the overlaps are matched on
    the cluster's worker processes: same offsets as the threads, and the truth's."""
    from swathflow.cluster import dask_client
    lay = M.scan_inputs(scene["paths"])
    with dask_client(n_workers=2) as client:
        assert M._active_client() is client
        net, pairs, matches, _ = M.plan(lay, anchors=["0"])
        assert len(client.run(lambda: 1)) == 2   # two real worker processes
    assert M._active_client() is None
    local, *_ = M.plan(lay, anchors=["0"], workers=1)
    assert np.array_equal(np.asarray(net.offsets), np.asarray(local.offsets))
    for k, key in enumerate(net.nodes):
        assert np.hypot(*(np.asarray(net.offsets[k]) - scene["shifts"][int(key)])) < 0.2


def test_kept_swings_matched_on_local_threads_beside_a_local_cluster(scene):
    """With the swings decoded in this process (the flow's mosaic stage: a local cluster
    of one worker per core is active) the overlaps are matched on local threads over the
    kept swings, not sent to the workers (which would decode every window again): no task
    reaches the cluster, and the offsets are the cluster's and the truth's."""
    from distributed import get_task_stream

    from swathflow.cluster import dask_client
    lay = M.scan_inputs(scene["paths"])
    handles = M.swing_store()
    handles.keep_if_fits(lay.swings)
    assert handles.keep_bytes > 0
    try:
        with dask_client(n_workers=1) as client:
            assert M._active_client() is client
            with get_task_stream(client) as kept_tasks:
                kept, *_ = M.plan(lay, anchors=["0"], handles=handles)
            with get_task_stream(client) as cluster_tasks:    # nothing kept: the workers
                on_cluster, *_ = M.plan(lay, anchors=["0"])
    finally:
        handles.close()
    assert len(kept_tasks.data) == 0 and len(cluster_tasks.data) > 0
    local, *_ = M.plan(lay, anchors=["0"], workers=1)
    assert np.array_equal(np.asarray(kept.offsets), np.asarray(local.offsets))
    assert np.array_equal(np.asarray(on_cluster.offsets), np.asarray(local.offsets))
    for k, key in enumerate(kept.nodes):
        assert np.hypot(*(np.asarray(kept.offsets[k]) - scene["shifts"][int(key)])) < 0.2


def test_low_texture_overlap_reported_and_skipped(result):
    _, rep = result
    lake = [o for o in rep["overlaps"] if (o["ref"], o["mov"]) == ("S0_1", "S1_1")]
    assert lake and lake[0]["status"] == "low_texture" and not lake[0]["used"]
    assert {"ref": "S0_1", "mov": "S1_1", "status": "low_texture"} in rep["skipped"]
    used = [o for o in rep["overlaps"] if o["used"]]
    assert len(used) >= 20 and all(max(map(abs, o["residual"])) < 0.3 for o in used)


def test_mosaic_matches_truth_in_every_tile(scene, result):
    out, _ = result
    mos, ovr, prof = _read(out)
    truth = truth_grid(scene["shape"], lake=LAKE)
    lake = truth_grid(scene["shape"], truth=lambda r, c: 0 * r, lake=LAKE) != 0
    shifts = _tile_shifts(mos, truth, skip=lake)
    assert len(shifts) >= 60
    assert shifts.max() < 0.2, shifts.max()
    assert np.median(shifts) < 0.05
    # radiometry balanced back to the anchor strip's (offset-free) levels
    ok = np.isfinite(mos)
    assert abs(np.median(mos[ok] - truth[ok])) < 1.0
    # output: COG with overviews, PNG quicklook, JSON report
    assert ovr and prof["tiled"]
    assert os.path.exists(str(out)[:-4] + ".png")
    rep = json.load(open(str(out)[:-4] + ".json"))
    assert rep["format"] == "swathflow-mosaic/1"


def test_without_matching_the_mosaic_is_off(scene, tmp_path):
    """The test can fail: with the offsets left in, tiles are off by the strip offsets."""
    M.mosaic(scene["paths"], tmp_path / "raw.tif", match=False, png=False, tile=256)
    mos, _, _ = _read(tmp_path / "raw.tif")
    truth = truth_grid(scene["shape"], lake=LAKE)
    assert _tile_shifts(mos, truth).max() > 1.0


def test_nodata_aware_coverage(scene, result):
    out, _ = result
    mos, _, _ = _read(out)
    union = np.any(scene["fps"], axis=0)
    got = np.isfinite(mos)
    assert got.sum() >= 0.97 * union.sum()
    from scipy import ndimage
    grown = ndimage.binary_dilation(union, iterations=6)   # footprints move by <= 5 px
    assert not (got & ~grown).any()
    assert (~got).any()                                    # nodata stays nodata


def test_tiling_does_not_change_the_result(scene, tmp_path):
    lay = M.scan_inputs(scene["paths"])
    off = np.repeat(scene["shifts"], 3, axis=0)
    rad = np.repeat(scene["rads"], 3)
    M.write_mosaic(lay, tmp_path / "a.tif", off, rad, tile=128, cog=False)
    M.write_mosaic(lay, tmp_path / "b.tif", off, rad, tile=1024, cog=False)
    a, _, _ = _read(tmp_path / "a.tif")
    b, _, _ = _read(tmp_path / "b.tif")
    assert np.array_equal(np.isfinite(a), np.isfinite(b))
    assert np.nanmax(np.abs(a - b)) < 1e-3


def test_mosaic_cog_is_valid_and_holds_the_plain_geotiffs_pixels(scene, tmp_path):
    """The mosaic's COG (GDAL's COG driver): ``rio cogeo validate`` passes, a COG layout
    with overviews, the same pixels as the plain GeoTIFF without overviews, and its first
    overview the area-weighted mean of the valid pixels under each of its pixels (every
    one valid; NaN where none is), as GDAL's average resampling gives."""
    from cogcheck import cog_problems
    lay = M.scan_inputs(scene["paths"])
    off = np.repeat(scene["shifts"], 3, axis=0)
    rad = np.repeat(scene["rads"], 3)
    M.write_mosaic(lay, tmp_path / "cog.tif", off, rad, tile=256, blocksize=128, workers=2)
    M.write_mosaic(lay, tmp_path / "plain.tif", off, rad, tile=256, cog=False)
    a = tmp_path / "cog.tif"
    assert cog_problems(a) == []
    with rasterio.open(a) as x, rasterio.open(tmp_path / "plain.tif") as z:
        assert x.tags(ns="IMAGE_STRUCTURE")["LAYOUT"] == "COG"
        assert len(x.overviews(1)) >= 1
        full = x.read(1, masked=True).astype(float).filled(np.nan)      # nodata: NaN
        assert np.isfinite(full).any()
        assert np.array_equal(x.read(), z.read(), equal_nan=True)
    with rasterio.open(a, overview_level=0) as ov:
        got = ov.read(1, masked=True).astype(float).filled(np.nan)
    h, w = full.shape

    def weights(n, m):
        lo = np.arange(m)[:, None] * (n / m)
        k = np.arange(n)[None, :]
        return np.clip(np.minimum(lo + n / m, k + 1) - np.maximum(lo, k), 0, None)
    wy, wx = weights(h, got.shape[0]), weights(w, got.shape[1])
    ok = np.isfinite(full)
    s, n = wy @ np.where(ok, full, 0.0) @ wx.T, wy @ ok.astype(float) @ wx.T
    whole = np.isclose(n, wy @ np.ones((h, w)) @ wx.T)
    assert np.array_equal(np.isnan(got), n == 0)
    assert np.abs(got - s / np.where(n > 0, n, 1))[whole].max() < 1e-3


def test_swings_corrected_first_or_on_demand_same_pixels(scene, tmp_path, monkeypatch):
    """The corrected swings made first on all threads (they fit in the cache) or on demand
    by the tiles (a cache too small for them, evicting): the same pixels."""
    import functools

    from swathflow.mosaicking import output
    lay = M.scan_inputs(scene["paths"])
    off = np.repeat(scene["shifts"], 3, axis=0)
    rad = np.repeat(scene["rads"], 3)
    M.write_mosaic(lay, tmp_path / "first.tif", off, rad, tile=128, cog=False, workers=2)
    monkeypatch.setattr(output, "swing_cache",
                        functools.partial(output.swing_cache, max_bytes=2 ** 20))
    M.write_mosaic(lay, tmp_path / "lazy.tif", off, rad, tile=128, cog=False, workers=2)
    a, _, _ = _read(tmp_path / "first.tif")
    b, _, _ = _read(tmp_path / "lazy.tif")
    assert np.isfinite(a).any()
    assert np.array_equal(a, b, equal_nan=True)


def test_seams_vanish_with_feathering(tmp_path):
    """Strips with a slow radiometric drift along track (constant offsets cannot remove it):
    seams show with hard cuts, not with feathering."""
    shifts, rads = random_shifts(N, seed=2)
    paths, fps, shape = make_swings(tmp_path / "in", n_strips=N, shifts=shifts, rads=rads,
                                    drift=6.0, seed=5)
    truth = truth_grid(shape)
    vis = {}
    for mode in ("feather", "cut"):
        rep = M.mosaic(paths, tmp_path / f"{mode}.tif", anchors=["0"], mode=mode, png=False)
        mos, _, _ = _read(tmp_path / f"{mode}.tif")
        vis[mode] = (M.seam_visibility(mos, fps), M.seam_visibility(mos - truth, fps))
        nodes = {n["node"]: n for n in rep["nodes"]}
        for k in range(N):
            assert np.hypot(*(np.array(nodes[str(k)]["offset"]) - shifts[k])) < 0.2
    (f_seam, f_in), (fe_seam, fe_in) = vis["feather"]
    (c_seam, c_in), (ce_seam, ce_in) = vis["cut"]
    print(f"\nseam/inner gradient: feather {f_seam:.3f}/{f_in:.3f}, cut {c_seam:.3f}/{c_in:.3f};"
          f" of the error image: feather {fe_seam:.3f}/{fe_in:.3f}, cut {ce_seam:.3f}/{ce_in:.3f}")
    assert f_seam <= f_in
    assert f_seam < c_seam
    assert fe_seam < 0.6 * ce_seam              # the step itself: clearly lower


def test_per_image_offsets(scene, tmp_path):
    rep = M.mosaic(scene["paths"], tmp_path / "pi.tif", per_image=True, anchors=["S0_0"],
                   png=False)
    nodes = {n["node"]: n for n in rep["nodes"]}
    for k in range(N):
        for s in range(3):
            iid = f"S{k}_{s}"
            if iid in ("S0_1",):      # in the lake: linked only along its strip
                pass
            est = np.array(nodes[iid]["offset"])
            assert np.hypot(*(est - scene["shifts"][k])) < 0.2, (iid, est, scene["shifts"][k])


def test_network_anchor_free_and_outlier():
    def obs(i, j, d, ok=True):
        return (i, j, OverlapMatch(ok, "ok", offset=d, sigma=(0.02, 0.02), radiometric=0.0,
                                   radiometric_sigma=0.1))
    t = np.array([[0, 0], [1.0, 2.0], [-1.5, 0.5], [3.0, -2.0]])
    o = [obs(i, j, tuple(t[j] - t[i])) for i, j in [(0, 1), (1, 2), (2, 3), (0, 2), (1, 3),
                                                     (0, 3)]]
    o.append(obs(0, 3, (t[3][0] + 2.0, t[3][1])))     # a blunder
    net = M.solve_network([0, 1, 2, 3], o, anchors=[0])
    assert np.allclose(net.offsets, t, atol=1e-6)
    assert not net.used[-1] and net.used[:-1].all()
    free = M.solve_network([0, 1, 2, 3], o[:-1], anchors=[])
    assert np.allclose(free.offsets, t - t.mean(0), atol=1e-6)
    assert free.free_groups == [[0, 1, 2, 3]]


def test_network_dense_equals_sparse():
    """Small networks are solved densely without scipy; the same components (numbered as
    scipy numbers them) and the same solution as the sparse path of large ones."""
    from swathflow.mosaicking.network import _components, _solve_lsq
    rng = np.random.default_rng(3)
    for _trial in range(20):
        n = int(rng.integers(2, 30))
        m = int(rng.integers(0, 2 * n))
        edges = [tuple(int(v) for v in rng.integers(0, n, 2)) for _ in range(m)]
        ncomp, labels = _components(n, edges)
        ncomp_s, labels_s = _components(n, edges, max_dense=0)
        assert ncomp == ncomp_s and np.array_equal(labels, labels_s), (edges, labels, labels_s)
        if not edges:
            continue
        values, weights = rng.normal(0, 3, m), rng.uniform(1, 100, m)
        anchored = sorted(set(int(v) for v in rng.integers(0, n, int(rng.integers(0, 3)))))
        k = int(rng.integers(0, 3))
        tied = (list(rng.integers(0, n, k)), list(rng.normal(0, 2, k)),
                list(rng.uniform(1, 10, k))) if k else ()
        x, sx = _solve_lsq(n, edges, values, weights, anchored, labels, tied)
        xs, sxs = _solve_lsq(n, edges, values, weights, anchored, labels, tied, max_dense=0)
        assert np.allclose(x, xs, rtol=0, atol=1e-9), (x, xs)
        assert np.isfinite(sx).all() and np.isnan(sxs).all()


def test_real_orthophoto_strips(tmp_path):
    from spec_vectors import DATA
    path = str(DATA / "autzen" / "autzen.jpg")
    truth = ImageTruth(path, rows=700, cols=820, r0=1500, c0=1000)
    shifts, rads = random_shifts(5, seed=7)
    paths, fps, shape = make_swings(tmp_path / "in", n_strips=5, length=600, shifts=shifts,
                                    rads=rads, truth=truth, noise=1.0)
    rep = M.mosaic(paths, tmp_path / "m.tif", anchors=["0"], png=False)
    nodes = {n["node"]: n for n in rep["nodes"]}
    for k in range(5):
        assert np.hypot(*(np.array(nodes[str(k)]["offset"]) - shifts[k])) < 0.2
    mos, _, _ = _read(tmp_path / "m.tif")
    g = truth_grid(shape, truth=truth)
    sh = _tile_shifts(mos, g)
    assert len(sh) > 40 and np.percentile(sh, 95) < 0.2, np.sort(sh)[-5:]


def test_cli(scene, tmp_path):
    from swathflow.flows.cli import main
    out = tmp_path / "cli.tif"
    assert main(["mosaic", str(scene["dir"]), "--out", str(out), "--anchor", "0"]) == 0
    assert out.exists() and (tmp_path / "cli.png").exists() and (tmp_path / "cli.json").exists()
    empty = tmp_path / "empty"
    empty.mkdir()
    assert main(["mosaic", str(empty), "--out", str(tmp_path / "x.tif")]) == 2
    with pytest.raises(SwathflowError, match="anchor"):
        M.mosaic(scene["paths"][:3], tmp_path / "y.tif", anchors=["nope"])


def test_report_arrows_stay_in_the_map():
    """The residual arrows of the report's map stay inside the map's frame: an overlap at
    the left edge whose residual points left (the survey's arrow ran past the edge), one
    at the top edge pointing up, and one whose residual is much the smallest, keep their
    direction and stay in."""
    from affine import Affine

    from swathflow.mosaicking.inputs import Layout
    from swathflow.mosaicking.report import arrow_ends
    layout = Layout(None, Affine(2.0, 0, 1000.0, 0, -2.0, 5000.0), (100, 200))
    ov = [dict(window=[40, 0, 60, 30], residual=[0.0, -0.008], used=True, ok=True),
          dict(window=[10, 150, 30, 200], residual=[0.01, 0.004], used=True, ok=True),
          dict(window=[0, 60, 8, 80], residual=[-0.01, 0.0], used=True, ok=True),
          dict(window=[50, 90, 90, 110], residual=[0.0003, 0.0002], used=True, ok=True)]
    ends, gain = arrow_ends({"overlaps": ov}, layout)
    assert len(ends) == len(ov) and gain > 0
    x0, x1, y0, y1 = 1000.0, 1400.0, 4800.0, 5000.0          # the grid's map extent
    for (a, b), o in zip(ends, ov):
        for x, y in (a, b):
            assert x0 <= x <= x1 and y0 <= y <= y1, (x, y)
        d = np.array([b[0] - a[0], b[1] - a[1]])
        r = np.array([o["residual"][1], -o["residual"][0]])   # col east, row south
        assert np.linalg.norm(d) > 0
        assert np.dot(d, r) / np.linalg.norm(d) / np.linalg.norm(r) > 0.999


def test_scan_hands_its_datasets_to_the_decoding(scene, monkeypatch):
    """With a swing store keeping whole swings, each file is opened once (the scan's
    dataset decodes it and is closed); the decoded swings equal a fresh read; a store too
    small to keep them closes the scan's datasets at once."""
    opened = []
    real = rasterio.open

    def counting(path, *a, **k):
        ds = real(path, *a, **k)
        opened.append(ds)
        return ds
    monkeypatch.setattr(rasterio, "open", counting)
    h = M.swing_store()
    try:
        lay, *_ = M.plan_mosaic(scene["paths"], match=False, handles=h)
        assert len(opened) == len(scene["paths"])
        assert all(ds.closed for ds in opened) and not h._opened
        for sw in lay.swings:
            data, ok = h.whole(sw)
            with real(sw.path) as ds:
                assert np.array_equal(data, ds.read(1))
    finally:
        h.close()
    opened.clear()
    for small in (M.swing_store(keep_mb=0), M._Handles(keep_bytes=1000)):
        try:
            M.plan_mosaic(scene["paths"], match=False, handles=small)
            assert small.keep_bytes == 0
            assert all(ds.closed for ds in opened) and not small._opened
        finally:
            small.close()


def test_products_from_the_first_overview_level_are_the_cogs(scene, tmp_path, monkeypatch):
    """The quicklook, report picture and HTML made from the first overview level in memory
    (beside the COG's layout) are byte for byte those made from the written COG."""
    H, W = scene["shape"]
    side = max(H, W) // 2
    if (H % 2, W % 2) != (0, 0) or max(H, W) % 2:
        pytest.skip("the scene's sides are not even")
    monkeypatch.setattr(M, "QUICKLOOK_SIDE", side)
    used = []
    real = M.level_overview
    monkeypatch.setattr(M, "level_overview", lambda *a: used.append(real(*a)) or used[-1])
    for d in ("early", "read"):
        (tmp_path / d).mkdir()
    M.mosaic(scene["paths"], tmp_path / "early" / "m.tif", anchors=["0"], tile=256)
    assert len(used) == 1 and used[0] is not None and used[0][0].shape == (H // 2, W // 2)
    monkeypatch.setattr(M, "level_overview", lambda *a: None)
    M.mosaic(scene["paths"], tmp_path / "read" / "m.tif", anchors=["0"], tile=256)
    for ext in (".png", ".report.png", ".html"):
        assert (tmp_path / "early" / f"m{ext}").read_bytes() == \
            (tmp_path / "read" / f"m{ext}").read_bytes()
    # the COG's pixels (its bytes may differ run to run: base too, tiles land in any order)
    np.testing.assert_array_equal(_read(tmp_path / "early" / "m.tif")[0],
                                  _read(tmp_path / "read" / "m.tif")[0])
    data, f = M.overview(tmp_path / "read" / "m.tif", side)
    np.testing.assert_array_equal(used[0][0], data)
    assert used[0][1] == f
    assert M.level_overview(used[0][0][:-1], np.nan, (H, W), side) is None
