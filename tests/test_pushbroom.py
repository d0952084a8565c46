"""The push-broom sensor model against the spec vectors, closed forms and numerical truth."""
import numpy as np
import pytest
import xarray as xr
from hypothesis import given, settings, strategies as st

from spec_vectors import load_cases, pos_dataset
from swathflow.errors import FormatError
from swathflow.geometry.geodesy import ecef_to_geodetic, geodetic_to_ecef
from swathflow.formats.pos import Trajectory
from swathflow.geometry.rotations import r_en
from swathflow.sensormodel import get_sensor
from swathflow.sensors.pushbroom.model import (PushbroomModel, continuity_matrix,
                                         continuity_residuals, example_sensor, views)

CASES = load_cases("pushbroom-v1.json")


def _vector_model(case):
    sensor = dict(case["camera"])
    if case["fixes"]:
        sensor["fixes"] = case["fixes"]
    traj = Trajectory.from_dataset(pos_dataset(case["pos"]))
    return PushbroomModel.build(sensor, case["lines"], traj, case["params"])


# --- the spec vectors --------------------------------------------------------------------------
@pytest.mark.parametrize("case", CASES, ids=[c["name"] for c in CASES])
def test_spec_vectors_image_to_ground(case):
    m = _vector_model(case)
    rows = case["image_to_ground"]
    img = np.array([[r["line"], r["element"]] for r in rows])
    want = geodetic_to_ecef(np.array([[r["lat"], r["lon"], r["h"]] for r in rows]))
    got = m.image_to_ground(img, case["terrain_height"])
    assert np.linalg.norm(got - want, axis=-1).max() < 1e-3


@pytest.mark.parametrize("case", CASES, ids=[c["name"] for c in CASES])
def test_spec_vectors_ground_to_image(case):
    m = _vector_model(case)
    rows = case["ground_to_image"]
    ground = geodetic_to_ecef(np.array([[r["lat"], r["lon"], r["h"]] for r in rows]))
    want = np.array([[r["line"], r["element"]] for r in rows])
    got = m.ground_to_image(ground)
    assert np.abs(got - want).max() < 1e-3


def test_vectors_with_fixes_need_the_fixes():
    """The fix corrections matter: without them the vector cases are missed by far."""
    case = next(c for c in CASES if c["fixes"])
    sensor = dict(case["camera"])
    m = PushbroomModel.build(sensor, case["lines"],
                             Trajectory.from_dataset(pos_dataset(case["pos"])), case["params"])
    rows = case["ground_to_image"]
    ground = geodetic_to_ecef(np.array([[r["lat"], r["lon"], r["h"]] for r in rows]))
    want = np.array([[r["line"], r["element"]] for r in rows])
    assert np.abs(m.ground_to_image(ground) - want).max() > 0.5


# --- closed forms ----------------------------------------------------------------------------------
def _level_north(n_lines=200, h=1000.0, heading=0.0):
    t = np.arange(-1.0, n_lines * 0.005 + 1.0, 0.005)
    lat = np.degrees(60.0 * t / 6_335_439.0) * np.cos(np.radians(heading))
    lon = np.degrees(60.0 * t / 6_378_137.0) * np.sin(np.radians(heading))
    z = np.zeros_like(t)
    ds = xr.Dataset({"lat": ("time", lat), "lon": ("time", lon), "h": ("time", z + h),
                     "roll": ("time", z), "pitch": ("time", z), "heading": ("time", z + heading)},
                    coords={"time": t})
    return Trajectory.from_dataset(ds), {"time": np.arange(n_lines) * 0.005}


NOMINAL = {"n_elements": 3072, "segments": [0, 1024, 2048], "pixel_pitch": 1e-5,
           "focal_length": 0.1, "s_c": 1535.5}


