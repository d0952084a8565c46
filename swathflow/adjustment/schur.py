"""Normal equations with the point unknowns eliminated block by block (Schur complement).

The unknowns split into *camera* unknowns (the calibration parameters, few) and *point*
unknowns: blocks of ``k`` (3: a ground point's coordinates) that each observation touches
at most one of. The normal matrix is then ``[[Ncc, W], [W', H]]`` with ``H`` block
diagonal; with ``B = W H^-1`` the reduced system ``S = Ncc - B W'`` over the camera
unknowns is solved (dense Cholesky for a few hundred unknowns, sparse LU above), and each
point's step follows from its own ``k x k`` block. Memory grows with the number of points,
not with its square.

The cofactor matrix is never formed whole: for an observation row ``j = (j_c, j_p)`` of
point block ``b``, ``j Q j' = u Qcc u' + j_p H_b^-1 j_p'`` with ``u = j_c - B_b j_p``
(:class:`SchurCovariance`), which gives the redundancy numbers and the per-point blocks of
the blunder tests.
"""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from swathflow.adjustment.normal import factorize
from swathflow.adjustment.problem import RankDeficiencyError

#: camera unknowns above which the reduced system is solved sparse
SPARSE_REDUCED = 300


class PointSplit:
    """The free columns of a Jacobian split into the camera part (dense, ``(m, nc)``) and
    one point block per row (``block`` (m,), -1 for none; ``jp`` ``(m, k)``)."""

    def __init__(self, Jf, cam, point_of, slot_of, n_blocks: int, k: int):
        Jf = sp.csr_matrix(Jf)
        m = Jf.shape[0]
        self.Jc = Jf[:, cam].toarray()
        coo = Jf.tocoo()
        pb = point_of[coo.col]
        sel = pb >= 0
        rows, blocks = coo.row[sel], pb[sel]
        self.block = -np.ones(m, np.intp)
        self.block[rows] = blocks
        if np.any(self.block[rows] != blocks):
            raise ValueError("an observation touches two point blocks")
        self.jp = np.zeros((m, k))
        np.add.at(self.jp, (rows, slot_of[coo.col[sel]]), coo.data[sel])
        self.n_blocks, self.k = n_blocks, k


