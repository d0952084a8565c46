"""The COG writer (swathflow.rectification.writing: GDAL's COG driver through rasterio):
overviews against a resampled truth (the area-weighted mean of the valid pixels under each
overview pixel's footprint, each level from the one above), a valid COG layout
(``rio cogeo validate`` and the validators' checks), full-resolution pixels, nodata, codec,
predictor and metadata kept, atomic writes."""
from __future__ import annotations

import math

import numpy as np
import pytest
import rasterio
from rasterio.transform import from_origin
from swathflow.geometry.grid import Grid
from swathflow.rectification.writing import overview_factors, write_cogs
from cogcheck import cog_problems

H, W = 1100, 1301           # odd width: the last overview column averages one column


def _weights(n: int, m: int) -> np.ndarray:
    """(m, n): the length of source pixel k inside overview pixel i, when ``n`` pixels are
    resampled to ``m`` over the same extent (GDAL's overview grid: the overview's pixel is
    ``n / m`` source pixels)."""
    r = n / m
    lo = np.arange(m)[:, None] * r
    k = np.arange(n)[None, :]
    return np.clip(np.minimum(lo + r, k + 1) - np.maximum(lo, k), 0, None)


def _gather(x, shape, fill, reduce):
    """Reduce (``reduce``: np.fmin, np.fmax, np.logical_and) the pixels of ``x`` (bands,
    rows, cols) each pixel of ``shape`` touches (at most 3 x 3: the footprints are about 2
    pixels wide), from ``fill``."""
    (sy, cy), (sx, cx) = [((t := _weights(n, m) > 0).argmax(1), t.sum(1))
                          for n, m in zip(x.shape[1:], shape)]
    out = np.full((x.shape[0],) + tuple(shape), fill)
    for a in range(3):
        for b in range(3):
            rows = np.minimum(sy + a, x.shape[1] - 1)
            cols = np.minimum(sx + b, x.shape[2] - 1)
            use = (a < cy)[:, None] & (b < cx)[None, :]
            out = np.where(use, reduce(out, x[:, rows][:, :, cols]), out)
    return out


def _levels(data, nodata, shapes):
    """The truth of each overview level, each resampled from the one above it (as GDAL
    does): per level (mean, min, max, whole): the area-weighted mean of the valid pixels
    under each pixel's footprint (NaN where none), the range of the valid full-resolution
    pixels under it, and whether every pixel under it is valid."""
    x = data.astype(float)
    if not math.isnan(nodata):
        x = np.where(data == nodata, np.nan, x)
    lo, hi, whole = x, x, ~np.isnan(x)
    out = []
    for shape in shapes:
        wy, wx = _weights(x.shape[1], shape[0]), _weights(x.shape[2], shape[1])
        ok = ~np.isnan(x)
        s, n = wy @ np.where(ok, x, 0.0) @ wx.T, wy @ ok.astype(float) @ wx.T
        with np.errstate(invalid="ignore", divide="ignore"):
            x = np.where(n > 0, s / n, np.nan)
        lo = _gather(lo, shape, np.inf, np.fmin)
        hi = _gather(hi, shape, -np.inf, np.fmax)
        whole = _gather(whole, shape, True, np.logical_and)
        out.append((x, lo, hi, whole))
    return out


def _cube(nb, dtype):
    b, r, c = np.ogrid[0:nb, 0:H, 0:W]
    return (2000 + 7 * b + 300 * np.sin(r / 9.0 + b / 17.0) * np.cos(c / 7.0)).astype(dtype)


def test_overview_levels_halve_until_one_block():
    assert overview_factors(1354, 1400, 512) == [2, 4]
    assert overview_factors(512, 512, 512) == []
    assert overview_factors(513, 100, 512) == [2]
    assert overview_factors(1100, 1301, 256) == [2, 4, 8]
    assert overview_factors(2600, 8200, 512) == [2, 4, 8, 16]     # as GDAL's COG driver


@pytest.mark.parametrize("dtype,nodata", [(np.uint16, 0), (np.float32, float("nan")),
                                          (np.int16, -32768)])
