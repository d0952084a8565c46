"""Weighted least-squares adjustment with priors (generic: no sensor knowledge).

A :class:`Problem` holds named unknowns and observation groups; :func:`solve` estimates
the unknowns by Gauss-Newton with Levenberg-Marquardt damping, and returns a
:class:`Solution` with covariance, correlation, variance components and the points a
robust phase or data snooping rejected.

Conventions
-----------
- A nonlinear group is a function ``fn(x, jacobian) -> (r, J)``: ``r`` (m,) are the
  residuals *observed minus computed* at the unknowns ``x`` (NaN where an observation
  cannot be computed; it is then left out of that iteration), ``J`` (m, n) the partial
  derivatives of the *computed* values with respect to all unknowns (dense or
  ``scipy.sparse``; ``None`` when ``jacobian`` is False).
- Every observation has an a-priori sigma and a variance-component label; components
  can be estimated from the data (variance component estimation, Foerstner's iterative
  method with redundancy numbers).
- Observations belong to *points* (e.g. the line and element of one image point): the
  robust phase and data snooping test and reject whole points with their 2-D (k-D)
  statistic ``v' Qvv^-1 v``, chi-square with k degrees of freedom.
- Priors are pseudo-observations ``x_i = value_i +- sigma_i``; linear (soft) constraints
  are observations ``A x = b +- sigma``; hard equality constraints ``C x = d`` are solved
  exactly (bordered normal equations).
- Fixed unknowns keep their start values and have zero covariance.

Dense normal equations are used when the Jacobian is dense; sparse ones (SuperLU) when any
group returns a sparse Jacobian or ``sparse=True``. Redundancy numbers (needed by variance
component estimation and snooping) need the covariance of all free unknowns, formed densely
up to ``max_dense_cov`` free unknowns.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable, Sequence

import numpy as np
import scipy.linalg as sla
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from scipy import stats

from swathflow.errors import SwathflowError


class AdjustmentError(SwathflowError):
    """The adjustment cannot be solved as posed (the message says what to change)."""


class RankDeficiencyError(AdjustmentError):
    """The observations do not determine some combination of the unknowns.

    ``directions`` lists, per undetermined direction, ``{name: weight}`` of the unknowns
    involved (largest first)."""

    def __init__(self, message: str, directions: list[dict[str, float]]):
        super().__init__(message)
        self.directions = directions


@dataclass
class Group:
    """One observation group (see the module docstring)."""

    name: str
    fn: Callable
    sigma: np.ndarray
    component: np.ndarray          # (m,) variance-component label per observation
    point: np.ndarray              # (m,) point index per observation (-1: not tested)
    point_names: np.ndarray        # (n_points,) names for reports
    robust: bool = True
    linear: bool = False
    counted: bool = True           # False: a regularising prior, outside sigma0 and the
    #                                redundancy (its value carries no information)

    @property
    def size(self) -> int:
        return int(self.sigma.size)


class Problem:
    """Unknowns and observation groups of a least-squares adjustment."""

    def __init__(self, names: Sequence[str], x0, units: Sequence[str] | None = None):
        self.names = [str(n) for n in names]
        if len(set(self.names)) != len(self.names):
            raise AdjustmentError("unknown names must be unique")
        self.x0 = np.asarray(x0, float).copy()
        if self.x0.shape != (len(self.names),):
            raise AdjustmentError(f"x0 needs {len(self.names)} values, got {self.x0.shape}")
        self.units = list(units) if units is not None else [""] * len(self.names)
        self.fixed = np.zeros(len(self.names), bool)
        self.groups: list[Group] = []
        self.constraints: list[tuple[np.ndarray | sp.spmatrix, np.ndarray]] = []

    @property
    def n(self) -> int:
        return len(self.names)

    def index(self, names: Sequence[str]) -> np.ndarray:
        pos = {n: i for i, n in enumerate(self.names)}
        missing = [n for n in names if n not in pos]
        if missing:
            raise AdjustmentError(f"unknown(s) {', '.join(missing)}; known: "
                                  f"{', '.join(self.names)}")
        return np.array([pos[n] for n in names], int)

    def fix(self, which) -> None:
        """Hold unknowns (names or a boolean mask) at their start values."""
        if isinstance(which, np.ndarray) and which.dtype == bool:
            self.fixed |= which
        else:
            self.fixed[self.index(list(which))] = True

    def add_observations(self, name: str, fn: Callable, sigma, component=None, point=None,
                         point_names=None, robust=True, counted: bool = True) -> Group:
        """``robust``: whether the blunder tests may reject this group's points: one flag,
        or an array of flags indexed by point number. ``counted=False``: a regularising
        group (a weak prior that only keeps unknowns determined): it weighs in the
        solution but not in sigma0, the redundancy or the variance components."""
        sigma = np.asarray(sigma, float).ravel()
        m = sigma.size
        if np.any(~(sigma > 0)):
            raise AdjustmentError(f"group {name}: every sigma must be positive")
        comp = np.asarray([name] * m if component is None else
                          ([component] * m if isinstance(component, str) else component),
                          dtype=object)
        pt = np.arange(m) if point is None else np.asarray(point, int)
        npts = int(pt.max()) + 1 if pt.size and pt.max() >= 0 else 0
        pn = (np.array([f"{name}#{i}" for i in range(npts)], dtype=object)
              if point_names is None else np.asarray(point_names, dtype=object))
        if comp.size != m or pt.size != m or pn.size < npts:
            raise AdjustmentError(f"group {name}: component/point arrays need {m} entries")
        g = Group(name, fn, sigma, comp, pt, pn, robust, counted=counted)
        self.groups.append(g)
        return g

    def add_linear(self, name: str, A, b, sigma, component=None, robust: bool = False,
                   point=None, point_names=None, counted: bool = True) -> Group:
        """Soft linear observations ``A x = b +- sigma`` (constraints, pseudo-observations)."""
        A = A.tocsr() if sp.issparse(A) else np.atleast_2d(np.asarray(A, float))
        b = np.asarray(b, float).ravel()
        if A.shape != (b.size, self.n):
            raise AdjustmentError(f"group {name}: A must be ({b.size}, {self.n}), got {A.shape}")

        def fn(x, jacobian=True):
            return b - A @ x, (A if jacobian else None)

        g = self.add_observations(name, fn, np.broadcast_to(np.asarray(sigma, float), b.shape),
                                  component, point, point_names, robust, counted)
        g.linear = True
        return g

    def add_priors(self, values, sigmas, name: str = "priors", component: str | None = None,
                   counted: bool = True) -> Group | None:
        """A pseudo-observation ``x_i = values_i +- sigmas_i`` for every unknown with a
        finite sigma (a sigma of inf or NaN means no prior); ``counted`` as in
        :meth:`add_observations`."""
        values = np.broadcast_to(np.asarray(values, float), (self.n,))
        sigmas = np.broadcast_to(np.asarray(sigmas, float), (self.n,))
        idx = np.flatnonzero(np.isfinite(sigmas) & (sigmas > 0))
        if idx.size == 0:
            return None
        A = sp.csr_matrix((np.ones(idx.size), (np.arange(idx.size), idx)),
                          shape=(idx.size, self.n))
        return self.add_linear(name, A, values[idx], sigmas[idx], component or name,
                               point_names=np.array([self.names[i] for i in idx], dtype=object),
                               counted=counted)

    def add_constraint(self, A, d) -> None:
        """Hard linear equality constraints ``A x = d`` (satisfied exactly)."""
        A = A.tocsr() if sp.issparse(A) else np.atleast_2d(np.asarray(A, float))
        d = np.asarray(d, float).ravel()
        if A.shape != (d.size, self.n):
            raise AdjustmentError(f"constraint: A must be ({d.size}, {self.n}), got {A.shape}")
        self.constraints.append((A, d))

    # --- evaluation -------------------------------------------------------------------
    def evaluate(self, x, jacobian: bool = True):
        rs, Js = [], []
        for g in self.groups:
            r, J = g.fn(x, jacobian)
            r = np.asarray(r, float).ravel()
            if r.size != g.size:
                raise AdjustmentError(f"group {g.name}: returned {r.size} residuals, "
                                      f"expected {g.size}")
            rs.append(r)
            Js.append(J)
        r = np.concatenate(rs) if rs else np.zeros(0)
        if not jacobian:
            return r, None
        if any(sp.issparse(J) for J in Js):
            J = sp.vstack([sp.csr_matrix(J) for J in Js], format="csr")
        else:
            J = np.vstack([np.asarray(J, float).reshape(g.size, self.n)
                           for J, g in zip(Js, self.groups)])
        return r, J


@dataclass
class Solution:
    """The result of :func:`solve`."""

    names: list[str]
    units: list[str]
    x: np.ndarray
    x0: np.ndarray
    fixed: np.ndarray
    cov: np.ndarray                      # (n, n), zero rows/columns for fixed unknowns
    sigma0: float                        # a-posteriori sigma of unit weight
    redundancy: float
    components: dict[str, dict]          # label -> {s2, sigma_factor, redundancy, n, estimated}
    residuals: dict[str, np.ndarray]     # group -> observed minus computed (NaN: not computed)
    normalized: dict[str, np.ndarray]    # group -> w-test statistic per observation
    used: dict[str, np.ndarray]          # group -> bool, observation took part
    rejected: list[dict]                 # {group, point, name, statistic, critical, phase}
    iterations: int
    evaluations: int
    converged: bool
    history: list[dict] = field(default_factory=list)
    #: the Gauss-Newton step computed at ``x`` and not taken because it was shorter than the
    #: tolerance (zeros for fixed unknowns; None when the last step was taken): how far ``x``
    #: is from the solution, to first order
    remaining: np.ndarray | None = None

    @property
    def sigma(self) -> np.ndarray:
        return np.sqrt(np.clip(np.diag(self.cov), 0, None))

    @property
    def corr(self) -> np.ndarray:
        s = self.sigma
        with np.errstate(invalid="ignore", divide="ignore"):
            c = self.cov / np.outer(s, s)
        c[~np.isfinite(c)] = 0.0
        np.fill_diagonal(c, np.where(s > 0, 1.0, 0.0))
        return c

    def value(self, name: str) -> float:
        return float(self.x[self.names.index(name)])


# ---------------------------------------------------------------------------------------
class _Normal:
    """Factorised (possibly bordered) normal equations over the free unknowns."""

    def __init__(self, J, w, free, constraints, damping=0.0, sparse=False, names=None,
                 rcond=1e-12):
        self.sparse = sparse
        Jf = J[:, free]
        if sparse:
            Jf = sp.csr_matrix(Jf)
            N = (Jf.T @ sp.diags(w) @ Jf).tocsc()
        else:
            Jw = Jf * w[:, None]
            N = Jw.T @ Jf
        self.N = N
        nf = int(free.sum())
        diag = np.asarray(N.diagonal()).copy()
        if damping:
            N = N + damping * (sp.diags(diag) if sparse else np.diag(diag))
        C = [((A[:, free] if not sp.issparse(A) else A.tocsc()[:, free]), d)
             for A, d in constraints]
        self.nc = sum(d.size for _, d in C)
        self.nf = nf
        self.names = names
        self._check_rank(N, diag, C, rcond)
        if self.nc:
            Cm = sp.vstack([sp.csr_matrix(a) for a, _ in C]) if sparse else \
                np.vstack([a.toarray() if sp.issparse(a) else a for a, _ in C])
            if sparse:
                K = sp.bmat([[N, Cm.T], [Cm, None]], format="csc")
            else:
                K = np.block([[N, Cm.T], [Cm, np.zeros((self.nc, self.nc))]])
        else:
            K = N
        self.K = K
        try:
            if sparse:
                self._lu = spla.splu(sp.csc_matrix(K))
                self._solve = self._lu.solve
            elif self.nc:
                lu = sla.lu_factor(K)
                self._solve = lambda b: sla.lu_solve(lu, b)
            else:
                cf = sla.cho_factor(K)
                self._solve = lambda b: sla.cho_solve(cf, b)
        except (RuntimeError, np.linalg.LinAlgError, sla.LinAlgError) as exc:
            raise RankDeficiencyError(
                f"the normal equations are singular ({exc}); fix unknowns, add priors or "
                f"add observations", []) from None

    def _check_rank(self, N, diag, C, rcond):
        names = np.asarray(self.names, dtype=object)
        Cd = None
        if C:
            Cd = np.vstack([a.toarray() if sp.issparse(a) else np.asarray(a) for a, _ in C])
        if self.sparse and self.nf > 500:
            info = diag + (np.abs(Cd).sum(0) if Cd is not None else 0)
            empty = np.flatnonzero(~(info > 0))
            if empty.size:
                raise RankDeficiencyError(
                    "no observation determines " + ", ".join(names[empty][:10]),
                    [{str(names[i]): 1.0} for i in empty])
            return
        Nd = N.toarray() if sp.issparse(N) else np.asarray(N)
        if Cd is not None:          # constrained directions are determined
            Nd = Nd + Cd.T @ Cd * (np.abs(diag).max() / max(np.abs(Cd).max(), 1e-300) ** 2)
        d = np.sqrt(np.abs(np.diag(Nd)))
        s = np.where(d > 0, 1.0 / np.where(d > 0, d, 1.0), 0.0)
        Ns = Nd * np.outer(s, s)
        ev, vec = np.linalg.eigh(Ns)
        bad = ev < rcond * max(ev.max(), 1e-300)
        if d.size and np.any(d == 0):
            bad_cols = np.flatnonzero(d == 0)
        else:
            bad_cols = np.zeros(0, int)
        if not bad.any() and not bad_cols.size:
            return
        directions = []
        for k in np.flatnonzero(bad):
            v = vec[:, k] * s
            v = v / (np.abs(v).max() or 1.0)
            order = np.argsort(-np.abs(v))
            directions.append({str(names[i]): round(float(v[i]), 3) for i in order
                               if abs(v[i]) > 0.1})
        for i in bad_cols:
            directions.append({str(names[i]): 1.0})
        text = "; ".join(" + ".join(f"{w:+.2f}*{n}" for n, w in dd.items()) or "?"
                         for dd in directions[:6])
        raise RankDeficiencyError(
            f"the observations do not determine {len(directions)} combination(s) of the "
            f"unknowns: {text}. Add observations that separate them, add priors, or fix "
            f"some of them", directions)

    def solve(self, g, cres=None):
        b = g if not self.nc else np.concatenate([g, cres])
        out = self._solve(b)
        return out[:self.nf]

    def inverse(self) -> np.ndarray:
        """Covariance (cofactor) matrix of the free unknowns (constrained if needed)."""
        n = self.nf
        E = np.zeros((n + self.nc, n))
        E[np.arange(n), np.arange(n)] = 1.0
        X = self._solve(E)
        Q = X[:n, :n]
        return 0.5 * (Q + Q.T)


def _diag_jqjt(J, Q, chunk: int = 4096) -> np.ndarray:
    """diag(J Q J') for dense or sparse J, in row chunks."""
    m = J.shape[0]
    out = np.empty(m)
    for i in range(0, m, chunk):
        Jc = J[i:i + chunk]
        JQ = np.asarray(Jc @ Q)
        out[i:i + chunk] = np.asarray((Jc.multiply(JQ) if sp.issparse(Jc) else Jc * JQ)
                                      .sum(axis=1)).ravel()
    return out


def _point_blocks(J, Q, obs_idx: np.ndarray) -> np.ndarray:
    """J_p Q J_p' blocks, (n_points, k, k), for observation index arrays (n_points, k);
    -1 entries give zero rows and columns."""
    npnt, k = obs_idx.shape
    valid = obs_idx >= 0
    flat = np.where(valid, obs_idx, 0).ravel()
    Jp = J[flat]
    Jp = Jp.toarray() if sp.issparse(Jp) else np.asarray(Jp)
    Jp = Jp.reshape(npnt, k, -1) * valid[..., None]
    return np.einsum("pin,nm,pjm->pij", Jp, Q, Jp)


@dataclass
class _PointIndex:
    group: np.ndarray     # (P,) group number
    point: np.ndarray     # (P,) point number within the group
    obs: np.ndarray       # (P, k) global observation indices (-1 padded)
    robust: np.ndarray    # (P,) bool


def _points(problem: Problem, offsets) -> _PointIndex:
    gs, ps, rows, rob = [], [], [], []
    for gi, g in enumerate(problem.groups):
        pt = g.point
        ok = pt >= 0
        if not ok.any():
            continue
        uniq, inv = np.unique(pt[ok], return_inverse=True)
        obs = np.flatnonzero(ok) + offsets[gi]
        order = np.argsort(inv, kind="stable")
        counts = np.bincount(inv, minlength=uniq.size)
        k = counts.max()
        mat = -np.ones((uniq.size, k), int)
        pos = np.arange(order.size) - np.repeat(np.cumsum(counts) - counts, counts)
        mat[inv[order], pos] = obs[order]
        gs.append(np.full(uniq.size, gi))
        ps.append(uniq)
        rows.append(mat)
        r = np.asarray(g.robust)        # one flag for the group, or one per point number
        rob.append(np.full(uniq.size, bool(r)) if r.ndim == 0 else r[uniq].astype(bool))
    if not rows:
        return _PointIndex(np.zeros(0, int), np.zeros(0, int), np.zeros((0, 1), int),
                           np.zeros(0, bool))
    k = max(r.shape[1] for r in rows)
    rows = [np.pad(r, ((0, 0), (0, k - r.shape[1])), constant_values=-1) for r in rows]
    return _PointIndex(np.concatenate(gs), np.concatenate(ps), np.vstack(rows),
                       np.concatenate(rob))


def _block_stat(v, q_blocks, obs_idx, qll, r_min: float = 0.01):
    """v_p' Q_p^+ v_p per point (padding ignored) and its degrees of freedom.

    The blocks are whitened by the a-priori variances ``qll`` (per point, (P, k)); for
    Qvv their eigenvalues are the redundancy numbers (0..1), and directions below
    ``r_min`` are left out of the test: an observation without redundancy (the last ray
    of a tie point) cannot be tested, and dividing its convergence noise by a zero
    variance would reject it."""
    valid = (obs_idx >= 0) & np.isfinite(qll) & (qll > 0)
    vp = np.where(valid, v[np.where(obs_idx >= 0, obs_idx, 0)], 0.0)
    s = np.where(valid, 1.0 / np.sqrt(np.where(valid, qll, 1.0)), 0.0)
    R = q_blocks * s[:, :, None] * s[:, None, :]
    lam, V = np.linalg.eigh(R)
    keep = lam > r_min
    proj = np.einsum("pki,pk->pi", V, vp * s)
    t = np.sum(np.where(keep, proj ** 2 / np.where(keep, lam, 1.0), 0.0), axis=1)
    return t, keep.sum(1)


def solve(problem: Problem, *, vce: bool | Sequence[str] = True, robust: bool = False,
          alpha: float = 0.001, max_iter: int = 50, tol: float = 1e-4,
          sparse: bool | None = None, max_dense_cov: int = 4000, min_redundancy: float = 2.0,
          scale_covariance: bool | None = None, damping: bool = True,
          rcond: float = 1e-12, jac_refresh: float = 0.5) -> Solution:
    """Estimate the unknowns of ``problem``.

    vce: estimate the variance components of all labels (True), of the given labels, or
        none (False). A component whose redundancy is below ``min_redundancy`` keeps 1.
    robust: first an iteratively reweighted phase (Huber, then Tukey's biweight on the
        per-point statistic with a median-based scale) removes gross errors, then data
        snooping removes the worst point while its chi-square test fails at ``alpha``;
        rejected points whose prediction passes the test are re-admitted once.
    tol: convergence when the step's length in sigma units (``sqrt(dx' N dx)``) is below.
    jac_refresh: steps shorter than this (sigma units) keep the Jacobian (modified
        Newton); the final statistics always use a Jacobian at the solution.
    scale_covariance: multiply the covariance by sigma0^2 (default: when no component was
        estimated).
    """
    P = problem
    n = P.n
    if n == 0:
        raise AdjustmentError("no unknowns")
    free = ~P.fixed
    if not free.any():
        raise AdjustmentError("every unknown is fixed: nothing to estimate")
    sizes = [g.size for g in P.groups]
    offsets = np.concatenate([[0], np.cumsum(sizes)]).astype(int)
    m = int(offsets[-1])
    if m == 0:
        raise AdjustmentError("no observations")
    sigma = np.concatenate([g.sigma for g in P.groups])
    comp = np.concatenate([g.component for g in P.groups])
    labels = list(dict.fromkeys(comp.tolist()))
    comp_idx = np.array([labels.index(c) for c in comp], int)
    counted = np.concatenate([np.full(g.size, g.counted) for g in P.groups])
    uncounted = set(comp[~counted].tolist())
    if vce is True:
        est = set(labels) - uncounted
    elif vce is False or vce is None:
        est = set()
    else:
        est = set(vce) - uncounted
    s2 = np.ones(len(labels))
    pts = _points(P, offsets)
    point_ok = np.ones(len(pts.group), bool)       # not rejected
    obs_point = -np.ones(m, int)
    for p, row in enumerate(pts.obs):
        obs_point[row[row >= 0]] = p
    rho = np.ones(len(pts.group))                   # robust weights per point
    rejected: dict[int, dict] = {}
    names_free = [nm for nm, f in zip(P.names, free) if f]
    cons = [(A, d) for A, d in P.constraints]
    use_sparse = sparse
    history: list[dict] = []
    x = P.x0.copy()
    state = {"evals": 0, "iters": 0, "remaining": None}

    def obs_mask():
        ok = np.ones(m, bool)
        pts_bad = ~point_ok
        if pts_bad.any():
            rows = pts.obs[pts_bad]
            ok[rows[rows >= 0]] = False
        return ok

    def weights(r, mask):
        w = 1.0 / (sigma ** 2 * s2[comp_idx])
        rw = np.ones(m)
        has = obs_point >= 0
        rw[has] = rho[obs_point[has]]
        act = mask & np.isfinite(r)
        return np.where(act, w * rw, 0.0), act

    def evaluate(xx, jac=True):
        state["evals"] += 1
        r, J = P.evaluate(xx, jac)
        if J is not None:           # rows of uncomputable observations carry no weight
            if sp.issparse(J):
                J = sp.csr_matrix(J, copy=True)
                J.data[~np.isfinite(J.data)] = 0.0
            elif not np.isfinite(J).all():
                J = np.where(np.isfinite(J), J, 0.0)
        return r, J

    def cres(xx):
        return np.concatenate([d - A @ xx for A, d in cons]) if cons else None

    def gauss_newton(x, max_it, cur=None):
        """Iterate from x; ``cur`` = (r, J, fresh) already evaluated at x. Returns
        x, r, J, fresh (J evaluated at x), converged. A step shorter than ``tol`` is not
        taken (x and r stay valid without a new evaluation)."""
        nonlocal use_sparse
        if cur is None:
            r, J = evaluate(x)
            fresh = True
        else:
            r, J, fresh = cur
        if use_sparse is None:
            use_sparse = sp.issparse(J)
        lam = 0.0
        conv = False
        state["remaining"] = None
        for it in range(max_it):
            mask = obs_mask()
            w, act = weights(r, mask)
            rr = np.where(act, r, 0.0)
            cost = float(np.sum(w * rr ** 2))
            g = (J[:, free].T @ (w * rr)) if not sp.issparse(J) else \
                np.asarray(sp.csr_matrix(J)[:, free].T @ (w * rr)).ravel()
            for tries in range(12):
                ne = _Normal(J, w, free, cons, lam, bool(use_sparse), names_free, rcond)
                dxf = ne.solve(g, None if not cons else cres(x))
                step = float(np.sqrt(max(dxf @ (ne.N @ dxf), 0.0)))
                if step < tol and lam == 0.0:
                    conv = True
                    state["remaining"] = np.zeros(n)
                    state["remaining"][free] = dxf
                    break
                state["iters"] += 1
                dx = np.zeros(n)
                dx[free] = dxf
                xn = x + dx
                rn, _ = evaluate(xn, False)
                both = act & np.isfinite(rn)
                wn, actn = weights(rn, mask)
                cost_old = float(np.sum(np.where(both, w * r ** 2, 0.0)))
                cost_new = float(np.sum(np.where(both, wn * rn ** 2, 0.0)))
                lost = int(act.sum() - both.sum())
                if damping and step < tol and lost == 0 and \
                        cost_new > cost_old * (1 + 1e-9) + 1e-12:
                    # a step below the tolerance that does not lower the cost: x is the
                    # solution within the tolerance (a rough, e.g. piecewise-linear,
                    # model would otherwise be walked uphill)
                    conv = True
                    ne0 = ne if lam == 0.0 else _Normal(J, w, free, cons, 0.0,
                                                       bool(use_sparse), names_free, rcond)
                    state["remaining"] = np.zeros(n)
                    state["remaining"][free] = ne0.solve(g, None if not cons else cres(x))
                    break
                if not damping or cost_old == 0 or (step < tol and lost == 0) or (
                        cost_new <= cost_old * (1 + 1e-9) + 1e-12 and (lost == 0 or tries >= 4)):
                    break
                lam = max(lam * 10.0, 1e-4)
            else:
                raise AdjustmentError("Levenberg-Marquardt found no step that lowers the "
                                      "cost; check the start values and the observations")
            if conv:
                break
            x = xn
            lam = lam / 10.0 if lam > 1e-6 else 0.0
            history.append({"cost": cost, "cost_new": cost_new, "step_sigma": step,
                            "damping": lam, "active": int(act.sum())})
            if step > jac_refresh:
                r, J = evaluate(x)
                fresh = True
            else:                    # near the solution: keep the Jacobian (modified Newton)
                r, fresh = rn, False
        return x, r, J, fresh, conv

    def vce_linear(r, J):
        """Variance components on the model linearised at the current solution (no new
        evaluations); returns True when a component changed."""
        changed_any = False
        for _ in range(50):
            mask = obs_mask()
            w, act = weights(r, mask)
            ne = _Normal(J, w, free, cons, 0.0, bool(use_sparse), names_free, rcond)
            if ne.nf > max_dense_cov:
                return changed_any
            Q = ne.inverse()
            Jf = J[:, free] if not sp.issparse(J) else sp.csr_matrix(J)[:, free]
            rr = np.where(act, r, 0.0)
            dxf = Q @ np.asarray(Jf.T @ (w * rr)).ravel() if not cons else \
                ne.solve(np.asarray(Jf.T @ (w * rr)).ravel(), cres(x))
            v = rr - np.asarray(Jf @ dxf).ravel()
            red = np.where(act & counted, 1.0 - w * _diag_jqjt(Jf, Q), 0.0)
            changed = False
            for k, lab in enumerate(labels):
                sel = (comp_idx == k) & act
                rk = float(red[sel].sum())
                if lab not in est or rk < min_redundancy:
                    continue
                f = float(np.sum(w[sel] * v[sel] ** 2)) / rk
                s2[k] *= f
                changed |= abs(f - 1.0) > 1e-3
            changed_any |= changed
            if not changed:
                break
        return changed_any

    def snoop_stats(Q, Jf, r):
        """Per-point v' Qvv^-1 v with the current components, its dof, J Q J' blocks and
        the a-priori variances per point."""
        w0 = 1.0 / (sigma ** 2 * s2[comp_idx])
        qll = np.where(np.isfinite(w0), 1.0 / w0, np.inf)
        blocks = _point_blocks(Jf, Q, pts.obs)
        valid = pts.obs >= 0
        qdiag = np.where(valid, qll[np.where(valid, pts.obs, 0)], 0.0)
        idx = np.arange(blocks.shape[1])
        qvv = -blocks.copy()
        qvv[:, idx, idx] += qdiag
        rr = np.where(np.isfinite(r), r, 0.0)
        T, k_p = _block_stat(rr, qvv, pts.obs, qdiag)
        return T, k_p, blocks, qdiag

    def statistics(x, r, J):
        mask = obs_mask()
        w, act = weights(r, mask)
        ne = _Normal(J, w, free, cons, 0.0, bool(use_sparse), names_free, rcond)
        Jf = J[:, free] if not sp.issparse(J) else sp.csr_matrix(J)[:, free]
        if ne.nf > max_dense_cov:
            Q = None
        else:
            Q = ne.inverse()
        return ne, Q, Jf, w, act

    converged = False
    cur = None
    n_outer = 0
    robust_done = not robust
    readmitted = False
    while True:
        n_outer += 1
        # 1) converge with fixed weights, re-estimating variance components
        for vit in range(30):
            x, r, J, fresh, converged = gauss_newton(x, max_iter, cur)
            cur = (r, J, fresh)
            if not est or not vce_linear(r, J):
                break
        if robust_done is False:
            robust_done = True
            # gate: the reweighting phase only when several points fail the test
            ne, Q, Jf, w, act = statistics(x, r, J)
            if Q is not None:
                T, k_p, _, _ = snoop_stats(Q, Jf, r)
                crit = stats.chi2.ppf(1 - alpha, np.maximum(k_p, 1))
                if int(np.sum((T > crit) & pts.robust & point_ok)) < 2:
                    continue
        if robust_done is False:
            # 2) IRLS on per-point statistics (median scale), then reject the zero-weight ones
            rp = pts.robust & point_ok
            prev = None
            for it in range(25):
                w0 = 1.0 / (sigma ** 2 * s2[comp_idx])
                valid = pts.obs >= 0
                vv = np.where(valid, (r ** 2 * w0)[np.where(valid, pts.obs, 0)], 0.0)
                k_p = valid.sum(1)
                t = np.sqrt(np.nansum(vv, 1) / k_p)
                med_ref = np.sqrt(stats.chi2.median(k_p) / k_p)
                u_raw = t / med_ref
                scale = float(np.nanmedian(u_raw[rp])) if rp.any() else 1.0
                u = t / max(scale, 1e-12)
                if it < 3:
                    new = np.minimum(1.0, 2.0 / np.maximum(u, 1e-12))
                else:
                    new = np.where(u < 4.685, (1 - (u / 4.685) ** 2) ** 2, 0.0)
                new = np.where(np.isfinite(u), new, 0.0)
                rho = np.where(rp, new, rho)
                if prev is not None and np.max(np.abs(rho - prev)) < 1e-3 and it >= 3:
                    break
                prev = rho.copy()
                x, r, J, fresh, converged = gauss_newton(x, max_iter, cur)
                cur = (r, J, fresh)
            gross = rp & (rho == 0.0)
            for p in np.flatnonzero(gross):
                rejected[int(p)] = {"phase": "robust", "statistic": float(u[p] ** 2 * k_p[p]),
                                    "dof": int(k_p[p])}
            point_ok &= ~gross
            rho = np.ones(len(pts.group))
            continue
        if not robust:
            break
        # 3) data snooping on the accepted points
        ne, Q, Jf, w, act = statistics(x, r, J)
        if Q is None:
            break
        T, k_p, blocks, qdiag = snoop_stats(Q, Jf, r)
        crit = stats.chi2.ppf(1 - alpha, np.maximum(k_p, 1))
        idx = np.arange(blocks.shape[1])
        rr = np.where(np.isfinite(r), r, 0.0)
        cand = pts.robust & point_ok & (k_p > 0)
        ratio = np.where(cand, T / crit, 0.0)
        if cand.any() and ratio.max() > 1.0:
            p = int(np.argmax(ratio))
            rejected[p] = {"phase": "snooping", "statistic": float(T[p]), "dof": int(k_p[p])}
            point_ok[p] = False
            continue
        if not readmitted and rejected:
            qpl = blocks.copy()
            qpl[:, idx, idx] += qdiag
            Tp, kp = _block_stat(rr, qpl, pts.obs, qdiag)
            crit_p = stats.chi2.ppf(1 - alpha, np.maximum(kp, 1))
            back = [p for p in rejected if Tp[p] <= crit_p[p]]
            readmitted = True
            if back:
                for p in back:
                    rejected.pop(p)
                    point_ok[p] = True
                continue
        break

    # final statistics, with the Jacobian at the solution
    if not cur[2]:
        r, J = evaluate(x)
    ne, Q, Jf, w, act = statistics(x, r, J)
    cov = np.zeros((n, n))
    red = np.full(m, np.nan)
    if Q is not None:
        red = np.where(act & counted, 1.0 - w * _diag_jqjt(Jf, Q), 0.0)
    redundancy = (float((act & counted).sum() - free.sum() + ne.nc) if Q is None
                  else float(red.sum()))
    vpv = float(np.sum(np.where(act & counted, w * r ** 2, 0.0)))
    s0sq = vpv / redundancy if redundancy > 0 else float("nan")
    if scale_covariance is None:
        scale_covariance = not any(lab in est for lab in labels)
    if Q is not None:
        Qs = Q * (s0sq if scale_covariance and np.isfinite(s0sq) else 1.0)
        cov[np.ix_(free, free)] = Qs
    components = {}
    for k, lab in enumerate(labels):
        sel = (comp_idx == k) & act
        rk = float(red[sel].sum()) if Q is not None else float("nan")
        components[lab] = {"s2": float(s2[k]), "sigma_factor": float(math.sqrt(s2[k])),
                           "redundancy": rk, "n": int(sel.sum()),
                           "estimated": bool(lab in est and rk >= min_redundancy),
                           "vpv": float(np.sum(w[sel] * r[sel] ** 2))}
    # per-observation w-tests
    wtest = np.full(m, np.nan)
    if Q is not None:
        qv = np.where(act, 1.0 / np.where(w > 0, w, 1.0) - _diag_jqjt(Jf, Q), np.nan)
        with np.errstate(invalid="ignore", divide="ignore"):
            wtest = np.where(act & (qv > 0), r / np.sqrt(np.abs(qv)), np.nan)
    res, nrm, used = {}, {}, {}
    for gi, g in enumerate(P.groups):
        sl = slice(offsets[gi], offsets[gi + 1])
        res[g.name], nrm[g.name], used[g.name] = r[sl].copy(), wtest[sl].copy(), act[sl].copy()
    rej_list = []
    for p, info in sorted(rejected.items()):
        g = P.groups[int(pts.group[p])]
        kp = info["dof"]
        rej_list.append({"group": g.name, "point": int(pts.point[p]),
                         "name": str(g.point_names[int(pts.point[p])]),
                         "statistic": info["statistic"],
                         "critical": float(stats.chi2.ppf(1 - alpha, max(kp, 1))),
                         "phase": info["phase"]})
    return Solution(list(P.names), list(P.units), x, P.x0.copy(), P.fixed.copy(), cov,
                    float(math.sqrt(s0sq)) if np.isfinite(s0sq) and s0sq >= 0 else float("nan"),
                    redundancy, components, res, nrm, used, rej_list, state["iters"],
                    state["evals"], bool(converged), history,
                    state["remaining"] if converged else None)
