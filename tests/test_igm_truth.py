"""image_to_ground on a DEM (the compiled kernel of geometry/march.py with the DEM's frame of
geometry/demframe.py) against known truth: the frame against pyproj and Heikkinen, points
on the DEM's surface, round trips through ground_to_image, the spec vectors on a flat DEM,
rays aimed at known points, nodata holes, a DEM large enough to need several tiles, and
every sensor model through the same generic path."""
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest

from spec_vectors import load_cases, pos_dataset
from swathflow.formats.pos import Trajectory
from swathflow.formats.raster import write_geotiff
from swathflow.geometry.demframe import FRAME_TOL, dem_frame, frame_points
from swathflow.geometry.geodesy import (ecef_to_geodetic, geodetic_to_ecef, transformer,
                                        up_vector, utm_crs_for)
from swathflow.geometry.grid import Grid, footprint_grid
from swathflow.geometry.intersect import intersect
from swathflow.geometry.terrain import DEM, ConstantHeight
from swathflow.sensormodel import get_sensor

ROOT = Path(__file__).resolve().parents[1]


def _on_surface(dem, g):
    """Ray height minus DEM height (m) at ECEF points, through pyproj (the exact path)."""
    llh = ecef_to_geodetic(g)
    return llh[:, 2] - dem.height(llh[:, 0], llh[:, 1])


@pytest.fixture(scope="module")
def hills(tmp_path_factory):
    from test_rectify import hills_dem, scene_model
    model = scene_model(n_lines=600, n_elements=192)
    dem = hills_dem(tmp_path_factory.mktemp("igm") / "hills.tif",
                    footprint_grid(model, ConstantHeight(5.0), 1.5))
    return model, dem


def _image(model, n, seed=0):
    rng = np.random.default_rng(seed)
    nl, ne = model.shape
    return np.stack([rng.uniform(0, nl - 1, n), rng.uniform(0, ne - 1, n)], axis=-1)


def test_frame_matches_pyproj_and_heikkinen(hills):
    _, dem = hills
    frame = dem_frame(dem)
    assert frame is not None and frame.error_m < FRAME_TOL
    rng = np.random.default_rng(1)
    a, b, c, d, e, f = dem.transform
    nr, nc = dem.data.shape
    col, row = rng.uniform(0, nc - 1, 3000), rng.uniform(0, nr - 1, 3000)
    h = rng.uniform(dem.h_min, dem.h_max, 3000)
    x, y = c + a * (col + 0.5) + b * (row + 0.5), f + d * (col + 0.5) + e * (row + 0.5)
    lon, lat = transformer(dem.crs_wkt, "EPSG:4326").transform(x, y)
    got = frame_points(frame, geodetic_to_ecef(np.stack([lat, lon, h], axis=-1)))
    assert np.abs(got[:, 0] - col).max() * abs(a) < 1e-6          # metres
    assert np.abs(got[:, 1] - row).max() * abs(e) < 1e-6
    assert np.abs(got[:, 2] - h).max() < 1e-6


def test_hits_lie_on_the_dem_and_round_trip(hills):
    model, dem = hills
    img = _image(model, 20000)
    g = model.image_to_ground(img, dem)
    assert np.isfinite(g).all()
    assert np.abs(_on_surface(dem, g)).max() < 1e-3                 # metres
    back = model.ground_to_image(g)
    assert np.abs(back - img).max() < 1e-3                           # pixels
    # the numpy marching (intersect(compiled=False)) on the same rays: the same points
    o, d = model.ray(img[:2000])
    ref = intersect(o, d, dem, compiled=False)
    assert np.linalg.norm(g[:2000] - ref, axis=-1).max() < 1e-3


def _models():
    from test_rectify import scene_model
    from swathflow.sensors.pushbroom import PushbroomModel
    return {"pendulum": scene_model(n_lines=600, n_elements=192),
            "pushbroom": PushbroomModel.example_model("forward", n_lines=300),
            "rotating-mirror": _plugin_model()}