def test_cog_with_our_overviews_matches_block_means(tmp_path, dtype, nodata):
    nb = 5
    data = _cube(nb, dtype)
    data[:, :100, :300] = nodata                       # a nodata corner
    data[2, 500:503, 700:702] = nodata                 # and a few pixels of one band
    grid = Grid("EPSG:32633", from_origin(500000, 6000000, 0.5, 0.5), (H, W))
    path = tmp_path / "cube.tif"
    write_cogs([{"path": path, "array": data, "grid": grid, "nodata": nodata,
                 "tags": {"product": "test"}}], blocksize=256)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cube.tif"]      # no leftovers
    is_int = np.dtype(dtype).kind in "ui"
    with rasterio.open(path) as src:
        assert src.tags(ns="IMAGE_STRUCTURE").get("LAYOUT") == "COG"
        assert src.tags()["product"] == "test" and src.crs.to_epsg() == 32633
        assert src.transform == grid.transform and src.count == nb
        assert src.overviews(1) == [2, 4, 8] and src.dtypes[0] == np.dtype(dtype).name
        assert np.array_equal(src.read(), data, equal_nan=True)
    shapes = [(-(-H // f), -(-W // f)) for f in (2, 4, 8)]      # gdaladdo's sizes
    for lv, (mean, lo, hi, whole) in enumerate(_levels(data, nodata, shapes)):
        with rasterio.open(path, overview_level=lv) as ov:
            got = ov.read().astype(float)
        if not is_int:
            got[np.isnan(got)] = np.nan
        else:
            got[got == nodata] = np.nan
        assert got.shape == mean.shape
        # nodata exactly where a block has no valid pixel
        assert np.array_equal(np.isnan(got), np.isnan(mean))
        ok = ~np.isnan(mean)
        # within the range of the valid pixels under it (plus integer rounding)
        assert (got[ok] >= np.floor(lo[ok]) - 1e-6).all() and (got[ok] <= np.ceil(hi[ok]) + 1e-6).all()
        # every pixel under it valid: each level is the mean of the one above, so the
        # truth's (integer output: rounded once per level)
        tol = 0.5 * (lv + 1) + 1e-9 if is_int else 1e-3
        assert np.abs(got - mean)[whole].max() <= tol, (lv, np.abs(got - mean)[whole].max())


def _cog_layout_problems(path) -> list[str]:
    """The layout checks of the COG validators (GDAL's validate_cloud_optimized_geotiff,
    rio-cogeo), on the offsets GDAL itself reports, plus every tile's leader (its byte
    count) and trailer (its last four bytes) that the ghost area announces."""
    problems = []
    with rasterio.open(path) as src:
        tiff = lambda key, ds=src: ds.get_tag_item(key, "TIFF", bidx=1)  # noqa: E731
        ifd0 = int(tiff("IFD_OFFSET"))
        if ifd0 > 300:
            problems.append(f"main IFD at {ifd0}")
        if src.tags(ns="IMAGE_STRUCTURE").get("LAYOUT") != "COG":
            problems.append("GDAL does not see LAYOUT=COG")
        levels = [src]
        for k in range(len(src.overviews(1))):
            levels.append(rasterio.open(path, overview_level=k))
        ifds = [int(tiff("IFD_OFFSET", ds)) for ds in levels]
        if ifds != sorted(ifds):
            problems.append(f"IFDs not in order {ifds}")
        blocks = []
        for ds in levels:
            bw, bh = ds.block_shapes[0][1], ds.block_shapes[0][0]
            offs = []
            planes = ds.count if ds.interleaving.name == "BAND" else 1
            for b in range(1, planes + 1):
                for y in range(-(-ds.height // bh)):
                    for x in range(-(-ds.width // bw)):
                        off = int(ds.get_tag_item(f"BLOCK_OFFSET_{x}_{y}", "TIFF", bidx=b))
                        size = int(ds.get_tag_item(f"BLOCK_SIZE_{x}_{y}", "TIFF", bidx=b))
                        offs.append((off, size))
            blocks.append(offs)
        for ds in levels[1:]:
            ds.close()
    if max(ifds) >= min(o for offs in blocks for o, _ in offs):
        problems.append("an IFD after image data")
    firsts = [offs[0][0] for offs in blocks]
    if firsts != sorted(firsts, reverse=True):
        problems.append(f"data not from the smallest overview to the full resolution {firsts}")
    raw = open(path, "rb").read()
    for offs in blocks:
        if [o for o, _ in offs] != sorted(o for o, _ in offs):
            problems.append("tiles of a level out of order")
        for off, size in offs:
            lead = int.from_bytes(raw[off - 4:off], "little")
            if lead != size or raw[off + size:off + size + 4] != raw[off + size - 4:off + size]:
                problems.append(f"bad leader/trailer at {off}")
                break
    return problems


@pytest.mark.parametrize("nb,dtype,nodata,big,ram", [(1, np.uint16, 0, False, True),
                                                     (3, np.float32, float("nan"), False, True),
                                                     (1, np.uint16, 0, False, False),
                                                     (2, np.int16, -32768, True, False)])
def test_cog_layout_metadata_and_pixels(tmp_path, monkeypatch, nb, dtype, nodata, big, ram):
    """The COG made by GDAL's COG driver: ``rio cogeo validate`` and the validators'
    layout checks, LAYOUT=COG, full-resolution pixels, overviews, nodata, tags and band
    descriptions as written; a BigTIFF (``BIGTIFF=YES`` forced here: GDAL makes one when
    the file could pass 4 GB); the streamed ``.part`` in memory, or (``ram`` False: as
    for outputs too large for that) in a scratch file beside the target."""
    from swathflow.rectification import writing
    from swathflow.rectification.rawimage import BandInfo
    if big:
        monkeypatch.setattr(writing, "BIGTIFF", "YES")
    if not ram:
        monkeypatch.setattr(writing, "PART_RAM_BYTES", 0)
    data = _cube(nb, dtype)
    data[:, :100, :300] = nodata
    grid = Grid("EPSG:32633", from_origin(500000, 6000000, 0.5, 0.5), (H, W))
    path = tmp_path / "out.tif"
    arr = data[0] if nb == 1 else data
    infos = [BandInfo(i + 1, f"band {i}", 500.0 + i, 10.0, "nm") for i in range(nb)]
    write_cogs([{"path": path, "array": arr, "grid": grid, "nodata": nodata,
                 "tags": {"product": "layout"}, "bands": infos}], blocksize=256)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.tif"]
    assert _cog_layout_problems(path) == []
    assert cog_problems(path) == []
    assert open(path, "rb").read(4) == (b"II+\0" if big else b"II*\0")
    with rasterio.open(path) as src:
        assert src.count == nb and src.dtypes[0] == np.dtype(dtype).name
        assert src.crs.to_epsg() == 32633 and src.transform == grid.transform
        assert src.tags()["product"] == "layout" and src.overviews(1) == [2, 4, 8]
        assert src.descriptions == tuple(f"band {i}" for i in range(nb))
        assert src.tags(nb)["wavelength"] == repr(500.0 + nb - 1)
        assert src.tags(1, ns="IMAGERY")["CENTRAL_WAVELENGTH_UM"] == repr(0.5)
        assert (math.isnan(src.nodata) if math.isnan(nodata) else src.nodata == nodata)
        assert src.compression.name.lower() == "deflate"
        assert np.array_equal(src.read(), data, equal_nan=True)
        ov = src.read(out_shape=(nb, -(-H // 8), -(-W // 8)))
    mean, _, _, whole = _levels(data, nodata, [(-(-H // f), -(-W // f)) for f in (2, 4, 8)])[-1]
    got = ov.astype(float)
    if not math.isnan(nodata):
        got[ov == nodata] = np.nan
    assert np.array_equal(np.isnan(got), np.isnan(mean))
    tol = 1.5 + 1e-9 if np.dtype(dtype).kind in "ui" else 1e-3
    assert np.abs(got - mean)[whole].max() <= tol


@pytest.mark.parametrize("compress", ["zstd", "deflate"])
def test_cog_codecs(tmp_path, compress):
    """``compress`` (``--compress``): DEFLATE (the default) or ZSTD, each with the
    predictor, in the same COG layout, pixels unchanged."""
    data = _cube(1, np.uint16)[0]
    grid = Grid("EPSG:32633", from_origin(500000, 6000000, 0.5, 0.5), (H, W))
    path = tmp_path / "z.tif"
    write_cogs([{"path": path, "array": data, "grid": grid, "nodata": 0}], blocksize=256,
               compress=compress)
    assert _cog_layout_problems(path) == []
    with rasterio.open(path) as src:
        assert src.compression.name.lower() == compress
        assert src.tags(ns="IMAGE_STRUCTURE")["PREDICTOR"] == "2"
        assert np.array_equal(src.read(1), data)


@pytest.mark.parametrize("scheduler", [None, "sync"])
def test_any_chunking_of_a_dask_array(tmp_path, scheduler):
    """Blocks split across bands, or of odd sizes (the first overview level then comes
    from the streamed file), a raster smaller than one tile: same pixels, valid COGs (on
    the threads, and block by block in this process on the synchronous scheduler)."""
    import dask.array as da
    for shape, chunks in [((3, 600, 600), (1, 300, 300)), ((513, 1100), 255),
                          ((100, 90), 512)]:
        data = (np.arange(np.prod(shape)) % 1000).reshape(shape).astype(np.uint16)
        grid = Grid("EPSG:32633", from_origin(500000, 6000000, 1, 1), shape[-2:])
        path = tmp_path / f"c{len(shape)}_{shape[-1]}.tif"
        write_cogs([{"path": path, "array": da.from_array(data, chunks=chunks), "grid": grid,
                     "nodata": 0}], blocksize=256, scheduler=scheduler)
        assert _cog_layout_problems(path) == []
        with rasterio.open(path) as src:
            assert np.array_equal(src.read() if len(shape) == 3 else src.read(1), data)


def test_synchronous_blocks_run_each_task_once(tmp_path):
    """On the synchronous scheduler the writer runs the graph itself (store.py): a slice
    of a larger array whose blocks share a task, rechunked, gives the pixels of the same
    expression in numpy, each needed block computed once and no block outside the slice."""
    import dask.array as da
    calls = []

    def f(x, block_id=None):
        calls.append(block_id)
        return x * 3 + 1

    data = (np.arange(900 * 700) % 5000).reshape(900, 700).astype(np.uint16)
    base = da.from_array(data, chunks=300).map_blocks(f, dtype=np.uint16)
    arr = (base[:600] + base[:600, ::-1]).rechunk(256)       # blocks read two tasks each
    grid = Grid("EPSG:32633", from_origin(500000, 6000000, 1, 1), arr.shape)
    calls.clear()                            # dask's own probes while building the graph
    write_cogs([{"path": tmp_path / "s.tif", "array": arr, "grid": grid, "nodata": 0}],
               blocksize=256, scheduler="sync")
    truth = (data[:600] * 3 + 1) + (data[:600, ::-1] * 3 + 1)
    with rasterio.open(tmp_path / "s.tif") as src:
        assert np.array_equal(src.read(1), truth.astype(np.uint16))
    assert sorted(calls) == [(i, j) for i in range(2) for j in range(3)]


def test_configured_synchronous_scheduler_runs_the_blocks_here(tmp_path):
    """No scheduler given and dask configured with ``scheduler="sync"`` (the flow's Dask
    workers, where ``distributed`` is imported): every block is computed in this thread,
    as dask itself picks the configured scheduler before any Client."""
    import threading

    import dask
    import dask.array as da
    import distributed  # noqa: F401
    threads = set()

    def f(x):
        threads.add(threading.get_ident())
        return x

    data = (np.arange(600 * 500) % 3000).reshape(600, 500).astype(np.uint16)
    grid = Grid("EPSG:32633", from_origin(500000, 6000000, 1, 1), data.shape)
    with dask.config.set(scheduler="sync"):
        write_cogs([{"path": tmp_path / "c.tif",
                     "array": da.from_array(data, chunks=256).map_blocks(f, dtype=data.dtype),
                     "grid": grid, "nodata": 0}], blocksize=256)
    assert threads == {threading.get_ident()}
    assert _cog_layout_problems(tmp_path / "c.tif") == []
    with rasterio.open(tmp_path / "c.tif") as src:
        assert np.array_equal(src.read(1), data)


def _all_nodata(block, nodata) -> bool:
    return bool(np.isnan(block).all() if math.isnan(nodata) else (block == nodata).all())


@pytest.mark.parametrize("dtype,nodata", [(np.uint16, 0), (np.float32, float("nan")),
                                          (np.int16, -32768)])
def test_tiles_of_nodata_are_written(tmp_path, dtype, nodata):
    """Tiles holding only nodata are in the COG at every level (no sparse tile, which some
    readers take for zeros), read back as nodata; the predictor is the type's (2 for
    integers, 3 for floats) and the codec the one asked for (DEFLATE, or ZSTD), the
    same pixels either way."""
    data = _cube(2, dtype)
    data[:, :, :700] = nodata                   # whole tiles of nodata, at every level
    data[:, :, 1200:] = nodata                  # and at the right edge (narrower tiles)
    grid = Grid("EPSG:32633", from_origin(500000, 6000000, 0.5, 0.5), (H, W))
    for compress in ("deflate", "zstd"):
        path = tmp_path / f"sparse-{compress}.tif"
        write_cogs([{"path": path, "array": data, "grid": grid, "nodata": nodata}],
                   blocksize=256, compress=compress)
        assert _cog_layout_problems(path) == [] and cog_problems(path) == []
        blank = [_all_nodata(data[b, r * 256:(r + 1) * 256, c * 256:(c + 1) * 256], nodata)
                 for b in range(2) for r in range(-(-H // 256)) for c in range(-(-W // 256))]
        assert 0 < sum(blank) < len(blank)
        with rasterio.open(path) as src:
            assert src.compression.name.lower() == compress
            pred = "3" if np.dtype(dtype).kind == "f" else "2"
            assert src.tags(ns="IMAGE_STRUCTURE")["PREDICTOR"] == pred
            assert np.array_equal(src.read(), data, equal_nan=True)
            for k, f in enumerate(src.overviews(1)):
                with rasterio.open(path, overview_level=k) as ov:
                    for y in range(-(-ov.height // 256)):
                        for x in range(-(-ov.width // 256)):
                            size = ov.get_tag_item(f"BLOCK_SIZE_{x}_{y}", "TIFF", bidx=1)
                            assert int(size) > 0, (k, x, y)
                    left = ov.read()[:, :, :700 // f].astype(float)      # nodata only
                    assert (np.isnan(left) if math.isnan(nodata) else left == nodata).all()


def test_tags_as_json_with_version_date_and_software(tmp_path):
    """Tags that are not strings are written as JSON (a mapping, a list, a number, a
    bool); ``software`` names swathflow's version; TIFF's own DateTime and Software tags
    are set (GDAL reads them back as TIFFTAG_DATETIME and TIFFTAG_SOFTWARE); a
    single-band output has a band description."""
    import datetime
    import json

    import swathflow
    data = _cube(1, np.uint16)[0]
    grid = Grid("EPSG:32633", from_origin(500000, 6000000, 0.5, 0.5), (H, W))
    path = tmp_path / "t.tif"
    before = datetime.datetime.now(datetime.timezone.utc).replace(microsecond=0)
    write_cogs([{"path": path, "array": data, "grid": grid, "nodata": 0,
                 "tags": {"terrain": {"kind": "constant", "h": 5.0}, "ids": ["L1", "L2"],
                          "tolerance_px": 0.05, "flag": True, "name": "plain text"}}],
               blocksize=256)
    after = datetime.datetime.now(datetime.timezone.utc)
    with rasterio.open(path) as src:
        tags = src.tags()
        assert src.descriptions == ("band 1",)
    assert json.loads(tags["terrain"]) == {"kind": "constant", "h": 5.0}
    assert json.loads(tags["ids"]) == ["L1", "L2"]
    assert json.loads(tags["tolerance_px"]) == 0.05 and json.loads(tags["flag"]) is True
    assert tags["name"] == "plain text"
    assert tags["software"] == tags["TIFFTAG_SOFTWARE"] == f"swathflow {swathflow.__version__}"
    when = datetime.datetime.strptime(tags["TIFFTAG_DATETIME"], "%Y:%m:%d %H:%M:%S")
    assert before <= when.replace(tzinfo=datetime.timezone.utc) <= after
    raw = path.read_bytes()
    assert f"swathflow {swathflow.__version__}".encode() in raw   # TIFF tag 305, not XML only


@pytest.mark.parametrize("ram", [True, False])
def test_a_failed_write_leaves_nothing_and_keeps_the_old_file(tmp_path, monkeypatch, ram):
    """A block that fails while the COG is written: no file is left in the folder (no
    ``.part``, no scratch file) and an existing output keeps its content."""
    import dask.array as da
    from swathflow.rectification import writing
    if not ram:
        monkeypatch.setattr(writing, "PART_RAM_BYTES", 0)
    data = _cube(1, np.uint16)[0]
    grid = Grid("EPSG:32633", from_origin(500000, 6000000, 0.5, 0.5), (H, W))
    path = tmp_path / "keep.tif"
    path.write_bytes(b"old")

    def f(x, block_info=None):
        if block_info[None]["chunk-location"] == (2, 3):
            raise RuntimeError("disk on fire")
        return x

    arr = da.from_array(data, chunks=256).map_blocks(f, dtype=data.dtype)
    with pytest.raises(RuntimeError, match="disk on fire"):
        write_cogs([{"path": path, "array": arr, "grid": grid, "nodata": 0}], blocksize=256,
                   scheduler="sync")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["keep.tif"]
    assert path.read_bytes() == b"old"


@pytest.mark.parametrize("case", ["uint16", "nan", "bands", "mask", "no-nodata"])
def test_valid_mask_kept_while_writing_is_the_files_dataset_mask(tmp_path, case):
    """The valid mask the writer fills as the tiles go by (``valid``) is what rasterio's
    ``dataset_mask`` reads back from the COG: nodata in every band (not in one), NaN, the
    internal mask band, or no nodata at all; and the footprint traced from it is the one
    traced from the file."""
    from swathflow.formats.stac import raster_facts
    h, w = 300, 420
    nodata, mask = {"uint16": (0, False), "nan": (float("nan"), False),
                    "bands": (-32768, False), "mask": (None, True),
                    "no-nodata": (None, False)}[case]
    dtype = {"nan": np.float32, "bands": np.int16}.get(case, np.uint16)
    r, c = np.ogrid[0:h, 0:w]
    hole = (r - 150) ** 2 + (c - 200) ** 2 < 60 ** 2            # a hole in the middle
    edge = r > 2 * c                                             # and a cut corner
    if case == "bands":
        data = np.stack([(1000 + r + c).astype(dtype)] * 3)
        data[:, hole | edge] = nodata
        data[1, :50, :] = nodata                 # one band's nodata alone stays valid
    elif case == "mask":
        vals = (1000 + r + c).astype(dtype)
        plane = np.where(hole | edge, 0, 255).astype(dtype)
        data = np.stack([vals, plane])
    else:
        data = (1000 + r + c).astype(dtype)
        if nodata is not None:
            data[hole | edge] = nodata
    grid = Grid("EPSG:32633", from_origin(500000, 6000000, 2.0, 2.0), (h, w))
    valid = np.empty((h, w), np.uint8)
    path = tmp_path / "v.tif"
    write_cogs([{"path": path, "array": data, "grid": grid, "nodata": nodata, "mask": mask,
                 "valid": valid}], blocksize=128)
    assert cog_problems(path) == []
    with rasterio.open(path) as src:
        assert np.array_equal(valid, src.dataset_mask())
    expect = {"uint16": hole | edge, "nan": hole | edge, "bands": hole | edge,
              "mask": hole | edge, "no-nodata": np.zeros((h, w), bool)}[case]
    assert np.array_equal(valid == 0, expect)
    assert raster_facts(path, valid) == raster_facts(path)
