"""The pendulum's ground_to_image on lines that hold several POS epochs, against a truth
computed another way.

The survey's lines (50 Hz POS, a line every 61 ms) each hold 3-4 POS epochs, and the
compiled ``ground_to_image`` cuts such a line at each epoch (a kink of the condition) and
solves on the piece with the sign change (``kernel.ground_to_image``, ``epoch_frames``).
Here the truth is docs/geometry.md's image-to-ground formula written out below in numpy
(its own rotations, POS interpolation and pyproj's ECEF, no swathflow geometry): a ground
point on the ray of a known ``(line, element)``. ``ground_to_image`` must give that
``(line, element)`` back to 1e-6 px.

The flight wobbles in roll, pitch and heading between the epochs (sines of 1.7-7.9 Hz
and a random step at every epoch), so a line's camera frames at its epochs differ and a
cut at the wrong epoch shows (checked: with every epoch given the line's first epoch's
frame, or the first epoch skipped, the points come back up to 1e-5 - 1e-3 px off). The
roll, and the heading seen from the detector's ends, turn slower than the gimbal swings,
and the truth checks that every point is crossed by the lines' viewing planes once only:
the inverse is unique (a fast yaw wobble under a long detector line sees points two or
three times, and no solver can pick the image point then).
"""
import numpy as np
import pytest
import xarray as xr
from pyproj import Transformer

from swathflow.formats.pos import Trajectory
from swathflow.sensors.pendulum import PendulumModel

# the survey preset's sensor (sensors/pendulum/simulate.py): 2 m pixels from 650 m
AGL, SPEED, LINE_DT, SWING = 650.0, 55.0, 0.061, 15.0
SENSOR = {"pixel_pitch": 15e-6, "focal_length": 0.004875, "n_elements": 320, "k0": 159.5,
          "y0": 2e-6}
PARAMS = {"u_gps": [-0.08, 0.24, 0.91], "u_sen": [-0.07, -0.11, -2.01],
          "opk_sen": [0.03, -0.47, -0.04], "opk_pos_L": [0.73, 0.2, -0.11],
          "opk_pos_R": [0.68, -0.31, -0.07]}
TOL_PX = 1e-6


