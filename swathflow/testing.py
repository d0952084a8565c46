"""The sensor-model contract suite: every registered model must pass it, and a plugin
author runs it on a third-party model.

Use from pytest::

    from swathflow.testing import check_model
    def test_my_model_contract():
        check_model(MyModel.example_model())

or run all registered models: ``python -m swathflow.testing`` (exit code 0 when all pass).
Each check raises ``AssertionError`` with a message saying what broke.
"""
from __future__ import annotations

import json
import sys

import numpy as np
import xarray as xr

from swathflow.geometry.geodesy import geodetic_to_ecef, ecef_to_geodetic
from swathflow.formats.pos import Trajectory


def straight_trajectory(n_lines: int = 500, line_rate: float = 100.0, speed: float = 60.0,
                        height: float = 1000.0, heading: float = 30.0, lat0: float = 31.0,
                        lon0: float = 121.0, pos_rate: float = 200.0, t0: float = 345600.0,
                        wobble: float = 0.5):
    """A gently wobbling straight flight and a line table of ``time`` (for example models).

    Returns ``(Trajectory, {"time": ...})``; the POS covers the lines with a margin.
    """
    dur = n_lines / line_rate
    t = t0 + np.arange(-1.0, dur + 1.0, 1.0 / pos_rate)
    d = speed * (t - t0)
    hd = np.radians(heading)
    north, east = d * np.cos(hd), d * np.sin(hd)
    lat = lat0 + np.degrees(north / 6_371_000.0)
    lon = lon0 + np.degrees(east / (6_371_000.0 * np.cos(np.radians(lat0))))
    w = 2 * np.pi * (t - t0)
    ds = xr.Dataset({"lat": ("time", lat), "lon": ("time", lon),
                     "h": ("time", height + 2.0 * np.sin(0.3 * w)),
                     "roll": ("time", wobble * np.sin(0.7 * w)),
                     "pitch": ("time", 2.0 + 0.5 * wobble * np.sin(0.45 * w)),
                     "heading": ("time", heading + wobble * np.sin(0.2 * w))},
                    coords={"time": t})
    lines = {"time": t0 + np.arange(n_lines) / line_rate}
    return Trajectory.from_dataset(ds), lines


def _interior_points(model, n: int, rng, margin: float = 0.1) -> np.ndarray:
    nl, ne = model.shape
    line = rng.uniform(margin * (nl - 1), (1 - margin) * (nl - 1), n)
    elem = rng.uniform(margin * (ne - 1), (1 - margin) * (ne - 1), n)
    return np.stack([line, elem], axis=-1)


def check_round_trip(model, height: float = 50.0, n: int = 200, tol_px: float = 1e-3, seed=0):
    """image -> ground (constant height) -> image returns the start within ``tol_px``."""
    rng = np.random.default_rng(seed)
    img = _interior_points(model, n, rng)
    ground = model.image_to_ground(img, height)
    assert np.isfinite(ground).all(), "image_to_ground gave NaN for interior image points"
    llh = ecef_to_geodetic(ground)
    assert np.allclose(llh[:, 2], height, atol=1e-3), "ground points are not on the terrain"
    back = model.ground_to_image(ground)
    err = np.abs(back - img).max()
    assert err < tol_px, f"round trip error {err:.3g} px exceeds {tol_px} px"


def check_unseen(model):
    """A point far from the image is flagged (NaN), not projected."""
    origin, _ = model.ray(np.array([[model.n_lines / 2, model.n_elements / 2]]))
    llh = ecef_to_geodetic(origin)[0]
    far = geodetic_to_ecef(np.array([llh[0] + 5.0, llh[1] + 5.0, 0.0]))
    assert np.isnan(model.ground_to_image(far[None])).all(), \
        "a point 500 km away was not flagged as unseen"


