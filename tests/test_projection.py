"""Bulk projection (SensorModel.projector): one call over every observation of every image,
parameters as vectors, analytic partials checked against numerical ones."""
import numpy as np
import pytest

from swathflow.sensormodel.base import SensorModel
from swathflow.sensormodel.projection import NumericalProjector, projectors
from swathflow.sensors.pendulum.model import PendulumModel
from swathflow.sensors.pendulum.projection import PendulumProjector
from swathflow.testing import check_projector
from numeric_partials import central_partials


class PlainPendulum(PendulumModel):
    """A plugin without the hook: the generic fallback."""

    projector = classmethod(SensorModel.projector.__func__)


def _setup(n=60, seed=0):
    models = [PendulumModel.example_model("L"), PendulumModel.example_model("R")]
    rng = np.random.default_rng(seed)
    img = np.stack([rng.uniform(40, 760, 2 * n), rng.uniform(10, 500, 2 * n)], -1)
    ground = np.concatenate([models[0].image_to_ground(img[:n], 30.0),
                             models[1].image_to_ground(img[n:], 80.0)])
    idx = np.repeat([0, 1], n)
    # each image gets its own vector, away from the one its model was built with
    V = np.stack([m.parameters.vector() for m in models])
    V = V + rng.normal(0, 0.05, V.shape)
    return models, idx, ground, V


def test_pendulum_has_the_hook_and_plain_plugins_fall_back():
    models, *_ = _setup(2)
    assert isinstance(PendulumModel.projector(models), PendulumProjector)
    plain = [PlainPendulum.from_state(m.to_state()) for m in models]
    assert isinstance(PlainPendulum.projector(plain), NumericalProjector)
    groups = projectors(models + plain)
    assert [pos.tolist() for _, pos in groups] == [[0, 1], [2, 3]]


def test_bulk_image_equals_each_models_ground_to_image():
    models, idx, ground, V = _setup()
    out = PendulumModel.projector(models).project(idx, ground, V, partials=False)
    for k, m in enumerate(models):
        want = m.with_vector(V[k]).ground_to_image(ground[idx == k], clip=False)
        assert np.isfinite(want).all()
        np.testing.assert_allclose(out.image[idx == k], want, atol=1e-5)
    # a point the swing never sees is NaN, not an error
    far = ground[:1] + np.array([[5e4, 5e4, 0.0]])
    miss = PendulumModel.projector(models).project([0], far, V, partials=False)
    assert np.isnan(miss.image).all()


def _numerical(models, idx, ground, V, h_par=1e-3, h_g=0.02):
    """Central differences of each model's ground_to_image (rebuilt per step)."""
    return central_partials(models, idx, ground, V, h_par, h_g)


def test_analytic_partials_match_numerical_ones():
    models, idx, ground, V = _setup()
    out = PendulumModel.projector(models).project(idx, ground, V)
    dp, dg = _numerical(models, idx, ground, V)
    # the line times are piecewise linear: at a line centre the derivative has two sides
    line = out.image[:, 0]
    smooth = np.abs(line - np.round(line)) > 0.05
    assert smooth.sum() > 0.8 * idx.size
    scale_p = np.abs(dp[smooth]).max(axis=(0, 1))
    err_p = np.abs(out.d_parameters[smooth] - dp[smooth]).max(axis=(0, 1))
    assert (err_p <= 2e-3 * np.maximum(scale_p, 1.0)).all(), (err_p, scale_p)
    # the other direction's boresight does not act on an image
    names = models[0].parameters.flat_names()
    assert np.all(out.d_parameters[idx == 0][..., names.index("opk_pos_R[0]")] == 0)
    assert np.all(out.d_parameters[idx == 1][..., names.index("opk_pos_L[2]")] == 0)
    err_g = np.abs(out.d_ground[smooth] - dg[smooth]).max()
    assert err_g <= 2e-3 * np.abs(dg).max(), err_g


def test_fallback_agrees_with_the_compiled_hook():
    models, idx, ground, V = _setup(15)
    fast = PendulumModel.projector(models).project(idx, ground, V)
    plain = [PlainPendulum.from_state(m.to_state()) for m in models]
    slow = PlainPendulum.projector(plain).project(idx, ground, V)
    np.testing.assert_allclose(slow.image, fast.image, atol=1e-5)
    line = fast.image[:, 0]
    smooth = np.abs(line - np.round(line)) > 0.05
    scale = np.abs(fast.d_parameters).max()
    assert np.abs(slow.d_parameters[smooth] - fast.d_parameters[smooth]).max() < 1e-3 * scale
    assert np.abs(slow.d_ground[smooth] - fast.d_ground[smooth]).max() < \
        2e-3 * np.abs(fast.d_ground).max()


@pytest.mark.parametrize("direction", ["L", "R"])
def test_contract_check_of_the_hook(direction):
    check_projector(PendulumModel.example_model(direction))


def test_contract_check_catches_a_wrong_partial():
    class Broken(PendulumProjector):
        def project(self, *a, **k):
            out = super().project(*a, **k)
            if out.d_parameters is not None:
                out.d_parameters[..., 0] *= 1.5
            return out

    class BrokenModel(PendulumModel):
        @classmethod
        def projector(cls, models):
            return Broken(models)

    m = PendulumModel.example_model("L")
    with pytest.raises(AssertionError, match="u_gps"):
        check_projector(BrokenModel.from_state(m.to_state()))
