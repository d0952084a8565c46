"""The push-broom camera's bulk projection (:meth:`PushbroomModel.projector`): the images'
parameter-free tables (line times, POS) gathered once; per call the parameter vectors
turned into each image's lever arm, boresight, viewing-tangent cubics and fix corrections,
every observation solved in one compiled call (:func:`swathflow.sensors.pushbroom.bulk.project`),
and the partial derivatives by the parameters and the ground in closed form (numpy) by the
implicit-function theorem at the solution.

With ``g = R_BS^T (R_opk(d_opk)^T R_NB^T R_EN^T (G - X_ant - R_EN d_ned) - u_gps)`` the
camera vector and ``F = (g_x / -g_z - tan_psi_x(s), g_y / -g_z - tan_psi_y(s))`` the
conditions: ``d(line, element)/dq = -J^-1 dF/dq`` with ``J = dF/d(line, element)`` from the
kernel, ``dF/dq = dF/dg dg/dq`` for the lever arm, the boresight, the fix corrections (each
fix weighted by its linear interpolation weight at the line's time) and the ground, and
``dF/da_k = -(s - s_segment)^k`` for the APs of the element's segment.
"""
from __future__ import annotations

import math
from typing import Sequence

import numpy as np

from swathflow.geometry.navkernel import pos_table
from swathflow.geometry.rotations import T, opk_derivatives, r_en, r_nb
from swathflow.sensormodel.projection import Projection, Projector
from swathflow.sensors.pushbroom import bulk
from swathflow.sensors.pushbroom.viewing import ap_name

DEG = math.pi / 180.0


def _t(a) -> np.ndarray:
    """Transpose of stacked 3x3 matrices."""
    return np.swapaxes(a, -1, -2)


def _offsets(sizes) -> np.ndarray:
    """Start offsets of pieces of ``sizes`` laid end to end, and the total."""
    return np.concatenate([[0], np.cumsum(sizes)]).astype(np.intp)