class SchurNormal:
    """Damped normal equations of the free unknowns (``free_cam``: positions among the
    free unknowns of the camera unknowns, ``free_blocks`` ``(P, k)``: of the point
    unknowns), the point blocks eliminated; the same interface as ``normal._Normal``."""

    def __init__(self, split: PointSplit, w, free_cam, free_blocks, constraints, damping,
                 names, rcond):
        self.split, self.w = split, w
        self.free_cam, self.free_blocks = free_cam, free_blocks
        nc, P, k = free_cam.size, free_blocks.shape[0], free_blocks.shape[1]
        self.nf = nc + P * k
        Jc, jp, blk = split.Jc, split.jp, split.block
        has = blk >= 0
        Ncc = (Jc * w[:, None]).T @ Jc
        # the sums over each point's rows as sparse products: Sel[row, block * k + a] =
        # w jp[row, a], so (Sel' jp)[(p, a), b] = H[p, a, b], (Sel' Jc)[(p, a), c] = W[p, c, a]
        rows = np.flatnonzero(has)
        Sel = sp.csr_matrix(((w[rows, None] * jp[rows]).ravel(),
                             (np.repeat(rows, k), (blk[rows, None] * k + np.arange(k)).ravel())),
                            shape=(Jc.shape[0], P * k))
        H = np.asarray(Sel.T @ jp).reshape(P, k, k)
        W = np.ascontiguousarray(np.asarray(Sel.T @ Jc).reshape(P, k, nc).transpose(0, 2, 1))
        self.diag_c = np.diag(Ncc).copy()
        self.diag_p = np.einsum("pii->pi", H).copy()
        if damping:
            Ncc = Ncc + damping * np.diag(self.diag_c)
            idx = np.arange(k)
            H[:, idx, idx] += damping * self.diag_p
        self._check_points(H, names, free_blocks, rcond)
        self.Hinv = np.linalg.inv(H)
        self.B = W @ self.Hinv                                      # (P, nc, k)
        # sum over points of B_p W_p' as one matrix product (einsum's loop: 0.4 s here)
        S = Ncc - self.B.transpose(1, 0, 2).reshape(nc, -1) @ W.transpose(1, 0, 2).reshape(
            nc, -1).T
        S = 0.5 * (S + S.T)
        C = [((A.tocsc()[:, free_cam].toarray() if sp.issparse(A) else
               np.asarray(A)[:, free_cam]), d) for A, d in constraints]
        self.nc = sum(d.size for _, d in C)
        cam_names = [names[i] for i in free_cam]
        _check_reduced(S, C, cam_names, rcond)
        if self.nc:
            Cm = np.vstack([a for a, _ in C])
            K = np.block([[S, Cm.T], [Cm, np.zeros((self.nc, self.nc))]])
        else:
            K = S
        self._solve_reduced = factorize(K, nc > SPARSE_REDUCED, bool(self.nc),
                                        "the reduced normal equations")
        self.W = W
        self.ncam = nc

    @staticmethod
    def _check_points(H, names, free_blocks, rcond):
        d = np.sqrt(np.abs(np.einsum("pii->pi", H)))
        s = np.where(d > 0, 1.0 / np.where(d > 0, d, 1.0), 0.0)
        Hs = H * s[:, :, None] * s[:, None, :]
        ev = np.linalg.eigvalsh(Hs)
        bad = (ev[:, 0] < rcond * np.maximum(ev[:, -1], 1e-300)) | (d == 0).any(axis=1)
        if bad.any():
            p = np.flatnonzero(bad)
            text = ", ".join(names[free_blocks[i, 0]] for i in p[:5])
            raise RankDeficiencyError(
                f"the observations do not determine {p.size} point(s) ({text}): they need "
                f"two rays or a prior", [{names[j]: 1.0} for i in p[:6]
                                         for j in free_blocks[i]])

    def _assemble(self, dc, dp):
        out = np.zeros(self.nf)
        out[self.free_cam] = dc
        out[self.free_blocks.ravel()] = dp.ravel()
        return out

    def solve(self, g, cres=None):
        gc = g[self.free_cam]
        gp = g[self.free_blocks]                                  # (P, k)
        rhs = gc - np.einsum("pck,pk->c", self.B, gp)
        if self.nc:
            rhs = np.concatenate([rhs, cres])
        dc = self._solve_reduced(rhs)[:self.ncam]
        dp = np.einsum("pkl,pl->pk", self.Hinv, gp - np.einsum("pck,c->pk", self.W, dc))
        return self._assemble(dc, dp)

    def step_norm2(self, dx) -> float:
        """``dx' N dx`` (undamped), through the Jacobian."""
        dc, dp = dx[self.free_cam], dx[self.free_blocks]
        s = self.split
        v = s.Jc @ dc + np.einsum("mk,mk->m", s.jp, dp[np.maximum(s.block, 0)]) * (
            s.block >= 0)
        return float(np.sum(self.w * v ** 2))

    def covariance(self) -> "SchurCovariance":
        E = np.zeros((self.ncam + self.nc, self.ncam))
        E[np.arange(self.ncam), np.arange(self.ncam)] = 1.0
        Qcc = self._solve_reduced(E)[:self.ncam]
        return SchurCovariance(0.5 * (Qcc + Qcc.T), self)


