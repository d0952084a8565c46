"""The generic least-squares engine against closed forms and known truth."""
import numpy as np
import pytest
import scipy.sparse as sp

from swathflow.adjustment import AdjustmentError, Problem, RankDeficiencyError, solve
from swathflow.errors import SwathflowError


def _poly(n=200, seed=1, noise=0.5):
    rng = np.random.default_rng(seed)
    t = np.linspace(0, 10, n)
    A = np.stack([np.ones_like(t), t, t ** 2], 1)
    xt = np.array([1.0, -2.0, 0.3])
    return A, xt, A @ xt + rng.normal(0, noise, n)


@pytest.mark.parametrize("sparse", [False, True])
def test_linear_matches_closed_form(sparse):
    A, xt, y = _poly()
    P = Problem(["a", "b", "c"], [0, 0, 0])
    P.add_linear("obs", sp.csr_matrix(A) if sparse else A, y, 0.5)
    s = solve(P, vce=False, scale_covariance=False)
    x_ref = np.linalg.solve(A.T @ A, A.T @ y)
    cov_ref = 0.25 * np.linalg.inv(A.T @ A)
    assert np.allclose(s.x, x_ref, atol=1e-9)
    assert np.allclose(s.cov, cov_ref, rtol=1e-8)
    v = y - A @ x_ref
    assert s.sigma0 == pytest.approx(np.sqrt(v @ v / 0.25 / (len(y) - 3)), rel=1e-8)


@pytest.mark.parametrize("sparse", [False, True])
def test_remaining_is_the_step_not_taken(sparse):
    """With an infinite tolerance no step is taken; ``remaining`` is the step to the
    closed-form solution, and zero for a fixed unknown."""
    A, xt, y = _poly()
    x0 = np.array([1.0, -2.0, 0.5])
    P = Problem(["a", "b", "c"], x0)
    P.add_linear("obs", sp.csr_matrix(A) if sparse else A, y, 0.5)
    s = solve(P, vce=False, tol=np.inf)
    assert np.array_equal(s.x, x0) and s.converged
    assert np.allclose(s.remaining, np.linalg.solve(A.T @ A, A.T @ y) - x0, atol=1e-9)
    P.fix(["c"])
    s = solve(P, vce=False, tol=np.inf)
    Af = A[:, :2]
    ref = np.linalg.solve(Af.T @ Af, Af.T @ (y - A @ x0))
    assert np.allclose(s.remaining[:2], ref, atol=1e-9) and s.remaining[2] == 0.0
    # at convergence what remains is below the tolerance
    s = solve(P, vce=False, tol=1e-6)
    assert s.converged and np.abs(s.remaining).max() < 1e-6


def test_uncounted_prior_leaves_sigma0_alone():
    """A weak regularising prior (counted=False) adds nothing to the redundancy: sigma0
    stays the closed form's; counted, its near-zero residuals would deflate sigma0."""
    A, xt, y = _poly(n=20)
    v = y - A @ np.linalg.solve(A.T @ A, A.T @ y)
    s0 = np.sqrt(v @ v / 0.25 / (len(y) - 3))
    out = {}
    for counted in (False, True):
        P = Problem(["a", "b", "c"], [0, 0, 0])
        P.add_linear("obs", A, y, 0.5)
        P.add_priors([0, 0, 0], 1e6, name="weak", counted=counted)
        out[counted] = solve(P, vce=False)
    assert out[False].sigma0 == pytest.approx(s0, rel=1e-6)
    # asked to estimate every component, the weak prior's is left alone
    P = Problem(["a", "b", "c"], [0, 0, 0])
    P.add_linear("obs", A, y, 0.5)
    P.add_priors([0, 0, 0], 1e6, name="weak", counted=False)
    c = solve(P, vce=True).components
    assert c["obs"]["estimated"] and not c["weak"]["estimated"] and c["weak"]["s2"] == 1.0
    assert out[True].sigma0 < 0.95 * s0      # sqrt(17 / 20): 3 redundancy, no residual


def test_prior_gives_weighted_mean():
    # one unknown, three observations of sigma 2 and a prior 10 +- 1: weighted mean
    P = Problem(["x"], [0.0])
    P.add_linear("obs", np.ones((3, 1)), [4.0, 5.0, 6.0], 2.0)
    P.add_priors([10.0], [1.0])
    s = solve(P, vce=False, scale_covariance=False)
    w = np.array([0.25, 0.25, 0.25, 1.0])
    val = np.array([4, 5, 6, 10.0])
    assert s.x[0] == pytest.approx((w @ val) / w.sum())
    assert s.sigma[0] == pytest.approx(1 / np.sqrt(w.sum()))


