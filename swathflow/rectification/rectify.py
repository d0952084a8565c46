"""Orthorectification of raw line-scanner images onto an output grid.

Two methods (papers.md sections 1 and 3):

``exact`` (default, gap-free, inverse mapping)
    For each output tile the raw image coordinates (line, element) of the ground under the
    output pixel centres (map x, y with terrain heights) come from the sensor model's
    ``ground_to_image``, evaluated on a coarse lattice of the tile and interpolated
    bilinearly. Every lattice cell is checked at its centre and edge midpoints against the
    exact model; where the interpolation misses by ``tol`` pixels or more (default
    :data:`TOLERANCE_PX` = 0.05 raw pixel, in line and in element) the cell is split in four
    and checked again, down to single pixels (exact). Then the raw image is resampled
    (nearest, bilinear, or Keys cubic convolution), nodata-aware. Tiles are independent dask
    blocks; a tile reads only the raw window it needs, so memory is bounded by the tile size.

``polynomial`` (the fast forward method of You and Li)
    A few equally spaced pixels per scan line are projected to the ground, cubic
    polynomials in the element index are fitted to map x and y, every raw pixel is mapped
    forward to its nearest output pixel (mean of the pixels landing there) and the gaps
    inside the footprint are filled with the 3 x 3 inverse-distance window (weights 1/d).

Products: the rectified image, and optionally the GLT (output pixel -> raw pixel lookup,
ENVI convention: band 1 = element + 1, band 2 = line + 1, 0 = none) and the IGM (map x, y
and ellipsoidal height of every raw pixel centre, in raw geometry).

Outputs are float32 with NaN as nodata, written as Cloud-Optimized GeoTIFFs.
"""
from __future__ import annotations

import math
import os
import warnings
from collections.abc import Mapping

import numpy as np
from swathflow.errors import FormatError, SwathflowError
from swathflow.geometry.grid import Grid, ecef_to_map, footprint_grid
from swathflow.geometry.terrain import open_terrain
from swathflow.rectification.lattice import TOLERANCE_PX, exact_raw, inverse_map
from swathflow.rectification.rawimage import RawImage, RawSource, open_raw_image
from swathflow.rectification.tiles import (
    KERNELS,
    check_inputs,
    glt_blocks,
    output_plan,
    rectify,
    rectify_blocks,
    rectify_tile,
)
from swathflow.rectification.writing import GDAL_CACHE_MB, write_cog, write_cogs  # noqa: F401

__all__ = ["KERNELS", "TOLERANCE_PX", "RawImage", "RawSource", "exact_raw", "inverse_map",
           "open_raw_image", "rectify", "rectify_image", "rectify_tile", "resample",
           "write_cog", "write_cogs"]
METHODS = ("exact", "polynomial")


# ----------------------------------------------------------------------------------------
# raw image access and the inverse map (rectification/ holds the engine)
# ----------------------------------------------------------------------------------------
_exact_raw = exact_raw


# ----------------------------------------------------------------------------------------
# resampling kernels
# ----------------------------------------------------------------------------------------
def _keys(t):
    """Keys cubic convolution weights (a = -0.5) for offsets t (|t| < 2)."""
    a = -0.5
    t = np.abs(t)
    return np.where(t <= 1, (a + 2) * t ** 3 - (a + 3) * t ** 2 + 1,
                    np.where(t < 2, a * t ** 3 - 5 * a * t ** 2 + 8 * a * t - 4 * a, 0.0))


def _taps(x, n, kernel):
    """Tap indices ``(N, k)`` (clamped to [0, n-1]) and weights ``(N, k)``."""
    if kernel == "nearest":
        i = np.floor(x + 0.5)
        return np.clip(i, 0, n - 1).astype(np.intp)[:, None], np.ones((x.size, 1))
    i0 = np.floor(x)
    f = x - i0
    if kernel == "bilinear":
        idx = i0[:, None] + np.array([0, 1])
        wts = np.stack([1 - f, f], axis=-1)
    elif kernel == "cubic":
        off = np.array([-1, 0, 1, 2])
        idx = i0[:, None] + off
        wts = _keys(f[:, None] - off)
    else:
        raise FormatError(f"unknown resampling kernel {kernel!r}; use one of {', '.join(KERNELS)}")
    return np.clip(idx, 0, n - 1).astype(np.intp), wts