@pytest.mark.parametrize("which", ["pendulum", "pushbroom", "rotating-mirror"])
def test_compiled_rays_equal_the_numpy_rays(which):
    from swathflow.errors import OutOfRangeError
    model = _models()[which]
    nl, ne = model.shape
    img = _image(model, 5000, seed=2)
    img[:8, 0] = [-3.0, -0.5, 0.0, nl - 1.0, nl - 0.3, nl + 2.0, 0.25, 1.0]
    img[8:12, 1] = [-0.5, 0.0, ne - 1.0, ne - 0.5]
    c, d = model.ray(img)
    c0, d0 = model._ray_numpy(img)
    assert np.abs(c - c0).max() < 1e-6 and np.abs(d - d0).max() < 1e-10     # 1e-6 px
    assert model.ray(img[:5000].reshape(50, 100, 2))[1].shape == (50, 100, 3)
    # a line that is not a number: the numpy path reports it, as before
    with pytest.raises(OutOfRangeError):
        model.ray(np.array([[np.nan, 3.0]]))


def test_rays_aimed_at_known_points_on_the_hills(hills):
    _, dem = hills
    a, _, c, _, e, f = dem.transform
    nr, nc = dem.data.shape
    rng = np.random.default_rng(4)
    x = c + a * rng.uniform(20, nc - 20, 1000)
    y = f + e * rng.uniform(20, nr - 20, 1000)
    lon, lat = transformer(dem.crs_wkt, "EPSG:4326").transform(x, y)
    truth = geodetic_to_ecef(np.stack([lat, lon, dem.height(lat, lon)], axis=-1))
    up = up_vector(lat, lon)
    for tilt_deg in (0.0, 15.0, 35.0):
        side = rng.normal(size=up.shape)
        side -= np.sum(side * up, axis=-1, keepdims=True) * up
        side /= np.linalg.norm(side, axis=-1, keepdims=True)
        d = -(up + np.tan(np.radians(tilt_deg)) * side)
        d /= np.linalg.norm(d, axis=-1, keepdims=True)
        origin = truth - 3000.0 / np.sum(-d * up, axis=-1, keepdims=True) * d
        got = intersect(origin, d, dem)
        err = np.linalg.norm(got - truth, axis=-1)
        assert np.abs(_on_surface(dem, got)).max() < 1e-3
        if tilt_deg == 0:
            assert err.max() < 1e-3
        else:
            # a tilted ray may meet a ridge before its target: then the numpy marching
            # meets the same ridge
            assert (err < 1e-3).mean() > 0.9
            far = err >= 1e-3
            ref = intersect(origin[far], d[far], dem, compiled=False)
            assert np.linalg.norm(got[far] - ref, axis=-1).max(initial=0.0) < 1e-3


def test_spec_vectors_through_a_flat_dem(tmp_path):
    cases = load_cases("pendulum-v1.json")
    for case in cases:
        traj = Trajectory.from_dataset(pos_dataset(case["pos"]))
        m = get_sensor("pendulum").build(case["sensor"], case["lines"], traj, case["params"],
                                         direction=case["direction"])
        img = np.array([[p["line"], p["element"]] for p in case["image_to_ground"]])
        llh = np.array([[p["lat"], p["lon"], p["h"]] for p in case["image_to_ground"]])
        crs = utm_crs_for(float(llh[:, 0].mean()), float(llh[:, 1].mean()))
        xs, ys = transformer("EPSG:4326", crs).transform(llh[:, 1], llh[:, 0])
        grid = Grid.from_bounds(crs, (min(xs) - 300, min(ys) - 300, max(xs) + 300,
                                      max(ys) + 300), 10.0)
        path = tmp_path / f"flat-{case['name']}.tif"
        write_geotiff(path, np.full(grid.shape, case["terrain_height"], np.float32), grid.crs,
                      grid.transform)
        got = m.image_to_ground(img, DEM.open(path))
        dist = np.linalg.norm(got - geodetic_to_ecef(llh), axis=-1)
        assert dist.max() < 1e-3, f"{case['name']}: worst {dist.max() * 1000:.3f} mm"


