"""The COG writer (swathflow.rectification.writing): overviews built here, block by block,
against the closed form (2 x 2 means of the valid pixels, each level from the full
resolution), a valid COG layout, full-resolution pixels and metadata kept."""
from __future__ import annotations

import math
import warnings

import numpy as np
import pytest
import rasterio
from rasterio.transform import from_origin
from swathflow.geometry.grid import Grid
from swathflow.rectification.writing import overview_factors, write_cogs

H, W = 1100, 1301           # odd width: the last overview column averages one column


def _blocks(data, f, nodata):
    """Per f x f block of the (ceil-sized) overview: mean, min and max of the valid pixels
    (NaN where none), and whether the block is whole (inside the image, every pixel valid)."""
    nb, h, w = data.shape
    oh, ow = -(-h // f), -(-w // f)
    x = data.astype(float)
    if not math.isnan(nodata):
        x = np.where(data == nodata, np.nan, x)
    pad = np.full((nb, oh * f, ow * f), np.nan)
    pad[:, :h, :w] = x
    b = pad.reshape(nb, oh, f, ow, f)
    with np.errstate(invalid="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        mean, lo, hi = np.nanmean(b, (2, 4)), np.nanmin(b, (2, 4)), np.nanmax(b, (2, 4))
    whole = np.isfinite(b).all((2, 4))
    return mean, lo, hi, whole


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
    for lv, f in enumerate([2, 4, 8]):
        with rasterio.open(path, overview_level=lv) as ov:
            got = ov.read().astype(float)
        if not is_int:
            got[np.isnan(got)] = np.nan
        else:
            got[got == nodata] = np.nan
        mean, lo, hi, whole = _blocks(data, f, nodata)
        assert got.shape == mean.shape
        # nodata exactly where a block has no valid pixel
        assert np.array_equal(np.isnan(got), np.isnan(mean))
        ok = ~np.isnan(mean)
        # within the range of the block's valid pixels (plus integer rounding)
        assert (got[ok] >= np.floor(lo[ok]) - 1e-6).all() and (got[ok] <= np.ceil(hi[ok]) + 1e-6).all()
        # a whole block: each level is the mean of the one above, so the block mean
        # (integer output: rounded half up once per level)
        tol = 0.5 * (lv + 1) + 1e-9 if is_int else 1e-3
        assert np.abs(got - mean)[whole].max() <= tol, (f, np.abs(got - mean)[whole].max())
