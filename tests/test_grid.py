"""Output grids (swathflow.geometry.grid): coordinates against rasterio's conventions, snapping,
tiling, auto-UTM and footprints against independent projections."""
from __future__ import annotations

import numpy as np
import pytest
import rasterio.transform
from affine import Affine

from swathflow.errors import FormatError
from swathflow.geometry.geodesy import ecef_to_geodetic, transformer
from swathflow.geometry.grid import Grid, ecef_to_map, footprint_grid, resolve_crs, union_grid
from swathflow.geometry.terrain import ConstantHeight


def _grid():
    return Grid("EPSG:32651", Affine(0.5, 0, 260000.0, 0, -0.5, 3601000.0), (300, 420))


def test_xy_and_rowcol_follow_rasterio():
    g = _grid()
    rows = np.array([0, 5, 299, 17])
    cols = np.array([0, 419, 3, 200])
    x, y = g.xy(rows, cols)
    xr_, yr_ = rasterio.transform.xy(g.transform, rows, cols, offset="center")
    assert np.allclose(x, xr_) and np.allclose(y, yr_)
    xu, yu = g.xy(rows, cols, offset="ul")
    assert np.allclose(xu, np.array(rasterio.transform.xy(g.transform, rows, cols,
                                                          offset="ul"))[0])
    r, c = g.rowcol(x + 0.2, y - 0.2)
    rr, cc = rasterio.transform.rowcol(g.transform, x + 0.2, y - 0.2)
    assert np.array_equal(r, rr) and np.array_equal(c, cc)
    # continuous inverse: pixel centres at integers
    rf, cf = g.rowcol(*g.xy(rows + 0.25, cols - 0.3), op=None)
    assert np.allclose(rf, rows + 0.25) and np.allclose(cf, cols - 0.3)


def test_from_bounds_snaps_and_covers():
    g = Grid.from_bounds("EPSG:32651", (100.3, 200.7, 160.1, 251.2), 2.0)
    assert g.bounds == (100.0, 200.0, 162.0, 252.0)
    assert g.shape == (26, 31)
    assert g.res == (2.0, 2.0)
    with pytest.raises(FormatError):
        Grid.from_bounds("EPSG:32651", (0, 0, 1, 1), 0.0)
    with pytest.raises(ValueError):
        Grid("EPSG:32651", Affine(1, 0, 0, 0, 1, 0), (2, 2))     # not north-up


def test_tiles_cover_the_grid_exactly_once_and_windows_agree():
    g = _grid()
    hits = np.zeros(g.shape, int)
    for rs, cs in g.tiles(128):
        hits[rs, cs] += 1
        sub = g.window(rs, cs)
        x, y = sub.centres()
        x0, y0 = g.centres(rs, cs)
        assert np.allclose(x, x0) and np.allclose(y, y0)
    assert (hits == 1).all()
    assert tuple(map(sum, g.chunks(128))) == g.shape
    assert union_grid([g.window(slice(0, 10), slice(0, 10)),
                       g.window(slice(200, 300), slice(400, 420))]).bounds == g.bounds


def test_resolve_crs_auto_utm():
    assert resolve_crs("auto-utm", 32.52, 120.45) == "EPSG:32651"
    assert resolve_crs("auto-utm", -33.9, 18.4) == "EPSG:32734"
    assert resolve_crs("EPSG:32633", 0, 0) == "EPSG:32633"
    with pytest.raises(FormatError):
        resolve_crs("EPSG:4326", 0, 0)
    with pytest.raises(FormatError):
        resolve_crs("not a crs", 0, 0)


def test_to_ecef_puts_points_on_the_terrain():
    g = _grid()
    x, y = g.centres(slice(0, 3), slice(0, 4))
    ecef = g.to_ecef(x, y, ConstantHeight(37.5))
    llh = ecef_to_geodetic(ecef)
    assert np.allclose(llh[..., 2], 37.5, atol=1e-6)
    xb, yb, h = ecef_to_map(ecef, g.crs)
    assert np.allclose(xb, x, atol=1e-6) and np.allclose(yb, y, atol=1e-6)


