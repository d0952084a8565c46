"""Partial derivatives of image coordinates with respect to a sensor model's parameters,
through the model's rays (generic: any SensorModel)."""
from __future__ import annotations

from typing import Sequence

import numpy as np


def _ray_miss(model, image, ground, basis):
    c, d = model.ray(image)
    u = ground - c
    u = u / np.linalg.norm(u, axis=-1, keepdims=True)
    diff = u - d
    return np.stack([np.einsum("ij,ij->i", basis[0], diff),
                     np.einsum("ij,ij->i", basis[1], diff)], axis=-1)


def _line_subset(model, image):
    """A copy of ``model`` whose line table holds only the lines around ``image`` points,
    and the points' coordinates in it. Per-line quantities are interpolated linearly
    between line centres (docs/geometry.md), so rays are unchanged; rebuilding the small
    model per parameter step is then cheap."""
    lines = model.lines
    nl = model.n_lines
    if nl < 8 or 4 * image.shape[0] >= nl:
        return model, image
    j = np.clip(np.floor(image[:, 0]), 0, nl - 2).astype(int)
    rows = np.unique(np.clip(np.concatenate([j - 1, j, j + 1, j + 2]), 0, nl - 1))
    sub = {k: (np.asarray(v)[rows] if np.ndim(v) == 1 and len(v) == nl else v)
           for k, v in lines.items()}
    try:
        small = type(model)(model.sensor, sub, model.trajectory, model.parameters,
                            **model.image_attrs)
    except Exception:            # a model that cannot be cut: use it whole
        return model, image
    im = image.copy()
    im[:, 0] = np.searchsorted(rows, j) + (image[:, 0] - j)
    return small, im


def image_partials(model, ground, image=None, names: Sequence[str] | None = None,
                   skip: Sequence[bool] | None = None, central: bool = True) -> np.ndarray:
    """d(line, element)/d(parameter), ``(n, 2, P)``, by the implicit function theorem.

    The image point ``image`` of ``ground`` (default: ``model.ground_to_image``) is where
    the ray meets the point. With ``F`` the angular miss between the ray of an image point
    and the direction to the ground point (two components across the ray),
    ``d(image)/dp = -(dF/dimage)^-1 dF/dp``; both by finite differences of
    :meth:`ray`, which is direct, so this needs no iterative back-projection per parameter
    (``model.parameter_partials`` needs two). ``skip`` marks parameters known to have no
    effect (their columns are zero)."""
    ground = np.asarray(ground, float).reshape(-1, 3)
    if image is None:
        image = model.ground_to_image(ground, clip=False)
    image = np.asarray(image, float).reshape(-1, 2)
    params = model.parameters
    flat = params.flat_names()
    units = params.flat_units()
    sel = list(range(len(flat))) if names is None else [flat.index(n) for n in names]
    out = np.zeros((ground.shape[0], 2, len(sel)))
    ok = np.isfinite(image).all(axis=1) & np.isfinite(ground).all(axis=1)
    if not ok.any():
        return np.where(ok[:, None, None], out, np.nan)
    g, im = ground[ok], image[ok]
    model, im = _line_subset(model, im)
    _, d0 = model.ray(im)
    a = np.eye(3)[np.argmin(np.abs(d0), axis=1)]
    b1 = np.cross(d0, a)
    b1 /= np.linalg.norm(b1, axis=1, keepdims=True)
    b2 = np.cross(d0, b1)
    basis = (b1, b2)
    f0 = _ray_miss(model, im, g, basis)
    hl = 1e-3
    d_img = np.empty((g.shape[0], 2, 2))
    for k in range(2):
        e = np.zeros(2)
        e[k] = hl
        d_img[:, :, k] = (_ray_miss(model, im + e, g, basis)
                          - _ray_miss(model, im - e, g, basis)) / (2 * hl)
    v0 = params.vector()
    cols = np.zeros((g.shape[0], 2, len(sel)))
    for c, i in enumerate(sel):
        if skip is not None and skip[c]:
            continue
        h = model.fd_steps.get(units[i], model.fd_steps.get("", 1e-6))
        vp = v0.copy()
        vp[i] += h
        fp = _ray_miss(model.with_vector(vp), im, g, basis)
        if central:
            vm = v0.copy()
            vm[i] -= h
            fm = _ray_miss(model.with_vector(vm), im, g, basis)
            cols[:, :, c] = (fp - fm) / (2 * h)
        else:
            cols[:, :, c] = (fp - f0) / h
    out[ok] = -np.linalg.solve(d_img, cols)
    out[~ok] = np.nan
    return out

