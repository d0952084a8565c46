"""The lattice's ground points without a projection call a point (grid.TileFrame: the
ellipsoid point and normal as polynomials over the tile, pyproj at Chebyshev nodes),
against pyproj at every point (Grid.to_ecef), on tiles from 5 cm to 40 m pixels, over a
constant height and over a DEM (NaN exactly where the DEM has no height)."""
import warnings

import numpy as np
import pytest
from affine import Affine

from swathflow.formats.raster import write_geotiff
from swathflow.geometry.grid import Grid, tile_frame
from swathflow.geometry.terrain import DEM, ConstantHeight

CRS = "EPSG:32651"
X0, Y0 = 259_700.0, 3_602_800.0


@pytest.fixture(scope="module")
def dem(tmp_path_factory):
    rng = np.random.default_rng(2)
    h = 30.0 + np.cumsum(np.cumsum(rng.normal(0, 0.5, (300, 300)), 0), 1) / 50
    h[100:120, 100:120] = np.nan                            # a hole: no height there
    path = tmp_path_factory.mktemp("frame") / "dem.tif"
    write_geotiff(path, h.astype(np.float32), CRS, Affine(80.0, 0, X0 - 200, 0, -80.0, Y0 + 200))
    return DEM.open(path)


@pytest.mark.parametrize("res", [0.05, 0.3, 2.0, 40.0])
@pytest.mark.parametrize("which", ["constant", "dem"])
def test_frame_agrees_with_pyproj(res, which, dem):
    terrain = ConstantHeight(123.0) if which == "constant" else dem
    grid = Grid(CRS, Affine(res, 0, X0, 0, -res, Y0), (512, 512))
    H = W = 545                                   # the lattice's window reaches past the tile
    frame = tile_frame(grid, terrain, H, W)
    assert frame is not None
    rng = np.random.default_rng(7)
    r, c = rng.integers(0, H, 30000), rng.integers(0, W, 30000)
    r[:4], c[:4] = [0, 0, H - 1, H - 1], [0, W - 1, 0, W - 1]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ref = grid.to_ecef(*grid.xy(r, c), terrain)
    got = frame.ecef(r, c)
    assert np.array_equal(np.isnan(got), np.isnan(ref))
    if which == "dem" and res == 40.0:
        assert np.isnan(ref).any()                # the hole is inside the 20 km tile
    ok = np.isfinite(ref).all(axis=1)
    assert ok.mean() > 0.5
    assert np.abs(got[ok] - ref[ok]).max() < 1e-8    # metres


def test_no_frame_where_heights_need_longitude_and_latitude(dem):
    grid = Grid("EPSG:3857", Affine(1.0, 0, 0, 0, -1.0, 0), (64, 64))   # another CRS than the DEM's
    assert tile_frame(grid, dem, 65, 65) is None
    assert tile_frame(Grid(CRS, Affine(1.0, 0, X0, 0, -1.0, Y0), (64, 64)),
                      ConstantHeight(0.0), 65, 65) is not None