# --- docs/geometry.md, written out (the truth) -------------------------------------------
def _rx(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def _ry(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def _rz(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def _opk(o, p, k):
    return _rx(np.radians(o)) @ _ry(np.radians(p)) @ _rz(np.radians(k))


def _r_en(lat, lon):
    la, lo = np.radians(lat), np.radians(lon)
    return np.array([[-np.sin(la) * np.cos(lo), -np.sin(lo), -np.cos(la) * np.cos(lo)],
                     [-np.sin(la) * np.sin(lo), np.cos(lo), -np.cos(la) * np.sin(lo)],
                     [np.cos(la), 0.0, -np.sin(la)]])


class Truth:
    """The spec's pendulum ray, one image point at a time: the POS interpolated linearly
    in time (ECEF positions, latitude, longitude and attitude), the line's time, swing
    and pitch compensation linearly in line."""

    def __init__(self, pos: dict, lines: dict, direction: str):
        self.pos, self.lines = pos, lines
        ecef = Transformer.from_crs("EPSG:4979", "EPSG:4978", always_xy=True).transform(
            pos["lon"], pos["lat"], pos["h"])
        self.ecef = np.stack(ecef, axis=-1)
        self.r_bp = _opk(*PARAMS[f"opk_pos_{direction}"])
        self.r_hs = _opk(*PARAMS["opk_sen"]) @ np.diag([1.0, -1.0, -1.0])

    def frame(self, line):
        """Antenna position, R_EN R_NB and R_BP R_PH at fractional ``line``."""
        n = len(self.lines["time"])
        j = min(int(line), n - 2)
        w = line - j
        t, s, q = ((1 - w) * self.lines[k][j] + w * self.lines[k][j + 1]
                   for k in ("time", "swing", "pitch_comp"))
        tp = self.pos["time"]
        k = int(np.searchsorted(tp, t, side="right")) - 1
        u = (t - tp[k]) / (tp[k + 1] - tp[k])
        at = {c: (1 - u) * self.pos[c][k] + u * self.pos[c][k + 1]
              for c in ("lat", "lon", "roll", "pitch", "heading")}
        x_ant = (1 - u) * self.ecef[k] + u * self.ecef[k + 1]
        r_eb = _r_en(at["lat"], at["lon"]) @ (_rz(np.radians(at["heading"]))
                                              @ _ry(np.radians(at["pitch"]))
                                              @ _rx(np.radians(at["roll"])))
        return x_ant, r_eb, self.r_bp @ _rx(np.radians(s)) @ _ry(np.radians(q))

    def point(self, line, element, lam):
        """``X_E(lam)``: the point at ``lam`` along the ray of ``(line, element)``."""
        x_ant, r_eb, r_bh = self.frame(line)
        c = np.array([(element - SENSOR["k0"]) * SENSOR["pixel_pitch"], SENSOR["y0"],
                      -SENSOR["focal_length"]])
        return x_ant + r_eb @ (np.asarray(PARAMS["u_gps"]) + r_bh @ (
            np.asarray(PARAMS["u_sen"]) + lam * self.r_hs @ c))

    def condition(self, line, g):
        """``f g_y / (-g_z) - y0`` ``(lines, points)`` with ``g`` the camera-frame vector
        of ground points ``g`` ``(n, 3)`` seen from fractional lines ``line``: zero where
        the line's viewing plane holds the point."""
        x_ant, r_eb, r_bh = (np.stack(a) for a in zip(*(self.frame(x) for x in line)))
        v = np.einsum("mji,mnj->mni", r_eb, g[None] - x_ant[:, None]) - PARAMS["u_gps"]
        v = np.einsum("mji,mnj->mni", r_bh, v) - PARAMS["u_sen"]
        v = v @ self.r_hs
        return SENSOR["focal_length"] * v[..., 1] / -v[..., 2] - SENSOR["y0"]


# --- the scene -----------------------------------------------------------------------------
def scene(pos_rate: float, direction: str, n_lines: int = 120, seed: int = 0):
    """A short swing of the survey's sensor (``n_lines`` of the full swing's 171:
    +-10.5 deg) on a POS at ``pos_rate`` Hz that wobbles between its epochs; the truth,
    the line table, and the model."""
    rng = np.random.default_rng(seed)
    t0 = 345600.0
    tp = t0 + np.arange(-1.0, n_lines * LINE_DT + 1.0, 1.0 / pos_rate)
    w = 2 * np.pi * (tp - t0)
    d = SPEED * (tp - t0)
    heading = 30.0
    lat = 31.0 + np.degrees(d * np.cos(np.radians(heading)) / 6_371_000.0)
    lon = 121.0 + np.degrees(d * np.sin(np.radians(heading))
                             / (6_371_000.0 * np.cos(np.radians(31.0))))
    jitter = rng.normal(size=(3, tp.size))
    # wobbles of 1.7-7.9 Hz and a random step at every epoch (smaller at denser POS: the
    # same rate); the roll's rate, and the heading's times the along-track offset of the
    # detector's ends over the range (< 0.5), stay below the gimbal's 2.9 deg/s
    step = 50.0 / pos_rate
    pos = {"time": tp, "lat": lat, "lon": lon,
           "h": AGL + 3.0 * np.sin(0.9 * w),
           "roll": (0.4 + 0.04 * np.sin(3.1 * w) + 0.004 * np.sin(7.3 * w)
                    + 0.001 * step * jitter[0]),
           "pitch": (1.5 + 0.3 * np.sin(2.3 * w + 1.0) + 0.01 * np.sin(7.9 * w)
                     + 0.01 * step * jitter[1]),
           "heading": (heading + 0.1 * np.sin(1.7 * w + 2.0) + 0.005 * np.sin(6.7 * w)
                       + 0.005 * step * jitter[2])}
    ds = xr.Dataset({k: ("time", v) for k, v in pos.items() if k != "time"},
                    coords={"time": tp})
    half = SWING * (n_lines - 1) / 170
    sweep = np.linspace(-half, half, n_lines)
    lines = {"time": t0 + LINE_DT * np.arange(n_lines),
             "swing": sweep if direction == "L" else sweep[::-1],
             "pitch_comp": np.linspace(0.6, -0.6, n_lines)}
    model = PendulumModel.build(SENSOR, lines, Trajectory.from_dataset(ds), PARAMS,
                                direction=direction)
    return Truth(pos, lines, direction), lines, model


def epochs_in_lines(pos_time, line_time) -> np.ndarray:
    """How many POS epochs fall strictly between each line's time and the next's."""
    return (np.searchsorted(pos_time, line_time[1:], side="left")
            - np.searchsorted(pos_time, line_time[:-1], side="right"))


def image_points(truth: Truth, lines: dict, rng, n: int = 400) -> np.ndarray:
    """Image points in lines holding several epochs: random fractional lines, the epochs'
    own lines (the kinks) and integer lines, random elements on the detector."""
    counts = epochs_in_lines(truth.pos["time"], lines["time"])
    multi = np.flatnonzero(counts >= 2)
    multi = multi[(multi >= 2) & (multi < len(lines["time"]) - 3)]   # not the swing's ends
    lt, tp = lines["time"], truth.pos["time"]
    inside = tp[(tp > lt[multi[0]]) & (tp < lt[multi[-1] + 1])]
    at_epochs = np.interp(inside, lt, np.arange(lt.size, dtype=float))
    line = np.concatenate([rng.choice(multi, n) + rng.uniform(0, 1, n),
                           at_epochs[:n // 4], rng.choice(multi, 20).astype(float)])
    elem = rng.uniform(0, SENSOR["n_elements"] - 1, line.size)
    return np.stack([line, elem], axis=-1)


def truth_points(truth: Truth, img: np.ndarray, rng) -> np.ndarray:
    """A point on each image point's ray, 0.85 to 1.15 of the flying height away."""
    lam = rng.uniform(0.85, 1.15, len(img)) * AGL / SENSOR["focal_length"]
    return np.array([truth.point(ln, el, la) for (ln, el), la in zip(img, lam)])


def crossings(truth: Truth, lines: dict, g, near, per_line: int = 16) -> tuple:
    """How many times the lines' viewing planes cross each point of ``g``: the sign
    changes of the truth's condition at every line, every epoch and ``per_line - 1``
    lines between (the condition is smooth between a line and an epoch); and whether it is
    strictly monotonic on that grid within 10 lines of ``near`` (no pair of roots close
    together can hide between two grid lines there; further out the condition is far
    from zero: it reverses only 69 lines and more from the image point, on the edges'
    far ends)."""
    lt, tp = lines["time"], truth.pos["time"]
    at = np.interp(tp[(tp > lt[0]) & (tp < lt[-1])], lt, np.arange(lt.size, dtype=float))
    grid = np.union1d(np.linspace(0, lt.size - 1, per_line * (lt.size - 1) + 1), at)
    f = truth.condition(grid, g)
    d = np.sign(np.diff(f, axis=0))
    close = np.abs(grid[:-1, None] - near[None]) < 10
    turn = (d != np.sign(f[-1] - f[0])) & close
    return np.count_nonzero(np.sign(f[1:]) != np.sign(f[:-1]), axis=0), ~turn.any(axis=0)


CASES = [(50.0, "L"), (50.0, "R"), (200.0, "L")]


@pytest.fixture(scope="module", params=CASES, ids=[f"{r:g}Hz-{d}" for r, d in CASES])
def case(request):
    rate, direction = request.param
    truth, lines, model = scene(rate, direction)
    rng = np.random.default_rng(int(rate) + ord(direction))
    img = image_points(truth, lines, rng)
    return truth, lines, model, img, truth_points(truth, img, rng)


def test_the_scene_holds_several_epochs_a_line_and_points_seen_once(case):
    truth, lines, model, img, g = case
    counts = epochs_in_lines(truth.pos["time"], lines["time"])
    assert counts.min() >= 3                     # every line holds 3 or more epochs
    # the attitude turns between a line's epochs (the pitch by 0.05 px and more, median) and
    # kinks at each (the condition is not smooth across an epoch): in pixels (IFOV), the
    # median step and second difference
    ifov = np.degrees(SENSOR["pixel_pitch"] / SENSOR["focal_length"])
    assert np.median(np.abs(np.diff(truth.pos["pitch"]))) > 0.05 * ifov
    for k in ("roll", "pitch", "heading"):
        assert np.median(np.abs(np.diff(truth.pos[k], 2))) > 1e-3 * ifov
    # the image points lie in lines holding several epochs, on and between them
    assert np.isin(np.floor(img[:, 0]).astype(int), np.flatnonzero(counts >= 3)).all()
    count, monotonic = crossings(truth, lines, g, img[:, 0])
    assert (count == 1).all() and monotonic.all()


def test_ground_to_image_gives_back_the_image_points(case):
    truth, lines, model, img, g = case
    got = model.ground_to_image(g)
    assert np.isfinite(got).all()
    err = np.abs(got - img)
    assert err[:, 0].max() < TOL_PX, f"line off by {err[:, 0].max():.3g} px"
    assert err[:, 1].max() < TOL_PX, f"element off by {err[:, 1].max():.3g} px"


def test_the_fully_converged_solve_agrees(case):
    """The model's own exact reference solve (secant to 1e-12 line) against the truth:
    the truth and the model are the same geometry."""
    truth, lines, model, img, g = case
    assert np.abs(model._ground_to_image_converged(g) - img).max() < TOL_PX


def test_image_to_ground_lies_on_the_truth_ray(case):
    """The forward model (rays and the intersection at a constant height) gives points
    on the truth's rays, and those go back to their image points too."""
    truth, lines, model, img, g = case
    sub = img[::7]
    ground = model.image_to_ground(sub, 25.0)
    for (line, elem), p in zip(sub, ground):
        a, b = (truth.point(line, elem, lam) for lam in (0.0, AGL / SENSOR["focal_length"]))
        d = (b - a) / np.linalg.norm(b - a)
        off = (p - a) - ((p - a) @ d) * d
        assert np.linalg.norm(off) < 1e-6      # metres from the ray
    assert np.abs(model.ground_to_image(ground) - sub).max() < TOL_PX


def test_numpy_dask_and_xarray_inputs(case):
    """The public ground_to_image takes any array of ``(..., 3)`` ECEF points: a grid, a
    dask array (computed), an xarray DataArray; the same values, in the input's shape."""
    import dask.array as da
    truth, lines, model, img, g = case
    n = (len(g) // 20) * 20
    want = model.ground_to_image(g[:n])
    grid = g[:n].reshape(20, -1, 3)
    for arr in (grid, da.from_array(grid, chunks=(5, -1, 3)),
                xr.DataArray(grid, dims=("y", "x", "xyz"))):
        got = np.asarray(model.ground_to_image(arr))
        assert got.shape == (20, n // 20, 2)
        assert np.array_equal(got.reshape(-1, 2), want, equal_nan=True)
    assert np.abs(want - img[:n]).max() < TOL_PX


def test_the_numpy_path_gives_back_the_image_points(case):
    """The numpy path (the compiled one's reference in test_pendulum_epochs, and its
    fallback) against the same truth."""
    truth, lines, model, img, g = case
    assert np.abs(model._ground_to_image_numpy(g, True) - img).max() < TOL_PX


@pytest.fixture(scope="module")
def on_epochs():
    """A 400 Hz POS (24-25 epochs a line) and three image points at every epoch's own
    fractional line: the root of each lies on an epoch, the end of two pieces."""
    truth, lines, model = scene(400.0, "R", seed=5)
    lt, tp = lines["time"], truth.pos["time"]
    at = np.interp(tp[(tp > lt[3]) & (tp < lt[-4])], lt, np.arange(lt.size, dtype=float))
    rng = np.random.default_rng(0)
    img = np.stack([np.repeat(at, 3), rng.uniform(0, SENSOR["n_elements"] - 1, 3 * at.size)],
                   axis=-1)
    return truth, lines, model, img, truth_points(truth, img, rng)


def test_points_on_the_epochs_are_seen_once_and_the_converged_solve_agrees(on_epochs):
    truth, lines, model, img, g = on_epochs
    assert epochs_in_lines(truth.pos["time"], lines["time"]).min() >= 24
    count, monotonic = crossings(truth, lines, g[::40], img[::40, 0])
    assert (count == 1).all() and monotonic.all()
    assert np.abs(model._ground_to_image_converged(g) - img).max() < TOL_PX


def test_ground_to_image_on_the_epochs(on_epochs):
    truth, lines, model, img, g = on_epochs
    assert np.abs(model.ground_to_image(g) - img).max() < TOL_PX