def test_fixed_unknown_keeps_value():
    A, xt, y = _poly()
    P = Problem(["a", "b", "c"], [1.0, 0, 0])
    P.fix(["a"])
    P.add_linear("obs", A, y, 0.5)
    s = solve(P, vce=False)
    ref = np.linalg.lstsq(A[:, 1:], y - A[:, 0] * 1.0, rcond=None)[0]
    assert s.x[0] == 1.0 and s.sigma[0] == 0.0
    assert np.allclose(s.x[1:], ref, atol=1e-9)


@pytest.mark.parametrize("sparse", [False, True])
def test_hard_constraint_lagrange(sparse):
    # minimise |A x - y|^2 subject to x0 + x1 + x2 = 1: closed-form KKT solution
    A, xt, y = _poly()
    C = np.array([[1.0, 1.0, 1.0]])
    P = Problem(["a", "b", "c"], [0, 0, 0])
    P.add_linear("obs", sp.csr_matrix(A) if sparse else A, y, 1.0)
    P.add_constraint(C, [1.0])
    s = solve(P, vce=False, scale_covariance=False)
    K = np.block([[A.T @ A, C.T], [C, np.zeros((1, 1))]])
    ref = np.linalg.solve(K, np.concatenate([A.T @ y, [1.0]]))[:3]
    assert np.allclose(s.x, ref, atol=1e-8)
    assert s.x.sum() == pytest.approx(1.0, abs=1e-10)
    # the constrained covariance gives zero variance along the constraint
    assert abs(C @ s.cov @ C.T)[0, 0] < 1e-10


def test_variance_components_recover_two_noise_levels():
    rng = np.random.default_rng(3)
    n = 3000
    t = rng.uniform(-1, 1, n)
    A = np.stack([np.ones(n), t], 1)
    x = np.array([2.0, -1.0])
    y1 = A @ x + rng.normal(0, 0.5, n)
    y2 = A @ x + rng.normal(0, 2.0, n)
    P = Problem(["a", "b"], [0, 0])
    P.add_linear("g1", A, y1, 1.0)     # a-priori sigmas both wrong
    P.add_linear("g2", A, y2, 1.0)
    s = solve(P, vce=True)
    assert s.components["g1"]["sigma_factor"] == pytest.approx(0.5, rel=0.05)
    assert s.components["g2"]["sigma_factor"] == pytest.approx(2.0, rel=0.05)
    assert s.sigma0 == pytest.approx(1.0, abs=0.01)


def test_robust_flags_gross_errors_by_name():
    A, xt, y = _poly(n=300, seed=5)
    bad = np.arange(0, 300, 10)                  # 10 %
    rng = np.random.default_rng(9)
    y = y.copy()
    y[bad] += rng.choice([-1, 1], bad.size) * rng.uniform(10, 25, bad.size)
    P = Problem(["a", "b", "c"], [0, 0, 0])
    names = [f"p{i}" for i in range(300)]
    P.add_linear("obs", A, y, 0.5, robust=True, point_names=names)
    s = solve(P, vce=True, robust=True)
    flagged = {r["name"] for r in s.rejected}
    assert {f"p{i}" for i in bad} <= flagged
    assert len(flagged - {f"p{i}" for i in bad}) <= 2
    assert np.all(np.abs(s.x - xt) < 3 * s.sigma)


def _shift_scale_points(blunders: dict, robust=True, n: int = 200):
    """2-D points observed as ``s * u + t`` (unknowns tx, ty, s) with 0.01 noise and the
    given blunders ``{point: (dx, dy)}``; returns the problem and the truth."""
    rng = np.random.default_rng(4)
    u = rng.uniform(-1, 1, (n, 2))
    truth = np.array([0.3, -0.2, 1.5])
    obs = truth[2] * u + truth[:2] + rng.normal(0, 0.01, (n, 2))
    for p, d in blunders.items():
        obs[p] += d

    def fn(x, jacobian=True):
        J = np.zeros((n, 2, 3))
        J[:, 0, 0] = 1
        J[:, 1, 1] = 1
        J[:, :, 2] = u
        return (obs - (x[2] * u + x[:2])).ravel(), J.reshape(-1, 3) if jacobian else None

    P = Problem(["tx", "ty", "s"], [0, 0, 1])
    P.add_observations("pts", fn, np.full(2 * n, 0.01), point=np.repeat(np.arange(n), 2),
                       point_names=[f"P{i}" for i in range(n)], robust=robust)
    return P, truth


