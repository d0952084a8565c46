"""Solving the push-broom calibration problem: ``joint`` (everything at once) and the
paper's iterative ``two-step`` scheme (exterior, then interior, with Anderson acceleration,
until the joint Gauss-Newton step is below a fraction of a joint sigma)."""
from __future__ import annotations

import math

import numpy as np
import scipy.sparse as sp
from threadpoolctl import threadpool_limits

from swathflow.adjustment import RankDeficiencyError, solve
from swathflow.calibration.unknowns import CalibrationError
from swathflow.sensors.pushbroom.calibration.problem import Setup


def _vce(vce):
    return ["x", "y", "tie x", "tie y"] if vce else False


def _run(P, vce, robust, alpha, tol=None, max_iter=50, damping=True, covariance=True):
    # convergence: the step's length in sigma units (sqrt(dx' N dx)) below 1 % of a sigma
    # per unknown; the model's piecewise-linear POS interpolation puts a floor under it
    tol = 1e-2 * math.sqrt(max(int((~P.fixed).sum()), 1)) if tol is None else tol
    try:
        # no covariance: the engine forms none above max_dense_cov unknowns
        extra = {} if covariance else {"max_dense_cov": 0}
        # one BLAS thread: the reduced systems are a few hundred unknowns, where OpenBLAS's
        # threads only wait on each other (measured 80x slower on a busy 2-core machine)
        with threadpool_limits(1, user_api="blas"):
            return solve(P, vce=_vce(vce), robust=robust, alpha=alpha, sparse=True, tol=tol,
                         max_iter=max_iter, damping=damping, **extra)
    except RankDeficiencyError as exc:
        raise CalibrationError(
            f"the observations cannot determine the parameters: {exc}. Add control or tie "
            f"points (spread across the CCD lines and along the strips), give finite prior "
            f"sigmas, or fix parameters (--fix NAME)") from None


def solve_joint(st: Setup, z0, free, *, vce, robust, alpha, obs_sigma, tie_sigma):
    P = st.problem(z0, free, obs_sigma, tie_sigma)
    return _run(P, vce, robust, alpha), P


def solve_two_step(st: Setup, z0, free, *, vce, alpha, obs_sigma, tie_sigma,
                   max_rounds: int = 50, gap_sigma: float = 0.1, step_iter: int = 2,
                   accelerate: int = 10):
    """The paper's iterative scheme; returns (Solution at the two-step solution with the
    joint covariance, rounds history, converged).

    A round is the exterior step (lever arm, boresight, fix corrections and tie points with
    the APs held) then the interior step (APs and tie points with the exterior held), each
    ``step_iter`` Gauss-Newton iterations with the a-priori weights (damped in the first
    round only, so that a round is a smooth map).

    Stopping: after every round the joint normal equations are formed at the current
    values and their Gauss-Newton step is computed but not taken; the rounds stop when no
    parameter of that step exceeds ``gap_sigma`` of its joint sigma (the two-step solution
    is then that close to the joint optimum, to first order). A test on the change per
    round does not work here: the blocks are so correlated (boresight and AP offsets,
    conditional sigmas 1/200 of the joint ones) that the plain alternation moves by
    0.004 conditional sigma per round while still 1.3 joint sigma away.

    ``accelerate`` > 0 extrapolates over the last that many rounds (Anderson acceleration
    of the round as a fixed-point map; each round is still the paper's two steps);
    0 gives the plain alternation (on the two-strip test mission still 1 joint sigma away
    after 45 rounds).
    Variance components, when asked for, are estimated once at the end."""
    z = z0.copy()
    ext = free & ~st.ap_mask
    inn = free & st.ap_mask
    idx = np.flatnonzero(free)
    rounds = []
    Xh, Fh = [], []                   # Anderson history: round inputs and changes (free)
    wts = None
    prev_norm = np.inf
    converged = False
    final = joint_sig = None
    best = None                       # (gap, solution) of the round closest to the optimum
    for r in range(max_rounds):
        zin = z.copy()
        sig = np.ones(st.n_par)
        for blk in (ext, inn):
            if not blk.any():
                continue
            # a tiny tolerance: a sub-step is always taken (a larger one stalls the rounds)
            # (conditional sigmas, for the extrapolation's scaling, in the first round only)
            sol = _run(st.problem(z, blk, obs_sigma, tie_sigma), False, False, alpha,
                       tol=1e-9, max_iter=step_iter, damping=r == 0, covariance=r == 0)
            z = sol.x.copy()
            sig[blk] = sol.sigma[:st.n_par][blk]
        if wts is None:
            wts = 1.0 / np.maximum(sig[idx], 1e-12)
        f = (z[idx] - zin[idx]) * wts          # the round's change, in conditional sigmas
        gap, final, joint_sig = _gap(st, z, free, obs_sigma, tie_sigma, alpha, joint_sig)
        rounds.append({"round": r + 1, "gap_sigma": gap,
                       "max_change_sigma": float(np.max(np.abs(f))) if idx.size else 0.0,
                       "sigma0": final.sigma0})
        if best is None or gap < best[0]:
            best = (gap, final)
        if gap < gap_sigma:
            converged = True
            break
        if not accelerate:
            continue
        norm = float(np.linalg.norm(f))
        if norm > 10 * prev_norm:              # extrapolation overshot: restart
            Xh, Fh = [], []
        prev_norm = norm
        Xh.append(zin[idx] * wts)
        Fh.append(f)
        Xh, Fh = Xh[-(accelerate + 1):], Fh[-(accelerate + 1):]
        if len(Fh) < 2:
            continue
        dF = np.diff(np.array(Fh), axis=0).T
        dX = np.diff(np.array(Xh), axis=0).T
        gamma = np.linalg.lstsq(dF, f, rcond=1e-10)[0]
        z[idx] = (Xh[-1] + f - (dX + dF) @ gamma) / wts
        # the extrapolated values are the next round's start; z (the tie points too) is
        # re-solved by its first step
    if not converged and best is not None and best[0] < gap:
        final = best[1]
    z = final.x.copy()          # the values measured closest to the joint optimum
    no_cov = (final.cov.count_nonzero() == 0 if sp.issparse(final.cov)
              else not final.cov.any())
    if vce or no_cov:               # statistics at the two-step solution (no step taken)
        final = _run(st.problem(z, free, obs_sigma, tie_sigma), vce, False, alpha,
                     tol=np.inf)
        final.x[:] = z
    return final, rounds, converged


def _gap(st: Setup, z, free, obs_sigma, tie_sigma, alpha, sig=None):
    """The first-order distance from ``z`` to the joint optimum: the largest |joint
    Gauss-Newton step| over the free parameters, in joint sigmas; with the joint
    solution's statistics at ``z`` (no step taken) and the sigmas used. Given ``sig``
    (the joint sigmas change little from round to round) the covariance is not formed."""
    P = st.problem(z, free, obs_sigma, tie_sigma)
    sol = _run(P, False, False, alpha, tol=np.inf, covariance=sig is None)
    sol.x[:] = z
    if sig is None:
        sig = sol.sigma[:st.n_par][free]
    rem = np.abs(sol.remaining[:st.n_par][free]) if sol.remaining is not None else np.inf
    gap = float(np.max(rem / np.maximum(sig, 1e-300))) if free.any() else 0.0
    return gap, sol, sig
