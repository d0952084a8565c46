"""Synthetic rectified swings with known truth, for the mosaic tests and benchmark.

The ground truth is a function ``f(row, col)`` of continuous grid coordinates (pixel centres
at integers): a procedural multi-scale texture with sharp-edged fields, or a real orthophoto
interpolated by cubic splines. A strip displaced by ``t = (drow, dcol)`` is sampled as
``f(row - drow, col - dcol)`` (an exact sub-pixel shift, no resampling of a raster), plus a
radiometric offset, optional slow radiometric drift along the strip, and noise. Strips run
along the rows (north-south flight lines), overlap across-track by ``overlap`` with wavy
edges, and are cut into swings that overlap along-track. Every swing is written as its own
GeoTIFF (nodata outside its footprint) on one common 2 m grid, one at a time, so memory stays
bounded by a swing however large the area.
"""
from __future__ import annotations

import os

import numpy as np

X0, Y0, CRS = 500000.0, 4000000.0, "EPSG:32633"


def _hash(ix, iy, seed):
    m = np.uint64(0xFFFFFFFF)
    h = (ix.astype(np.uint64) * np.uint64(0x9E3779B1) + iy.astype(np.uint64) * np.uint64(0x85EBCA77)
         + np.uint64((seed * 0xC2B2AE3D + 12345) & 0xFFFFFFFF)) & m
    h ^= h >> np.uint64(15)
    h = (h * np.uint64(0x2C1B3C6D)) & m
    h ^= h >> np.uint64(12)
    h = (h * np.uint64(0x297A2D39)) & m
    h ^= h >> np.uint64(15)
    return h.astype(np.float64) / 4294967296.0


def value_noise(r, c, scale, seed):
    """Smooth (quintic-faded) lattice noise in [0, 1) with lattice spacing ``scale`` px."""
    u, v = r / scale, c / scale
    i, j = np.floor(u), np.floor(v)
    fade = lambda t: t * t * t * (t * (t * 6 - 15) + 10)  # noqa: E731
    a, b = fade(u - i), fade(v - j)
    i = i.astype(np.int64) + 1_000_000
    j = j.astype(np.int64) + 1_000_000
    return (_hash(i, j, seed) * (1 - a) * (1 - b) + _hash(i + 1, j, seed) * a * (1 - b)
            + _hash(i, j + 1, seed) * (1 - a) * b + _hash(i + 1, j + 1, seed) * a * b)


def texture(r, c, seed: int = 0):
    """Procedural truth: octaves from 96 px down to 4 px plus sharp-edged fields."""
    r = np.asarray(r, float)
    c = np.asarray(c, float)
    out = np.full(np.broadcast(r, c).shape, 100.0)
    for k, (s, amp) in enumerate([(96, 40), (48, 30), (24, 20), (12, 14), (6, 10), (4, 5)]):
        out += amp * value_noise(r, c, s, seed + k)
    out += 30 * np.tanh((value_noise(r, c, 40, seed + 99) - 0.5) * 25)
    return out


class ImageTruth:
    """A real orthophoto as a truth function (cubic spline, edges mirrored)."""

    def __init__(self, path, rows: int, cols: int, r0: int = 0, c0: int = 0):
        import rasterio
        from scipy import ndimage
        with rasterio.open(path) as ds:
            from rasterio.windows import Window
            a = ds.read(window=Window(c0, r0, cols, rows)).astype(float)
        self.grey = a[:3].mean(0) if a.shape[0] >= 3 else a[0]
        self.coef = ndimage.spline_filter(self.grey, order=3, mode="mirror")

    def __call__(self, r, c, seed: int = 0):
        from scipy import ndimage
        r, c = np.broadcast_arrays(np.asarray(r, float), np.asarray(c, float))
        return ndimage.map_coordinates(self.coef, [r.ravel(), c.ravel()], order=3,
                                       mode="mirror", prefilter=False).reshape(r.shape)


def _soft(z, w=0.8):
    return 0.5 * (1 + np.tanh(z / w))


def lake_weight(r, c, lake):
    """Weight (0..1, soft edges) of a flat "lake" box ``(r0, r1, c0, c1)`` in truth coords."""
    a0, a1, b0, b1 = lake
    return _soft(r - a0) * _soft(a1 - r) * _soft(c - b0) * _soft(b1 - c)


