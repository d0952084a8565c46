"""Bulk projection: the image coordinates of many ground points seen in many images of one
sensor, with the parameters of each image passed as a vector, and the partial derivatives
of the image coordinates with respect to the parameters and to the ground coordinates.

This is what an adjustment evaluates at every iteration. A sensor plugin provides it through
:meth:`SensorModel.projector <swathflow.sensormodel.base.SensorModel.projector>` (one
vectorised or compiled call over every observation of every image, analytic partials);
:class:`NumericalProjector` is the generic fallback, made of the per-image methods
(``with_vector``, ``ground_to_image``) with numerical partials.
"""
from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import Sequence

import numpy as np


@dataclass
class Projection:
    """The result of :meth:`Projector.project` for ``n`` observations of a sensor with
    ``P`` parameters: ``image`` ``(n, 2)`` (line, element; NaN where the point is not seen,
    not clipped to the detector), ``d_parameters`` ``(n, 2, P)`` and ``d_ground``
    ``(n, 2, 3)`` (ECEF metres), None when partials were not asked for."""

    image: np.ndarray
    d_parameters: np.ndarray | None = None
    d_ground: np.ndarray | None = None


class Projector(ABC):
    """Projects ground points into the images of ``models`` (all of one sensor class).

    ``project(image_index, ground, vectors)``: ``image_index`` ``(n,)`` the image (its
    position in ``models``) of each observation, ``ground`` ``(n, 3)`` ECEF, ``vectors``
    ``(len(models), P)`` each image's parameter vector (the order of
    ``ParameterSet.flat_names``). ``start`` ``(n, 2)`` optionally gives image coordinates
    near the answer (the previous iteration's), which a plugin may use to search less."""

    def __init__(self, models: Sequence):
        self.models = list(models)
        if not self.models:
            raise ValueError("a projector needs at least one model")
        self.n_parameters = int(self.models[0].parameters.vector().size)

    @abstractmethod
    def project(self, image_index, ground, vectors, partials: bool = True,
                start=None) -> Projection:
        """See the class docstring."""

    def _check(self, image_index, ground, vectors):
        idx = np.asarray(image_index, dtype=np.intp).ravel()
        g = np.ascontiguousarray(np.asarray(ground, float).reshape(-1, 3))
        v = np.ascontiguousarray(np.asarray(vectors, float).reshape(len(self.models), -1))
        if idx.size != g.shape[0]:
            raise ValueError(f"{idx.size} image indices for {g.shape[0]} ground points")
        if v.shape[1] != self.n_parameters:
            raise ValueError(f"parameter vectors need {self.n_parameters} values, "
                             f"got {v.shape[1]}")
        if idx.size and (idx.min() < 0 or idx.max() >= len(self.models)):
            raise ValueError("image index out of range")
        return idx, g, v


class NumericalProjector(Projector):
    """The generic fallback: per image, a model with that image's parameters
    (``with_vector``), ``ground_to_image``, and central differences of it for the partials
    (through :meth:`SensorModel.parameter_partials` and :meth:`ground_partials`, which a
    plugin may override with analytic ones)."""

    def project(self, image_index, ground, vectors, partials: bool = True,
                start=None) -> Projection:
        idx, g, v = self._check(image_index, ground, vectors)
        n, P = idx.size, self.n_parameters
        image = np.full((n, 2), np.nan)
        dp = np.zeros((n, 2, P)) if partials else None
        dg = np.zeros((n, 2, 3)) if partials else None
        for k in np.unique(idx):
            rows = np.flatnonzero(idx == k)
            model = self.models[k]
            if not np.array_equal(model.parameters.vector(), v[k]):
                model = model.with_vector(v[k])
            image[rows] = model.ground_to_image(g[rows], clip=False)
            if partials:
                dp[rows] = model.parameter_partials(g[rows])
                dg[rows] = model.ground_partials(g[rows])
        if partials:
            bad = ~np.isfinite(image).all(axis=1)
            dp[bad] = np.nan
            dg[bad] = np.nan
        return Projection(image, dp, dg)


def projectors(models: Sequence) -> list[tuple[Projector, np.ndarray]]:
    """One projector per sensor class among ``models``, each with the positions in
    ``models`` of its images."""
    out = []
    classes = list(dict.fromkeys(type(m) for m in models))
    for cls in classes:
        pos = np.array([i for i, m in enumerate(models) if type(m) is cls], dtype=np.intp)
        out.append((cls.projector([models[i] for i in pos]), pos))
    return out
