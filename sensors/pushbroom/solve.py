"""Ground to image for the push-broom model: the line and the element of ground points.

Every image line is one instant, so a ground point is seen on the line whose viewing plane
contains it, at the element whose viewing angles point at it. :class:`GroundSolver` (a base
of :class:`~swathflow.sensors.pushbroom.model.PushbroomModel`) brackets the line with the
viewing plane of the middle element, then solves the two conditions
``(r - tan_psi_x(s), q - tan_psi_y(s)) = 0`` jointly in (line, element) by Newton, with the
state linear between the model's knots, then exact correction steps where that
interpolation is not negligible. It reads the knots and the state of the model
(``_kline``, ``_Mt``, ``_p``, ``_cq``, ``_nvec``, ``_dvec``, ``_state_t``, ``view_tangents``).
"""
from __future__ import annotations

import numpy as np

from swathflow.geometry.rotations import apply_t
from swathflow.sensors.pushbroom.frames import matvec


class GroundSolver:
    """The solve of :meth:`ground_to_image` and the implicit-function Jacobian it returns
    (a mixin: the model supplies the knots and the state)."""

    #: points per block in the solve (temporaries stay in cache: about 2.5x faster)
    chunk: int = 32768
    #: exact correction steps follow the interpolated solve when linear interpolation of
    #: the state between lines is estimated to be off by more than this (pixels)
    exact_threshold_px: float = 1e-4

    def _solve(self, g: np.ndarray):
        """Lines and elements of ECEF points ``g`` (n, 3) and the 2x2 Jacobian of the
        conditions (r - tan_psi_x, q - tan_psi_y) in (line, element) at the solution."""
        n = g.shape[0]
        line = np.full(n, np.nan)
        elem = np.full(n, np.nan)
        jac = np.full((n, 2, 2), np.nan)
        if self.n_lines < 2:
            return line, elem, jac
        for i0 in range(0, n, self.chunk):
            sl = slice(i0, i0 + self.chunk)
            line[sl], elem[sl], jac[sl] = self._solve_block(g[sl])
        return line, elem, jac

    def _solve_block(self, g: np.ndarray, tol: float = 1e-7, max_iter: int = 10):
        """Bracket the knot interval with the viewing plane of the middle element, then
        Newton jointly in (line, element) with position and rotation linear between the two
        knots (the camera vector is then quadratic in the fraction), moving to the
        neighbouring interval while the solution lies outside; then exact correction steps
        when that interpolation is not negligible. Points the plane does not bracket but
        that lie within a few lines of an end start from that end."""
        n = g.shape[0]
        line = np.full(n, np.nan)
        elem = np.full(n, np.nan)
        jac = np.full((n, 2, 2), np.nan)
        K = self._kline.size
        L = self.n_lines
        nv, dv = self._nvec, self._dvec

        def f_at(i, j):
            if i is None:                  # all points, one line: no gathers
                return g @ nv[j] - dv[j]
            gi = g[i]
            nj = nv[j]
            return nj[:, 0] * gi[:, 0] + nj[:, 1] * gi[:, 1] + nj[:, 2] * gi[:, 2] - dv[j]

        j, fj, fj1, found = _bracket(f_at, n, L)     # over lines (uniform steps)
        with np.errstate(invalid="ignore", divide="ignore"):
            w = fj / (fj - fj1)
        # near misses at the ends (the middle element's plane is not the point's plane)
        near = ~found & np.isfinite(fj) & np.isfinite(fj1)
        if near.any():
            i = np.flatnonzero(near)
            f0, fK = fj[i], fj1[i]
            first = np.abs(f0) < np.abs(fK)
            jj = np.where(first, 0, L - 2)
            slope = np.abs(f_at(i, jj + 1) - f_at(i, jj))
            close = np.where(first, np.abs(f0), np.abs(fK)) < 20 * slope
            i, jj, first = i[close], jj[close], first[close]
            found[i] = True
            j[i] = jj
            w[i] = np.where(first, 0.0, 1.0)
        k = np.flatnonzero(found)
        if k.size == 0:
            return line, elem, jac
        # camera vector at the bracket's first line: element guess, then the line estimate
        # corrected from the middle element's plane to the guessed element's
        gk = g[k]
        jl, w = j[k], np.where(np.isfinite(w[k]), w[k], 0.5)
        kj = self._line_knot[jl]
        g0 = matvec(self._Mt[kj], gk) - self._p[kj]
        with np.errstate(invalid="ignore", divide="ignore"):
            s = self._element_guess(g0[:, 1] / -g0[:, 2])
            dw = (self.view_tangents(s)[0] - self._tpx_mid) * g0[:, 2] / (fj[k] - fj1[k])
        l0 = jl + w + np.where(np.isfinite(dw), dw, 0.0)
        kl, dl = self._kline, self._dline
        j = np.clip(np.searchsorted(kl, l0, side="right") - 1, 0, K - 2)
        w = (l0 - kl[j]) / dl[j]
        a, b, c = self._quadratic(gk, j)
        w, s, J, gz = self._newton(a, b, c, w, s, tol, max_iter)
        for _ in range(4):  # solutions outside [j, j + 1]: move there and solve again
            out = np.flatnonzero((w < -1e-9) | (w > 1 + 1e-9))
            lo_ = kl[j[out]] + w[out] * dl[j[out]]
            jn = np.clip(np.searchsorted(kl, lo_, side="right") - 1, 0, K - 2)
            keep = jn != j[out]
            mv, jn, lo_ = out[keep], jn[keep], lo_[keep]
            if mv.size == 0:
                break
            j[mv] = jn
            wm = (lo_ - kl[jn]) / dl[jn]
            am, bm, cm = self._quadratic(gk[mv], j[mv])
            w[mv], s[mv], J[mv], gz[mv] = self._newton(am, bm, cm, wm, s[mv], tol, max_iter)
        lk = kl[j] + w * dl[j]
        J[:, :, 0] /= dl[j][:, None]          # d/dw -> d/dline
        if self._interp_px > self.exact_threshold_px:
            for _ in range(3):
                F = self._conditions_exact(gk, lk, s)
                d_l, d_e = _solve2(J, F)
                lk, s = lk - d_l, s - d_e
                if np.nanmax(np.abs(d_l) + np.abs(d_e), initial=0.0) < 1e-8:
                    break
        ok = np.isfinite(lk) & (gz < 0) & (lk >= -1e-6) & (lk <= self.n_lines - 1 + 1e-6)
        line[k] = np.where(ok, lk, np.nan)
        elem[k] = np.where(ok, s, np.nan)
        jac[k] = J
        return line, elem, jac

    def _quadratic(self, g, j):
        """g_S(w) = a + w b + w^2 c: the camera-frame vector of ``g`` at the fraction ``w``
        of knot interval ``j``, with position and rotation linear between the knots."""
        a = matvec(self._Mt[j], g) - self._p[j]
        e = matvec(self._Mt[j + 1], g) - self._p[j + 1]
        c = self._cq[j]
        return a, e - a - c, c

    def _newton(self, a, b, c, w, s, tol, max_iter):
        for _ in range(max_iter):
            gw = a + w[:, None] * (b + w[:, None] * c)
            dg = b + 2 * w[:, None] * c
            F, J = self._cond_jac(gw, dg, s)
            dw, ds = _solve2(J, F)
            w = w - dw
            s = s - ds
            if np.nanmax(np.abs(dw) + np.abs(ds) * 1e-3, initial=0.0) < tol:
                break   # converged: J (one step old) is as good as new
        return w, s, J, gw[:, 2]

    def _cond_jac(self, gw, dg, s):
        """Conditions F = (g_x/-g_z - tan_psi_x(s), g_y/-g_z - tan_psi_y(s)) and their
        Jacobian in (w, element), given g and dg/dw."""
        with np.errstate(invalid="ignore", divide="ignore"):
            iz = -1.0 / gw[:, 2]
            r = gw[:, 0] * iz
            q = gw[:, 1] * iz
            dr = (dg[:, 0] + r * dg[:, 2]) * iz
            dq = (dg[:, 1] + q * dg[:, 2]) * iz
        tx, ty, dtx, dty = self.view_tangents(s)
        F = np.stack([r - tx, q - ty], axis=-1)
        J = np.empty(gw.shape[:1] + (2, 2))
        J[:, 0, 0], J[:, 0, 1], J[:, 1, 0], J[:, 1, 1] = dr, -dtx, dq, -dty
        return F, J

    def _camera_vector(self, g, line) -> np.ndarray:
        c, r = self._state_t(self._line_time(line))
        return apply_t(r, g - c)

    def _conditions_exact(self, g, line, s) -> np.ndarray:
        ok = np.isfinite(line) & np.isfinite(s)
        F = np.full(line.shape + (2,), np.nan)
        if ok.any():
            gv = self._camera_vector(g[ok], np.clip(line[ok], 0, self.n_lines - 1))
            tx, ty, _, _ = self.view_tangents(s[ok])
            with np.errstate(invalid="ignore", divide="ignore"):
                F[ok, 0] = gv[:, 0] / -gv[:, 2] - tx
                F[ok, 1] = gv[:, 1] / -gv[:, 2] - ty
        return F