def test_nodata_hole_gives_nan_and_the_rest_hits(tmp_path, hills):
    model, dem = hills
    data = dem.data.copy()
    nr, nc = data.shape
    r0, r1, c0, c1 = nr // 3, nr // 2, nc // 3, nc // 2
    data[r0:r1, c0:c1] = np.nan
    holed = DEM(dem.path, data, dem.transform, dem.crs_wkt)
    img = _image(model, 5000, seed=5)
    full = model.image_to_ground(img, dem)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        g = model.image_to_ground(img, holed)
    col, row, _ = frame_points(dem_frame(dem), full).T
    # distance (cells) of the hit on the whole DEM from the hole (negative inside it)
    dist = np.maximum(np.maximum(c0 - col, col - (c1 - 1)), np.maximum(r0 - row, row - (r1 - 1)))
    miss = np.isnan(g).any(axis=-1)
    assert miss[dist < -1].all() and (dist < -1).sum() > 100      # landed in the hole
    far = dist > 12                                                 # a 12 deg ray: < 10 cells
    assert not miss[far].any()
    assert np.linalg.norm(g[far] - full[far], axis=-1).max() < 1e-3
    assert np.abs(_on_surface(holed, g[~miss])).max() < 1e-3      # near the rim: on the DEM


def test_a_large_dem_takes_several_tiles(tmp_path):
    """40 x 40 km of 100 m cells with 1.5 km of relief: the frame tiles itself and keeps
    its tolerance; vertical and tilted rays from 6 km land on the surface."""
    crs = utm_crs_for(46.5, 9.0)
    x0, y0 = transformer("EPSG:4326", crs).transform(9.0, 46.5)
    grid = Grid.from_bounds(crs, (x0 - 20000, y0 - 20000, x0 + 20000, y0 + 20000), 100.0)
    x, y = grid.centres()
    h = 800 + 700 * np.sin((x - x0) / 3000.0) * np.cos((y - y0) / 4100.0)
    path = tmp_path / "alps.tif"
    write_geotiff(path, h.astype(np.float32), grid.crs, grid.transform)
    dem = DEM.open(path)
    frame = dem_frame(dem)
    assert frame is not None and frame.error_m < FRAME_TOL
    assert frame.grid[4] * frame.grid[5] > 1
    rng = np.random.default_rng(6)
    px, py = x0 + rng.uniform(-18000, 18000, 3000), y0 + rng.uniform(-18000, 18000, 3000)
    lon, lat = transformer(crs, "EPSG:4326").transform(px, py)
    ground = geodetic_to_ecef(np.stack([lat, lon, dem.height(lat, lon)], axis=-1))
    up = up_vector(lat, lon)
    d = -(up + 0.3 * np.cross(up, [0.0, 0.0, 1.0]))
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    for dd in (-up, d):
        origin = ground - 6000.0 / np.sum(-dd * up, axis=-1, keepdims=True) * dd
        got = intersect(origin, dd, dem)
        assert np.isfinite(got).all()
        assert np.abs(_on_surface(dem, got)).max() < 1e-3
        ref = intersect(origin[:300], dd[:300], dem, compiled=False)
        assert np.linalg.norm(got[:300] - ref, axis=-1).max() < 1e-3


def _plugin_model():
    sys.path.insert(0, str(ROOT / "plugins" / "rotating-mirror"))
    from swathflow_rotating_mirror.model import RotatingMirrorModel
    return RotatingMirrorModel.example_model()


@pytest.mark.parametrize("which", ["pushbroom", "rotating-mirror"])
def test_every_model_through_the_generic_path(tmp_path, which):
    from test_rectify import hills_dem
    if which == "pushbroom":
        from swathflow.sensors.pushbroom import PushbroomModel
        model = PushbroomModel.example_model("nadir", n_lines=300)
    else:
        model = _plugin_model()
    dem = hills_dem(tmp_path / "hills.tif", footprint_grid(model, ConstantHeight(5.0), 2.0))
    img = _image(model, 3000, seed=7)
    g = model.image_to_ground(img, dem)
    assert np.isfinite(g).all()
    assert np.abs(_on_surface(dem, g)).max() < 1e-3
    assert np.abs(model.ground_to_image(g) - img).max() < 1e-3
    ref = intersect(*model.ray(img[:500]), dem, compiled=False)
    assert np.linalg.norm(g[:500] - ref, axis=-1).max() < 1e-3
