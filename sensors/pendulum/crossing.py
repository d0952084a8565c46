"""The numpy path of the pendulum's ground_to_image (the reference of the compiled kernel,
and its fallback where the POS has a gap): the fractional line where a ground point crosses
the scan plane, refined inside its bracketing pair of lines (inverse quadratic through one
exact evaluation, Lagrange camera vector; split at a POS epoch; exact secant where rough).
:class:`Crossing` is mixed into ``PendulumModel``, whose frames and camera vectors it uses."""
from __future__ import annotations

import numpy as np

from swathflow.geometry.linesolve import bracket_lines, plane_brackets, secant_lines
from swathflow.geometry.rotations import apply_t

#: root estimates (secant, inverse quadratic) further apart than this (lines) mark a
#: condition that is not smooth inside the line: those points are solved exactly
ROUGH_LINE = 1e-6


def _quadratic_root(x0, x2, f0, f2, l1, f1):
    """The root inside brackets ``[x0, x2]`` (condition ``f0``, ``f2`` at the ends, ``f1``
    at the chord point ``l1``): the inverse quadratic through the three, the secant
    against the bracket end on the other side of the chord point where the quadratic
    leaves the bracket; and where the two differ by more than ``ROUGH_LINE`` (rough:
    solve exactly)."""
    same = np.sign(f1) == np.sign(f0)
    ja = np.where(same, x2, x0)
    fa = np.where(same, f2, f0)
    with np.errstate(invalid="ignore", divide="ignore"):
        w = f1 / (f1 - fa)
    line = l1 + np.where(np.isfinite(w), w, 0.0) * (ja - l1)
    with np.errstate(invalid="ignore", divide="ignore"):
        q = (x0 * f1 * f2 / ((f0 - f1) * (f0 - f2))
             + l1 * f0 * f2 / ((f1 - f0) * (f1 - f2))
             + x2 * f0 * f1 / ((f2 - f0) * (f2 - f1)))
    use = np.isfinite(q) & (q >= x0) & (q <= x2)
    return np.where(use, q, line), ~use | (np.abs(q - line) > ROUGH_LINE)


def _lagrange(line, x0, x1, x2, cam0, cam1, cam2):
    """Camera vectors at ``line``: the quadratic through those at x0, x1, x2 (linear
    between the ends where the chord point sits on one)."""
    with np.errstate(invalid="ignore", divide="ignore"):
        L0 = (line - x1) * (line - x2) / ((x0 - x1) * (x0 - x2))
        L1 = (line - x0) * (line - x2) / ((x1 - x0) * (x1 - x2))
        L2 = (line - x0) * (line - x1) / ((x2 - x0) * (x2 - x1))
    ok = np.isfinite(L0) & np.isfinite(L1) & np.isfinite(L2)
    t = (line - x0) / (x2 - x0)
    lin = cam0 + t[:, None] * (cam2 - cam0)
    with np.errstate(invalid="ignore"):       # the non-finite weights are not selected
        return np.where(ok[:, None], L0[:, None] * cam0 + L1[:, None] * cam1
                        + L2[:, None] * cam2, lin)


