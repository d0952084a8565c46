"""The forward (polynomial) rectification method of the fast-rectification paper (You and
Li; docs/references.md section 3), and the IGM rows of a swing.

``polynomial``: a few equally spaced pixels per scan line are projected to the ground,
cubic polynomials in the element index are fitted to map x and y, every raw pixel is
mapped forward to its nearest output pixel (mean of the pixels landing there) and the gaps
inside the footprint are filled with the 3 x 3 inverse-distance window (weights 1/d). The
output is float32 with NaN as nodata. (The default ``exact`` method, inverse mapping tile by
tile, is :mod:`.tiles` over :mod:`.lattice`; the public entry for both is
:func:`swathflow.rectification.api.rectify`.)

The IGM (:func:`igm_block`): map x, y and ellipsoidal height of every raw pixel centre, in
raw geometry (:func:`swathflow.rectification.api.geolocation`).
"""
from __future__ import annotations

import math
import warnings

import numpy as np
from swathflow.errors import FormatError
from swathflow.geometry.grid import Grid, ecef_to_map
from swathflow.geometry.terrain import open_terrain
from swathflow.rectification.rawimage import RawSource, open_raw_image
# the calibration's reference matching reads the tile rectifier and the single-band
# reader from here
from swathflow.rectification.tiles import rectify_tile

__all__ = ["RawSource", "fill_gaps_idw", "footprint_mask", "igm_block", "rectify_polynomial",
           "rectify_tile"]


# ----------------------------------------------------------------------------------------
# the polynomial (forward) method of the fast-rectification paper
# ----------------------------------------------------------------------------------------
def _quiet_ground(model, image, terrain) -> np.ndarray:
    """``model.image_to_ground`` without the ray-miss warning (misses are NaN)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return model.image_to_ground(image, terrain)


def _forward_xy(model, terrain, crs, lines: np.ndarray, samples: int, degree: int,
                elements: np.ndarray | None = None):
    """Map x, y ``(len(lines), len(elements))`` of raw pixels from per-line polynomials in
    the element index fitted to ``samples`` exact projections per line."""
    ne = model.n_elements
    ks = np.linspace(0, ne - 1, samples)
    img = np.stack(np.broadcast_arrays(lines[:, None].astype(float), ks[None, :]), axis=-1)
    g = _quiet_ground(model, img, terrain)
    x, y, _ = ecef_to_map(g, crs)
    u = (ks - (ne - 1) / 2) / max(ne - 1, 1)            # scaled for conditioning
    V = np.vander(u, degree + 1)
    pinv = np.linalg.pinv(V)
    cx, cy = x @ pinv.T, y @ pinv.T                      # (lines, degree + 1)
    ek = np.arange(ne, dtype=float) if elements is None else elements
    Va = np.vander((ek - (ne - 1) / 2) / max(ne - 1, 1), degree + 1)
    return cx @ Va.T, cy @ Va.T


def rectify_polynomial(model, image, grid: Grid, terrain, samples: int = 9, degree: int = 3,
                       block_lines: int = 1024, fill: bool = True,
                       stats: dict | None = None) -> np.ndarray:
    """The paper's forward method; returns a float32 array over ``grid`` (NaN = nodata).

    Holds the output grid in memory (sum and count arrays); reads the raw image in blocks
    of ``block_lines`` lines."""
    source = open_raw_image(image)
    if source.count != 1:
        raise FormatError(f"the polynomial method rectifies one band; the raw image has "
                          f"{source.count}: select one (bands) or use the exact method")
    terrain = open_terrain(terrain)
    nl, ne = model.shape
    hgt, wid = grid.shape
    total = np.zeros(hgt * wid)
    count = np.zeros(hgt * wid, np.int32)
    for l0 in range(0, nl, block_lines):
        l1 = min(l0 + block_lines, nl)
        x, y = _forward_xy(model, terrain, grid.crs, np.arange(l0, l1), samples, degree)
        r, c = grid.rowcol(x, y, op=None)
        r = np.floor(r + 0.5)
        c = np.floor(c + 0.5)
        v = _as_float(source, source.read(l0, l1, 0, ne)[0])
        ok = (r >= 0) & (r < hgt) & (c >= 0) & (c < wid) & np.isfinite(v)
        flat = (r[ok] * wid + c[ok]).astype(np.intp)
        total += np.bincount(flat, v[ok], minlength=hgt * wid)
        count += np.bincount(flat, minlength=hgt * wid).astype(np.int32)
    out = np.full(hgt * wid, np.nan)
    hit = count > 0
    out[hit] = total[hit] / count[hit]
    out = out.reshape(hgt, wid)
    hit = hit.reshape(hgt, wid)
    foot = footprint_mask(model, terrain, grid, samples, degree)
    holes = foot & ~hit
    if stats is not None:
        stats["footprint_pixels"] = int(foot.sum())
        stats["holes_before_fill"] = int(holes.sum())
    if fill and holes.any():
        out = fill_gaps_idw(out, holes)
    if stats is not None:
        stats["holes_after_fill"] = int((foot & np.isnan(out)).sum())
    return out.astype(np.float32)


def _as_float(source, a) -> np.ndarray:
    """float64 with NaN for the source's nodata."""
    a = a.astype(np.float64)
    nd = source.nodata
    if nd is not None and not (isinstance(nd, float) and math.isnan(nd)):
        a[a == nd] = np.nan
    return a


