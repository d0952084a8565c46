"""The push-broom camera's bulk projection (PushbroomModel.projector): one compiled call over
every observation of every image, the parameters as vectors, analytic partials checked
against central differences of each image's own ground_to_image (a model rebuilt per step);
the generic fallback for a plugin without the hook (a push-broom subclass and the
rotating-mirror plugin); the full push-broom preset calibrated against the simulator's truth.
"""
import json
import sys
from pathlib import Path

import numpy as np
import pytest

from swathflow.sensormodel.base import SensorModel
from swathflow.sensormodel.projection import NumericalProjector
from swathflow.sensors.pushbroom.model import PushbroomModel
from swathflow.sensors.pushbroom.projection import PushbroomProjector
from swathflow.testing import check_projector
from numeric_partials import central_partials

ROOT = Path(__file__).resolve().parents[1]


class PlainPushbroom(PushbroomModel):
    """A plugin without the hook: the generic fallback."""

    projector = classmethod(SensorModel.projector.__func__)


def _setup(n=25, seed=0):
    """Three images (the three lines), points seen in each, and per image a parameter
    vector away from the one its model was built with (APs, boresight, lever arm, fixes)."""
    models = [PushbroomModel.example_model(v, n_lines=400)
              for v in ("forward", "nadir", "backward")]
    rng = np.random.default_rng(seed)
    ground, idx = [], []
    for k, m in enumerate(models):
        img = np.stack([rng.uniform(30, 370, n), rng.uniform(50, 3020, n)], -1)
        ground.append(m.image_to_ground(img, rng.uniform(0, 80)))
        idx.append(np.full(n, k))
    steps = models[0].fd_step_sizes()
    V = np.stack([m.parameters.vector() for m in models])
    V = V + 30 * steps * rng.normal(0, 1, V.shape)
    return models, np.concatenate(idx), np.concatenate(ground), V


def test_pushbroom_has_the_hook_and_a_plain_subclass_falls_back():
    models, *_ = _setup(2)
    assert isinstance(PushbroomModel.projector(models), PushbroomProjector)
    plain = [PlainPushbroom.from_state(m.to_state()) for m in models]
    assert isinstance(PlainPushbroom.projector(plain), NumericalProjector)


def test_bulk_image_equals_each_models_ground_to_image():
    models, idx, ground, V = _setup()
    proj = PushbroomModel.projector(models)
    out = proj.project(idx, ground, V, partials=False)
    for k, m in enumerate(models):
        want = m.with_vector(V[k]).ground_to_image(ground[idx == k], clip=False)
        assert np.isfinite(want).all()
        np.testing.assert_allclose(out.image[idx == k], want, atol=1e-5)
    # started from the answer it gives the answer; started far off it still finds it
    again = proj.project(idx, ground, V, partials=False, start=out.image + [40.0, -300.0])
    np.testing.assert_allclose(again.image, out.image, atol=1e-6)
    # a point the image never sees is NaN, not an error
    far = ground[:1] + np.array([[5e4, 5e4, 0.0]])
    assert np.isnan(proj.project([0], far, V, partials=False).image).all()


def _numerical(models, idx, ground, V, h_g=0.01):
    """Central differences of each model's ground_to_image, the model rebuilt per step."""
    return central_partials(models, idx, ground, V, models[0].fd_step_sizes(), h_g)


def test_analytic_partials_match_numerical_ones():
    models, idx, ground, V = _setup(12)
    out = PushbroomModel.projector(models).project(idx, ground, V)
    dp, dg = _numerical(models, idx, ground, V)
    names = models[0].parameters.flat_names()
    scale = np.abs(dp).max(axis=(0, 1))                  # per parameter
    err = np.abs(out.d_parameters - dp).max(axis=(0, 1))
    acts = scale > 0
    assert acts.sum() > 0.9 * len(names)                  # the fixes' and views' columns act
    bad = [(names[i], err[i], scale[i]) for i in range(len(names))
           if err[i] > 2e-3 * scale[i] + 1e-9]
    assert not bad, bad
    # an image does not depend on the other lines' APs: exact zeros there
    for k, m in enumerate(models):
        other = [i for i, nm in enumerate(names) if nm.startswith(("ax_", "bx_"))
                 and f"_{m.view}_" not in nm]
        assert np.all(out.d_parameters[idx == k][..., other] == 0)
    assert np.abs(out.d_ground - dg).max() <= 2e-3 * np.abs(dg).max()


def test_fallback_agrees_with_the_compiled_hook():
    models, idx, ground, V = _setup(6)
    fast = PushbroomModel.projector(models).project(idx, ground, V)
    plain = [PlainPushbroom.from_state(m.to_state()) for m in models]
    slow = PlainPushbroom.projector(plain).project(idx, ground, V)
    np.testing.assert_allclose(slow.image, fast.image, atol=1e-5)
    scale = np.abs(fast.d_parameters).max(axis=(0, 1))
    assert (np.abs(slow.d_parameters - fast.d_parameters).max(axis=(0, 1))
            <= 2e-3 * scale + 1e-12).all()
    assert np.abs(slow.d_ground - fast.d_ground).max() < 2e-3 * np.abs(fast.d_ground).max()


@pytest.mark.parametrize("view", ["forward", "nadir", "backward"])
def test_contract_check_of_the_hook(view):
    check_projector(PushbroomModel.example_model(view))


def test_contract_check_catches_a_wrong_partial():
    class Broken(PushbroomProjector):
        def project(self, *a, **k):
            out = super().project(*a, **k)
            if out.d_parameters is not None:
                names = self.models[0].parameters.flat_names()
                out.d_parameters[..., names.index("d_opk_1[1]")] *= 1.5
            return out

    class BrokenModel(PushbroomModel):
        @classmethod
        def projector(cls, models):
            return Broken(models)

    m = PushbroomModel.example_model("nadir")
    with pytest.raises(AssertionError, match=r"d_opk_1\[1\]"):
        check_projector(BrokenModel.from_state(m.to_state()))


def test_plugin_without_the_hook_goes_through_the_generic_fallback():
    sys.path.insert(0, str(ROOT / "plugins" / "rotating-mirror"))
    from swathflow_rotating_mirror.model import RotatingMirrorModel
    m = RotatingMirrorModel.example_model()
    assert isinstance(RotatingMirrorModel.projector([m]), NumericalProjector)
    check_projector(m)


@pytest.mark.slow
def test_full_preset_calibrates_every_parameter_within_3_sigma(tmp_path):
    """The full push-broom preset (114 parameters: three lines of three segments, six fixes)
    calibrated to the end; every parameter within 3 sigma of the simulator's truth."""
    from swathflow.ingest.mission import load_mission
    from swathflow.sensors.pushbroom.calibration import calibrate_pushbroom, mission_ties
    from swathflow.sensors.pushbroom.simulate import simulate
    path = tmp_path / "m"
    simulate(path, "pushbroom", seed=4, gcp_noise=0.3, tie_noise=0.3, render=False,
             write_ortho=False)
    m = load_mission(path)
    models = {i: m.model(i) for i in m.image_ids}
    res = calibrate_pushbroom(models, m.gcps, mission_ties(m), m.priors, robust=True,
                              vce=True, obs_sigma_px=0.3)
    assert res.values.size == 114
    assert res.solution.converged
    truth = json.loads((path / "truth" / "truth.json").read_text())["parameters"]
    tv = np.concatenate([truth[b.name] for b in res.parameters.blocks])
    z = np.abs(res.values - tv) / res.sigmas
    assert np.all(res.sigmas > 0)
    assert np.all(z < 3.0), sorted(zip(z, res.names))[-5:]
