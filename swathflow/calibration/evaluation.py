"""The calibration's observations evaluated in bulk: every image observation of every image
in one call of its sensor's projector (:meth:`SensorModel.projector`), each image's model
vector ``M_image @ x`` from the adjustment's unknowns ``x``, with the partials by the
unknowns (through ``M``) and by the ground coordinates."""
from __future__ import annotations

from typing import Mapping, Sequence

import numpy as np

from swathflow.sensormodel.projection import projectors


class BulkObservations:
    """Observations ``(image id, ground point)``; :meth:`evaluate` gives their computed
    image coordinates ``(n, 2)`` at the unknowns ``x``, ``d/dx`` ``(n, 2, len(x))`` and
    ``d/dground`` ``(n, 2, 3)``. The previous answer starts the next search."""

    def __init__(self, models: Mapping[str, object], mats: Mapping[str, np.ndarray],
                 image_ids: Sequence[str]):
        ids = list(dict.fromkeys(str(i) for i in image_ids))
        self.ids = ids
        pos = {iid: k for k, iid in enumerate(ids)}
        self.image = np.array([pos[str(i)] for i in image_ids], dtype=np.intp)
        self.M = np.stack([np.asarray(mats[iid], float) for iid in ids])      # (K, P, n)
        self.groups = []
        for proj, members in projectors([models[iid] for iid in ids]):
            rows = np.flatnonzero(np.isin(self.image, members))
            local = np.searchsorted(members, self.image[rows])
            self.groups.append((proj, members, rows, local))
        self._start = None

    @property
    def size(self) -> int:
        return int(self.image.size)

    def evaluate(self, x, ground, partials: bool = True):
        x = np.asarray(x, float)
        ground = np.asarray(ground, float).reshape(-1, 3)
        n = self.size
        V = self.M @ x                                               # (K, P)
        image = np.full((n, 2), np.nan)
        d_x = np.zeros((n, 2, x.size)) if partials else None
        d_g = np.zeros((n, 2, 3)) if partials else None
        for proj, members, rows, local in self.groups:
            start = None if self._start is None else self._start[rows]
            out = proj.project(local, ground[rows], V[members], partials, start)
            image[rows] = out.image
            if partials:
                M = self.M[members][local]                           # (r, P, n)
                d_x[rows] = np.einsum("rap,rpn->ran", np.nan_to_num(out.d_parameters), M)
                d_g[rows] = np.nan_to_num(out.d_ground)
        ok = np.isfinite(image).all(axis=1)
        self._start = np.where(ok[:, None], image,
                               np.nan if self._start is None else self._start)
        return image, d_x, d_g