def fill_gaps_idw(values: np.ndarray, holes: np.ndarray) -> np.ndarray:
    """Fill ``holes`` with the inverse-distance weighted mean (weights 1/d: 1 for the four
    edge neighbours, 1/sqrt(2) for the diagonals) of the valid pixels of the 3 x 3 window
    (the fast-rectification paper's gap filling). Holes without a valid neighbour stay NaN."""
    from scipy import ndimage
    w = np.array([[1 / math.sqrt(2), 1, 1 / math.sqrt(2)], [1, 0, 1],
                  [1 / math.sqrt(2), 1, 1 / math.sqrt(2)]])
    valid = np.isfinite(values)
    num = ndimage.correlate(np.where(valid, values, 0.0), w, mode="constant")
    den = ndimage.correlate(valid.astype(float), w, mode="constant")
    out = values.copy()
    with np.errstate(invalid="ignore", divide="ignore"):
        fillv = num / den
    sel = holes & (den > 0)
    out[sel] = fillv[sel]
    return out


def footprint_mask(model, terrain, grid: Grid, samples: int = 9, degree: int = 3,
                   per_side: int = 256) -> np.ndarray:
    """Output pixels whose centre lies inside the raw image's ground footprint (the
    polygon of the image border mapped forward)."""
    from rasterio import features
    nl, ne = model.shape
    lines = np.unique(np.linspace(0, nl - 1, per_side).round())
    bx0, by0 = _forward_xy(model, terrain, grid.crs, np.array([0.0]), samples, degree)
    bx1, by1 = _forward_xy(model, terrain, grid.crs, np.array([nl - 1.0]), samples, degree)
    ex = np.array([0.0, ne - 1.0])
    sx, sy = _forward_xy(model, terrain, grid.crs, lines, samples, degree, elements=ex)
    xs = np.concatenate([bx0[0], sx[:, 1], bx1[0][::-1], sx[::-1, 0]])
    ys = np.concatenate([by0[0], sy[:, 1], by1[0][::-1], sy[::-1, 0]])
    ring = [(float(a), float(b)) for a, b in zip(xs, ys) if np.isfinite(a) and np.isfinite(b)]
    if len(ring) < 3:
        return np.zeros(grid.shape, bool)
    ring.append(ring[0])
    return features.rasterize([({"type": "Polygon", "coordinates": [ring]}, 1)],
                              out_shape=grid.shape, transform=grid.transform, fill=0,
                              dtype="uint8").astype(bool)


# ----------------------------------------------------------------------------------------
# geolocation products
# ----------------------------------------------------------------------------------------
def igm_block(model, terrain, crs, l0: int, l1: int) -> np.ndarray:
    """IGM rows ``l0:l1``: ``(3, l1 - l0, n_elements)`` map x, y and ellipsoidal height of
    the raw pixel centres on the terrain (NaN where the ray misses)."""
    ne = model.n_elements
    ll, ee = np.meshgrid(np.arange(l0, l1, dtype=float), np.arange(ne, dtype=float),
                         indexing="ij")
    g = _quiet_ground(model, np.stack([ll, ee], axis=-1), open_terrain(terrain))
    x, y, h = ecef_to_map(g, crs)
    return np.stack([x, y, h])