def _linearity(model, partial_fn, perturb, base_img, scale, tol, what):
    """First-order prediction of an image-coordinate change matches the true change."""
    jac = partial_fn()
    for k, delta in perturb:
        moved = delta()
        pred = base_img + jac[..., k] * scale
        err = np.nanmax(np.abs(moved - pred))
        assert err < tol, f"{what} {k}: linear prediction off by {err:.3g} px"


def check_ground_partials(model, height: float = 50.0, n: int = 20, seed=1):
    """ground_partials predict the image motion of a 1 cm ground displacement (to 2 % or
    2e-4 px: trajectories interpolated piecewise-linearly have slope changes at POS epochs)."""
    rng = np.random.default_rng(seed)
    img = _interior_points(model, n, rng)
    ground = model.image_to_ground(img, height)
    base = model.ground_to_image(ground, clip=False)
    jac = model.ground_partials(ground)
    assert jac.shape == (n, 2, 3), f"ground_partials shape {jac.shape}, expected {(n, 2, 3)}"
    for k in range(3):
        d = np.zeros(3)
        d[k] = 0.01
        moved = model.ground_to_image(ground + d, clip=False)
        err = np.abs(moved - (base + jac[..., k] * 0.01)).max()
        scale = np.abs(moved - base).max()
        assert scale > 0, f"moving the ground along axis {k} does not move the image point"
        assert err < max(2e-4, 2e-2 * scale), \
            f"ground_partials axis {k}: linear prediction off by {err:.3g} px"


def check_parameter_partials(model, height: float = 50.0, n: int = 20, seed=2):
    """parameter_partials predict the image motion of a small change of every parameter."""
    rng = np.random.default_rng(seed)
    img = _interior_points(model, n, rng)
    ground = model.image_to_ground(img, height)
    base = model.ground_to_image(ground, clip=False)
    jac = model.parameter_partials(ground)
    p = model.parameters
    names = p.flat_names()
    assert jac.shape == (n, 2, len(names)), f"parameter_partials shape {jac.shape}"
    v0 = p.vector()
    units = p.flat_units()
    assert names == [] or np.abs(jac).max() > 0, "parameter_partials are all zero"
    # a model may say how big a "small change" of each parameter is (e.g. polynomial
    # coefficients of very different scales): ``fd_step_sizes()`` -> one step per parameter
    steps = model.fd_step_sizes() if hasattr(model, "fd_step_sizes") else None
    for i, name in enumerate(names):
        h = steps[i] if steps is not None else {"deg": 2e-3, "m": 2e-3}.get(units[i], 1e-5)
        v = v0.copy()
        v[i] += h
        moved = model.with_vector(v).ground_to_image(ground, clip=False)
        change = moved - base
        err = np.abs(change - jac[..., i] * h).max()
        assert err < max(2e-4, 2e-2 * np.abs(change).max()), \
            f"parameter_partials {name}: linear prediction off by {err:.3g} px"


def check_serialisation(model, n: int = 50, seed=3):
    """to_state is JSON, from_state rebuilds an equal model, the token is stable."""
    state = model.to_state()
    text = json.dumps(state)
    again = type(model).from_state(json.loads(text))
    rng = np.random.default_rng(seed)
    img = _interior_points(model, n, rng)
    g = model.image_to_ground(img, 10.0)
    a, b = model.ground_to_image(g), again.ground_to_image(g)
    assert np.allclose(a, b, atol=1e-6, equal_nan=True), "from_state(to_state()) differs"
    assert model.token() == again.token(), "token changed across a serialisation round trip"
    import dask.base
    assert dask.base.tokenize(model) == dask.base.tokenize(again), "dask token unstable"
    v = model.parameters.vector()
    if v.size:
        v = v.copy()
        v[0] += 0.01
        other = model.with_vector(v)
        assert other.token() != model.token(), "token ignores the parameters"
        assert np.allclose(model.parameters.vector()[0], v[0] - 0.01), "model was mutated"


