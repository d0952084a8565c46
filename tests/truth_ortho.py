"""Compare a rectified image with the simulator's truth ortho (truth/ortho.tif)."""
from __future__ import annotations

import numpy as np


def overlap_with_truth(rect, transform, truth):
    """The part of ``rect`` (a rectified band with its affine ``transform``) inside the
    truth raster's grid, and the truth there: ``(sub_rect, sub_truth)``. Both grids are
    snapped to the same GSD (asserted). Outside the truth's coverage the image is NaN and
    the truth its mean (neutral for a phase correlation)."""
    t = transform
    col0 = (t.c - truth.transform.c) / truth.transform.a
    row0 = (t.f - truth.transform.f) / truth.transform.e
    assert abs(col0 - round(col0)) < 1e-6 and abs(row0 - round(row0)) < 1e-6
    col0, row0 = int(round(col0)), int(round(row0))
    r0, c0 = max(row0, 0), max(col0, 0)
    r1 = min(row0 + rect.shape[0], truth.data.shape[0])
    c1 = min(col0 + rect.shape[1], truth.data.shape[1])
    sub_t = truth.data[r0:r1, c0:c1]
    sub_r = rect[r0 - row0:r1 - row0, c0 - col0:c1 - col0]
    sub_r = np.where(np.isfinite(sub_t), sub_r, np.nan)
    sub_t = np.where(np.isfinite(sub_t), sub_t, np.nanmean(sub_t))
    return sub_r, sub_t