def _bracket(f_at, n: int, K: int):
    """Like :func:`swathflow.geometry.linesolve.bracket_lines` (same returns; ``f_at(None, j)``
    evaluates all points at one line ``j``), but faster for the
    near-linear push-broom condition: each step evaluates ``m`` and ``m + 1`` at a guess
    (first the bracket's chord, then a Newton step with the local slope ``f(m+1) - f(m)``)
    and usually settles in two or three steps; from the fourth step on, a step that does not
    halve the bracket makes the next one a bisection, so the worst case stays logarithmic."""
    lo = np.zeros(n, dtype=np.intp)
    hi = np.full(n, K - 1, dtype=np.intp)
    flo = f_at(None, 0)
    fhi = f_at(None, K - 1)
    found = (np.sign(flo) != np.sign(fhi)) & np.isfinite(flo) & np.isfinite(fhi)
    x = np.zeros(n)
    with np.errstate(invalid="ignore", divide="ignore"):
        x[:] = flo / (flo - fhi) * (K - 1)          # chord
    bisect = np.zeros(n, bool)
    act = np.flatnonzero(found & (hi - lo > 1))
    step = 0
    while act.size:
        step += 1
        l, h, fl = lo[act], hi[act], flo[act]
        xa = x[act]
        m = np.where(bisect[act] | ~np.isfinite(xa), (l + h) // 2,
                     np.floor(np.nan_to_num(xa)).astype(np.intp))
        m = np.clip(m, l + 1, h - 1)
        m1 = np.minimum(m + 1, h)
        fm = f_at(act, m)
        fm1 = f_at(act, m1)
        same = np.sign(fm) == np.sign(fl)
        same1 = np.sign(fm1) == np.sign(fl)
        # the root lies in (l, m), (m, m1) or (m1, h)
        nl = np.where(same, np.where(same1, m1, m), l)
        nfl = np.where(same, np.where(same1, fm1, fm), fl)
        nh = np.where(same, np.where(same1, h, m1), m)
        nfh = np.where(same, np.where(same1, fhi[act], fm1), fm)
        bisect[act] = (step >= 4) & ((nh - nl) * 2 > (h - l))
        with np.errstate(invalid="ignore", divide="ignore"):
            x[act] = m - fm / (fm1 - fm)           # Newton with the local slope
        lo[act], hi[act], flo[act], fhi[act] = nl, nh, nfl, nfh
        act = act[(nh - nl) > 1]
    return lo, flo, fhi, found


def _solve2(J, F) -> tuple[np.ndarray, np.ndarray]:
    """Solve the 2x2 systems ``J x = F`` (stacked), NaN where singular."""
    det = J[:, 0, 0] * J[:, 1, 1] - J[:, 0, 1] * J[:, 1, 0]
    with np.errstate(invalid="ignore", divide="ignore"):
        x0 = (J[:, 1, 1] * F[:, 0] - J[:, 0, 1] * F[:, 1]) / det
        x1 = (J[:, 0, 0] * F[:, 1] - J[:, 1, 0] * F[:, 0]) / det
    return x0, x1
