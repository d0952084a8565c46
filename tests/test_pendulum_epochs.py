"""The pendulum's ground_to_image where a POS epoch falls inside a line (a kink of the
condition between two line times): the line is split at the epoch and solved on the
smooth side. The compiled and numpy paths agree, both agree with a fully converged secant
solve and with the image coordinates the ground points were made from, and the secant
fallback is left for lines without a single epoch."""
import numpy as np
import pytest

from test_rectify import scene_model


@pytest.mark.parametrize("case", [0, 1])
def test_lines_holding_an_epoch_are_solved_on_each_side(case, monkeypatch):
    m = scene_model(n_lines=500, n_elements=160, case=case)
    t = m._line_cols[:, 0]
    pos_t = np.asarray(m._trajectory.time, float)
    k = np.searchsorted(pos_t, t[:-1], side="right")
    holds = (k < pos_t.size) & (pos_t[np.minimum(k, pos_t.size - 1)] < t[1:])
    assert 0.05 < holds.mean() < 0.95           # the case has lines with and without epochs
    rng = np.random.default_rng(3)
    j = rng.choice(np.flatnonzero(holds), 3000)
    img = np.stack([j + rng.uniform(0, 1, j.size), rng.uniform(0, m.n_elements - 1, j.size)],
                   -1)
    g = m.image_to_ground(img, 10.0)
    secant = []
    real = m._solve_exact
    monkeypatch.setattr(m, "_solve_exact", lambda *a, **k: secant.append(len(a[0])) or
                        real(*a, **k))
    ref = m._ground_to_image_numpy(g, True)
    assert sum(secant) < 0.01 * j.size          # the split solve, not the secant, for these
    got = m.ground_to_image(g)
    assert np.array_equal(np.isnan(got), np.isnan(ref))
    assert np.nanmax(np.abs(got - ref)) < 1e-8
    conv = m._ground_to_image_converged(g)
    assert np.abs(got - conv).max() < 1e-5
    assert np.abs(got - img).max() < 1e-4
