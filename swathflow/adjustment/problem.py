"""Unknowns, observation groups and the solution of an adjustment (see the package
docstring for the conventions)."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Sequence

import numpy as np
import scipy.sparse as sp

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
        self.point_blocks: np.ndarray | None = None

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

    def eliminate(self, blocks) -> None:
        """Declare point unknowns: ``blocks`` ``(P, k)`` unknown indices, one row per point
        (a ground point's coordinates). Every observation touches at most one block and the
        hard constraints none; the solver then eliminates them block by block (Schur
        complement, :mod:`swathflow.adjustment.schur`)."""
        b = np.asarray(blocks, int)
        if b.ndim != 2 or (b.size and (b.min() < 0 or b.max() >= self.n)):
            raise AdjustmentError("point blocks must be a (points, k) array of unknown "
                                  "indices")
        if np.unique(b).size != b.size:
            raise AdjustmentError("point blocks overlap")
        self.point_blocks = b if b.size else None

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
    #                                      (scipy.sparse above max_dense_cov unknowns)
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
        d = self.cov.diagonal() if sp.issparse(self.cov) else np.diag(self.cov)
        return np.sqrt(np.clip(np.asarray(d), 0, None))

    @property
    def corr(self) -> np.ndarray:
        """Correlations (dense: for solutions of up to ``max_dense_cov`` unknowns)."""
        if sp.issparse(self.cov):
            raise AdjustmentError(f"the correlation matrix of {len(self.names)} unknowns is "
                                  f"not formed densely; use cov (sparse)")
        s = self.sigma
        with np.errstate(invalid="ignore", divide="ignore"):
            c = self.cov / np.outer(s, s)
        c[~np.isfinite(c)] = 0.0
        np.fill_diagonal(c, np.where(s > 0, 1.0, 0.0))
        return c

    def value(self, name: str) -> float:
        return float(self.x[self.names.index(name)])
