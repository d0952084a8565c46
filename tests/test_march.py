"""The compiled ray / DEM intersection (swathflow.geometry.march) against known points:
rays aimed at points on a real DEM's surface (geographic CRS) return those points."""
import numpy as np

from spec_vectors import DATA
from swathflow.geometry.geodesy import ecef_to_geodetic, geodetic_to_ecef, up_vector
from swathflow.geometry.geodesy_kernel import geodetic_of_points
from swathflow.geometry.intersect import intersect
from swathflow.geometry.terrain import DEM


def test_heikkinen_geodetic_matches_pyproj():
    rng = np.random.default_rng(3)
    llh = np.stack([rng.uniform(-89, 89, 2000), rng.uniform(-180, 180, 2000),
                    rng.uniform(-500, 9000, 2000)], axis=-1)
    got = geodetic_of_points(geodetic_to_ecef(llh))
    assert np.abs(got[:, :2] - llh[:, :2]).max() < 1e-9          # degrees (0.1 mm)
    assert np.abs(got[:, 2] - llh[:, 2]).max() < 1e-6             # metres


def test_rays_hit_points_on_a_real_dem():
    path = DATA / "dem" / "jacksboro_fault_dem.tif"
    dem = DEM.open(path)                       # EPSG:4326, ~90 m cells, real relief
    a, _, c, _, e, f = dem.transform
    rows, cols = dem.data.shape
    rng = np.random.default_rng(5)
    lon = c + a * rng.uniform(2, cols - 2, 400)
    lat = f + e * rng.uniform(2, rows - 2, 400)
    h = dem.height(lat, lon)
    ok = np.isfinite(h)
    truth = geodetic_to_ecef(np.stack([lat[ok], lon[ok], h[ok]], axis=-1))
    up = up_vector(lat[ok], lon[ok])
    # vertical rays cross the surface once; tilted ones (20 deg) from 1500 m above
    tilt = rng.normal(size=up.shape)
    tilt -= np.sum(tilt * up, axis=-1, keepdims=True) * up
    tilt /= np.linalg.norm(tilt, axis=-1, keepdims=True)
    for vertical, d in ((True, -up), (False, -(up + np.tan(np.radians(20)) * tilt))):
        d = d / np.linalg.norm(d, axis=-1, keepdims=True)
        origin = truth - 1500.0 / np.sum(-d * up, axis=-1, keepdims=True) * d
        got = intersect(origin, d, dem)
        ref = intersect(origin, d, dem, compiled=False)       # the numpy path
        err = np.linalg.norm(got - truth, axis=-1)
        if vertical:
            assert np.nanmax(err) < 1e-3 and np.isfinite(err).all()
        else:
            # a tilted ray may meet a ridge first: then both paths must agree on it
            hit = err < 1e-3
            assert hit.mean() > 0.9
            assert np.nanmax(np.linalg.norm(got - ref, axis=-1)) < 1e-3
        assert np.abs(ecef_to_geodetic(got)[:, 2] - dem.height(*ecef_to_geodetic(got)[:, :2].T)
                      ).max() < 1e-4
