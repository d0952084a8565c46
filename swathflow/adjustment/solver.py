"""The estimator: Gauss-Newton with Levenberg-Marquardt damping, variance component
estimation, a robust reweighting phase and data snooping (see the package docstring)."""
from __future__ import annotations

import math
from typing import Sequence

import numpy as np
import scipy.sparse as sp

from swathflow.adjustment.normal import _Normal, _points
from swathflow.adjustment.problem import AdjustmentError, Problem, Solution
from swathflow.adjustment.schur import PointSplit, SchurNormal
from swathflow.adjustment.snooping import Snooping, critical


#: relative decrease of the cost a Gauss-Newton step predicts (``step^2 / cost``) below
#: which a step that does not lower the cost ends the iteration: the model's kinks (a
#: point's crossing found to a tolerance) make the cost rough at that level, and the
#: steps below it crawl (the survey took 13 more iterations for 0.01 sigma)
FTOL = 1e-4
#: a damped step, or one shorter than STALL_STEP (sigma units), lowering the cost by less
#: than this fraction ends the iteration
FTOL_STALL = 1e-6
STALL_STEP = 0.01
def solve(problem: Problem, *, vce: bool | Sequence[str] = True, robust: bool = False,
          alpha: float = 0.001, max_iter: int = 50, tol: float = 1e-4,
          sparse: bool | None = None, max_dense_cov: int = 4000, min_redundancy: float = 2.0,
          scale_covariance: bool | None = None, damping: bool = True,
          rcond: float = 1e-12, jac_refresh: float = 0.5) -> Solution:
    """Estimate the unknowns of ``problem``.

    vce: estimate the variance components of all labels (True), of the given labels, or
        none (False). A component whose redundancy is below ``min_redundancy`` keeps 1.
    robust: data snooping removes the worst point while its chi-square test (the 2-D
        or k-D statistic of the whole point) fails at ``alpha``, and with it every failing
        point that alone observes its point unknowns (a tie point tested whole) or whose
        redundancy numbers are all above ``LOW_LEVERAGE``; rejected
        points whose prediction passes the test are re-admitted once (not those: once
        rejected, nothing predicts them).
    tol: convergence when the step's length in sigma units (``sqrt(dx' N dx)``) is below.
    jac_refresh: steps shorter than this (sigma units) keep the Jacobian (modified
        Newton); the final statistics always use a Jacobian at the solution.
    scale_covariance: multiply the covariance by sigma0^2 (default: when no component was
        estimated).
    """
    s = _Solver(problem, vce, sparse, rcond, damping, tol, jac_refresh, max_dense_cov,
                min_redundancy)
    s.run(robust, alpha, max_iter)
    return s.solution(alpha, scale_covariance)


