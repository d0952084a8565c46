"""Data snooping of the estimator (:mod:`.solver`): each point's chi-square test of its
whole residual vector, with the variance components it belongs to estimated without it,
the rejection of the worst failing point (with the failing points that alone observe their
unknowns or that the adjustment hardly leans on) and the re-admission of rejected points
whose prediction passes. A mixin of the solver: it reads the solver's state (points,
weights, components, Schur split)."""
from __future__ import annotations

from typing import Any

import numpy as np
from scipy.special import chdtri

from swathflow.adjustment.normal import _block_stat

#: points whose observations all have redundancy numbers above this are rejected together
#: by data snooping (see Snooping._low_leverage)
LOW_LEVERAGE = 0.9


def critical(alpha, dof):
    """The chi-square quantile ``1 - alpha`` for ``dof`` degrees of freedom (scipy.special's
    inverse survival function: scipy.stats costs a second to import)."""
    return chdtri(dof, alpha)


class Snooping:
    """The data-snooping rounds of :class:`swathflow.adjustment.solver._Solver`."""

    # the solver's state these rounds read and update (set by the solver)
    pts: Any
    labels: list
    min_redundancy: float
    est: Any
    comp_idx: np.ndarray
    counted: np.ndarray
    point_ok: np.ndarray
    rejected: dict
    schur: Any
    _split: Any

    def statistics(self, r, J) -> tuple:
        """The normal system, its covariance, the free columns of ``J``, the weights and
        the active observations at residuals ``r`` (the solver's)."""
        raise NotImplementedError

    def a_priori_variances(self) -> np.ndarray:
        """The observations' a-priori variances with the current components (the
        solver's)."""
        raise NotImplementedError

    def snoop_stats(self, cov, Jf, r):
        """Per-point v' Qvv^-1 v with the current components, its dof, J Q J' blocks and
        the a-priori variances per point."""
        qll = self.a_priori_variances()
        obs = self.pts.obs
        blocks = cov.point_blocks(Jf, obs)
        valid = obs >= 0
        qdiag = np.where(valid, qll[np.where(valid, obs, 0)], 0.0)
        idx = np.arange(blocks.shape[1])
        qvv = -blocks.copy()
        qvv[:, idx, idx] += qdiag
        rr = np.where(np.isfinite(r), r, 0.0)
        T, k_p = _block_stat(rr, qvv, obs, qdiag)
        return T, k_p, blocks, qdiag

    def snoop(self, r, J, alpha, readmit: bool) -> str:
        """One round of data snooping: 'rejected' (the worst failing point), 'readmitted'
        (rejected points whose prediction passes), or 'done'."""
        _, Q, Jf, w, act = self.statistics(r, J)
        if Q is None:
            return "done"
        T, k_p, blocks, qdiag = self.snoop_stats(Q, Jf, r)
        T = T / self._leave_one_out(r, w, act, Q, Jf)
        crit = critical(alpha, np.maximum(k_p, 1))
        cand = self.pts.robust & self.point_ok & (k_p > 0)
        ratio = np.where(cand, T / crit, 0.0)
        if cand.any() and ratio.max() > 1.0:
            # the worst point, and with it every failing point with unknowns of its own
            # alone (a tie point's ground, :meth:`_sole_owners`): one round for them all,
            # not one re-adjustment each
            worst = int(np.argmax(ratio))
            out = (ratio > 1.0) & (self._sole_owners() | self._low_leverage(w, act, Q, Jf))
            out[worst] = True
            for p in np.flatnonzero(out):
                self.rejected[int(p)] = {"phase": "snooping", "statistic": float(T[p]),
                                         "dof": int(k_p[p])}
            self.point_ok[out] = False
            return "rejected"
        if readmit and self.rejected:
            idx = np.arange(blocks.shape[1])
            qpl = blocks.copy()
            qpl[:, idx, idx] += qdiag
            rr = np.where(np.isfinite(r), r, 0.0)
            Tp, kp = _block_stat(rr, qpl, self.pts.obs, qdiag)
            crit_p = critical(alpha, np.maximum(kp, 1))
            own = self._sole_owners()
            back = [p for p in self.rejected if not own[p] and Tp[p] <= crit_p[p]]
            for p in back:
                self.rejected.pop(p)
                self.point_ok[p] = True
            return "readmitted" if back else "done"
        return "done"

    def _low_leverage(self, w, act, cov, Jf) -> np.ndarray:
        """Per point: its observations' redundancy numbers are all at least
        :data:`LOW_LEVERAGE` (the adjustment hardly leans on it: a blunder in it hardly
        moves the unknowns or the other points' tests, so failing ones are rejected
        together; hundreds of automatic control points otherwise cost a re-adjustment
        each)."""
        red = np.where(act, 1.0 - w * cov.diag_jqjt(Jf), 0.0)
        obs = self.pts.obs
        valid = obs >= 0
        r = np.where(valid, red[np.where(valid, obs, 0)], np.inf)
        return valid.any(axis=1) & (r.min(axis=1) >= LOW_LEVERAGE)

    def _sole_owners(self) -> np.ndarray:
        """Per point: of the tested points, it alone observes its point unknowns (a tie
        point tested whole: its ground). Once rejected, such a point is not predicted by
        the adjustment (its ground then follows only its weak prior, so a prediction test
        always passes: it is not re-admitted), and a blunder in it moves its own ground,
        hardly the rest (failing ones are rejected together). Rays of one ground point
        tested one by one share it: a blunder in one fails the others, so they are
        rejected one at a time."""
        own = np.zeros(len(self.pts.group), bool)
        if self.schur is None or self._split is None:
            return own
        blk = self._split[1].block
        obs = self.pts.obs
        valid = obs >= 0
        b = np.where(valid, blk[np.where(valid, obs, 0)], -1).max(axis=1)   # its block
        has = (b >= 0) & self.pts.robust             # tested points (not the priors)
        count = np.bincount(b[has], minlength=int(b.max()) + 1 if has.any() else 0)
        own[has] = count[b[has]] == 1
        return own

    def _leave_one_out(self, r, w, act, cov, Jf) -> np.ndarray:
        """Per point, the factor of its estimated variance components were they estimated
        without it (its share of their ``v'Pv`` and redundancy left out; 1 for components
        not estimated): the test then is not blinded by a blunder that inflated the
        component it belongs to (a false tie among few)."""
        f = np.ones(len(self.pts.group))
        if not self.est:
            return f
        red = np.where(act & self.counted, 1.0 - w * cov.diag_jqjt(Jf), 0.0)
        vpv = np.where(act & self.counted, w * np.where(act, r, 0.0) ** 2, 0.0)
        est = np.array([lab in self.est for lab in self.labels])
        k = self.comp_idx
        vk = np.bincount(k, vpv, len(self.labels))
        rk = np.bincount(k, red, len(self.labels))
        obs = self.pts.obs
        valid = obs >= 0
        o = np.where(valid, obs, 0)
        kk = k[o]
        vp = np.zeros((obs.shape[0], len(self.labels)))
        rp = np.zeros_like(vp)
        rows = np.repeat(np.arange(obs.shape[0]), obs.shape[1])
        np.add.at(vp, (rows, kk.ravel()), np.where(valid, vpv[o], 0.0).ravel())
        np.add.at(rp, (rows, kk.ravel()), np.where(valid, red[o], 0.0).ravel())
        with np.errstate(invalid="ignore", divide="ignore"):
            s_all = vk / rk
            s_wo = (vk - vp) / (rk - rp)
            ratio = s_wo / s_all
        ok = est & (rk >= self.min_redundancy)
        ratio = np.where(ok[None, :] & ((rk - rp) >= self.min_redundancy) &
                         np.isfinite(ratio) & (ratio > 0), ratio, 1.0)
        wgt = rp * ok[None, :]
        tot = wgt.sum(1)
        return np.where(tot > 0, (ratio * wgt).sum(1) / np.where(tot > 0, tot, 1.0), 1.0)