def _ned(model, img, height=0.0):
    """Ground point minus the antenna position at the line's time, in north/east/down."""
    g = model.image_to_ground(np.asarray(img, float), height)
    t = model.image_time(np.asarray(img, float))
    pos = model.trajectory.interpolate(t)
    ren = r_en(np.radians(pos["lat"]), np.radians(pos["lon"]))
    return np.einsum("...ji,...j->...i", ren, g - pos["ecef"])


def test_nominal_geometry_closed_form():
    traj, lines = _level_north()
    nadir = PushbroomModel.build({**NOMINAL, "psi_x0_deg": 0.0}, lines, traj)
    d = _ned(nadir, [[100.0, 1535.5], [100.0, 1635.5], [100.0, 1435.5]])
    assert np.abs(d[0, :2]).max() < 1e-6                       # nadir
    # 100 elements = tan 0.01: 10 m at 1000 m; larger elements look LEFT (west)
    assert d[1, 1] == pytest.approx(-10.0, abs=2e-3) and abs(d[1, 0]) < 1e-6
    assert d[2, 1] == pytest.approx(10.0, abs=2e-3)
    fwd = PushbroomModel.build({**NOMINAL, "psi_x0_deg": 25.0}, lines, traj)
    back = PushbroomModel.build({**NOMINAL, "psi_x0_deg": -25.0}, lines, traj)
    ahead = 1000.0 * np.tan(np.radians(25.0))                  # 466.3 m, flat earth
    assert _ned(fwd, [[100.0, 1535.5]])[0, 0] == pytest.approx(ahead, abs=0.03)
    assert _ned(back, [[100.0, 1535.5]])[0, 0] == pytest.approx(-ahead, abs=0.03)


def test_lever_arm_and_boresight_closed_form():
    traj, lines = _level_north()
    base = {**NOMINAL, "psi_x0_deg": 0.0}
    m = PushbroomModel.build(base, lines, traj, {"u_gps": [1.0, 2.0, 3.0]})
    d = _ned(m, [[100.0, 1535.5]])[0]
    # heading 0, level: body = NED, so the lever arm shifts the nadir point by (1, 2)
    assert d[0] == pytest.approx(1.0, abs=1e-6) and d[1] == pytest.approx(2.0, abs=1e-6)
    m = PushbroomModel.build(base, lines, traj, {"opk_cam": [0.0, 1.0, 0.0]})
    d = _ned(m, [[100.0, 1535.5]])[0]
    # phi = 1 deg tilts the camera about the body y axis: nadir ray to 1000 tan(1 deg) ahead
    assert abs(d[0]) == pytest.approx(1000.0 * np.tan(np.radians(1.0)), abs=5e-3)


def test_three_line_views_see_the_same_point_at_separated_lines():
    traj, lines = _level_north(n_lines=2000)
    sensor = {**NOMINAL, "views": {"forward": 25.0, "nadir": 0.0, "backward": -25.0}}
    mods = {v: PushbroomModel.build(sensor, lines, traj, view=v)
            for v in ("forward", "nadir", "backward")}
    g = mods["nadir"].image_to_ground(np.array([[300.0, 1535.5]]), 0.0)
    got = {v: m.ground_to_image(g, clip=False)[0] for v, m in mods.items()}
    # 60 m/s, 200 lines/s: 0.3 m per line; 466.3 m ahead = 1554.4 lines
    shift = 1000.0 * np.tan(np.radians(25.0)) / 0.3
    assert np.isnan(got["forward"][0])        # the forward line passed it before line 0
    assert got["backward"][0] == pytest.approx(300.0 + shift, abs=0.2)
    assert got["backward"][1] == pytest.approx(1535.5, abs=0.01)
    g2 = mods["forward"].image_to_ground(np.array([[10.0, 1535.5]]), 0.0)
    back = mods["nadir"].ground_to_image(g2)[0]
    assert back[0] == pytest.approx(10.0 + shift, abs=0.2)
    assert back[1] == pytest.approx(1535.5, abs=0.01)


