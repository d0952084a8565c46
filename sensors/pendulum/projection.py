"""The pendulum scanner's bulk projection (:meth:`PendulumModel.projector`): the swings'
parameter-free tables gathered once, then every observation of every swing projected in
one compiled call (:func:`swathflow.sensors.pendulum.bulk.project`) with analytic partials.
"""
from __future__ import annotations

from typing import Sequence

import numpy as np

from swathflow.geometry.navkernel import pos_table
from swathflow.geometry.rotations import T, opk_derivatives
from swathflow.sensormodel.projection import Projection, Projector
from swathflow.sensors.pendulum import bulk

#: the parameter blocks, in the order of the kernel's partials (the boresight block is the
#: swing direction's)
BLOCKS = ("u_gps", "u_sen", "opk_sen", "opk_pos")


class PendulumProjector(Projector):
    """Bulk projection over pendulum swings (see the module docstring)."""

    def __init__(self, models: Sequence):
        super().__init__(models)
        flat = self.models[0].parameters.flat_names()
        self._index = {name: flat.index(name) for name in flat}
        cols, trajs, pos_of, optics, dirs, gaps = [], {}, [], [], [], []
        for m in self.models:
            cols.append(np.asarray(m._line_cols, float))
            key = id(m.trajectory)
            if key not in trajs:
                trajs[key] = pos_table(m.trajectory)
            pos_of.append(list(trajs).index(key))
            gaps.append(trajs[key][2])
            s = m.sensor
            optics.append((float(s["k0"]), float(s["pixel_pitch"]), float(s.get("y0", 0.0)),
                           float(s["focal_length"])))
            dirs.append(m.direction)
        self._cols = np.ascontiguousarray(np.concatenate(cols))
        self._col_off = np.concatenate([[0], np.cumsum([c.shape[0] for c in cols])]).astype(
            np.intp)
        tabs = list(trajs.values())
        self._time = np.ascontiguousarray(np.concatenate([t[0] for t in tabs]))
        self._table = np.ascontiguousarray(np.concatenate([t[1] for t in tabs]))
        self._pos_off = np.concatenate([[0], np.cumsum([t[0].size for t in tabs])]).astype(
            np.intp)
        self._pos_of = np.asarray(pos_of, np.intp)
        self._gaps = np.asarray(gaps, float)
        self._optics = np.ascontiguousarray(optics, dtype=float)
        self._dirs = np.array(dirs)
        # the flat parameter columns of the kernel's 12 partials, per swing
        cols12 = []
        for d in dirs:
            names = [f"{b}[{i}]" for b in BLOCKS[:3] for i in range(3)] + \
                [f"opk_pos_{d}[{i}]" for i in range(3)]
            cols12.append([self._index[n] for n in names])
        self._cols12 = np.asarray(cols12, np.intp)

    def _rig(self, v):
        """R_BP, R_HS, u_gps, u_sen and the rotations' derivatives of every swing."""
        c = self._cols12
        rows = np.arange(len(self.models))[:, None]
        ugps, usen = v[rows, c[:, 0:3]], v[rows, c[:, 3:6]]
        r_hs, d_hs = opk_derivatives(v[rows, c[:, 6:9]])
        r_bp, d_bp = opk_derivatives(v[rows, c[:, 9:12]])
        r_hs, d_hs = r_hs @ T, d_hs @ T
        return tuple(np.ascontiguousarray(a) for a in (r_bp, r_hs, ugps, usen, d_bp, d_hs))

    def project(self, image_index, ground, vectors, partials: bool = True,
                start=None) -> Projection:
        idx, g, v = self._check(image_index, ground, vectors)
        n = idx.size
        s = np.full(n, np.nan) if start is None else \
            np.ascontiguousarray(np.asarray(start, float).reshape(n, -1)[:, 0])
        out = np.empty((n, 2))
        d12 = np.zeros((n, 2, 12)) if partials else np.zeros((0, 2, 12))
        dg = np.zeros((n, 2, 3)) if partials else np.zeros((0, 2, 3))
        bulk.project(g, idx, s, self._cols, self._col_off, self._time, self._table,
                     self._pos_off, self._pos_of, self._gaps, *self._rig(v), self._optics,
                     bool(partials), out, d12, dg)
        if not partials:
            return Projection(out)
        dp = np.zeros((n, 2, self.n_parameters))
        cols = self._cols12[idx]                                   # (n, 12)
        np.put_along_axis(dp, np.broadcast_to(cols[:, None, :], (n, 2, 12)), d12, axis=2)
        bad = ~np.isfinite(out).all(axis=1)
        dp[bad] = np.nan
        dg[bad] = np.nan
        return Projection(out, dp, dg)
