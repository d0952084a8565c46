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


def test_heights_from_map_says_when_map_heights_gives_heights(dem):
    from swathflow.geometry.grid import _heights_from_map, _map_heights
    x, y = np.array([X0 + 10.0]), np.array([Y0 - 10.0])
    for crs in (CRS, "EPSG:3857", "EPSG:4326", "EPSG:32632"):
        for terrain in (ConstantHeight(5.0), dem):
            assert _heights_from_map(crs, terrain) == (
                _map_heights(crs, terrain, x, y) is not None), (crs, terrain)
    assert _heights_from_map(CRS, dem) and not _heights_from_map("EPSG:3857", dem)


def test_frame_nodes_are_pyprojs_values_at_the_chebyshev_nodes(dem):
    """The nodes the frame interpolates are pyproj's own values (the frame is made at every
    tile: its inputs are built without broadcast views, to the same numbers)."""
    from swathflow.geometry.grid import _nodes_basis, _to_ecef
    grid = Grid(CRS, Affine(0.05, 0, X0, 0, -0.05, Y0), (512, 512))
    frame = tile_frame(grid, dem, 513, 545)
    rn, cn = _nodes_basis(513)[0], _nodes_basis(545)[0]
    x, y = grid.xy(rn[:, None, None], cn[None, :, None])
    x, y, h = np.broadcast_arrays(x, y, np.array([0.0, 1000.0]))
    p = np.stack(_to_ecef(CRS).transform(x, y, h), axis=-1)
    p0, p1 = p[:, :, 0], p[:, :, 1]
    assert frame.origin.tobytes() == p0[2, 2].tobytes()
    ref = np.concatenate([p0 - p0[2, 2], (p1 - p0) / 1000.0], axis=-1)
    assert frame.nodes.tobytes() == np.ascontiguousarray(ref).tobytes()