def resample(raw: np.ndarray, line, element, kernel: str = "bilinear") -> np.ndarray:
    """Values of ``raw`` (2-D, NaN = nodata) at continuous (line, element) coordinates
    (pixel centres at integers). NaN where a coordinate is NaN, off the image by more than
    half a pixel, or where a tap with non-zero weight is nodata. Off-edge taps repeat the
    edge pixel."""
    line = np.asarray(line, float)
    element = np.asarray(element, float)
    shape = line.shape
    li, ei = line.ravel(), element.ravel()
    nl, ne = raw.shape
    ok = (li >= -0.5) & (li <= nl - 0.5) & (ei >= -0.5) & (ei <= ne - 0.5)
    out = np.full(li.size, np.nan)
    k = np.flatnonzero(ok)
    if k.size and nl and ne:
        il, wl = _taps(li[k], nl, kernel)
        ie, we = _taps(ei[k], ne, kernel)
        acc = np.zeros(k.size)
        for a in range(il.shape[1]):
            for b in range(ie.shape[1]):
                wgt = wl[:, a] * we[:, b]
                v = raw[il[:, a], ie[:, b]]
                acc += np.where(wgt != 0, wgt * v, 0.0)
        out[k] = acc
    return out.reshape(shape)


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


# ----------------------------------------------------------------------------------------
# one image, end to end
# ----------------------------------------------------------------------------------------
def rectify_image(model, image, terrain, out_path, grid: Grid | None = None, gsd=None,
                  crs="auto-utm", method: str = "exact", kernel: str = "bilinear",
                  tol: float = TOLERANCE_PX, tile: int = 512, products=(),
                  tags: Mapping | None = None, scheduler=None, bands=None,
                  dtype=None, mask_band: bool = False) -> dict:
    """Rectify one raw image to a COG at ``out_path`` (and ``<stem>.glt.tif`` /
    ``<stem>.igm.tif`` when asked in ``products``). The grid is ``grid`` or the image's
    footprint at ``gsd`` in ``crs``. Every band (or the ``bands`` selected) is written,
    in the raw dtype (``dtype`` overrides; integer nodata, or a mask band with
    ``mask_band``: see :func:`output_plan`), with the bands' descriptions, wavelengths and
    units. Returns a small summary dict."""
    import time
    from swathflow._version import __version__
    if method not in METHODS:
        raise FormatError(f"unknown rectification method {method!r}; use one of "
                          f"{', '.join(METHODS)}")
    if kernel not in KERNELS:
        raise FormatError(f"unknown resampling kernel {kernel!r}; use one of {', '.join(KERNELS)}")
    unknown = set(products) - {"glt", "igm"}
    if unknown:
        raise FormatError(f"unknown product(s) {', '.join(sorted(unknown))}; use glt, igm")
    terrain = open_terrain(terrain)
    if grid is None:
        if gsd is None:
            raise FormatError("rectify_image needs a grid or a gsd")
        grid = footprint_grid(model, terrain, gsd, crs)
    t0 = time.perf_counter()
    base = {"software": f"swathflow {__version__}", "method": method, "kernel": kernel,
            "sensor": getattr(model, "name", ""), "tolerance_px": tol if method == "exact" else "",
            "terrain": str(terrain.state())}
    base.update({k: str(v) for k, v in (tags or {}).items()})
    stem = os.path.splitext(os.fspath(out_path))[0]
    summary = {"path": os.fspath(out_path), "grid": grid.state(), "method": method,
               "kernel": kernel}
    if method == "exact":
        source = open_raw_image(image, bands=bands)
        check_inputs(model, source, kernel)
        dt, out_nodata, use_mask = output_plan(source, dtype, mask_band)
        arr = rectify_blocks(model, source, grid, terrain, kernel, tol, tile, dtype=dtype,
                             mask_plane=use_mask)
        outs = [{"path": out_path, "array": arr, "grid": grid, "nodata": out_nodata, "tags": base,
                     "mask": use_mask, "bands": source.band_info}]
        summary.update(bands=source.count, dtype=dt.name,
                       nodata="mask band" if use_mask else str(out_nodata))
        if "glt" in products:
            outs.append({"path": stem + ".glt.tif",
                             "array": glt_blocks(model, source, grid, terrain, kernel, tol, tile),
                             "grid": grid, "nodata": 0, "dtype": np.int32,
                             "tags": {**base, "product": "GLT", "bands": "element+1,line+1",
                                   "convention": "ENVI GLT, 1-based, 0 = none"}})
        write_cogs(outs, blocksize=tile, scheduler=scheduler)
    else:
        st: dict = {}
        arr = rectify_polynomial(model, image, grid, terrain, stats=st)
        write_cog(out_path, arr, grid, nodata=float("nan"), tags=base, blocksize=tile)
        summary.update(st)
    if "igm" in products:
        import dask.array as da
        nl, ne = model.shape
        blk = max(1, min(nl, 2_000_000 // max(ne, 1)))
        parts = [da.from_delayed(_delayed(igm_block)(model, terrain, grid.crs, l0,
                                                     min(l0 + blk, nl)),
                                 shape=(3, min(l0 + blk, nl) - l0, ne), dtype=np.float64)
                 for l0 in range(0, nl, blk)]
        write_cog(stem + ".igm.tif", da.concatenate(parts, axis=1).rechunk((3, tile, tile)),
                  None, nodata=float("nan"), blocksize=tile, scheduler=scheduler,
                  tags={**base, "product": "IGM", "crs": grid.pyproj_crs.to_string(),
                        "bands": "x,y,h_ellipsoidal", "geometry": "raw (line, element)"})
    summary["seconds"] = round(time.perf_counter() - t0, 3)
    return summary


def _delayed(f):
    import dask
    return dask.delayed(f, pure=True)


# ----------------------------------------------------------------------------------------
# quality measurement: subpixel phase correlation
# ----------------------------------------------------------------------------------------
def _xcorr_peak(a, w, b, upsample: int = 20) -> np.ndarray:
    """Peak of the cross-correlation of the weighted template ``w * a`` with ``b`` (same
    shapes), to 1/upsample px with an upsampled DFT (Guizar-Sicairos et al. 2008)."""
    r = np.fft.fft2(a * w) * np.conj(np.fft.fft2(b))
    cc = np.fft.ifft2(r).real
    peak = np.array(np.unravel_index(np.argmax(cc), cc.shape), float)
    n = np.array(a.shape, float)
    peak = np.where(peak > n // 2, peak - n, peak)
    size = math.ceil(upsample * 1.5)
    rows = (np.arange(size) - size // 2) / upsample + peak[0]
    cols = (np.arange(size) - size // 2) / upsample + peak[1]
    kr = np.fft.fftfreq(a.shape[0]) * a.shape[0]
    kc = np.fft.fftfreq(a.shape[1]) * a.shape[1]
    m = (np.exp(2j * np.pi * np.outer(rows, kr) / a.shape[0]) @ r
         @ np.exp(2j * np.pi * np.outer(kc, cols) / a.shape[1])).real
    i, j = np.unravel_index(np.argmax(m), m.shape)
    return np.array([rows[i], cols[j]])


def phase_shift(a: np.ndarray, b: np.ndarray, iterations: int = 5,
                with_sigma: bool = False):
    """Subpixel shift (drow, dcol) of ``a``'s content relative to ``b``'s
    (``a(p) ~= b(p - shift)``), in pixels.

    ``a`` may hold NaN (outside a footprint, or around a tile); ``b`` (the reference, e.g.
    a truth ortho) must be finite. The template ``a`` is Hann-windowed and masked, ``b``
    is not, so neither the window nor the mask correlates with itself (a window on both
    images biases a whitened phase correlation towards zero: measured 0.13 px for a true
    0.3 px). Gauss-Newton on ``sum w (a - b(p - shift) - offset)^2`` (``b`` shifted by
    cubic B-spline interpolation: a Fourier shift rings from the patch's borders)
    starts from the cross-correlation peak (upsampled DFT) and from zero; the better fit
    wins;
    on analytic textures it recovers imposed shifts to 1e-3 px. ``with_sigma`` also returns
    the standard errors of the two components from the residuals (treated as white noise:
    optimistic where the residual is correlated, e.g. resampled sensor noise)."""
    a = np.asarray(a, float)
    b = np.asarray(b, float)
    va = np.isfinite(a)
    if va.sum() < 16 or not np.isfinite(b).all():
        nan = float("nan")
        return ((nan, nan), (nan, nan)) if with_sigma else (nan, nan)
    w = np.outer(np.hanning(a.shape[0] + 2)[1:-1], np.hanning(a.shape[1] + 2)[1:-1]) * va
    am = np.where(va, a, 0.0)
    am = np.where(va, am - np.sum(w * am) / w.sum(), 0.0)
    b = b - b.mean()
    from scipy import ndimage
    coef = ndimage.spline_filter(b, order=3, mode="mirror")

    def shifted(d):
        # cubic B-spline interpolation in the spatial domain: no wrap-around ringing
        return ndimage.shift(coef, d, order=3, mode="mirror", prefilter=False)

    def fit(d):
        for i in range(iterations + 1):
            bs = shifted(d)
            gr, gc = np.gradient(bs)
            res = np.where(va, am - (bs - np.sum(w * bs) / w.sum()), 0.0)
            A = np.array([[np.sum(w * gr * gr), np.sum(w * gr * gc)],
                          [np.sum(w * gr * gc), np.sum(w * gc * gc)]])
            if i == iterations:
                break
            step = -np.linalg.lstsq(A, [np.sum(w * gr * res), np.sum(w * gc * res)],
                                    rcond=None)[0]
            d = d + step
            if np.abs(step).max() < 1e-5:
                bs = shifted(d)
                gr, gc = np.gradient(bs)
                res = np.where(va, am - (bs - np.sum(w * bs) / w.sum()), 0.0)
                break
        return d, float(np.sum(w * res ** 2)), A, gr, gc, res

    # from the cross-correlation peak and from zero (the expected answer): keep the better
    # fit, so a repeated pattern (rows of roofs) cannot capture the estimate
    fits = [fit(_xcorr_peak(am, w, b)), fit(np.zeros(2))]
    d, _, A, gr, gc, res = min(fits, key=lambda f: f[1])
    d = (float(d[0]), float(d[1]))
    if not with_sigma:
        return d
    G = np.stack([gr[va], gc[va]], axis=-1)
    wv = w[va]
    sigma2 = np.sum(wv * res[va] ** 2) / np.sum(wv)
    Ainv = np.linalg.pinv(A)
    cov = sigma2 * Ainv @ ((G * (wv ** 2)[:, None]).T @ G) @ Ainv
    return d, (float(np.sqrt(cov[0, 0])), float(np.sqrt(cov[1, 1])))


def _isotropy(img: np.ndarray) -> float:
    """Smallest over largest eigenvalue of the gradient structure tensor (0: a straight
    edge or a flat patch, along which a shift cannot be measured; 1: isotropic texture)."""
    gr, gc = np.gradient(np.asarray(img, float))
    a, b, c = np.sum(gr * gr), np.sum(gr * gc), np.sum(gc * gc)
    ev = np.linalg.eigvalsh(np.array([[a, b], [b, c]]))
    return float(ev[0] / ev[1]) if ev[1] > 0 else 0.0


def shift_report(rect: np.ndarray, truth: np.ndarray, tile: int = 128, margin: int = 16,
                 min_valid: float = 0.98, min_isotropy: float = 0.1,
                 max_sigma: float = 0.03) -> dict:
    """Positional agreement of a rectified image with a truth image on the same grid
    (:func:`phase_shift`): over the whole footprint (the bounding box of the valid
    pixels) and per ``tile`` x ``tile`` tile with at least ``min_valid`` valid pixels (the
    template is the tile, matched within ``margin`` pixels of truth around it). The worst
    tile is the one with the largest shift. Tiles whose truth is essentially one-dimensional
    (structure-tensor eigenvalue ratio below ``min_isotropy``: one straight edge, or flat)
    or whose own standard error (:func:`phase_shift`) exceeds ``max_sigma`` px (noise
    dominating a weak texture) are skipped and counted in ``skipped_tiles``."""
    valid = np.isfinite(rect)
    if not valid.any():
        raise SwathflowError("shift_report: the rectified image has no valid pixel")
    rr = np.flatnonzero(valid.any(axis=1))
    cc = np.flatnonzero(valid.any(axis=0))
    box = (slice(rr[0], rr[-1] + 1), slice(cc[0], cc[-1] + 1))
    whole = phase_shift(rect[box], truth[box])
    tiles = []
    skipped = 0
    H, W = rect.shape
    for r in range(margin, H - tile - margin + 1, tile):
        for c in range(margin, W - tile - margin + 1, tile):
            win = (slice(r, r + tile), slice(c, c + tile))
            if valid[win].mean() < min_valid:
                continue
            big = (slice(r - margin, r + tile + margin), slice(c - margin, c + tile + margin))
            if not np.isfinite(truth[big]).all():
                continue
            if _isotropy(truth[win]) < min_isotropy:
                skipped += 1                 # 1-D structure (an edge): shift ill-posed
                continue
            a = np.full((tile + 2 * margin,) * 2, np.nan)
            a[margin:-margin, margin:-margin] = rect[win]
            d, sd = phase_shift(a, truth[big], with_sigma=True)
            if not max(sd) <= max_sigma:
                skipped += 1                 # the tile cannot measure to that precision
                continue
            tiles.append((r, c, d[0], d[1], math.hypot(*d)))
    worst = max(tiles, key=lambda t: t[4]) if tiles else None
    mags = np.array([t[4] for t in tiles])
    return {"whole": whole, "whole_px": math.hypot(*whole), "tiles": len(tiles),
            "skipped_tiles": skipped, "worst_tile": worst,
            "worst_tile_px": float(mags.max()) if tiles else float("nan"),
            "median_tile_px": float(np.median(mags)) if tiles else float("nan")}
