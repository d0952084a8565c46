"""Partial derivatives of the push-broom model's image coordinates, by the
implicit-function theorem at the solution of the two viewing conditions (no re-solve):
with respect to the ground point in closed form, with respect to the parameters in closed
form for the APs and by central differences of the conditions for the lever arm, the
boresight and the orientation-fix corrections.

:class:`Partials` is a base of :class:`~swathflow.sensors.pushbroom.model.PushbroomModel`.
"""
from __future__ import annotations

import numpy as np

from swathflow.geometry.rotations import T, apply, apply_t, r_opk
from swathflow.sensors.pushbroom.frames import compose
from swathflow.sensors.pushbroom.viewing import AP_STEP


class Partials:
    """``parameter_partials``, ``ground_partials`` and ``fd_step_sizes`` (a mixin: the
    model supplies ``_solve``, ``_frames``, ``_state_t``, ``view_tangents`` and the
    parameter layout)."""

    def fd_step_sizes(self) -> np.ndarray:
        """A sensible finite-difference step per flat parameter (for contract tests):
        1e-4 m, 1e-4 deg, and for AP coefficient k ``1e-6 / 1000**k``."""
        out = []
        for b in self._params.blocks:
            if b.units == "":
                out += list(AP_STEP[:b.size])
            else:
                out += [self.fd_steps.get(b.units, 1e-6)] * b.size
        return np.array(out)

    def parameter_partials(self, ground, names: list[str] | None = None) -> np.ndarray:
        """d(line, element)/d(parameter), ``(..., 2, P)``, by the implicit-function theorem
        at the solution: AP columns in closed form, geometric columns from central
        differences of the conditions at the fixed (line, element) (no re-solve).
        Parameters this image does not depend on get zero columns."""
        ground = np.asarray(ground, float)
        shape = ground.shape[:-1]
        g = ground.reshape(-1, 3)
        flat = self._params.flat_names()
        sel = list(range(len(flat))) if names is None else [flat.index(n) for n in names]
        line, s, J = self._solve(g)
        out = np.zeros((g.shape[0], 2, len(sel)))
        out[~np.isfinite(line)] = np.nan
        ok = np.flatnonzero(np.isfinite(line))
        if ok.size == 0 or not sel:
            return out.reshape(shape + (2, len(sel)))
        gk, lk, sk = g[ok], line[ok], s[ok]
        segk = np.clip(np.searchsorted(self._seg, sk, side="right") - 1, 0, self._seg.size - 1)
        dsk = sk - self._seg[segk]
        dF = np.zeros((ok.size, 2, len(sel)))
        blocks = [(b.name, i) for b in self._params.blocks for i in range(b.size)]
        geo = []
        for col, p in enumerate(sel):
            if not self._relevant[p]:
                continue
            bname, comp = blocks[p]
            if bname.startswith(("ax_", "bx_")):
                seg = int(bname.rsplit("_", 1)[1])
                row = 0 if bname.startswith("ax_") else 1
                dF[:, row, col] = np.where(segk == seg, -dsk ** comp, 0.0)
            else:
                geo.append((col, p, bname, comp))
        if geo:
            self._geometric_partials(gk, lk, sk, geo, dF)
        Jinv = np.linalg.inv(J[ok])
        out[ok] = -Jinv @ dF
        return out.reshape(shape + (2, len(sel)))

    def _geometric_partials(self, g, line, s, cols, dF) -> None:
        """Central differences of the conditions at fixed (line, element) for the lever
        arm, boresight and fix-correction columns ``cols`` = [(column, flat index, block,
        component)], written into ``dF``. The trajectory is interpolated once; a fix
        correction is differenced only where its interpolation weight is non-zero."""
        t = self._line_time(np.clip(line, 0, self.n_lines - 1))
        x, ren, rnb, do = self._frames(t)
        do = np.zeros(t.shape + (3,)) if do is None else do
        tx, ty, _, _ = self.view_tangents(s)
        opk = np.radians(np.asarray(self._params["opk_cam"], float))
        steps = self.fd_step_sizes()

        def cond(i, x_, do_, u, R_bs):
            # the centre relative to the ground point: differences of small numbers (ECEF
            # coordinates would cost the central differences 1e-9 m of rounding)
            c, r = compose(x_ - g[i], ren[i], rnb[i], do_, u, R_bs)
            gv = apply_t(r, -c)
            with np.errstate(invalid="ignore", divide="ignore"):
                return np.stack([gv[:, 0] / -gv[:, 2] - tx[i],
                                 gv[:, 1] / -gv[:, 2] - ty[i]], axis=-1)

        every = np.arange(t.size)
        for col, p, bname, k in cols:
            h = steps[p]
            e = np.zeros(3)
            e[k] = h
            i, xs, dos, us, rs = every, (x, x), (do, do), (self._u_gps,) * 2, (self._R_bs,) * 2
            if bname == "u_gps":
                us = (self._u_gps + e, self._u_gps - e)
            elif bname == "opk_cam":
                rs = tuple(r_opk(*(opk + sgn * np.radians(e))) @ T for sgn in (1, -1))
            else:                                  # d_ned_<j> / d_opk_<j>
                j = int(bname.rsplit("_", 1)[1])
                w = np.interp(t, self._ft, np.eye(self._ft.size)[j])
                i = np.flatnonzero(w != 0)
                if not i.size:
                    continue
                if bname.startswith("d_ned_"):
                    d = apply(ren[i], w[i, None] * e)
                    xs = (x[i] + d, x[i] - d)
                else:
                    d = w[i, None] * np.radians(e)
                    dos = (do[i] + d, do[i] - d)
            xs = tuple(a if a.shape[0] == i.size else a[i] for a in xs)
            dos = tuple(a if a.shape[0] == i.size else a[i] for a in dos)
            fp = cond(i, xs[0], dos[0], us[0], rs[0])
            fm = cond(i, xs[1], dos[1], us[1], rs[1])
            dF[i, :, col] = (fp - fm) / (2 * h)

    def ground_partials(self, ground, step: float = 0.01) -> np.ndarray:
        """d(line, element)/d(X, Y, Z) in ECEF, ``(..., 2, 3)``, in closed form by the
        implicit-function theorem at the solution (``step`` is not used)."""
        ground = np.asarray(ground, float)
        shape = ground.shape[:-1]
        g = ground.reshape(-1, 3)
        line, s, J = self._solve(g)
        out = np.full((g.shape[0], 2, 3), np.nan)
        ok = np.flatnonzero(np.isfinite(line))
        if ok.size:
            c, r = self._state_t(self._line_time(line[ok]))
            gv = apply_t(r, g[ok] - c)
            iz = -1.0 / gv[:, 2]
            d = np.zeros((ok.size, 2, 3))          # d(r, q)/d(g_S)
            d[:, 0, 0] = iz
            d[:, 0, 2] = gv[:, 0] * iz * iz
            d[:, 1, 1] = iz
            d[:, 1, 2] = gv[:, 1] * iz * iz
            dF = d @ np.swapaxes(r, -1, -2)         # g_S = R^T (G - C)
            out[ok] = -np.linalg.inv(J[ok]) @ dF
        return out.reshape(shape + (2, 3))
