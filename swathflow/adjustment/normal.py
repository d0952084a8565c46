"""Normal equations (dense or sparse, bordered by hard constraints) with a rank check that
names the undetermined directions, and the per-point statistics of the blunder tests."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg as sla
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from swathflow.adjustment.problem import Problem, RankDeficiencyError


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
        self._solve = factorize(K, sparse, bool(self.nc), "the normal equations")

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
        check_determined(Nd, names, rcond)

    def step_norm2(self, dx) -> float:
        return float(dx @ (self.N @ dx))

    def covariance(self) -> _DenseCov:
        return _DenseCov(self.inverse())

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


class _DenseCov:
    """The cofactor matrix ``Q`` of the free unknowns, formed densely."""

    def __init__(self, Q):
        self.Q = Q

    def diag_jqjt(self, J) -> np.ndarray:
        return _diag_jqjt(J, self.Q)

    def point_blocks(self, J, obs_idx) -> np.ndarray:
        return _point_blocks(J, self.Q, obs_idx)

    def full(self, sparse: bool = False) -> np.ndarray:
        return self.Q


def _directions(vectors, names) -> list[dict[str, float]]:
    """Each column of ``vectors`` (an undetermined direction) as {name: weight}, the
    weights scaled to a largest magnitude of 1 and listed largest first (above 0.1)."""
    out = []
    for v in vectors.T:
        v = v / (np.abs(v).max() or 1.0)
        order = np.argsort(-np.abs(v))
        out.append({str(names[i]): round(float(v[i]), 3) for i in order if abs(v[i]) > 0.1})
    return out


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


def check_determined(Nd, names, rcond) -> None:
    """Raise :class:`RankDeficiencyError` naming the combinations of unknowns that the
    dense normal matrix ``Nd`` (constraints already added) leaves undetermined: its
    eigenvectors, after scaling to a unit diagonal, below ``rcond`` of the largest, and
    the unknowns no observation touches."""
    d = np.sqrt(np.abs(np.diag(Nd)))
    s = np.where(d > 0, 1.0 / np.where(d > 0, d, 1.0), 0.0)
    ev, vec = np.linalg.eigh(Nd * np.outer(s, s))
    bad = ev < rcond * max(ev.max(), 1e-300)
    bad_cols = np.flatnonzero(d == 0)
    if not bad.any() and not bad_cols.size:
        return
    directions = _directions(vec[:, bad] * s[:, None], names) + \
        [{str(names[i]): 1.0} for i in bad_cols]
    text = "; ".join(" + ".join(f"{w:+.2f}*{n}" for n, w in dd.items()) or "?"
                     for dd in directions[:6])
    raise RankDeficiencyError(
        f"the observations do not determine {len(directions)} combination(s) of the "
        f"unknowns: {text}. Add observations that separate them, add priors, or fix "
        f"some of them", directions)


def factorize(K, sparse: bool, bordered: bool, what: str):
    """The solver ``b -> K^-1 b`` of the normal matrix ``K``: a sparse LU, a dense LU when
    hard constraints border it (indefinite) or a Cholesky factor. A singular ``K`` is a
    :class:`RankDeficiencyError` naming ``what`` (e.g. "the normal equations")."""
    try:
        if sparse:
            return spla.splu(sp.csc_matrix(K)).solve
        if bordered:
            lu = sla.lu_factor(K)
            return lambda b: sla.lu_solve(lu, b)
        cf = sla.cho_factor(K)
        return lambda b: sla.cho_solve(cf, b)
    except (RuntimeError, np.linalg.LinAlgError, sla.LinAlgError) as exc:
        raise RankDeficiencyError(
            f"{what} are singular ({exc}); fix unknowns, add priors or add observations",
            []) from None
