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


def _paint_absolute(lv, nl, ne):
    from swathflow.rectification.paint import paint_leaves
    co = paint_leaves(lv, 0, 0, nl, ne)
    return np.stack([co[0], co[1]], axis=-1).astype(np.float64)


def test_tile_evaluated_at_every_pixel_is_the_exact_model(scene):
    """dense=True: every pixel on the image is the exact model's value, nodata exactly
    where the exact model puts the pixel off the image; cells clearly off the image
    are skipped (fewer evaluations than pixels)."""
    model, dem, grid, exact = scene["model"], scene["dem"], scene["grid"], scene["exact"]
    nl, ne = model.shape
    sub = grid.window(slice(0, min(384, grid.height)), slice(0, min(384, grid.width)))
    ex = exact[:sub.height, :sub.width]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        lv = L.leaves(model, sub, dem, TOL, raw_shape=model.shape, dense=True)
    assert lv.pixels is not None and lv.cells.size == 0
    got = _paint_absolute(lv, nl, ne)
    li, ei = ex[..., 0], ex[..., 1]
    with np.errstate(invalid="ignore"):
        on = (li >= -0.5) & (li <= nl - 0.5) & (ei >= -0.5) & (ei <= ne - 0.5)
    assert on.sum() > 10_000 and (~on).sum() > 1_000
    valid = np.isfinite(got[..., 0])
    assert (valid == on).all()
    # 1e-8 px: the ground points come from the tile's frame, within 1e-8 m of pyproj's
    # (test_lattice_frame; 1 m pixels here), float64 noise on ECEF coordinates of 6e6 m
    # (their spacing is 1e-9 m); the lattice's interpolation (dense=False) misses here by
    # 0.0044 px in the median, 0.031 at most: the bound still tells exact from interpolated
    assert np.abs(lv.pixels[on] - ex[on]).max() < 1e-8
    assert np.abs(got[on] - ex[on]).max() < 1e-4           # painted as float32
    assert lv.exact_evaluations < sub.height * sub.width


class _Wiggle:
    """The scene's model with a zig-zag of 0.3 raw px added to the line, 1.3 output
    pixels from kink to kink (a POS far denser than the output pixels): the exact
    mapping the lattice would have to refine down to single pixels everywhere."""

    def __init__(self, model, grid):
        self.model, self.grid = model, grid
        self.shape = model.shape

    def ground_to_image(self, g, clip=True):
        from swathflow.geometry.grid import ecef_to_map
        out = self.model.ground_to_image(g, clip=clip)
        x, _, _ = ecef_to_map(np.asarray(g).reshape(-1, 3), self.grid.crs)
        t = (x.reshape(out.shape[:-1]) / (1.3 * GSD)) % 2.0
        return out + np.stack([0.3 * np.abs(t - 1.0), np.zeros_like(t)], axis=-1)


def test_lattice_chooses_every_pixel_where_the_mapping_kinks_at_every_pixel(scene):
    """Per tile, the cheaper way: the smooth scene keeps the adaptive lattice; the
    wiggling one is evaluated at every pixel, and both stay within the bound of their
    exact model."""
    model, dem, grid = scene["model"], scene["dem"], scene["grid"]
    nl, ne = model.shape
    sub = grid.window(slice(0, min(256, grid.height)), slice(0, min(256, grid.width)))
    rr, cc = np.indices(sub.shape)
    for m, dense in ((model, False), (_Wiggle(model, sub), True)):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            lv = L.leaves(m, sub, dem, TOL, raw_shape=model.shape)
            ex = L.exact_raw(m, sub, dem, rr, cc)
        assert (lv.pixels is not None) == dense
        got = _paint_absolute(lv, nl, ne)
        ok = np.isfinite(got[..., 0]) & np.isfinite(ex[..., 0])
        assert ok.sum() > 5_000
        assert np.abs(got[ok] - ex[ok]).max() < TOL


@pytest.mark.parametrize("shape", [(200, 300), (97, 256), (256, 131)])
def test_partial_tile_evaluated_at_every_pixel(scene, shape):
    """A tile smaller than the lattice's power-of-two cell (the grid's last row or column
    of tiles), chosen for every-pixel evaluation: every pixel on the image is the exact
    model's value, nodata exactly where the exact model puts it off the image."""
    model, dem, grid = scene["model"], scene["dem"], scene["grid"]
    nl, ne = model.shape
    sub = grid.window(slice(0, shape[0]), slice(0, shape[1]))
    rr, cc = np.indices(sub.shape)
    wiggle = _Wiggle(model, sub)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        lv = L.leaves(wiggle, sub, dem, TOL, raw_shape=model.shape)
        ex = L.exact_raw(wiggle, sub, dem, rr, cc)
    assert lv.pixels is not None and lv.pixels.shape == sub.shape + (2,)
    li, ei = ex[..., 0], ex[..., 1]
    with np.errstate(invalid="ignore"):
        on = (li >= -0.5) & (li <= nl - 0.5) & (ei >= -0.5) & (ei <= ne - 0.5)
    assert on.sum() > 1_000
    got = _paint_absolute(lv, nl, ne)
    assert (np.isfinite(got[..., 0]) == on).all()
    assert np.abs(lv.pixels[on] - ex[on]).max() < 1e-8          # the frame's ground points


def _random_cells(rng, H, W, k):
    sr, sc = 2 ** rng.integers(0, 5, k), 2 ** rng.integers(0, 5, k)
    return np.stack([rng.integers(0, H, k), rng.integers(0, W, k), sr, sc],
                    axis=-1).astype(np.int64)


def test_touching_cells_by_closed_rectangles():
    """paint.touching against the definition: a cell touches when its closed rectangle and
    a marked one's share a pixel of the tile (pixel sets painted with numpy)."""
    from swathflow.rectification.paint import touching
    rng = np.random.default_rng(5)
    for H, W in ((33, 33), (65, 129), (20, 17)):
        for _ in range(40):
            a = _random_cells(rng, H, W, int(rng.integers(1, 30)))
            b = _random_cells(rng, H, W, int(rng.integers(0, 12)))
            mask = np.zeros((H, W), bool)
            for r, c, sr, sc in b:
                mask[r:r + sr + 1, c:c + sc + 1] = True
            want = [mask[r:r + sr + 1, c:c + sc + 1].any() for r, c, sr, sc in a]
            assert touching(a, b, H, W).tolist() == want


def test_dense_choice_passes_contiguous_cells_to_the_kernels(scene, monkeypatch):
    """Strided cells would be another numba type: compiled code each forked worker loads
    again."""
    model, dem, grid = scene["model"], scene["dem"], scene["grid"]
    sub = grid.window(slice(0, min(256, grid.height)), slice(0, min(256, grid.width)))
    seen = []

    def spy(kernel):
        def call(*args):
            seen.extend(a.flags.c_contiguous for a in args if isinstance(a, np.ndarray))
            return kernel(*args)
        return call

    monkeypatch.setattr(L, "_cell_unknown", spy(L._cell_unknown))
    monkeypatch.setattr(L, "_cell_tests", spy(L._cell_tests))
    chose = []
    dense_cheaper = L._dense_cheaper
    monkeypatch.setattr(L, "_dense_cheaper", lambda *a: chose.append(1) or dense_cheaper(*a))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        L.leaves(model, sub, dem, TOL, raw_shape=model.shape)
    assert chose and seen and all(seen)
