"""The rectifier's lattice of raw coordinates over a real DEM's relief, against the exact
sensor model at every output pixel.

The terrain is the real jacksboro DEM (shared/data/real/dem, ~90 m cells, 236-1076 m)
laid under the swing's footprint at 4 m cells with its heights scaled by 4/90, so its
slopes (and the kinks of its bilinear heights at every cell edge) are the real ones. The
lattice (with the raw image's shape, as the rectifier runs it) must give every pixel that
the exact model puts on the raw image within the 0.05 px bound, and must call nodata
exactly the pixels the exact model puts off the image (up to the bound at the edges).
"""
from __future__ import annotations

import warnings

import numpy as np
import pytest

from spec_vectors import DATA
from test_rectify import scene_model
from swathflow.formats.raster import write_geotiff
from swathflow.geometry.grid import Grid, footprint_grid
from swathflow.geometry.terrain import DEM, ConstantHeight
from swathflow.rectification import lattice as L
from swathflow.rectification import tiles as T
from swathflow.rectification.rawimage import open_raw_image

TOL = 0.05
GSD = 1.0


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    import rasterio
    path = DATA / "dem" / "jacksboro_fault_dem.tif"
    if not path.exists():
        pytest.skip("real DEM not available")
    with rasterio.open(path) as src:
        z = src.read(1, masked=True).astype(float).filled(np.nan)
    model = scene_model(n_lines=500, n_elements=160)
    flat = footprint_grid(model, ConstantHeight(300.0), GSD)
    xmin, ymin, xmax, ymax = flat.bounds
    cell = 4.0
    g = Grid.from_bounds(flat.crs, (xmin - 150, ymin - 150, xmax + 150, ymax + 150), cell)
    assert g.shape[0] <= z.shape[0] and g.shape[1] <= z.shape[1]
    h = 300.0 + (z[:g.shape[0], :g.shape[1]] - np.nanmin(z)) * cell / 90.0
    assert np.isfinite(h).all() and np.ptp(h) > 15            # real relief, scaled
    dem_path = tmp_path_factory.mktemp("dem") / "jacksboro_scaled.tif"
    write_geotiff(dem_path, h.astype(np.float32), g.crs, g.transform)
    dem = DEM.open(dem_path)
    grid = footprint_grid(model, dem, GSD)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        exact = L.exact_raw(model, grid, dem, *np.indices(grid.shape))
    return dict(model=model, dem=dem, grid=grid, exact=exact)


def test_lattice_over_real_relief_within_bound_of_exact_model(scene):
    model, dem, grid, exact = scene["model"], scene["dem"], scene["grid"], scene["exact"]
    nl, ne = model.shape
    src = open_raw_image(np.zeros((nl, ne), np.float32))
    tile = 128
    got = np.full(grid.shape + (2,), np.nan)
    st: dict = {}
    for r in range(0, grid.height, tile):
        for c in range(0, grid.width, tile):
            rs, cs = slice(r, min(r + tile, grid.height)), slice(c, min(c + tile, grid.width))
            co, win = T.tile_coords(model, src, grid.window(rs, cs), dem, tol=TOL, stats=st)
            if win is not None:
                got[rs, cs, 0] = co[0] + win[0]
                got[rs, cs, 1] = co[1] + win[2]
    li, ei = exact[..., 0], exact[..., 1]
    with np.errstate(invalid="ignore"):
        on = (li >= -0.5) & (li <= nl - 0.5) & (ei >= -0.5) & (ei <= ne - 0.5)
        edge = np.minimum.reduce([np.abs(li + 0.5), np.abs(li - nl + 0.5),
                                  np.abs(ei + 0.5), np.abs(ei - ne + 0.5)]) < TOL
    valid = np.isfinite(got[..., 0])
    assert on.sum() > 50_000 and (~on).sum() > 10_000          # both kinds of pixel
    assert not (valid != on)[~edge].any()                        # nodata where off the image
    both = valid & on
    err = np.abs(got[both] - exact[both]).max()
    print("max raw-coordinate error on the image:", err, "evaluations per pixel:",
          st["exact_evaluations"] / st["pixels"])
    assert err < TOL


def test_off_image_cells_are_not_refined(scene):
    """The pruning is real (fewer exact calls) and keeps the bound (previous test)."""
    model, dem, grid = scene["model"], scene["dem"], scene["grid"]
    sub = grid.window(slice(0, min(256, grid.height)), slice(0, min(256, grid.width)))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        full = L.leaves(model, sub, dem, TOL)
        pruned = L.leaves(model, sub, dem, TOL, raw_shape=model.shape)
    assert pruned.exact_evaluations < full.exact_evaluations