def test_snooping_2d_points():
    # 2-D points (x, y observations of one point) are tested and rejected together
    P, truth = _shift_scale_points({7: (0.2, -0.15)})
    s = solve(P, vce=False, robust=True)
    assert [r["name"] for r in s.rejected] == ["P7"]
    assert np.all(np.abs(s.x - truth) < 3 * s.sigma)


def test_per_point_robust_flags_protect_points_from_rejection():
    """robust may be one flag per point: a blunder on a protected point stays in, a blunder
    on an unprotected one is rejected."""
    robust = np.ones(200, bool)
    robust[11] = False
    P, _ = _shift_scale_points({7: (0.2, -0.15), 11: (-0.2, 0.2)}, robust=robust)
    s = solve(P, vce=False, robust=True)
    assert [r["name"] for r in s.rejected] == ["P7"]


def test_nonlinear_far_start_converges():
    rng = np.random.default_rng(2)
    t = np.linspace(0, 4, 80)
    truth = np.array([3.0, -0.7])
    y = truth[0] * np.exp(truth[1] * t) + rng.normal(0, 0.01, t.size)

    def fn(x, jacobian=True):
        e = np.exp(x[1] * t)
        return y - x[0] * e, (np.stack([e, x[0] * t * e], 1) if jacobian else None)

    P = Problem(["a", "k"], [10.0, 0.5])
    P.add_observations("y", fn, np.full(t.size, 0.01))
    s = solve(P, vce=False)
    assert s.converged
    assert np.all(np.abs(s.x - truth) < 4 * s.sigma)


def test_rank_deficiency_names_unknowns():
    # only a + b is observed: a clear error naming both, not a LinAlgError traceback
    P = Problem(["a", "b", "c"], [0, 0, 0])
    A = np.array([[1.0, 1.0, 0.0], [1.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    P.add_linear("obs", A, [1.0, 1.1, 2.0], 0.1)
    with pytest.raises(RankDeficiencyError) as e:
        solve(P, vce=False)
    assert isinstance(e.value, SwathflowError)
    d = e.value.directions[0]
    assert set(d) == {"a", "b"} and d["a"] == -d["b"]
    # a prior on one of them resolves it
    P.add_priors([0.5, np.inf, np.inf], [0.1, np.inf, np.inf])
    s = solve(P, vce=False)
    assert s.x[0] + s.x[1] == pytest.approx(1.05, abs=1e-9)


def test_sparse_many_unknowns_chain():
    # a levelling-like chain: 400 unknown heights, differences observed, first one fixed
    n = 400
    rng = np.random.default_rng(6)
    h = np.cumsum(rng.normal(0, 1, n))
    rows = np.repeat(np.arange(n - 1), 2)
    cols = np.stack([np.arange(n - 1), np.arange(1, n)], 1).ravel()
    vals = np.tile([-1.0, 1.0], n - 1)
    A = sp.csr_matrix((vals, (rows, cols)), shape=(n - 1, n))
    d = A @ h + rng.normal(0, 0.01, n - 1)
    x0 = np.zeros(n)
    x0[0] = h[0]
    P = Problem([f"h{i}" for i in range(n)], x0)
    P.fix(["h0"])
    P.add_linear("dh", A, d, 0.01)
    s = solve(P, vce=False, scale_covariance=False)
    # closed form: heights are cumulative sums, variance grows linearly along the chain
    assert np.allclose(s.x, h[0] + np.concatenate([[0], np.cumsum(d)]), atol=1e-9)
    assert s.sigma[-1] == pytest.approx(0.01 * np.sqrt(n - 1), rel=1e-6)


def test_bad_input_errors():
    P = Problem(["a"], [0.0])
    with pytest.raises(AdjustmentError):
        solve(P)
    with pytest.raises(AdjustmentError):
        P.add_linear("x", np.ones((2, 2)), [1, 2], 1.0)
    with pytest.raises(AdjustmentError):
        P.add_linear("x", np.ones((2, 1)), [1, 2], 0.0)