def test_views_share_boresight_and_have_their_own_aps():
    s = example_sensor()
    p = PushbroomModel.default_parameters(s)
    assert {"u_gps", "opk_cam", "ax_forward_0", "bx_backward_2", "d_ned_2", "d_opk_0"} <= set(p.names)
    assert len(p.vector()) == 6 + 3 * 3 * 8 + 3 * 6
    assert set(views(s)) == {"forward", "nadir", "backward"}


# --- round trips over random attitudes and parameters ------------------------------------------
def _trajectory(roll, pitch, heading, height, wobble, t0=500.0):
    t = np.arange(t0 - 1.0, t0 + 6.0, 0.005)
    d = 55.0 * (t - t0)
    hd = np.radians(heading)
    lat = 40.0 + np.degrees(d * np.cos(hd) / 6_371_000.0)
    lon = -100.0 + np.degrees(d * np.sin(hd) / (6_371_000.0 * np.cos(np.radians(40.0))))
    w = 2 * np.pi * (t - t0)
    ds = xr.Dataset({"lat": ("time", lat), "lon": ("time", lon), "h": ("time", height + 0 * t),
                     "roll": ("time", roll + wobble * np.sin(0.6 * w)),
                     "pitch": ("time", pitch + wobble * np.sin(0.4 * w + 1)),
                     "heading": ("time", (heading + wobble * np.sin(0.2 * w) + 180) % 360 - 180)},
                    coords={"time": t})
    return Trajectory.from_dataset(ds)


@settings(max_examples=25, deadline=None)
@given(roll=st.floats(-8, 8), pitch=st.floats(-8, 8), heading=st.floats(-180, 180),
       wobble=st.floats(0, 0.3), view=st.sampled_from(["forward", "nadir", "backward"]),
       opk=st.lists(st.floats(-3, 3), min_size=3, max_size=3),
       lever=st.lists(st.floats(-2, 2), min_size=3, max_size=3),
       ap_scale=st.floats(0, 1), seed=st.integers(0, 2 ** 16))
def test_round_trip_random_attitude_and_parameters(roll, pitch, heading, wobble, view, opk,
                                                   lever, ap_scale, seed):
    # (wobble <= 0.3 deg at <= 0.6 Hz: faster pitching than about 2 deg/s at 1500 m moves
    # the viewing plane backwards over the ground, and points are then imaged twice)
    rng = np.random.default_rng(seed)
    sensor = example_sensor()
    sensor["fixes"] = {"time": [499.0, 501.0, 503.0, 505.0],
                       "d_ned": rng.normal(0, 0.3, (4, 3)).tolist(),
                       "d_opk": rng.normal(0, 0.02, (4, 3)).tolist()}
    for v in sensor["views"].values():
        v["ax"] = (np.asarray(v["ax"]) * ap_scale).tolist()
        v["bx"] = (np.asarray(v["bx"]) * ap_scale).tolist()
    traj = _trajectory(roll, pitch, heading, 1500.0, wobble)
    lines = {"time": 500.0 + np.arange(800) * 0.004}
    m = PushbroomModel.build(sensor, lines, traj, {"u_gps": lever, "opk_cam": opk}, view=view)
    img = np.stack([rng.uniform(0, 799, 200), rng.uniform(0, 3071, 200)], axis=-1)
    g = m.image_to_ground(img, 100.0)
    assert np.abs(ecef_to_geodetic(g)[:, 2] - 100.0).max() < 1e-3
    back = m.ground_to_image(g)
    assert np.abs(back - img).max() < 1e-5


def test_points_off_the_image_are_nan():
    m = PushbroomModel.example_model("nadir")
    # 200 elements beyond each end of the detector
    off = np.array([[100.0, 3272.0], [100.0, -200.0]])
    g_off = m.image_to_ground(off, 50.0)
    assert np.isnan(m.ground_to_image(g_off)).all()
    assert np.abs(m.ground_to_image(g_off, clip=False) - off).max() < 1e-5   # kept unclipped
    # 100 m behind the first line (about 500 lines): never swept, even unclipped
    llh = ecef_to_geodetic(m.image_to_ground(np.array([[0.0, 1535.5]]), 50.0))
    heading = np.radians(30.0)
    llh[:, 0] -= np.degrees(100.0 * np.cos(heading) / 6.37e6)
    llh[:, 1] -= np.degrees(100.0 * np.sin(heading) / (6.37e6 * np.cos(np.radians(34.0))))
    assert np.isnan(m.ground_to_image(geodetic_to_ecef(llh), clip=False)).all()


