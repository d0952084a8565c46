"""A reference orthophoto made from a simulation's truth ortho, degraded as a real one is:
coarser pixels (area average), blur, gamma, gain/offset to 8-bit, noise, and patches changed
since the flight (replaced by flat or foreign texture). Used by the automatic-control truth
tests and benchmarks (:mod:`swathflow.calibration.reference`)."""
from __future__ import annotations

import os

import numpy as np
from affine import Affine
from scipy import ndimage


def degrade_reference(truth_ortho, out_path, factor: int = 2, blur: float = 0.7,
                      gamma: float = 0.8, noise: float = 2.0, changed: int = 3,
                      changed_size: float = 0.08, seed: int = 0) -> dict:
    """Write ``out_path`` (GeoTIFF, uint8 grey) from ``truth_ortho``; returns what was done
    (the changed patches as map-coordinate boxes)."""
    from swathflow.formats.raster import read_raster, write_geotiff
    r = read_raster(truth_ortho, masked_to_nan=True)
    a = np.asarray(r.data, float)
    f = int(factor)
    h, w = (a.shape[0] // f) * f, (a.shape[1] // f) * f
    a = a[:h, :w].reshape(h // f, f, w // f, f).mean(axis=(1, 3))
    if blur > 0:
        a = ndimage.gaussian_filter(a, blur)
    lo, hi = np.nanpercentile(a, [0.5, 99.5])
    a = np.clip((a - lo) / max(hi - lo, 1e-9), 0, 1) ** gamma
    rng = np.random.default_rng(seed)
    tr = r.transform @ Affine.scale(f)
    boxes = []
    for _ in range(int(changed)):
        ph = max(int(changed_size * a.shape[0]), 4)
        pw = max(int(changed_size * a.shape[1]), 4)
        r0 = int(rng.integers(0, max(a.shape[0] - ph, 1)))
        c0 = int(rng.integers(0, max(a.shape[1] - pw, 1)))
        if rng.random() < 0.5:
            a[r0:r0 + ph, c0:c0 + pw] = float(rng.uniform(0.2, 0.8))        # new pavement
        else:
            a[r0:r0 + ph, c0:c0 + pw] = np.clip(ndimage.gaussian_filter(
                rng.random((ph, pw)), 1.5) * 3 - 1, 0, 1)                     # new texture
        x0, y0 = tr @ (c0, r0)
        x1, y1 = tr @ (c0 + pw, r0 + ph)
        boxes.append([float(x0), float(y1), float(x1), float(y0)])
    a = a * 230 + 12 + rng.normal(0, noise, a.shape)
    write_geotiff(os.fspath(out_path), np.clip(np.round(a), 0, 255).astype(np.uint8),
                  r.crs, tr)
    return {"factor": f, "res": float(tr.a), "blur": blur, "gamma": gamma, "noise": noise,
            "changed_boxes": boxes}