class Crossing:
    """The numpy crossing solve of ``PendulumModel`` (see the module docstring)."""

    def _refine(self, g, j, fj, fj1):
        """Fractional line and camera vector of points ``g`` crossing between ``j, j+1``.

        One exact evaluation at the chord of the bracket; the root is then the inverse
        quadratic interpolation through the condition at ``j``, the chord point and
        ``j + 1``, and the camera vector there is the quadratic through the camera vectors
        at the same three lines (exact at the integer lines from their frames). Where that
        root leaves the bracket or differs from the secant step against the far bracket end
        by more than ``ROUGH_LINE``, the point is solved exactly (secant iterations). A line
        whose times hold one POS epoch (a kink in the condition: 30 % of the lattice's
        points on the demo mission) is split at the epoch first, and the same solve made on
        the side with the sign change (:meth:`_split_at_epoch`; where that is rough, as
        above). This agrees with a fully
        converged solve to far below 0.001 px (checked in the tests; a linear
        interpolation alone left 1.2e-3 px on a wobbling swing).
        """
        nvec = np.array([0.0, self._f, self._y0])
        with np.errstate(invalid="ignore", divide="ignore"):
            l1 = j + fj / (fj - fj1)
        l1 = np.where(np.isfinite(l1), l1, j + 0.5)
        cam1 = self._camera_of(l1, g)
        x0, x2 = j.astype(float), j + 1.0
        line, rough = _quadratic_root(x0, x2, fj, fj1, l1, cam1 @ nvec)
        # where the secant and the quadratic disagree the condition is not smooth inside the
        # line (a POS sample between the two line times puts a kink in it): solve each side
        rough = np.flatnonzero(rough)
        # the camera vector at ``line``: Lagrange quadratic through the three lines
        r_es, c = self._line_frames()
        cam0 = np.einsum("nji,nj->ni", r_es[j], g - c[j])
        cam2 = np.einsum("nji,nj->ni", r_es[j + 1], g - c[j + 1])
        cam = _lagrange(line, x0, l1, x2, cam0, cam1, cam2)
        # a POS epoch inside the line puts a kink in the condition: solve each side
        lr, cr = self._split_at_epoch(g, j, fj, fj1)
        split = np.isfinite(lr)
        line, cam = np.where(split, lr, line), np.where(split[:, None], cr, cam)
        # a line holding an epoch and not split (several epochs, or the split declined):
        # one quadratic across the kinks is not trusted, its roughness test can miss them
        kinked = np.zeros(j.shape, bool)
        kinked[rough] = True
        kinked |= self._holds_epoch(j)
        rough = np.flatnonzero(kinked & ~split)
        if rough.size:      # rough, or kinked and not split: solve exactly
            line[rough], cam[rough] = self._solve_exact(g[rough], j[rough], fj[rough],
                                                        fj1[rough], tol=1e-9)
        return line, cam

    def _holds_epoch(self, j):
        """True where the times of lines ``j`` and ``j + 1`` hold a POS epoch between them
        (strictly inside: a kink of the condition)."""
        time = np.asarray(self._trajectory.time, float)
        t0, t1 = self._line_cols[j, 0], self._line_cols[j + 1, 0]
        k = np.searchsorted(time, t0, side="right")
        return (k < time.size) & (time[np.minimum(k, time.size - 1)] < t1)

    def _split_at_epoch(self, g, j, fj, fj1):
        """The root inside lines ``[j, j+1]`` whose times hold one POS epoch (a kink of
        the condition): one exact evaluation at the epoch's fractional line picks the
        smooth side with the sign change, where the root is the inverse quadratic through
        its ends and one exact evaluation at its chord point (as in :meth:`_refine`). NaN
        lines where a line holds no single epoch or that solve is rough (the caller solves
        exactly)."""
        nvec = np.array([0.0, self._f, self._y0])
        time = np.asarray(self._trajectory.time, float)
        n = time.size
        t0, t1 = self._line_cols[j, 0], self._line_cols[j + 1, 0]
        k = np.searchsorted(time, t0, side="right")
        te, tn = time[np.minimum(k, n - 1)], time[np.minimum(k + 1, n - 1)]
        le = j + (te - t0) / (t1 - t0)
        one = ((k + 1 < n) & (te > t0) & (te < t1) & ~((k + 2 < n) & (tn < t1))
               & (le > j) & (le < j + 1))
        line, cam = np.full(j.shape, np.nan), np.full(g.shape, np.nan)
        i = np.flatnonzero(one)
        if not i.size:
            return line, cam
        g, j, fj, fj1, le = g[i], j[i], fj[i], fj1[i], le[i]
        r_es, c = self._line_frames()
        cam_e = self._camera_of(le, g)
        fe = cam_e @ nvec
        after = np.sign(fe) == np.sign(fj)          # the root is after the epoch
        jj = np.where(after, j + 1, j)
        cam_j = np.einsum("nji,nj->ni", r_es[jj], g - c[jj])
        x0, f0 = np.where(after, le, j), np.where(after, fe, fj)
        x2, f2 = np.where(after, j + 1.0, le), np.where(after, fj1, fe)
        c0 = np.where(after[:, None], cam_e, cam_j)
        c2 = np.where(after[:, None], cam_j, cam_e)
        with np.errstate(invalid="ignore", divide="ignore"):
            l1 = x0 + f0 / (f0 - f2) * (x2 - x0)
        l1 = np.where(np.isfinite(l1), l1, (x0 + x2) / 2)
        cam1 = self._camera_of(l1, g)
        ln, rough = _quadratic_root(x0, x2, f0, f2, l1, cam1 @ nvec)
        cm = _lagrange(ln, x0, l1, x2, c0, cam1, c2)
        zero = fe == 0
        ln, cm = np.where(zero, le, ln), np.where(zero[:, None], cam_e, cm)
        ln[rough & ~zero] = np.nan
        line[i], cam[i] = ln, cm
        return line, cam

    def _solve_exact(self, g, j, fj, fj1, tol: float):
        """Secant iterations on the exact condition inside brackets ``[j, j+1]``; the
        fractional lines and the exact camera vectors there."""
        nvec = np.array([0.0, self._f, self._y0])

        def f_exact(i, line):
            c, r = self._state(line)
            return apply_t(r, g[i] - c) @ nvec

        line = secant_lines(f_exact, j, fj, fj1, tol=tol, max_iter=30)
        c, r = self._state(line)
        return line, apply_t(r, g - c)

    def _line_frames(self) -> tuple[np.ndarray, np.ndarray]:
        """R_ES and the projection centre at every integer line (computed on first use)."""
        if getattr(self, "_r_es_lines", None) is None:
            sh = self._shared
            r_bs = np.einsum("ij,njk->nik", self._R_bp, sh["r_ph"]) @ self._R_hs
            self._r_es_lines = np.einsum("nij,njk->nik", sh["r_eb"], r_bs)
        return self._r_es_lines, self._c_lines

    def _ground_to_image_converged(self, ground) -> np.ndarray:
        """Reference solve: secant iterations to 1e-12 line (tests compare the fast path)."""
        g = np.asarray(ground, float).reshape(-1, 3)
        cl, nl = self._c_lines, self._n_lines
        j, fj, fj1, found = bracket_lines(
            lambda i, jj: np.einsum("ij,ij->i", nl[jj], g[i] - cl[jj]), g.shape[0], self.n_lines)
        k = np.flatnonzero(found)
        line, cam = self._solve_exact(g[k], j[k], fj[k], fj1[k], tol=1e-12)
        out = np.full((g.shape[0], 2), np.nan)
        out[k, 0] = line
        out[k, 1] = self._k0 + self._f * cam[:, 0] / (-cam[:, 2]) / self._pp
        return out

    def _pixels(self, line, cam, clip: bool) -> np.ndarray:
        """(line, element) from fractional lines and camera vectors; NaN behind the camera
        and, with ``clip``, off the detector."""
        with np.errstate(invalid="ignore", divide="ignore"):
            elem = self._k0 + self._f * cam[:, 0] / (-cam[:, 2]) / self._pp
        front = cam[:, 2] < 0
        elem = np.where(front, elem, np.nan)
        line = np.where(front, line, np.nan)
        if clip:
            off = (elem < -0.5) | (elem > self.n_elements - 0.5)
            elem = np.where(off, np.nan, elem)
            line = np.where(off, np.nan, line)
        return np.stack([line, elem], axis=-1)

    def _ground_to_image_numpy(self, g, clip: bool) -> np.ndarray:
        """The numpy path (reference for the compiled one, and its fallback)."""
        n = g.shape[0]
        out = np.full((n, 2), np.nan)
        planes = self._planes

        def f_int(i, j):
            pl = planes[j]
            gi = g[i]
            return (pl[:, 0] * gi[:, 0] + pl[:, 1] * gi[:, 1] + pl[:, 2] * gi[:, 2]
                    + pl[:, 3])

        lo, hi, flo, fhi = plane_brackets(g, planes)
        j, fj, fj1, found = bracket_lines(f_int, n, self.n_lines, lo, hi, flo, fhi)
        k = np.flatnonzero(found)
        if k.size:
            out[k] = self._pixels(*self._refine(g[k], j[k], fj[k], fj1[k]), clip)
        return out
