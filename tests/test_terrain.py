"""DEM intersection against a tilted plane with a known answer, misses, geoid handling."""
import numpy as np
import pytest
import rasterio
from rasterio.transform import from_origin

from swathflow import SwathflowError
from swathflow.errors import FormatError
from swathflow.geometry.geodesy import ecef_to_geodetic, geodetic_to_ecef, transformer
from swathflow.geometry.intersect import intersect
from swathflow.sensormodel import RayMissWarning
from swathflow.sensors.pendulum import PendulumModel
from swathflow.geometry.terrain import DEM, ConstantHeight, open_terrain

E0, N0 = 500000.0, 3430000.0   # UTM 51N, near 31 N 123 E
SLOPE_E, SLOPE_N, H0 = 0.15, -0.08, 40.0


def plane_height(e, n):
    return H0 + SLOPE_E * (e - E0) + SLOPE_N * (n - N0)


@pytest.fixture(scope="module")
def plane_dem(tmp_path_factory):
    """A tilted plane, linear in UTM easting/northing (so bilinear interpolation is exact)."""
    path = tmp_path_factory.mktemp("dem") / "plane.tif"
    res, n = 10.0, 400
    x0, y0 = E0 - n * res / 2, N0 + n * res / 2
    cols, rows = np.meshgrid(np.arange(n), np.arange(n))
    data = plane_height(x0 + (cols + 0.5) * res, y0 - (rows + 0.5) * res).astype("float64")
    with rasterio.open(path, "w", driver="GTiff", width=n, height=n, count=1, dtype="float64",
                       crs="EPSG:32651", transform=from_origin(x0, y0, res, res)) as dst:
        dst.write(data, 1)
    return path


def _ground_on_plane(rng, n):
    e = E0 + rng.uniform(-1500, 1500, n)
    nn = N0 + rng.uniform(-1500, 1500, n)
    lon, lat = transformer("EPSG:32651", "EPSG:4326").transform(e, nn)
    return geodetic_to_ecef(np.stack([lat, lon, plane_height(e, nn)], axis=-1))


def test_rays_through_known_plane_points(plane_dem):
    """Rays aimed at points on the plane, from 1500 m up and up to 45 deg off nadir, return them."""
    dem = DEM.open(plane_dem)
    rng = np.random.default_rng(1)
    truth = _ground_on_plane(rng, 500)
    llh = ecef_to_geodetic(truth)
    above = geodetic_to_ecef(np.stack([llh[:, 0] + rng.uniform(-0.01, 0.01, 500),
                                       llh[:, 1] + rng.uniform(-0.01, 0.01, 500),
                                       np.full(500, 1500.0)], axis=-1))
    got = intersect(above, truth - above, dem)
    err = np.linalg.norm(got - truth, axis=-1)
    assert err.max() < 1e-3, f"worst {err.max():.2e} m"


def test_rays_that_miss_give_nan_and_a_count(plane_dem):
    m = PendulumModel.example_model()
    dem = DEM.open(plane_dem)    # the example flies near 31 N 121 E: far from this DEM
    with pytest.warns(RayMissWarning, match="4 of 4 rays missed"):
        out = m.image_to_ground(np.array([[10, 10], [20, 20], [30, 30], [40, 40]]), dem)
    assert np.isnan(out).all()


def test_constant_height_intersection_is_on_the_surface():
    rng = np.random.default_rng(2)
    origin = geodetic_to_ecef(np.array([45.0, 7.0, 3000.0]))
    target = geodetic_to_ecef(np.stack([45 + rng.uniform(-0.03, 0.03, 100),
                                        7 + rng.uniform(-0.03, 0.03, 100),
                                        np.full(100, 321.0)], axis=-1))
    got = intersect(origin, target - origin, ConstantHeight(321.0))
    assert np.linalg.norm(got - target, axis=-1).max() < 1e-4


def test_orthometric_dem_needs_a_stated_geoid(plane_dem):
    with pytest.raises(FormatError, match="never converted silently"):
        DEM.open(plane_dem, vertical="orthometric")
    lifted = DEM.open(plane_dem, vertical="orthometric", undulation=28.3)
    plain = DEM.open(plane_dem)
    assert np.allclose(lifted.data, plain.data + 28.3)


def test_missing_geoid_grid_is_an_error_not_a_noop(plane_dem, monkeypatch):
    import swathflow.geometry.terrain as t
    monkeypatch.setattr(t, "_find_geoid_grid", lambda name: None)
    with pytest.raises(SwathflowError, match="proj-data"):
        DEM.open(plane_dem, vertical="orthometric", geoid="egm96")


def test_real_dem_heights(tmp_path):
    from spec_vectors import DATA
    path = DATA / "dem" / "jacksboro_fault_dem.tif"
    dem = DEM.open(path, vertical="orthometric", undulation=-30.0)
    assert 236 - 30 - 1 < dem.h_min < dem.h_max < 1076 - 30 + 1
    with rasterio.open(path) as src:
        raw = src.read(1).astype(float)
        lon, lat = src.xy(100, 200)
    assert dem.height(lat, lon) == pytest.approx(raw[100, 200] - 30.0, abs=1e-6)


def test_open_terrain_forms(plane_dem):
    assert open_terrain(12.0).height(0, 0) == 12.0
    assert open_terrain({"height": 10.0, "vertical": "orthometric", "undulation": 2.0}).h == 12.0
    assert isinstance(open_terrain({"dem": str(plane_dem)}), DEM)


def _write_gtx(path, lat0, lon0, dlat, dlon, values):
    """A PROJ .gtx vertical grid (big-endian header + float32 rows, south to north)."""
    import struct
    rows, cols = values.shape
    with open(path, "wb") as f:
        f.write(struct.pack(">4d2i", lat0, lon0, dlat, dlon, rows, cols))
        f.write(values.astype(">f4").tobytes())


def test_geoid_grid_converts_orthometric_heights(plane_dem, tmp_path):
    """A real PROJ grid file on the vgridshift path: h = H + N with N varying in latitude."""
    lat = np.arange(30.0, 32.01, 0.25)
    lon = np.arange(122.0, 124.01, 0.25)
    n = (20.0 + 4.0 * (lat[:, None] - 30.0) + 0.0 * lon[None, :])
    grid = tmp_path / "test_geoid.gtx"
    _write_gtx(grid, 30.0, 122.0, 0.25, 0.25, n)
    dem = DEM.open(plane_dem, vertical="orthometric", geoid=str(grid))
    plain = DEM.open(plane_dem)
    lon_c, lat_c = transformer("EPSG:32651", "EPSG:4326").transform(E0, N0)
    expected_n = 20.0 + 4.0 * (lat_c - 30.0)
    got = dem.height(lat_c, lon_c) - plain.height(lat_c, lon_c)
    assert got == pytest.approx(expected_n, abs=1e-3)
