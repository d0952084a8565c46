"""Point unknowns eliminated block by block (Schur complement) give the same adjustment as
the full normal equations: estimates, covariance, redundancy, variance components, the
points data snooping rejects; and the truth is recovered."""
import numpy as np
import pytest
import scipy.sparse as sp

from swathflow.adjustment import Problem, RankDeficiencyError, solve

NC = 5


def _problem(seed=0, n_pts=40, blunder=True, eliminate=True, constraint=False):
    """Five shared 'camera' unknowns and three coordinates per point, seen by three views
    with known parallax factors; 8 points have priors (control)."""
    rng = np.random.default_rng(seed)
    cam = np.array([0.02, -0.5, -0.01, 0.3, 0.05])
    pts = rng.uniform(-10, 10, (n_pts, 3))
    kx, ky = np.array([-0.4, 0.0, 0.4]), np.array([0.3, -0.2, 0.1])
    n = NC + 3 * n_pts

    def model(x):
        c, p = x[:NC], x[NC:].reshape(-1, 3)
        y1 = (p[:, None, 0] + kx * p[:, None, 2]) * (1 + c[0]) + c[1]
        y2 = (p[:, None, 1] + ky * p[:, None, 2]) * (1 + c[2]) + c[3] + c[4] * p[:, None, 0]
        return np.stack([y1, y2], -1)                        # (P, 3 views, 2)

    sigma = 0.01
    truth = np.concatenate([cam, pts.ravel()])
    obs = model(truth) + rng.normal(0, sigma, (n_pts, 3, 2))
    if blunder:
        obs[7, 1, 0] += 0.5
    m = obs.size

    def fn(x, jacobian=True):
        r = (obs - model(x)).ravel()
        if not jacobian:
            return r, None
        c, p = x[:NC], x[NC:].reshape(-1, 3)
        one = np.ones((n_pts, 3))
        col = NC + 3 * np.arange(n_pts)[:, None] * one
        zero = 0 * one
        # per (point, view): row 0 (y1) and row 1 (y2) entries as (column, value)
        e1 = [(zero, p[:, None, 0] + kx * p[:, None, 2]), (zero + 1, one),
              (col, (1 + c[0]) * one), (col + 2, kx * (1 + c[0]) * one)]
        e2 = [(zero + 2, p[:, None, 1] + ky * p[:, None, 2]), (zero + 3, one),
              (zero + 4, p[:, None, 0] * one), (col + 1, (1 + c[2]) * one),
              (col + 2, ky * (1 + c[2]) * one), (col, c[4] * one)]
        base = 2 * (3 * np.arange(n_pts)[:, None] + np.arange(3))
        rows = np.concatenate([np.ravel(base + 0 * v) for _, v in e1]
                              + [np.ravel(base + 1 + 0 * v) for _, v in e2])
        cols = np.concatenate([np.ravel(cc) for cc, _ in e1 + e2]).astype(int)
        vals = np.concatenate([np.ravel(v) for _, v in e1 + e2])
        J = sp.csr_matrix((vals, (rows, cols)), shape=(m, n))
        return r, J

    x0 = np.concatenate([np.zeros(NC), (pts + rng.normal(0, 0.3, pts.shape)).ravel()])
    P = Problem([f"c{i}" for i in range(NC)] + [f"p{i}.{a}" for i in range(n_pts)
                                                for a in "xyz"], x0)
    P.add_observations("image", fn, np.full(m, sigma),
                       component=np.tile(["y1", "y2"], m // 2).astype(object),
                       point=np.repeat(np.arange(n_pts), 6))
    ctrl = np.zeros(n)
    ctrl_sig = np.full(n, np.inf)
    for i in range(8):
        ctrl[NC + 3 * i:NC + 3 * i + 3] = pts[i] + rng.normal(0, 0.005, 3)
        ctrl_sig[NC + 3 * i:NC + 3 * i + 3] = 0.005
    P.add_priors(ctrl, ctrl_sig, name="control")
    if constraint:
        A = np.zeros((1, n))
        A[0, 0], A[0, 2] = 1.0, -1.0
        P.add_constraint(A, [0.03])
    if eliminate:
        P.eliminate(np.arange(NC, n).reshape(-1, 3))
    return P, truth


@pytest.mark.parametrize("constraint", [False, True])
def test_schur_equals_full_normal_equations(constraint):
    kw = dict(vce=True, robust=True)
    a = solve(_problem(n_pts=16, constraint=constraint)[0], **kw)
    b = solve(_problem(n_pts=16, eliminate=False, constraint=constraint)[0], **kw)
    assert a.converged and b.converged
    np.testing.assert_allclose(a.x, b.x, atol=1e-8)
    np.testing.assert_allclose(a.cov, b.cov, atol=1e-10, rtol=1e-6)
    assert a.redundancy == pytest.approx(b.redundancy, rel=1e-8)
    assert a.sigma0 == pytest.approx(b.sigma0, rel=1e-8)
    for k in a.components:
        assert a.components[k]["s2"] == pytest.approx(b.components[k]["s2"], rel=1e-6)
    assert [r["point"] for r in a.rejected] == [r["point"] for r in b.rejected]
    np.testing.assert_allclose(np.nan_to_num(a.normalized["image"]),
                               np.nan_to_num(b.normalized["image"]), atol=1e-6)


def test_schur_constraints_with_fixed_unknowns_before_them():
    """A fixed unknown shifts the free unknowns' positions: the constraint still acts on
    its own unknowns (c0 - c2 = 0.03 exactly) and both paths agree."""
    out = []
    for eliminate in (True, False):
        P, _ = _problem(n_pts=16, blunder=False, eliminate=eliminate, constraint=True)
        P.fix(["c1"])
        out.append(solve(P, vce=False, robust=False))
    a, b = out
    assert a.x[0] - a.x[2] == pytest.approx(0.03, abs=1e-12)
    np.testing.assert_allclose(a.x, b.x, atol=1e-8)
    np.testing.assert_allclose(a.cov, b.cov, atol=1e-10, rtol=1e-6)


def test_schur_recovers_the_truth_and_rejects_the_blunder():
    P, truth = _problem(seed=3)
    sol = solve(P, vce=True, robust=True)
    assert [r["point"] for r in sol.rejected] == [7]
    z = (sol.x - truth) / sol.sigma
    assert np.abs(z[:NC]).max() < 4
    assert np.mean(z ** 2) < 2.0
    assert sol.iterations <= 15


def test_large_problem_keeps_sparse_covariance():
    P, truth = _problem(seed=1, n_pts=1500, blunder=False)
    sol = solve(P, vce=False, robust=False, max_dense_cov=2000)
    assert sp.issparse(sol.cov)
    d = sol.x[:NC] - truth[:NC]
    nees = d @ np.linalg.solve(sol.cov[:NC, :NC].toarray(), d)
    assert nees < 20.5                     # chi-square, 5 dof, 99.9 %
    z = (sol.x - truth) / sol.sigma
    assert np.mean(z[NC:] ** 2) < 3.0      # correlated through the camera unknowns


def test_undetermined_point_is_named():
    P, _ = _problem(n_pts=10, blunder=False)
    # a point only seen by observations that do not involve its z: impossible here, so
    # give a point no observations at all (weights zero by rejection is not possible):
    # drop the image group and keep priors on 8 points only
    P.groups = [g for g in P.groups if g.name != "image"]
    with pytest.raises(RankDeficiencyError, match="point"):
        solve(P, vce=False)