# --- partial derivatives -------------------------------------------------------------------------
def test_parameter_partials_match_finite_differences_at_two_steps():
    m = PushbroomModel.example_model("forward")
    rng = np.random.default_rng(4)
    img = np.stack([rng.uniform(50, 550, 15), rng.uniform(20, 3050, 15)], axis=-1)
    g = m.image_to_ground(img, 60.0)
    names = ["u_gps[0]", "u_gps[2]", "opk_cam[0]", "opk_cam[1]", "opk_cam[2]",
             "ax_forward_0[0]", "ax_forward_1[1]", "ax_forward_2[3]", "bx_forward_1[0]",
             "bx_forward_2[2]", "d_ned_0[0]", "d_ned_1[2]", "d_opk_0[1]", "d_opk_1[2]",
             "ax_nadir_0[0]", "d_ned_2[1]"]
    jac = m.parameter_partials(g, names)
    flat = m.parameters.flat_names()
    v0 = m.parameters.vector()
    steps = m.fd_step_sizes()
    for c, name in enumerate(names):
        i = flat.index(name)
        fd = []
        for h in (steps[i] * 10, steps[i] * 2.5):
            vp, vm = v0.copy(), v0.copy()
            vp[i] += h
            vm[i] -= h
            fd.append((m.with_vector(vp).ground_to_image(g, clip=False)
                       - m.with_vector(vm).ground_to_image(g, clip=False)) / (2 * h))
        scale = max(np.abs(fd[1]).max(), 1e-12)
        for f in fd:
            assert np.abs(jac[..., c] - f).max() <= 1e-4 * scale + 1e-6, name
    # the forward image depends neither on the nadir APs nor on a fix outside its time span
    assert np.all(jac[..., names.index("ax_nadir_0[0]")] == 0)
    assert np.all(jac[..., names.index("d_ned_2[1]")] == 0)
    assert np.abs(jac[..., names.index("ax_forward_0[0]")]).max() > 100   # tan -> pixels


def test_contract_suite_on_every_view():
    from swathflow.testing import check_model
    for v in ("forward", "backward"):
        check_model(PushbroomModel.example_model(v))


# --- C0/C1 constraints -------------------------------------------------------------------------------
def test_continuity_holds_for_smooth_aps_and_measures_jumps():
    s = example_sensor()
    p = PushbroomModel.default_parameters(s)
    A, labels = continuity_matrix(s, p)
    assert A.shape == (3 * 2 * 2 * 2, p.vector().size) and len(labels) == A.shape[0]
    # example APs are one cubic over the whole line, re-expanded per segment: smooth
    assert np.abs(continuity_residuals(s, p)).max() < 1e-12
    # a value jump of 1e-4 in segment 1 of the nadir ax shows at both of its boundaries
    a1 = p["ax_nadir_1"].copy()
    a1[0] += 1e-4
    r = continuity_residuals(s, p.updated(ax_nadir_1=a1))
    i01 = labels.index("C0 ax nadir segments 0/1 at element 1024")
    i12 = labels.index("C0 ax nadir segments 1/2 at element 2048")
    assert r[i01] == pytest.approx(-1e-4, abs=1e-15)
    assert r[i12] == pytest.approx(1e-4, abs=1e-15)
    assert np.count_nonzero(np.abs(r) > 1e-12) == 2
    # a slope change of 1e-8 per element in segment 0 of the backward bx: C1 = 1e-8, and
    # C0 = 1024 * 1e-8 at the 0/1 boundary
    b0 = p["bx_backward_0"].copy()
    b0[1] += 1e-8
    r = continuity_residuals(s, p.updated(bx_backward_0=b0))
    assert r[labels.index("C1 bx backward segments 0/1 at element 1024")] == pytest.approx(1e-8)
    assert r[labels.index("C0 bx backward segments 0/1 at element 1024")] == pytest.approx(
        1024e-8)


