"""The compiled ground_to_image of the pendulum model (numba brackets over the per-line
planes and the compiled refinement) against an independent brute-force reference: every
line's plane evaluated for every point, the sign change picked by hand, then the numpy
refinement; and against the image coordinates the ground points were made from."""
import numpy as np
import pytest

from swathflow.sensors.pendulum import PendulumModel, model as pendulum_model


@pytest.fixture(scope="module", params=["L", "R"])
def model(request):
    return PendulumModel.example_model(direction=request.param, n_lines=600)


def _points(m, n=300, seed=5):
    """Ground points of known image coordinates, then a third of them pushed off the image
    (along or across track), so some are swept by no line or fall off the detector."""
    rng = np.random.default_rng(seed)
    img = np.stack([rng.uniform(0, m.n_lines - 1, n), rng.uniform(0, m.n_elements - 1, n)],
                   -1)
    g = m.image_to_ground(img, 10.0)
    off = rng.random(n) < 1 / 3
    g_off = g.copy()
    g_off[off] += rng.normal(0.0, 400.0, (off.sum(), 3)) * [1, 1, 0.1]
    return img, g, g_off, off


def _brute_force(m, g, clip=True):
    """Every line's plane for every point; the (single) sign change; numpy refinement."""
    pl = m._planes
    f = g[:, 0:1] * pl[:, 0] + g[:, 1:2] * pl[:, 1] + g[:, 2:3] * pl[:, 2] + pl[:, 3]
    change = np.signbit(f[:, 1:]) != np.signbit(f[:, :-1])
    assert change.sum(axis=1).max() <= 1      # one crossing a point: the bracket is unique
    found = change.any(axis=1)
    j = np.argmax(change, axis=1)
    rows = np.arange(g.shape[0])
    out = np.full((g.shape[0], 2), np.nan)
    k = np.flatnonzero(found)
    line, cam = m._refine(g[k], j[k], f[rows, j][k], f[rows, j + 1][k])
    out[k] = m._pixels(line, cam, clip)
    return out


def test_compiled_matches_brute_force_on_and_off_image(model):
    img, g, g_off, off = _points(model)
    for pts in (g, g_off):
        got = model.ground_to_image(pts)
        ref = _brute_force(model, pts)
        assert np.array_equal(np.isnan(got), np.isnan(ref))
        assert np.nanmax(np.abs(got - ref)) < 1e-9
    got = model.ground_to_image(g_off, clip=False)
    ref = _brute_force(model, g_off, clip=False)
    assert np.array_equal(np.isnan(got), np.isnan(ref))
    assert np.nanmax(np.abs(got - ref)) < 1e-9


def test_compiled_recovers_the_image_coordinates(model):
    img, g, g_off, off = _points(model)
    got = model.ground_to_image(g)
    assert not np.isnan(got).any()
    assert np.abs(got - img).max() < 1e-6
    got_off = model.ground_to_image(g_off)
    moved = np.isnan(got_off).any(axis=1)
    assert moved.sum() > 20                   # many pushed points are off the image ...
    assert not moved[~off].any()              # ... and no untouched point is
    inside = ~np.isnan(got_off).any(axis=1)
    assert np.all((got_off[inside, 0] >= 0) & (got_off[inside, 0] <= model.n_lines - 1))
    assert np.all(np.abs(got_off[inside, 1] - model.n_elements / 2 + 0.5)
                  <= model.n_elements / 2)


def test_compiled_agrees_with_numpy_path(model):
    """Same brackets and refinement; the only difference is rounding of the plane values
    at ECEF magnitudes (a BLAS product in the numpy path), far below 1e-6 px."""
    img, g, g_off, off = _points(model, n=2000, seed=9)
    for pts in (g, g_off):
        got = model.ground_to_image(pts)
        ref = model._ground_to_image_numpy(pts, True)
        assert np.array_equal(np.isnan(got), np.isnan(ref))
        assert np.nanmax(np.abs(got - ref)) < 1e-7


@pytest.mark.parametrize("case", [0, 1])
def test_compiled_exact_solve_matches_brute_force(case, monkeypatch):
    """Every point through the exact secant solve (the path taken where a POS sample puts a
    kink inside the line: a fifth of the points on the demo mission), on the spec vectors'
    trajectory, against the brute-force brackets and the numpy secant solve."""
    from test_rectify import scene_model
    m = scene_model(n_lines=500, n_elements=160, case=case)
    monkeypatch.setattr(pendulum_model, "ROUGH_LINE", -1.0)      # every point is "rough"
    img, g, g_off, off = _points(m, seed=11)
    for pts in (g, g_off):
        got = m.ground_to_image(pts)
        ref = _brute_force(m, pts)
        assert np.array_equal(np.isnan(got), np.isnan(ref))
        # both stop when a secant step is below 1e-9 line
        assert np.nanmax(np.abs(got - ref)) < 1e-8
    assert np.abs(m.ground_to_image(g) - img).max() < 1e-5


def test_one_chunk_and_many_chunks_agree_to_the_bit(model, monkeypatch):
    """A call of one chunk goes straight to the kernel; several chunks are stitched: the
    same values either way (per point), and NaN where the points are NaN."""
    img, g, g_off, off = _points(model, n=250)
    g_off[::7] = np.nan
    whole = model.ground_to_image(g_off, clip=False)
    monkeypatch.setattr(pendulum_model, "CHUNK", 64)
    parts = model.ground_to_image(g_off, clip=False)
    assert whole.tobytes() == parts.tobytes()
    assert np.isnan(whole[::7]).all()
    assert model.ground_to_image(g_off[:0]).shape == (0, 2)
    assert model.ground_to_image(g_off[:12].reshape(3, 4, 3)).shape == (3, 4, 2)


def test_kernel_arguments_belong_to_their_model(model):
    """The kernel's arguments are made once per model: a copy with other parameters
    (made after the first has been used) gets its own."""
    img, g, g_off, off = _points(model, n=50)
    before = model.ground_to_image(g)
    moved = model.with_parameters(opk_sen=[0.03, -0.47, 0.5])
    fresh = PendulumModel.build(model.sensor, model.lines, model.trajectory,
                                moved.parameters, direction=model.direction)
    got = moved.ground_to_image(g)
    assert got.tobytes() == fresh.ground_to_image(g).tobytes()
    assert np.nanmax(np.abs(got - before)) > 0.01          # the copy moved the points
    assert model.ground_to_image(g).tobytes() == before.tobytes()


def test_kernel_loop_counts_no_references():
    """The per-point loop is compiled without reference counting: with it, the arrays
    handed to the inlined helpers were counted in and out (atomically) at every point,
    2/3 of the kernel's time on the demo."""
    from swathflow.sensors.pendulum import kernel
    assert kernel._g2i.targetoptions["_nrt"] is False


def test_ray_loop_counts_no_references():
    """image_to_ground's compiled rays and DEM intersection: no reference counting in
    their per-ray loops (the same reason as the kernel's above)."""
    from swathflow.geometry import march
    from swathflow.sensors.pendulum import kernel
    for f in (kernel._rays, march.hits, march._one_ray, march._march_piece,
              march._may_graze, march._refine):
        assert f.targetoptions["_nrt"] is False, f.py_func.__name__