class PushbroomProjector(Projector):
    """Bulk projection over push-broom images (see the module docstring)."""

    def __init__(self, models: Sequence):
        super().__init__(models)
        flat = self.models[0].parameters.flat_names()
        self._ft = np.ascontiguousarray(self.models[0].fix_times, dtype=float)
        for m in self.models:
            if m.parameters.flat_names() != flat or not np.array_equal(m.fix_times, self._ft):
                raise ValueError("a push-broom projector needs images of one camera (the same "
                                 "parameters and orientation fixes)")
        self._columns({name: i for i, name in enumerate(flat)})
        ltimes = [np.asarray(m.lines["time"], float) for m in self.models]
        self._ltime = np.ascontiguousarray(np.concatenate(ltimes))
        self._line_off = _offsets([t.size for t in ltimes])
        self._pos_tables()
        self._segs = [m.segments for m in self.models]
        self._coef_off = _offsets([m.n_elements for m in self.models])

    def _columns(self, col) -> None:
        """The flat parameter columns of the lever arm, the boresight, the fix corrections
        ``(fixes, 3)`` and, per image, its view's APs ``(2, segments, 4)`` (ax, bx)."""
        nf = self._ft.size
        self._u_cols = np.array([col[f"u_gps[{i}]"] for i in range(3)])
        self._opk_cols = np.array([col[f"opk_cam[{i}]"] for i in range(3)])
        self._ned_cols = np.array([[col[f"d_ned_{k}[{i}]"] for i in range(3)]
                                   for k in range(nf)], np.intp).reshape(nf, 3)
        self._dopk_cols = np.array([[col[f"d_opk_{k}[{i}]"] for i in range(3)]
                                    for k in range(nf)], np.intp).reshape(nf, 3)
        self._ap_cols = [np.array([[[col[f"{ap_name(kind, m.view, i)}[{c}]"] for c in range(4)]
                                    for i in range(m.segments.size)]
                                   for kind in ("ax", "bx")], np.intp) for m in self.models]

    def _pos_tables(self) -> None:
        """The POS tables of the images' trajectories (each once), side by side."""
        trajs, pos_of = {}, []
        for m in self.models:
            key = id(m.trajectory)
            if key not in trajs:
                trajs[key] = pos_table(m.trajectory)
            pos_of.append(list(trajs).index(key))
        tabs = list(trajs.values())
        self._time = np.ascontiguousarray(np.concatenate([t[0] for t in tabs]))
        self._table = np.ascontiguousarray(np.concatenate([t[1] for t in tabs]))
        self._pos_off = _offsets([t[0].size for t in tabs])
        self._pos_of = np.asarray(pos_of, np.intp)
        self._gaps = np.array([tabs[k][2] for k in pos_of], float)

    # --- the parameters of every image ----------------------------------------------------
    def _camera(self, v):
        """Per image: lever arm, r_opk of the boresight and its derivatives, R_BS, the fix
        corrections (m, rad), the viewing-tangent cubics and tan_psi_x of the middle
        element."""
        u = np.ascontiguousarray(v[:, self._u_cols])
        r_opk_cam, d_opk_cam = opk_derivatives(v[:, self._opk_cols])
        rbs = np.ascontiguousarray(r_opk_cam @ T)
        nf = self._ft.size
        dned = np.ascontiguousarray(v[:, self._ned_cols].reshape(len(self.models), nf, 3))
        dopk = np.ascontiguousarray(np.radians(v[:, self._dopk_cols]).reshape(
            len(self.models), nf, 3))
        coefs, mids = [], []
        for k, m in enumerate(self.models):
            ax, bx = v[k, self._ap_cols[k][0]], v[k, self._ap_cols[k][1]]
            c = m.tangent_coefficients(ax, bx)                     # (8, n_elements)
            coefs.append(c)
            mid = 0.5 * (m.n_elements - 1)
            i = int(mid)
            w = mid - i
            mids.append(c[0, i] + w * (c[1, i] + w * (c[2, i] + w * c[3, i])))
        coef = np.ascontiguousarray(np.concatenate(coefs, axis=1))
        return u, rbs, d_opk_cam, dned, dopk, coef, np.asarray(mids, float)

    def project(self, image_index, ground, vectors, partials: bool = True,
                start=None) -> Projection:
        idx, g, v = self._check(image_index, ground, vectors)
        n = idx.size
        s = np.full((n, 2), np.nan) if start is None else \
            np.ascontiguousarray(np.asarray(start, float).reshape(n, 2))
        u, rbs, d_opk_cam, dned, dopk, coef, mids = self._camera(v)
        out = np.empty((n, 2))
        jac = np.full((n, 2, 2), np.nan)
        times = np.full(n, np.nan)
        pos = np.full((n, 8), np.nan)
        bulk.project(g, idx, s, self._ltime, self._line_off, self._time, self._table,
                     self._pos_off, self._pos_of, self._gaps, self._ft, dned, dopk, rbs, u,
                     coef, self._coef_off, mids, out, jac, times, pos)
        if not partials:
            return Projection(out)
        dp = np.full((n, 2, self.n_parameters), np.nan)
        dg = np.full((n, 2, 3), np.nan)
        ok = np.flatnonzero(np.isfinite(out).all(axis=1))
        if ok.size:
            dp[ok], dg[ok] = self._partials(idx[ok], g[ok], out[ok], jac[ok], times[ok],
                                            pos[ok], v, u, rbs, d_opk_cam, dned, dopk)
        return Projection(out, dp, dg)

    # --- partial derivatives ----------------------------------------------------------------
    def _partials(self, idx, g, img, J, t, pos, v, u, rbs, d_opk_cam, dned, dopk):
        n, P, nf = idx.size, self.n_parameters, self._ft.size
        ren = r_en(np.radians(pos[:, 3]), np.radians(pos[:, 4]))
        rnb = r_nb(np.radians(pos[:, 5]), np.radians(pos[:, 6]), np.radians(pos[:, 7]))
        if nf:
            W = np.stack([np.interp(t, self._ft, e) for e in np.eye(nf)], axis=-1)  # (n, nf)
            dn = np.einsum("nf,nfc->nc", W, dned[idx])
            do = np.einsum("nf,nfc->nc", W, dopk[idx])
        else:
            W = np.zeros((n, 0))
            dn = do = np.zeros((n, 3))
        r_do, d_do = opk_derivatives(np.degrees(do))
        # the body vector before the fix rotation, and after it less the lever arm
        b = np.einsum("nji,nj->ni", rnb, np.einsum("nji,nj->ni", ren, g - pos[:, :3]) - dn)
        vb = np.einsum("nji,nj->ni", r_do, b) - u[idx]
        R = rbs[idx]                                                  # R_BS
        cam = np.einsum("nji,nj->ni", R, vb)
        iz = -1.0 / cam[:, 2]
        dFdg = np.zeros((n, 2, 3))
        dFdg[:, 0, 0] = iz
        dFdg[:, 0, 2] = cam[:, 0] * iz * iz
        dFdg[:, 1, 1] = iz
        dFdg[:, 1, 2] = cam[:, 1] * iz * iz
        Rt = _t(R)
        to_cam = Rt @ _t(r_do) @ _t(rnb)                             # NED -> camera
        dF = np.zeros((n, 2, P))
        dF[:, :, self._u_cols] = dFdg @ -Rt
        # boresight: R_BS^T = T r_opk^T -> d/d angle = T (d r_opk)^T vb (per degree)
        d_bs = np.einsum("ij,nakj,nk->nia", T, d_opk_cam[idx], vb) * DEG
        dF[:, :, self._opk_cols] = dFdg @ d_bs
        if nf:
            d_ned = dFdg @ -to_cam                                   # (n, 2, 3)
            dF[np.arange(n)[:, None, None], np.arange(2)[None, :, None],
               self._ned_cols.ravel()[None, None, :]] = \
                (d_ned[:, :, None, :] * W[:, None, :, None]).reshape(n, 2, 3 * nf)
            d_rot = dFdg @ (np.einsum("nij,nakj,nk->nia", Rt, d_do, b) * DEG)
            dF[np.arange(n)[:, None, None], np.arange(2)[None, :, None],
               self._dopk_cols.ravel()[None, None, :]] = \
                (d_rot[:, :, None, :] * W[:, None, :, None]).reshape(n, 2, 3 * nf)
        for k in np.unique(idx):                                     # the APs
            rows = np.flatnonzero(idx == k)
            s = img[rows, 1]
            seg = self._segs[k]
            nel = int(self._coef_off[k + 1] - self._coef_off[k])
            e = np.clip(np.floor(s), 0, nel - 1)
            sg = np.clip(np.searchsorted(seg, e, side="right") - 1, 0, seg.size - 1)
            ds = s - seg[sg]
            pw = ds[:, None] ** np.arange(4)                          # (r, 4)
            cols = self._ap_cols[k]                                   # (2, seg, 4)
            for row in (0, 1):
                dF[rows[:, None], row, cols[row][sg]] = -pw
        Jinv = np.linalg.inv(J)
        d_par = -Jinv @ dF
        d_ground = -Jinv @ (dFdg @ (to_cam @ _t(ren)))
        return d_par, d_ground