def test_continuity_residuals_agree_with_the_model_at_the_boundary():
    """C0 residual = left limit minus value of tan_psi at the boundary, from the model."""
    s = example_sensor()
    p = PushbroomModel.default_parameters(s)
    rng = np.random.default_rng(1)
    p = p.updated({n: p[n] + rng.normal(0, 1, 4) * [1e-4, 1e-8, 1e-12, 1e-15]
                   for n in p.names if n.startswith(("ax_nadir", "bx_nadir"))})
    traj, lines = _level_north()
    m = PushbroomModel.build(s, lines, traj, p, view="nadir")
    A, labels = continuity_matrix(s, p)
    r = A @ p.vector()
    eps = 1e-6
    for b in (1024, 2048):
        tl = m.view_tangents(np.array([b - eps]))
        tr = m.view_tangents(np.array([float(b)]))
        jump_x = tl[0][0] + eps * tl[2][0] - tr[0][0]
        jump_y = tl[1][0] + eps * tl[3][0] - tr[1][0]
        seg = f"segments {b // 1024 - 1}/{b // 1024} at element {b}"
        assert r[labels.index(f"C0 ax nadir {seg}")] == pytest.approx(jump_x, abs=1e-12)
        assert r[labels.index(f"C0 bx nadir {seg}")] == pytest.approx(jump_y, abs=1e-12)
        assert r[labels.index(f"C1 ax nadir {seg}")] == pytest.approx(tl[2][0] - tr[2][0],
                                                                      abs=1e-12)
    assert np.allclose(m.continuity_residuals(), continuity_residuals(s, p))


# --- laboratory table -------------------------------------------------------------------------------
def test_laboratory_table_replaces_the_nominal_design():
    traj, lines = _level_north()
    k = 1e-5 / 0.1
    el = np.arange(3072.0)
    shift = 2.5 * k                                  # the table looks 2.5 elements further left
    table = {"n_elements": 3072, "segments": [0, 1024, 2048],
             "tan_psi_x": np.full(3072, np.tan(np.radians(3.0))).tolist(),
             "tan_psi_y": ((el - 1535.5) * k + shift).tolist()}
    m = PushbroomModel.build(table, lines, traj)
    d = _ned(m, [[100.0, 1535.5], [100.0, 1635.5]])
    # along track: 1000 tan(3 deg) ahead; across: 2.5 and 102.5 elements left of nadir
    assert d[:, 0] == pytest.approx(1000 * np.tan(np.radians(3.0)), abs=2e-3)
    assert d[0, 1] == pytest.approx(-0.25, abs=1e-4)
    assert d[1, 1] == pytest.approx(-10.25, abs=2e-3)
    g = m.image_to_ground(np.array([[50.0, 0.0], [150.0, 3071.0], [120.3, 1000.7]]), 0.0)
    assert np.abs(m.ground_to_image(g) - [[50.0, 0.0], [150.0, 3071.0], [120.3, 1000.7]]).max() < 1e-6