def test_footprint_grid_covers_the_image_corners():
    from test_rectify import scene_model
    model = scene_model(n_lines=200, n_elements=64)
    terrain = ConstantHeight(5.0)
    g = footprint_grid(model, terrain, 2.0)
    assert g.crs == "EPSG:32651" and g.res == (2.0, 2.0)
    nl, ne = model.shape
    corners = np.array([[-0.5, -0.5], [-0.5, ne - 0.5], [nl - 0.5, -0.5],
                        [nl - 0.5, ne - 0.5], [nl / 2, ne / 2]])
    ground = model.image_to_ground(corners, terrain)
    llh = ecef_to_geodetic(ground)
    x, y = transformer("EPSG:4326", g.crs).transform(llh[:, 1], llh[:, 0])
    xmin, ymin, xmax, ymax = g.bounds
    assert (x >= xmin).all() and (x <= xmax).all() and (y >= ymin).all() and (y <= ymax).all()
    # tight: no more than one pixel of slack beyond the extreme corners on every side
    assert x.min() - xmin < 2.0 + 1e-6 and xmax - x.max() < 2.0 + 1e-6
    assert y.min() - ymin < 2.0 + 1e-6 and ymax - y.max() < 2.0 + 1e-6


def test_footprint_grid_covers_every_pixel_on_hills(tmp_path):
    """A +-40 degree swing over a DEM with 300 m of relief: the grid traced from the
    image's border and a coarse interior lattice holds the ground point of every raw pixel
    (the truth: all of them projected), with at most one output pixel of slack beyond the
    extreme ones. (16 samples a side miss the western edge by 21 m.)"""
    from test_rectify import hills_dem, scene_model
    model = scene_model(n_lines=600, n_elements=192, swing=40.0)
    dem = hills_dem(tmp_path / "hills.tif", footprint_grid(model, ConstantHeight(5.0), 1.5),
                    relief=300.0)
    g = footprint_grid(model, dem, 1.5)
    nl, ne = model.shape
    li, ei = np.meshgrid(np.arange(-0.5, nl), np.arange(-0.5, ne), indexing="ij")
    ground = model.image_to_ground(np.stack([li, ei], axis=-1).reshape(-1, 2), dem)
    assert np.isfinite(ground).all()
    x, y, _ = ecef_to_map(ground, g.crs)
    xmin, ymin, xmax, ymax = g.bounds
    assert x.min() >= xmin - 1e-6 and x.max() <= xmax + 1e-6
    assert y.min() >= ymin - 1e-6 and y.max() <= ymax + 1e-6
    assert x.min() - xmin < 1.5 + 1e-6 and xmax - x.max() < 1.5 + 1e-6
    assert y.min() - ymin < 1.5 + 1e-6 and ymax - y.max() < 1.5 + 1e-6


def test_to_ecef_on_a_dem_in_the_grid_crs_sits_on_the_dem(tmp_path):
    """A DEM in the grid's own CRS (heights read straight from map x, y): the points are
    on the DEM's plane (bilinear interpolation reproduces a plane exactly) and back at
    their map position through the independent lon/lat route of ecef_to_map."""
    from swathflow.formats.raster import write_geotiff
    from swathflow.geometry.terrain import DEM
    g = _grid()
    x0, y0, cell = 259900.0, 3601100.0, 5.0
    rows, cols = np.mgrid[0:80, 0:80]
    xc, yc = x0 + (cols + 0.5) * cell, y0 - (rows + 0.5) * cell

    def plane(x, y):
        return 40.0 + 0.02 * (x - 260000.0) - 0.03 * (y - 3601000.0)
    write_geotiff(tmp_path / "dem.tif", plane(xc, yc), "EPSG:32651",
                  (cell, 0, x0, 0, -cell, y0))
    dem = DEM.open(tmp_path / "dem.tif")
    x, y = g.centres(slice(0, 300, 7), slice(0, 420, 11))
    ecef = g.to_ecef(x, y, dem)
    llh = ecef_to_geodetic(ecef)
    assert np.allclose(llh[..., 2], plane(x, y), atol=1e-6)
    xb, yb, _ = ecef_to_map(ecef, g.crs)
    assert np.allclose(xb, x, atol=1e-6) and np.allclose(yb, y, atol=1e-6)
    # the same DEM seen from another CRS's grid goes through lon/lat: same points
    g2 = Grid("EPSG:3857", Affine(1, 0, 0, 0, -1, 0), (1, 1))
    lon, lat = transformer(g.crs, "EPSG:4326").transform(x, y)
    x2, y2 = transformer("EPSG:4326", g2.crs).transform(lon, lat)
    assert np.allclose(g2.to_ecef(x2, y2, dem), ecef, atol=1e-4)