class _Solver(Snooping):
    """The state of one adjustment: unknowns, weights, variance components, rejected
    points. Each method is one phase of :func:`solve`."""

    def __init__(self, P: Problem, vce, sparse, rcond, damping, tol, jac_refresh,
                 max_dense_cov, min_redundancy):
        self.P = P
        self.n = n = P.n
        if n == 0:
            raise AdjustmentError("no unknowns")
        self.free = ~P.fixed
        if not self.free.any():
            raise AdjustmentError("every unknown is fixed: nothing to estimate")
        sizes = [g.size for g in P.groups]
        self.offsets = np.concatenate([[0], np.cumsum(sizes)]).astype(int)
        self.m = m = int(self.offsets[-1])
        if m == 0:
            raise AdjustmentError("no observations")
        self.sigma = np.concatenate([g.sigma for g in P.groups])
        comp = np.concatenate([g.component for g in P.groups])
        self.labels = list(dict.fromkeys(comp.tolist()))
        self.comp_idx = np.array([self.labels.index(c) for c in comp], int)
        self.counted = np.concatenate([np.full(g.size, g.counted) for g in P.groups])
        uncounted = set(comp[~self.counted].tolist())
        if vce is True:
            self.est = set(self.labels) - uncounted
        elif vce is False or vce is None:
            self.est = set()
        else:
            self.est = set(vce) - uncounted
        self.s2 = np.ones(len(self.labels))
        self.pts = pts = _points(P, self.offsets)
        self.point_ok = np.ones(len(pts.group), bool)       # not rejected
        self.obs_point = -np.ones(m, int)
        for p, row in enumerate(pts.obs):
            self.obs_point[row[row >= 0]] = p
        self.rho = np.ones(len(pts.group))                   # robust weights per point
        self.rejected: dict[int, dict] = {}
        self.names_free = [nm for nm, f in zip(P.names, self.free) if f]
        self.cons = [(A, d) for A, d in P.constraints]
        self.use_sparse = sparse
        self.rcond, self.damping, self.tol = rcond, damping, tol
        self.jac_refresh, self.max_dense_cov = jac_refresh, max_dense_cov
        self.min_redundancy = min_redundancy
        self.history: list[dict] = []
        self.x = P.x0.copy()
        self.evals = 0
        self.iters = 0
        self.remaining = None
        self.converged = False
        self.cur: tuple | None = None  # (r, J, fresh) at x
        self.schur = self._schur_layout(P)
        self._split: tuple | None = None

    def _schur_layout(self, P):
        """Positions among the free unknowns of the camera unknowns and the point blocks
        (None: no point unknowns, or some of them fixed: plain normal equations)."""
        b = P.point_blocks
        if b is None or not self.free[b].all():
            return None
        fpos = np.cumsum(self.free) - 1
        fb = fpos[b]
        nf = int(self.free.sum())
        point_of = -np.ones(nf, np.intp)
        slot_of = np.zeros(nf, np.intp)
        point_of[fb.ravel()] = np.repeat(np.arange(fb.shape[0]), fb.shape[1])
        slot_of[fb.ravel()] = np.tile(np.arange(fb.shape[1]), fb.shape[0])
        cam = np.flatnonzero(point_of < 0)
        return cam, fb, point_of, slot_of

    # --- weights and evaluation ----------------------------------------------------------
    def obs_mask(self):
        ok = np.ones(self.m, bool)
        pts_bad = ~self.point_ok
        if pts_bad.any():
            rows = self.pts.obs[pts_bad]
            ok[rows[rows >= 0]] = False
        return ok

    def weights(self, r, mask):
        w = 1.0 / (self.sigma ** 2 * self.s2[self.comp_idx])
        rw = np.ones(self.m)
        has = self.obs_point >= 0
        rw[has] = self.rho[self.obs_point[has]]
        act = mask & np.isfinite(r)
        return np.where(act, w * rw, 0.0), act

    def evaluate(self, xx, jac=True):
        self.evals += 1
        r, J = self.P.evaluate(xx, jac)
        if J is not None:           # rows of uncomputable observations carry no weight
            if sp.issparse(J):
                J = sp.csr_matrix(J, copy=True)
                J.data[~np.isfinite(J.data)] = 0.0
            elif not np.isfinite(J).all():
                J = np.where(np.isfinite(J), J, 0.0)
        return r, J

    def cres(self, xx):
        return np.concatenate([d - A @ xx for A, d in self.cons]) if self.cons else None

    def normal(self, J, w, lam=0.0):
        if self.schur is not None:
            cam, fb, point_of, slot_of = self.schur
            if self._split is None or self._split[0] is not J:
                self._split = (J, PointSplit(self._free_columns(J), cam, point_of, slot_of,
                                             fb.shape[0], fb.shape[1]))
            # the reduced system is over the free unknowns: so are its constraints' columns
            cons = [(A[:, self.free] if not sp.issparse(A) else
                     sp.csc_matrix(A)[:, self.free], d) for A, d in self.cons]
            return SchurNormal(self._split[1], w, cam, fb, cons, lam, self.names_free,
                               self.rcond)
        return _Normal(J, w, self.free, self.cons, lam, bool(self.use_sparse),
                       self.names_free, self.rcond)

    def covariance(self, ne):
        """The cofactor matrix of the free unknowns (dense, or factored with point
        blocks), or None when it would be too large."""
        size = ne.ncam if self.schur is not None else ne.nf
        return None if size > self.max_dense_cov else ne.covariance()

    def _free_columns(self, J):
        return J[:, self.free] if not sp.issparse(J) else sp.csr_matrix(J)[:, self.free]

    # --- Gauss-Newton / Levenberg-Marquardt ------------------------------------------------
    def gauss_newton(self, max_it):
        """Iterate from self.x (``self.cur`` = (r, J, fresh) already evaluated there, or
        None). A step shorter than ``tol`` is not taken (x and r stay valid)."""
        if self.cur is None:
            r, J = self.evaluate(self.x)
            fresh = True
        else:
            r, J, fresh = self.cur
        if self.use_sparse is None:
            self.use_sparse = sp.issparse(J)
        lam = 0.0
        conv = False
        self.remaining = None
        for _ in range(max_it):
            mask = self.obs_mask()
            w, act = self.weights(r, mask)
            rr = np.where(act, r, 0.0)
            cost = float(np.sum(w * rr ** 2))
            g = np.asarray(self._free_columns(J).T @ (w * rr)).ravel()
            conv, lam, xn, rn, step, cost_new = self._damped_step(r, J, w, act, mask, g, lam)
            if conv:
                break
            dxf = (xn - self.x)[self.free]
            self.x = xn
            lam = lam / 10.0 if lam > 1e-6 else 0.0
            self.history.append({"cost": cost, "cost_new": cost_new, "step_sigma": step,
                                 "damping": lam, "active": int(act.sum())})
            if (lam > 0.0 or step < STALL_STEP) and cost - cost_new < FTOL_STALL * cost:
                # damped steps, or steps of a hundredth of a sigma, that no longer lower the
                # cost (a kinked model; a crossing found to a tolerance puts a floor under
                # the step that grows with the number of unknowns): converged
                self._remaining(dxf)
                r, J = self.evaluate(self.x)
                fresh, conv = True, True
                break
            if step > self.jac_refresh:
                r, J = self.evaluate(self.x)
                fresh = True
            else:                    # near the solution: keep the Jacobian (modified Newton)
                r, fresh = rn, False
        self.cur = (r, J, fresh)
        self.converged = conv
        return r, J

    def _remaining(self, dxf):
        self.remaining = np.zeros(self.n)
        self.remaining[self.free] = dxf

    def _damped_step(self, r, J, w, act, mask, g, lam):
        """One accepted step (raising the damping until the cost falls), or convergence.
        Returns (converged, damping, x_new, r_new, step, cost_new)."""
        x = self.x
        tried_gn = lam == 0.0
        for tries in range(12):
            ne = self.normal(J, w, lam)
            dxf = ne.solve(g, self.cres(x))
            step = float(np.sqrt(max(ne.step_norm2(dxf), 0.0)))
            if step < self.tol:
                # a short damped step: converged when the undamped (Gauss-Newton) step is
                # short too; else take the undamped one (the damping only held it back)
                if lam > 0.0 and not tried_gn:
                    lam, tried_gn = 0.0, True
                    ne = self.normal(J, w, 0.0)
                    dxf = ne.solve(g, self.cres(x))
                    step = float(np.sqrt(max(ne.step_norm2(dxf), 0.0)))
                if step < self.tol:
                    self._remaining(dxf)
                    return True, lam, x, r, step, float("nan")
            self.iters += 1
            dx = np.zeros(self.n)
            dx[self.free] = dxf
            xn = x + dx
            rn, _ = self.evaluate(xn, False)
            both = act & np.isfinite(rn)
            wn, _ = self.weights(rn, mask)
            cost_old = float(np.sum(np.where(both, w * r ** 2, 0.0)))
            cost_new = float(np.sum(np.where(both, wn * rn ** 2, 0.0)))
            lost = int(act.sum() - both.sum())
            lower = cost_new <= cost_old * (1 + 1e-9) + 1e-12
            if self.damping and lost == 0 and not lower and (
                    step < self.tol or (lam == 0.0 and step ** 2 < FTOL * cost_old)):
                # a step below the tolerance, or a Gauss-Newton step that would lower the
                # cost by a negligible fraction, does not lower it: x is the solution
                # within the tolerance (a rough, e.g. piecewise-linear, model would
                # otherwise be walked uphill: a point whose crossing sits on a kink)
                ne0 = ne if lam == 0.0 else self.normal(J, w, 0.0)
                self._remaining(ne0.solve(g, self.cres(x)))
                return True, lam, x, r, step, cost_new
            if not self.damping or cost_old == 0 or (step < self.tol and lost == 0) or (
                    lower and (lost == 0 or tries >= 4)):
                return False, lam, xn, rn, step, cost_new
            lam = max(lam * 10.0, 1e-4)
        raise AdjustmentError("Levenberg-Marquardt found no step that lowers the "
                              "cost; check the start values and the observations")

    # --- variance components and statistics ---------------------------------------------------
    def vce_linear(self, r, J):
        """Variance components on the model linearised at the current solution (no new
        evaluations); returns True when a component changed."""
        changed_any = False
        for _ in range(50):
            w, act = self.weights(r, self.obs_mask())
            ne = self.normal(J, w)
            cov = self.covariance(ne)
            if cov is None:
                return changed_any
            Jf = self._free_columns(J)
            rr = np.where(act, r, 0.0)
            gv = np.asarray(Jf.T @ (w * rr)).ravel()
            dxf = ne.solve(gv, self.cres(self.x))
            v = rr - np.asarray(Jf @ dxf).ravel()
            red = np.where(act & self.counted, 1.0 - w * cov.diag_jqjt(Jf), 0.0)
            changed = False
            for k, lab in enumerate(self.labels):
                sel = (self.comp_idx == k) & act
                rk = float(red[sel].sum())
                if lab not in self.est or rk < self.min_redundancy:
                    continue
                f = float(np.sum(w[sel] * v[sel] ** 2)) / rk
                self.s2[k] *= f
                changed |= abs(f - 1.0) > 1e-3
            changed_any |= changed
            if not changed:
                break
        return changed_any

    def a_priori_variances(self):
        w0 = 1.0 / (self.sigma ** 2 * self.s2[self.comp_idx])
        return np.where(np.isfinite(w0), 1.0 / w0, np.inf)

    def statistics(self, r, J):
        w, act = self.weights(r, self.obs_mask())
        ne = self.normal(J, w)
        Jf = self._free_columns(J)
        return ne, self.covariance(ne), Jf, w, act

    # --- the phases -----------------------------------------------------------------------
    def converge(self, max_iter):
        """Converge with fixed weights, re-estimating the variance components."""
        for _ in range(30):
            r, J = self.gauss_newton(max_iter)
            if not self.est or not self.vce_linear(r, J):
                break
        return r, J

    def run(self, robust: bool, alpha: float, max_iter: int) -> None:
        r, J = self.converge(max_iter)
        if not robust:
            return
        readmit = True
        while True:
            state = self.snoop(r, J, alpha, readmit)
            if state == "done":
                return
            readmit = readmit and state != "readmitted"
            r, J = self.converge(max_iter)

    # --- the result -------------------------------------------------------------------------
    def solution(self, alpha, scale_covariance) -> Solution:
        """Final statistics, with the Jacobian at the solution."""
        P, n, m, free = self.P, self.n, self.m, self.free
        assert self.cur is not None, "run() first"
        r, J, fresh = self.cur
        if not fresh:
            r, J = self.evaluate(self.x)
        ne, Q, Jf, w, act = self.statistics(r, J)
        # dense up to max_dense_cov unknowns; above, sparse (camera and point blocks)
        cov = np.zeros((n, n)) if n <= self.max_dense_cov else sp.csr_matrix((n, n))
        red = np.full(m, np.nan)
        used_counted = act & self.counted
        if Q is not None:
            jqj = Q.diag_jqjt(Jf)
            red = np.where(used_counted, 1.0 - w * jqj, 0.0)
        redundancy = (float(used_counted.sum() - free.sum() + ne.nc) if Q is None
                      else float(red.sum()))
        vpv = float(np.sum(np.where(used_counted, w * r ** 2, 0.0)))
        s0sq = vpv / redundancy if redundancy > 0 else float("nan")
        if scale_covariance is None:
            scale_covariance = not any(lab in self.est for lab in self.labels)
        if Q is not None:
            f = s0sq if scale_covariance and np.isfinite(s0sq) else 1.0
            if n <= self.max_dense_cov:
                cov[np.ix_(free, free)] = Q.full(False) * f
            else:                       # the camera and per-point blocks, sparse
                fi = np.flatnonzero(free)
                Qs = sp.coo_matrix(Q.full(True))
                cov = sp.csr_matrix((Qs.data * f, (fi[Qs.row], fi[Qs.col])), shape=(n, n))
        components = self._components(r, w, act, red, Q is not None)
        wtest = np.full(m, np.nan)
        if Q is not None:            # per-observation w-tests
            qv = np.where(act, 1.0 / np.where(w > 0, w, 1.0) - jqj, np.nan)
            with np.errstate(invalid="ignore", divide="ignore"):
                wtest = np.where(act & (qv > 0), r / np.sqrt(np.abs(qv)), np.nan)
        res, nrm, used = {}, {}, {}
        for gi, g in enumerate(P.groups):
            sl = slice(self.offsets[gi], self.offsets[gi + 1])
            res[g.name], nrm[g.name], used[g.name] = r[sl].copy(), wtest[sl].copy(), act[sl].copy()
        sigma0 = float(math.sqrt(s0sq)) if np.isfinite(s0sq) and s0sq >= 0 else float("nan")
        return Solution(list(P.names), list(P.units), self.x, P.x0.copy(), P.fixed.copy(), cov,
                        sigma0, redundancy, components, res, nrm, used,
                        self._rejected_list(alpha), self.iters, self.evals,
                        bool(self.converged), self.history,
                        self.remaining if self.converged else None)

    def _components(self, r, w, act, red, have_q) -> dict:
        out = {}
        for k, lab in enumerate(self.labels):
            sel = (self.comp_idx == k) & act
            rk = float(red[sel].sum()) if have_q else float("nan")
            out[lab] = {"s2": float(self.s2[k]), "sigma_factor": float(math.sqrt(self.s2[k])),
                        "redundancy": rk, "n": int(sel.sum()),
                        "estimated": bool(lab in self.est and rk >= self.min_redundancy),
                        "vpv": float(np.sum(w[sel] * r[sel] ** 2))}
        return out

    def _rejected_list(self, alpha) -> list[dict]:
        out = []
        for p, info in sorted(self.rejected.items()):
            g = self.P.groups[int(self.pts.group[p])]
            kp = info["dof"]
            out.append({"group": g.name, "point": int(self.pts.point[p]),
                        "name": str(g.point_names[int(self.pts.point[p])]),
                        "statistic": info["statistic"],
                        "critical": float(critical(alpha, max(kp, 1))),
                        "phase": info["phase"]})
        return out