class SchurCovariance:
    """The cofactor matrix of the free unknowns in factored form (module docstring)."""

    def __init__(self, Qcc, ne: SchurNormal):
        self.Qcc, self.ne = Qcc, ne
        s = ne.split
        has = s.block >= 0
        self.U = s.Jc.copy()
        self.U[has] -= np.einsum("mck,mk->mc", ne.B[s.block[has]], s.jp[has])

    def diag_jqjt(self, J=None) -> np.ndarray:
        s, ne = self.ne.split, self.ne
        out = np.einsum("mc,mc->m", self.U @ self.Qcc, self.U)
        has = s.block >= 0
        out[has] += np.einsum("mk,mkl,ml->m", s.jp[has], ne.Hinv[s.block[has]], s.jp[has])
        return out

    def point_blocks(self, J, obs_idx: np.ndarray) -> np.ndarray:
        s, ne = self.ne.split, self.ne
        valid = obs_idx >= 0
        flat = np.where(valid, obs_idx, 0)
        U = self.U[flat] * valid[..., None]                          # (Pt, k, nc)
        out = np.einsum("pic,cd,pjd->pij", U, self.Qcc, U, optimize=True)
        b = np.where(valid, s.block[flat], -1)
        jp = s.jp[flat] * valid[..., None]
        same = (b[:, :, None] == b[:, None, :]) & (b[:, :, None] >= 0)
        Hb = ne.Hinv[np.maximum(b, 0)]                               # (Pt, k, 3, 3)
        jh = np.einsum("pia,piab->pib", jp, Hb)
        out += np.where(same, np.einsum("pib,pjb->pij", jh, jp), 0.0)
        return out

    def camera(self) -> np.ndarray:
        return self.Qcc

    def point(self) -> np.ndarray:
        """The point blocks of the cofactor matrix ``(P, k, k)``."""
        ne = self.ne
        return ne.Hinv + np.einsum("pck,cd,pdl->pkl", ne.B, self.Qcc, ne.B, optimize=True)

    def full(self, sparse: bool) -> np.ndarray | sp.spmatrix:
        """The cofactor matrix over the free unknowns: dense, or (``sparse``) its camera
        block, the camera-point blocks and each point's own block."""
        ne = self.ne
        n, fc, fb = ne.nf, ne.free_cam, ne.free_blocks
        Qcp = -np.einsum("cd,pdk->cpk", self.Qcc, ne.B).reshape(fc.size, -1)
        if not sparse:
            Q = np.zeros((n, n))
            cols = fb.ravel()
            Q[np.ix_(fc, fc)] = self.Qcc
            Q[np.ix_(fc, cols)] = Qcp
            Q[np.ix_(cols, fc)] = Qcp.T
            Bf = ne.B.transpose(1, 0, 2).reshape(fc.size, -1)        # (nc, P k)
            Qpp = Bf.T @ self.Qcc @ Bf
            P, k = fb.shape
            for a in range(k):
                for c in range(k):
                    Qpp[np.arange(P) * k + a, np.arange(P) * k + c] += ne.Hinv[:, a, c]
            Q[np.ix_(cols, cols)] = Qpp
            return Q
        P, k = fb.shape
        rows, cols_, vals = [], [], []
        r, c = np.meshgrid(fc, fc, indexing="ij")
        rows.append(r.ravel())
        cols_.append(c.ravel())
        vals.append(self.Qcc.ravel())
        r, c = np.meshgrid(fc, fb.ravel(), indexing="ij")
        for a, b in ((r, c), (c, r)):
            rows.append(a.ravel())
            cols_.append(b.ravel())
        vals += [Qcp.ravel(), Qcp.ravel()]
        pb = self.point()
        rows.append(np.repeat(fb, k, axis=1).ravel())
        cols_.append(np.tile(fb, (1, k)).ravel())
        vals.append(pb.ravel())
        return sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows),
                                                     np.concatenate(cols_))), shape=(n, n))


def _check_reduced(S, C, names, rcond):
    """The camera unknowns' reduced system determines them (as ``normal._Normal``)."""
    from swathflow.adjustment.normal import check_determined
    names = np.asarray(names, dtype=object)
    Nd = S.copy()
    diag = np.diag(S)
    if C:
        Cd = np.vstack([a for a, _ in C])
        Nd = Nd + Cd.T @ Cd * (np.abs(diag).max() / max(np.abs(Cd).max(), 1e-300) ** 2)
    check_determined(Nd, names, rcond)