# --- DEM -------------------------------------------------------------------------------------------
def test_dem_intersection(tmp_path):
    import rasterio
    from rasterio.transform import from_origin
    m = PushbroomModel.example_model("nadir")
    img = np.array([[0, 0], [0, 3071], [599, 0], [599, 3071]], float)
    llh = ecef_to_geodetic(m.image_to_ground(img, 80.0))
    lat0, lon0 = llh[:, 0].min() - 0.002, llh[:, 1].min() - 0.002
    lat1, lon1 = llh[:, 0].max() + 0.002, llh[:, 1].max() + 0.002
    res = 0.0001
    nr, nc = int((lat1 - lat0) / res) + 1, int((lon1 - lon0) / res) + 1
    lat_c = lat1 - (np.arange(nr) + 0.5) * res
    lon_c = lon0 + (np.arange(nc) + 0.5) * res

    def plane(lat, lon):   # a tilted plane: bilinear interpolation reproduces it exactly
        return 80.0 + 30000.0 * (lat - lat0) - 20000.0 * (lon - lon0)

    data = plane(lat_c[:, None], lon_c[None, :]).astype("float64")
    path = tmp_path / "dem.tif"
    with rasterio.open(path, "w", driver="GTiff", width=nc, height=nr, count=1,
                       dtype="float64", crs="EPSG:4326",
                       transform=from_origin(lon0, lat1, res, res)) as dst:
        dst.write(data, 1)
    rng = np.random.default_rng(5)
    pts = np.stack([rng.uniform(20, 580, 40), rng.uniform(50, 3020, 40)], axis=-1)
    g = m.image_to_ground(pts, str(path))
    gl = ecef_to_geodetic(g)
    assert np.abs(gl[:, 2] - plane(gl[:, 0], gl[:, 1])).max() < 1e-3     # on the DEM
    o, d = m.ray(pts)
    assert np.linalg.norm(np.cross(g - o, d), axis=-1).max() < 1e-3       # on the ray
    flat = ecef_to_geodetic(m.image_to_ground(pts, 80.0))
    assert np.abs(gl[:, 2] - flat[:, 2]).max() > 10                      # relief mattered
    assert np.abs(m.ground_to_image(g) - pts).max() < 1e-5


# --- configuration and registry ----------------------------------------------------------------
@pytest.mark.parametrize("bad, msg", [
    ({"segments": [0, 1024]}, "missing key 'n_elements'"),
    ({**NOMINAL, "segments": [1, 1024]}, "segments must start at 0"),
    ({**NOMINAL, "ax": [[0, 0, 0, 0]]}, "4 coefficients per segment"),
    ({"n_elements": 3072}, "missing key 'pixel_pitch'"),
    ({**NOMINAL, "fixes": {"time": [2.0, 1.0]}}, "fixes.time"),
    ({"n_elements": 10, "tan_psi_x": [0.0] * 10, "tan_psi_y": [0.0] * 9}, "tan_psi_y needs 10"),
])
def test_bad_sensor_tables_are_clear_errors(bad, msg):
    traj, lines = _level_north()
    with pytest.raises(FormatError, match=msg):
        PushbroomModel.build(bad, lines, traj)


def test_view_must_match_the_sensor():
    traj, lines = _level_north()
    sensor = {**NOMINAL, "views": {"forward": 25.0, "nadir": 0.0}}
    with pytest.raises(FormatError, match="set view = one of them"):
        PushbroomModel.build(sensor, lines, traj)
    with pytest.raises(FormatError, match="unknown view 'backward'"):
        PushbroomModel.build(sensor, lines, traj, view="backward")


def test_registered_as_builtin():
    assert get_sensor("pushbroom") is PushbroomModel
    assert PushbroomModel.kind == "push-broom"


def test_ground_partials_match_finite_differences():
    """Closed-form ground partials against central differences of ground_to_image (the
    line rate has steps of a few 1e-4 at POS epochs, so agreement is to 1e-3 relative)."""
    m = PushbroomModel.example_model("backward")
    rng = np.random.default_rng(6)
    img = np.stack([rng.uniform(20, 580, 30), rng.uniform(20, 3050, 30)], axis=-1)
    g = m.image_to_ground(img, 80.0)
    jac = m.ground_partials(g)
    for k in range(3):
        d = np.zeros(3)
        d[k] = 0.002
        fd = (m.ground_to_image(g + d, clip=False) - m.ground_to_image(g - d, clip=False)) / 0.004
        assert np.abs(jac[..., k] - fd).max() < 1e-3 * np.abs(fd).max()
    assert np.abs(jac).max() > 1.0           # pixels per metre at 0.2 m ground sampling