def truth_grid(shape, truth=texture, lake=None, lake_value=120.0, r0=0, c0=0):
    """The truth on grid rows ``r0..r0+shape[0]``, cols ``c0..`` (no noise, no offsets)."""
    rr, cc = np.mgrid[r0:r0 + shape[0], c0:c0 + shape[1]].astype(float)
    v = truth(rr, cc)
    if lake is not None:
        w = lake_weight(rr, cc, lake)
        v = (1 - w) * v + w * lake_value
    return v


def grid_shape(n_strips, swath, length, overlap):
    step = int(round(swath * (1 - overlap)))
    return length, step * (n_strips - 1) + swath + 8


def make_swings(folder, n_strips=5, swath=180, length=600, overlap=0.2, n_swings=3,
                swing_overlap=24, shifts=None, rads=None, drift=0.0, noise=0.5, lake=None,
                truth=texture, res=2.0, seed=0, dtype="float32", footprints=True,
                compress="deflate"):
    """Write ``n_strips * n_swings`` swing GeoTIFFs into ``folder``.

    ``shifts`` (n_strips, 2): each strip's displacement in px (``image[x] = truth[x - t]``);
    ``rads`` (n_strips,): radiometric offsets; ``drift``: amplitude of a slow along-track
    radiometric wave (period 300 px, phase per strip) that a constant offset cannot remove;
    ``lake``: a flat box ``(r0, r1, c0, c1)`` in truth coordinates. Returns ``(paths,
    footprint masks on the grid or None, grid shape)``. ``compress``: the swings' GeoTIFF
    compression (``"none"`` for the regional case: faster to write and to read).
    """
    from affine import Affine
    from swathflow.formats.raster import write_geotiff
    rng = np.random.default_rng(seed)
    os.makedirs(folder, exist_ok=True)
    step = int(round(swath * (1 - overlap)))
    H, W = grid_shape(n_strips, swath, length, overlap)
    seg = (length + (n_swings - 1) * swing_overlap) // n_swings
    paths, fps = [], []
    nodata = -9999.0 if dtype.startswith("float") else 0
    for k in range(n_strips):
        t = shifts[k] if shifts is not None else (0.0, 0.0)
        b = rads[k] if rads is not None else 0.0
        for s in range(n_swings):
            r0 = s * (seg - swing_overlap)
            r1 = H if s == n_swings - 1 else min(H, r0 + seg)
            c0, c1 = k * step, min(W, k * step + swath + 8)
            rr, cc = np.mgrid[r0:r1, c0:c1].astype(float)
            left = k * step + 4 + 3.0 * np.sin(2 * np.pi * rr / 170 + k)
            right = k * step + swath + 3.0 * np.sin(2 * np.pi * rr / 130 + 2 * k)
            fp = (cc >= left) & (cc < right)
            u, v = rr - t[0], cc - t[1]
            val = truth(u, v)
            if lake is not None:
                w = lake_weight(u, v, lake)
                val = (1 - w) * val + w * 120.0
            val = val + b + drift * np.sin(2 * np.pi * rr / 300 + 1.7 * k)
            if noise:
                val = val + rng.normal(0, noise, rr.shape)
            if dtype.startswith("float"):
                arr = np.where(fp, val, nodata).astype(dtype)
            else:
                arr = np.where(fp, np.clip(np.round(val), 1, np.iinfo(dtype).max), 0).astype(dtype)
            p = os.path.join(folder, f"s{k:03d}_{s:03d}.tif")
            tr = Affine(res, 0, X0 + c0 * res, 0, -res, Y0 - r0 * res)
            write_geotiff(p, arr, CRS, tr, nodata=nodata, compress=compress,
                          tags={"image_id": f"S{k}_{s}", "strip": k})
            paths.append(p)
            if footprints:
                full = np.zeros((H, W), bool)
                full[r0:r1, c0:c1] = fp
                fps.append(full)
    return paths, (fps if footprints else None), (H, W)


def random_shifts(n, seed=1, lo=1.0, hi=5.0, rad=15.0):
    """Strip offsets of ``lo..hi`` px in random directions and radiometric offsets of up to
    ``rad``; strip 0 (the anchor) gets neither."""
    rng = np.random.default_rng(seed)
    ang = rng.uniform(0, 2 * np.pi, n)
    mag = rng.uniform(lo, hi, n)
    sh = np.c_[mag * np.sin(ang), mag * np.cos(ang)]
    sh[0] = 0
    rads = rng.uniform(-rad, rad, n)
    rads[0] = 0
    return sh, rads
