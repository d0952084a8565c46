"""Seam metric for tests and benchmarks: where a mosaic may show seams, and how visible
they are against the inside of the strips."""
from __future__ import annotations

import numpy as np

__all__ = ["seam_lines", "seam_visibility"]


def seam_lines(footprints, band: int = 1):
    """Every line where a mosaic of ``footprints`` (boolean masks on one grid) may show a
    seam: the edge of a footprint lying inside another one (where "first valid wins" and
    feathering change source) and the boundary of the nearest-centre partition (where a
    hard cut changes source). In-memory: for tests and benchmarks."""
    from scipy import ndimage
    fps = [np.asarray(f, bool) for f in footprints]
    cover = np.sum(fps, axis=0)
    seam = np.zeros(cover.shape, bool)
    best = np.full(cover.shape, -1.0)
    label = np.full(cover.shape, -1)
    for k, fp in enumerate(fps):
        edge = fp & ~ndimage.binary_erosion(fp, iterations=band, border_value=0)
        seam |= edge & (cover >= 2)
        d = ndimage.distance_transform_edt(np.pad(fp, 1))[1:-1, 1:-1]
        take = d > best
        best[take] = d[take]
        label[take] = k
    cut = np.zeros(cover.shape, bool)
    cut[:-1] |= (label[:-1] != label[1:]) & (cover[:-1] >= 2) & (cover[1:] >= 2)
    cut[:, :-1] |= (label[:, :-1] != label[:, 1:]) & (cover[:, :-1] >= 2) & (cover[:, 1:] >= 2)
    return seam | cut, cover


def seam_visibility(image, footprints, valid=None, band: int = 1):
    """Mean absolute gradient of ``image`` on the seam lines (:func:`seam_lines`) and inside
    the strips (single coverage, more than ``band + 3`` px from any seam or outer edge).

    The gradient of a pixel is the larger absolute forward difference along rows or columns,
    so a step across a seam in any direction counts. Returns ``(seam, inner)``.
    """
    from scipy import ndimage
    img = np.asarray(image, float)
    if valid is None:
        valid = np.isfinite(img)
    seam, cover = seam_lines(footprints, band)
    gr = np.zeros(img.shape)
    gc = np.zeros(img.shape)
    with np.errstate(invalid="ignore"):
        gr[:-1] = np.abs(np.diff(img, axis=0))
        gc[:, :-1] = np.abs(np.diff(img, axis=1))
    g = np.maximum(gr, gc)
    ok = valid.copy()
    ok[:-1] &= valid[1:]
    ok[:, :-1] &= valid[:, 1:]
    ok[-1] = False
    ok[:, -1] = False
    near = ndimage.binary_dilation(seam, iterations=1)
    interior = ndimage.binary_erosion(cover >= 1, iterations=band + 3, border_value=0)
    inner = ok & interior & (cover == 1) & ~ndimage.binary_dilation(seam, iterations=band + 3)
    s = ok & near
    return (float(g[s].mean()) if s.any() else float("nan"),
            float(g[inner].mean()) if inner.any() else float("nan"))