def check_time(model):
    """image_time is finite inside the image and sensor_position lies near the trajectory."""
    img = np.array([[0.0, 0.0], [model.n_lines - 1, model.n_elements - 1]])
    t = model.image_time(img)
    assert np.isfinite(t).all(), "image_time not finite inside the image"
    pos = model.sensor_position(t)
    ant = model.trajectory.interpolate(t)["ecef"]
    dist = np.linalg.norm(pos - ant, axis=-1)
    assert (dist < 50).all(), f"sensor_position {dist.max():.1f} m from the antenna"


def check_projector(model, height: float = 50.0, n: int = 20, seed=4):
    """The bulk projection (:meth:`SensorModel.projector`) over two images (the model and a
    copy with other parameters, which it is given as a vector) agrees with
    ``ground_to_image`` of each, and its partials predict the image motion of a small
    change of every parameter and of the ground (as :func:`check_parameter_partials`)."""
    rng = np.random.default_rng(seed)
    img = _interior_points(model, n, rng)
    ground = model.image_to_ground(img, height)
    v0 = model.parameters.vector()
    steps = model.fd_step_sizes() if hasattr(model, "fd_step_sizes") else None
    units = model.parameters.flat_units()
    h = np.array([steps[i] if steps is not None else {"deg": 2e-3, "m": 2e-3}.get(u, 1e-5)
                  for i, u in enumerate(units)])
    v1 = v0 + 5 * h
    other = model.with_vector(v1)
    proj = type(model).projector([model, other])
    idx = np.repeat([0, 1], n)
    G = np.concatenate([ground, ground])
    V = np.stack([v0, v1])
    out = proj.project(idx, G, V)
    want = np.concatenate([model.ground_to_image(ground, clip=False),
                           other.ground_to_image(ground, clip=False)])
    assert out.image.shape == (2 * n, 2), f"projector image shape {out.image.shape}"
    err = np.nanmax(np.abs(out.image - want))
    assert np.array_equal(np.isnan(out.image), np.isnan(want)) and err < 1e-3, \
        f"projector disagrees with ground_to_image by {err:.3g} px"
    assert out.d_parameters.shape == (2 * n, 2, v0.size), \
        f"projector d_parameters shape {out.d_parameters.shape}"
    assert out.d_ground.shape == (2 * n, 2, 3), f"projector d_ground shape {out.d_ground.shape}"
    again = proj.project(idx, G, V, partials=False, start=out.image)
    assert np.nanmax(np.abs(again.image - out.image)) < 1e-6, \
        "projector gives another answer when started at its own"
    names = model.parameters.flat_names()
    for i, name in enumerate(names):
        Vp = V.copy()
        Vp[:, i] += h[i]
        change = proj.project(idx, G, Vp, partials=False).image - out.image
        err = np.nanmax(np.abs(change - out.d_parameters[..., i] * h[i]))
        assert err < max(2e-4, 2e-2 * np.nanmax(np.abs(change))), \
            f"projector partial by {name}: linear prediction off by {err:.3g} px"
    for k in range(3):
        d = np.zeros(3)
        d[k] = 0.01
        change = proj.project(idx, G + d, V, partials=False).image - out.image
        err = np.nanmax(np.abs(change - out.d_ground[..., k] * 0.01))
        assert err < max(2e-4, 2e-2 * np.nanmax(np.abs(change))), \
            f"projector ground partial axis {k}: linear prediction off by {err:.3g} px"


CHECKS = (check_round_trip, check_unseen, check_ground_partials, check_parameter_partials,
          check_projector, check_serialisation, check_time)


def check_model(model) -> None:
    """Run every contract check on one model instance."""
    for check in CHECKS:
        check(model)


def main(argv=None) -> int:
    """Run the suite over every registered model that provides ``example_model()``."""
    from swathflow.sensormodel import list_sensors
    failed = 0
    for name, cls in list_sensors().items():
        factory = getattr(cls, "example_model", None)
        if factory is None:
            print(f"{name}: SKIP (no example_model())")
            continue
        try:
            check_model(factory())
            print(f"{name}: ok")
        except AssertionError as exc:
            failed += 1
            print(f"{name}: FAIL {exc}")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
