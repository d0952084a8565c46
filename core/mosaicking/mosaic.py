"""Strip matching and feathered mosaicking of rectified swings (papers.md section 3).

Steps (:func:`mosaic` runs them all):

1. :func:`scan_inputs` reads the rectified swings' headers: one common grid (same CRS, pixel
   size, aligned transforms), each swing's place on it, image id and strip number.
2. :func:`find_overlaps` lists the pairs whose footprints overlap (bounds, then valid masks).
3. :func:`match_pair` estimates each overlap's systematic offset (swathflow.mosaicking.matching: the
   paper's minimum-mean-grey-difference search, phase correlation, least-squares polish,
   texture check, outlier rejection). Low-texture overlaps are reported and skipped.
4. :func:`solve_network` solves one least-squares network for per-strip (or per-image)
   offsets and radiometric offsets, anchored on given images (or, without anchors, on the
   mean of each connected group), with iterative rejection of inconsistent overlaps.
5. :func:`render_tile` blends the corrected swings with distance-transform feathering: the
   weight of a swing is its distance to its own footprint's edge (capped at ``feather``
   pixels), which is the paper's ``G = (Rl*Gr + Rr*Gl)/(Rl + Rr)`` for a straight overlap
   and works for any overlap shape. Tiles are computed over dask and streamed to disk, so
   memory does not grow with the mosaic; the result is a COG with overviews plus a PNG
   quicklook and a JSON report.

Offsets: a node's offset ``t = (drow, dcol)`` means its content sits ``t`` pixels away from
where it belongs (``image[x] = truth[x - t]``); the mosaic samples ``image[x + t]``.
Radiometric offset ``b``: ``image = truth + b``; the mosaic subtracts ``b``.
"""
from __future__ import annotations

import json
import math
import os
import threading
import time
from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage

from swathflow.errors import FormatError, SwathflowError
from swathflow.io import atomic_path, write_text
from swathflow.mosaicking.matching import OverlapMatch, combine_blocks, match_block

__all__ = ["Swing", "Layout", "scan_inputs", "find_overlaps", "match_pair", "solve_network",
           "render_tile", "write_mosaic", "mosaic", "mission_strips", "find_inputs",
           "quicklook", "seam_lines", "seam_visibility", "TAG_IMAGE", "TAG_STRIP"]

# plain tag names: GDAL splits "a:b=c" metadata at the colon, so no namespaced keys
TAG_IMAGE = "image_id"
TAG_STRIP = "strip"
TAG_DIRECTION = "direction"


# --- inputs -----------------------------------------------------------------------------------
@dataclass(frozen=True)
class Swing:
    """One rectified swing: its file and its place on the common grid (pixel offsets)."""
    path: str
    image_id: str
    strip: int
    row: int          # grid row of the file's first row
    col: int
    height: int
    width: int
    nodata: float | None
    dtype: str
    direction: str = ""

    @property
    def extent(self):
        return self.row, self.col, self.row + self.height, self.col + self.width


@dataclass
class Layout:
    """The common grid and the swings on it."""
    crs: object                 # rasterio CRS
    transform: object           # affine.Affine of the grid's top-left corner
    shape: tuple[int, int]
    swings: list[Swing] = field(default_factory=list)

    @property
    def res(self) -> float:
        return abs(self.transform.a)


def _tag(tags: dict, *names, default=None):
    for n in names:
        if n in tags and str(tags[n]).strip() != "":
            return tags[n]
    return default


def scan_inputs(paths, strips: dict | None = None) -> Layout:
    """Read the headers of rectified swings and place them on their common grid.

    All inputs must share the CRS and pixel size and be aligned to whole pixels; the grid is
    the union of their extents. Image ids come from the tag ``image_id`` (else the file
    name), strips from ``strips`` (image id -> strip, e.g. from mission.toml), else the tag
    ``strip``, else the file order (every file its own strip).
    """
    import rasterio
    from affine import Affine
    paths = [os.fspath(p) for p in paths]
    if not paths:
        raise FormatError("no rectified swings given (expected single-band GeoTIFFs)")
    heads = []
    for k, p in enumerate(paths):
        try:
            with rasterio.open(p) as ds:
                t = ds.transform
                if t.b != 0 or t.d != 0:
                    raise FormatError(f"{p}: rotated transforms are not supported; rectify "
                                      f"to a north-up grid")
                tags = ds.tags()
                nod = ds.nodata
                heads.append((p, ds.crs, t, ds.height, ds.width, nod, ds.dtypes[0], tags,
                              ds.count))
        except rasterio.errors.RasterioIOError as exc:
            raise FormatError(f"{p}: cannot read raster: {exc}") from None
    p0, crs0, t0 = heads[0][0], heads[0][1], heads[0][2]
    for p, crs, t, *_ in heads[1:]:
        if crs != crs0:
            raise FormatError(f"{p}: CRS differs from {p0}; rectify every swing to one grid")
        if not (math.isclose(t.a, t0.a, rel_tol=1e-9) and math.isclose(t.e, t0.e, rel_tol=1e-9)):
            raise FormatError(f"{p}: pixel size ({t.a}, {t.e}) differs from {p0} "
                              f"({t0.a}, {t0.e}); rectify every swing to one grid")
    xs = np.array([h[2].c for h in heads])
    ys = np.array([h[2].f for h in heads])
    x0, y0 = xs.min(), ys.max()
    cols = (xs - x0) / t0.a
    rows = (ys - y0) / t0.e
    for (p, *_), r, c in zip(heads, rows, cols):
        if abs(r - round(r)) > 1e-3 or abs(c - round(c)) > 1e-3:
            raise FormatError(f"{p}: not aligned with {p0} (offset of {r:.3f}, {c:.3f} "
                              f"pixels); rectify every swing to one aligned grid")
    swings = []
    for k, ((p, _, _, h, w, nod, dt, tags, count), r, c) in enumerate(zip(heads, rows, cols)):
        if count != 1:
            raise FormatError(f"{p}: has {count} bands; rectified swings are single-band")
        iid = str(_tag(tags, TAG_IMAGE, "IMAGE_ID", default=os.path.splitext(os.path.basename(p))[0]))
        strip = strips.get(iid) if strips else None
        if strip is None:
            strip = _tag(tags, TAG_STRIP, "STRIP", default=None)
        try:
            strip = int(float(strip)) if strip is not None else k
        except ValueError:
            raise FormatError(f"{p}: tag {TAG_STRIP}={strip!r} is not a strip number") from None
        direction = str(_tag(tags, TAG_DIRECTION, "DIRECTION", default=""))
        swings.append(Swing(p, iid, strip, int(round(r)), int(round(c)), h, w, nod, dt,
                            direction))
    ids = [s.image_id for s in swings]
    dup = {i for i in ids if ids.count(i) > 1}
    if dup:
        raise FormatError(f"image ids used by more than one file: {sorted(dup)}; give every "
                          f"swing a unique {TAG_IMAGE} tag")
    height = max(s.row + s.height for s in swings)
    width = max(s.col + s.width for s in swings)
    transform = Affine(t0.a, 0.0, float(x0), 0.0, t0.e, float(y0))
    return Layout(crs0, transform, (height, width), swings)


# --- windowed reading ---------------------------------------------------------------------------
class _Handles:
    """Open datasets, one small LRU set per thread (GDAL handles must not be shared across
    threads; an open dataset costs memory, so at most ``per_thread`` stay open)."""

    def __init__(self, per_thread: int = 16):
        self._local = threading.local()
        self._all = set()
        self._lock = threading.Lock()
        self.per_thread = per_thread

    def get(self, path):
        import rasterio
        from collections import OrderedDict
        cache = getattr(self._local, "cache", None)
        if cache is None:
            cache = self._local.cache = OrderedDict()
        ds = cache.get(path)
        if ds is not None:
            cache.move_to_end(path)
            return ds
        ds = cache[path] = rasterio.open(path)
        with self._lock:
            self._all.add(ds)
        while len(cache) > self.per_thread:
            _, old = cache.popitem(last=False)
            with self._lock:
                self._all.discard(old)
            old.close()
        return ds

    def close(self):
        with self._lock:
            for ds in self._all:
                ds.close()
            self._all.clear()


def _valid(a, nodata):
    ok = np.isfinite(a) if a.dtype.kind == "f" else np.ones(a.shape, bool)
    if nodata is not None and not (isinstance(nodata, float) and math.isnan(nodata)):
        ok &= a != nodata
    return ok


def read_window(handles: _Handles, sw: Swing, r0: int, c0: int, r1: int, c1: int,
                step: int = 1):
    """Values (float64) and valid mask of grid window ``[r0, r1) x [c0, c1)`` of one swing
    (outside the file: invalid). ``step > 1`` reads a decimated window (nearest)."""
    h, w = (r1 - r0 + step - 1) // step, (c1 - c0 + step - 1) // step
    val = np.zeros((h, w))
    ok = np.zeros((h, w), bool)
    # the part of the window inside the file, aligned to the decimation lattice
    a0 = max(r0, sw.row)
    b0 = max(c0, sw.col)
    a0 = r0 + -(-(a0 - r0) // step) * step
    b0 = c0 + -(-(b0 - c0) // step) * step
    a1, b1 = min(r1, sw.row + sw.height), min(c1, sw.col + sw.width)
    if a1 <= a0 or b1 <= b0:
        return val, ok
    from rasterio.windows import Window
    ds = handles.get(sw.path)
    win = Window(b0 - sw.col, a0 - sw.row, b1 - b0, a1 - a0)
    i0, j0 = (a0 - r0) // step, (b0 - c0) // step
    if step == 1:
        data = ds.read(1, window=win)
    else:
        shape = ((a1 - a0 + step - 1) // step, (b1 - b0 + step - 1) // step)
        data = ds.read(1, window=win, out_shape=shape)
    hh, ww = data.shape
    val[i0:i0 + hh, j0:j0 + ww] = data
    ok[i0:i0 + hh, j0:j0 + ww] = _valid(data, sw.nodata)
    val[~ok] = 0.0
    return val, ok


# --- overlaps ---------------------------------------------------------------------------------
def find_overlaps(layout: Layout, groups=None, min_pixels: int = 256, handles=None,
                  max_side: int = 512):
    """Pairs ``(i, j, window, n_common)`` of swings whose valid footprints overlap by at least
    ``min_pixels`` pixels (counted on a decimated read of at most ``max_side`` pixels a side).
    ``groups``: optional node key per swing; pairs within one group are left out."""
    sw = layout.swings
    ext = np.array([s.extent for s in sw])
    r0 = np.maximum(ext[:, None, 0], ext[None, :, 0])
    c0 = np.maximum(ext[:, None, 1], ext[None, :, 1])
    r1 = np.minimum(ext[:, None, 2], ext[None, :, 2])
    c1 = np.minimum(ext[:, None, 3], ext[None, :, 3])
    cand = (r1 > r0) & (c1 > c0)
    cand &= np.triu(np.ones(cand.shape, bool), 1)
    if groups is not None:
        g = np.asarray(groups, dtype=object)
        cand &= g[:, None] != g[None, :]
    own = handles is None
    handles = handles or _Handles()
    pairs = []
    try:
        for i, j in zip(*np.nonzero(cand)):
            win = (int(r0[i, j]), int(c0[i, j]), int(r1[i, j]), int(c1[i, j]))
            step = max(1, int(math.ceil(max(win[2] - win[0], win[3] - win[1]) / max_side)))
            _, oki = read_window(handles, sw[i], *win, step=step)
            _, okj = read_window(handles, sw[j], *win, step=step)
            n = int((oki & okj).sum()) * step * step
            if n >= min_pixels:
                pairs.append((int(i), int(j), win, n))
    finally:
        if own:
            handles.close()
    return pairs


def _blocks_for(handles, a: Swing, b: Swing, win, block: int, max_blocks: int,
                min_fraction: float = 0.3):
    """Block windows inside overlap ``win`` with enough common coverage, evenly thinned to
    at most ``max_blocks``."""
    r0, c0, r1, c1 = win
    hb = min(block, r1 - r0)
    wb = min(block, c1 - c0)
    rows = list(range(r0, r1 - hb + 1, hb)) or [r0]
    cols = list(range(c0, c1 - wb + 1, wb)) or [c0]
    if rows[-1] + hb < r1:
        rows.append(r1 - hb)
    if cols[-1] + wb < c1:
        cols.append(c1 - wb)
    step = max(1, min(hb, wb) // 8)
    _, oka = read_window(handles, a, r0, c0, r1, c1, step=step)
    _, okb = read_window(handles, b, r0, c0, r1, c1, step=step)
    joint = oka & okb
    out = []
    for br in rows:
        for bc in cols:
            sub = joint[(br - r0) // step:(br - r0 + hb) // step or 1,
                        (bc - c0) // step:(bc - c0 + wb) // step or 1]
            if sub.size and sub.mean() >= min_fraction:
                out.append((br, bc, br + hb, bc + wb))
    if len(out) > max_blocks:
        keep = np.unique(np.round(np.linspace(0, len(out) - 1, max_blocks)).astype(int))
        out = [out[k] for k in keep]
    return out


def match_pair(layout: Layout, i: int, j: int, win, handles=None, max_shift: int = 12,
               block: int = 128, max_blocks: int = 48, min_texture: float = 1.0,
               min_pixels: int = 256) -> OverlapMatch:
    """Offset of swing ``j`` relative to swing ``i`` over their overlap ``win``."""
    own = handles is None
    handles = handles or _Handles()
    a, b = layout.swings[i], layout.swings[j]
    S = int(max_shift)
    blocks = []
    try:
        for br0, bc0, br1, bc1 in _blocks_for(handles, a, b, win, block, max_blocks):
            ref, rok = read_window(handles, a, br0, bc0, br1, bc1)
            mov, mok = read_window(handles, b, br0 - S, bc0 - S, br1 + S, bc1 + S)
            if rok.sum() < min_pixels:
                continue
            m = match_block(ref, rok, mov, mok, S, min_texture=min_texture,
                            min_pixels=min(min_pixels, (br1 - br0) * (bc1 - bc0) // 4))
            m.centre = ((br0 + br1) / 2.0, (bc0 + bc1) / 2.0)
            blocks.append(m)
    finally:
        if own:
            handles.close()
    return combine_blocks(blocks)


# --- the network -----------------------------------------------------------------------------
@dataclass
class Network:
    nodes: list                          # node keys
    offsets: np.ndarray                  # (n, 2) px
    sigmas: np.ndarray                   # (n, 2) px (NaN when not computed)
    radiometric: np.ndarray              # (n,)
    residuals: np.ndarray                # (m, 2) per observation (NaN if rejected)
    used: np.ndarray                     # (m,) bool
    sigma0: float
    anchored: list
    free_groups: list                    # components without an anchor (mean fixed to 0)


def _components(n, edges):
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    if not edges:
        return n, np.arange(n)
    e = np.array(edges)
    g = coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(n, n))
    return connected_components(g, directed=False)


def _solve_lsq(n, obs_ij, values, weights, anchored, labels, max_dense: int = 1500):
    """Weighted LSQ of ``x_j - x_i = value`` with anchored nodes fixed at 0 and the mean
    of every anchor-free component fixed at 0 (sparse normal equations). Returns
    ``(x, sigma_x)``; ``sigma_x`` is NaN above ``max_dense`` nodes."""
    from scipy import sparse
    from scipy.sparse.linalg import spsolve
    rows, cols, vals, rhs, w = [], [], [], [], []
    r = 0
    for k, (i, j) in enumerate(obs_ij):
        rows += [r, r]
        cols += [j, i]
        vals += [1.0, -1.0]
        rhs.append(values[k])
        w.append(weights[k])
        r += 1
    anchored = set(anchored)
    wmed = float(np.median(weights)) if len(weights) else 1.0
    for comp in np.unique(labels):
        members = np.nonzero(labels == comp)[0]
        if not anchored.intersection(members.tolist()):
            rows += [r] * len(members)
            cols += members.tolist()
            vals += [1.0 / len(members)] * len(members)
            rhs.append(0.0)
            w.append(wmed)
            r += 1
    for k in sorted(anchored):
        rows.append(r)
        cols.append(k)
        vals.append(1.0)
        rhs.append(0.0)
        w.append(1e12)
        r += 1
    a = sparse.csr_matrix((vals, (rows, cols)), shape=(r, n))
    wd = sparse.diags(np.asarray(w, float))
    nmat = (a.T @ wd @ a).tocsc()
    b = a.T @ (np.asarray(w, float) * np.asarray(rhs, float))
    if n <= max_dense:
        cov = np.linalg.inv(nmat.toarray())
        return cov @ b, np.sqrt(np.maximum(np.diag(cov), 0.0))
    return spsolve(nmat, b), np.full(n, np.nan)


def solve_network(nodes: list, obs: list, anchors=(), reject: float = 4.0,
                  min_reject: float = 0.3, max_rounds: int = 20) -> Network:
    """Least-squares offsets per node from pairwise observations.

    ``obs``: ``(i, j, OverlapMatch)`` with node indices ``i, j`` (ref, mov): each accepted
    match says ``t_j - t_i = offset`` and ``b_j - b_i = radiometric``. ``anchors``: node
    indices held at zero offset (calibrated images); components of the overlap graph with no
    anchor get their mean fixed at zero instead. An observation whose normalised residual
    exceeds ``reject`` (and ``min_reject`` px) is dropped and the network solved again, as
    long as dropping it does not split the graph.
    """
    n = len(nodes)
    m = len(obs)
    used = np.array([o[2].ok for o in obs], bool)
    anchors = sorted(set(int(a) for a in anchors))
    while True:
        idx = np.nonzero(used)[0]
        edges = [(obs[k][0], obs[k][1]) for k in idx]
        ncomp, labels = _components(n, edges)
        if len(idx) == 0:
            x = np.zeros((n, 2))
            sx = np.full((n, 2), np.nan)
            rad = np.zeros(n)
            break
        d = np.array([obs[k][2].offset for k in idx])
        s = np.array([obs[k][2].sigma for k in idx])
        xs, sxs = [], []
        for c in range(2):
            xc, sc = _solve_lsq(n, edges, d[:, c], 1.0 / s[:, c] ** 2, anchors, labels)
            xs.append(xc)
            sxs.append(sc)
        x = np.column_stack(xs)
        pred = np.array([x[j] - x[i] for i, j in edges])
        v = d - pred
        norm = np.abs(v) / s
        n_free = ncomp - len({labels[a] for a in anchors})
        dof = max(2 * (len(idx) - (n - len(anchors) - n_free)), 0)
        s0 = float(np.sqrt((norm ** 2).sum() / dof)) if dof > 0 else float("nan")
        sx = np.column_stack(sxs) * (max(s0, 1.0) if np.isfinite(s0) else 1.0)
        worst = int(np.argmax(norm.max(axis=1)))
        if (max_rounds > 0 and norm[worst].max() > reject and np.abs(v[worst]).max() > min_reject):
            k = idx[worst]
            used[k] = False
            n2, _ = _components(n, [(obs[q][0], obs[q][1]) for q in np.nonzero(used)[0]])
            if n2 > ncomp:
                used[k] = True          # the only link: keep it (cannot be checked)
            else:
                max_rounds -= 1
                continue
        rv = np.array([obs[k][2].radiometric for k in idx])
        rs = np.array([obs[k][2].radiometric_sigma for k in idx])
        rs = np.where(np.isfinite(rs) & (rs > 0), rs, np.nanmedian(np.where(rs > 0, rs, np.nan))
                      if np.any(rs > 0) else 1.0)
        rs = np.where(np.isfinite(rs), rs, 1.0)
        rad, _ = _solve_lsq(n, edges, rv, 1.0 / np.maximum(rs, 1e-3) ** 2, anchors, labels)
        break
    residuals = np.full((m, 2), np.nan)
    for k in np.nonzero(used)[0]:
        i, j = obs[k][0], obs[k][1]
        residuals[k] = np.array(obs[k][2].offset) - (x[j] - x[i])
    if not used.any():
        s0 = float("nan")
        ncomp, labels = n, np.arange(n)
    free = [[nodes[q] for q in np.nonzero(labels == c)[0]] for c in np.unique(labels)
            if not set(anchors).intersection(np.nonzero(labels == c)[0].tolist())]
    return Network(list(nodes), x, sx, np.asarray(rad, float), residuals, used, s0,
                   [nodes[a] for a in anchors], free)


# --- blending -------------------------------------------------------------------------------------
def _fill_nearest(val, ok):
    if ok.all() or not ok.any():
        return val
    idx = ndimage.distance_transform_edt(~ok, return_distances=False, return_indices=True)
    return val[tuple(idx)]


def _corrected(handles, sw: Swing, t, r0, c0, r1, c1):
    """Swing ``sw`` corrected by offset ``t`` on grid window ``[r0,r1) x [c0,c1)``:
    ``out[x] = image[x + t]`` (cubic spline), and its valid mask (every pixel the
    interpolation leans on was valid)."""
    a = np.floor(t).astype(int)
    f = np.asarray(t, float) - a
    if f[0] < 1e-6 and f[1] < 1e-6:
        return read_window(handles, sw, r0 + a[0], c0 + a[1], r1 + a[0], c1 + a[1])
    p = 3
    val, ok = read_window(handles, sw, r0 + a[0] - p, c0 + a[1] - p, r1 + a[0] + p,
                          c1 + a[1] + p)
    h, w = r1 - r0, c1 - c0
    if not ok.any():
        return val[p:p + h, p:p + w], ok[p:p + h, p:p + w]
    val = _fill_nearest(val, ok)
    sv = ndimage.shift(val, -f, order=3, mode="nearest")
    # a cubic spline rings at steps (the outer edge of a swing, saturated targets): keep
    # the result within the values it interpolates (issue 13: -548..14,412 from 887..13,207)
    # (bounds of each pixel's 4 x 4 spline support, so the result does not depend on tiling)
    lo = ndimage.minimum_filter(val, size=4, origin=-1, mode="nearest")
    hi = ndimage.maximum_filter(val, size=4, origin=-1, mode="nearest")
    sv = np.clip(sv, lo, hi)
    # out[i] reads val[i + p + f]: valid where the pixels on both sides were valid
    m = ok[p:p + h + 1, p:p + w + 1]
    if f[0] >= 1e-6:
        m = m[:-1] & m[1:]
    else:
        m = m[:-1]
    if f[1] >= 1e-6:
        m = m[:, :-1] & m[:, 1:]
    else:
        m = m[:, :-1]
    return sv[p:p + h, p:p + w], m


def render_tile(layout: Layout, r0, c0, r1, c1, offsets, radiometric, handles,
                feather: int = 64, mode: str = "feather", sel=None):
    """Blend grid window ``[r0,r1) x [c0,c1)``. ``offsets`` (n_swings, 2) and
    ``radiometric`` (n_swings,) per swing. ``mode``: ``"feather"`` (distance-weighted),
    ``"cut"`` (each pixel from the swing deepest inside its footprint: hard seams) or
    ``"first"`` (first valid swing wins, like rasterio.merge). Returns (values, valid).

    A swing's weight is its distance to the nearest pixel outside its own (corrected)
    footprint, capped at ``feather``; it is computed on the tile grown by ``feather + 2``
    pixels, which is exact for a capped distance, so tiles join without seams.
    """
    h, w = r1 - r0, c1 - c0
    E = int(feather) + 2
    acc = np.zeros((h, w))
    wsum = np.zeros((h, w))
    best = np.full((h, w), -1.0)
    offsets = np.asarray(offsets, float)
    ext = np.array([s.extent for s in layout.swings], float)
    lo = np.floor(ext[:, :2] - offsets).astype(int) - 1      # corrected footprint bounds
    hi = np.ceil(ext[:, 2:] - offsets).astype(int) + 1
    hit = ((lo[:, 0] < r1 + E) & (hi[:, 0] > r0 - E) & (lo[:, 1] < c1 + E) & (hi[:, 1] > c0 - E))
    if sel is not None:
        hit &= sel
    for k in np.nonzero(hit)[0]:
        sw = layout.swings[k]
        # the part of the grown tile this swing can reach
        a0, b0 = max(r0 - E, lo[k, 0]), max(c0 - E, lo[k, 1])
        a1, b1 = min(r1 + E, hi[k, 0]), min(c1 + E, hi[k, 1])
        # the tile pixels inside it
        i0, j0 = max(a0, r0), max(b0, c0)
        i1, j1 = min(a1, r1), min(b1, c1)
        if i1 <= i0 or j1 <= j0:
            continue
        val, ok = _corrected(handles, sw, offsets[k], a0, b0, a1, b1)
        core = ok[i0 - a0:i1 - a0, j0 - b0:j1 - b0]
        if not core.any():
            continue
        v = val[i0 - a0:i1 - a0, j0 - b0:j1 - b0] - radiometric[k]
        ta, tb = slice(i0 - r0, i1 - r0), slice(j0 - c0, j1 - c0)
        if mode == "first":
            take = core & (wsum[ta, tb] == 0)
            acc[ta, tb][take] = v[take]
            wsum[ta, tb][take] = 1.0
            continue
        dist = ndimage.distance_transform_edt(np.pad(ok, 1))[1:-1, 1:-1]
        wt = np.minimum(dist[i0 - a0:i1 - a0, j0 - b0:j1 - b0], float(feather)) * core
        if mode == "cut":
            take = core & (wt > best[ta, tb])
            acc[ta, tb][take] = v[take]
            best[ta, tb][take] = wt[take]
            wsum[ta, tb][take] = 1.0
        else:
            acc[ta, tb] += wt * v
            wsum[ta, tb] += wt
    valid = wsum > 0
    out = np.where(valid, acc / np.where(valid, wsum, 1.0), np.nan)
    return out, valid


# --- the whole job ----------------------------------------------------------------------------
def _node_keys(layout: Layout, per_image: bool):
    if per_image:
        return [s.image_id for s in layout.swings]
    return [s.strip for s in layout.swings]


def _resolve_anchors(layout, keys, nodes, anchors):
    out = set()
    by_id = {s.image_id: k for k, s in enumerate(layout.swings)}
    strips = {str(s.strip) for s in layout.swings}
    for a in anchors or ():
        a = str(a)
        if a in by_id:
            out.add(nodes.index(keys[by_id[a]]))
        elif a.removeprefix("strip:") in strips:
            sn = int(a.removeprefix("strip:"))
            for k, s in enumerate(layout.swings):
                if s.strip == sn:
                    out.add(nodes.index(keys[k]))
        else:
            raise SwathflowError(f"anchor {a!r} is neither an image id nor a strip number of "
                                 f"the inputs (image ids: {sorted(by_id)[:5]}...)")
    return sorted(out)


def _active_client():
    """The Dask distributed client of this context (the mission flow's cluster), if any."""
    try:
        from distributed import get_client
        return get_client()
    except (ImportError, ValueError):
        return None


def plan(layout: Layout, per_image: bool = False, anchors=(), max_shift: int = 12,
         block: int = 128, min_texture: float = 1.0, workers: int | None = None,
         log=None):
    """Match every overlap and solve the network. Returns (network, pairs, matches, keys).
    The overlaps are matched on the active Dask distributed client's workers when there is
    one (the mission flow's cluster), else on ``workers`` local threads."""
    import dask
    keys = _node_keys(layout, per_image)
    nodes = list(dict.fromkeys(keys))
    handles = _Handles()
    try:
        pairs = find_overlaps(layout, groups=keys, handles=handles)
        if log:
            log(f"{len(layout.swings)} swings, {len(nodes)} nodes, {len(pairs)} overlaps")
        client = _active_client()
        if client is not None:
            # worker processes (the matching is mostly small numpy steps that hold the GIL:
            # threads do not add up); each task opens its own files
            lay = client.scatter(layout, broadcast=True)
            futures = [client.submit(match_pair, lay, i, j, win, None, max_shift, block, 48,
                                     min_texture, pure=False) for i, j, win, _ in pairs]
            matches = client.gather(futures)
        else:
            # the layout as one graph key: dask would otherwise walk its swings per task
            lay = dask.delayed(layout, traverse=False)
            tasks = [dask.delayed(match_pair)(lay, i, j, win, handles, max_shift, block,
                                              48, min_texture) for i, j, win, _ in pairs]
            matches = list(dask.compute(*tasks, scheduler="threads", num_workers=workers))
    finally:
        handles.close()
    obs = [(nodes.index(keys[i]), nodes.index(keys[j]), m)
           for (i, j, _, _), m in zip(pairs, matches)]
    net = solve_network(nodes, obs, _resolve_anchors(layout, keys, nodes, anchors))
    return net, pairs, matches, keys


class _Writer:
    """A dask ``store`` target writing windows into an open rasterio dataset."""

    def __init__(self, ds, nodata, dtype):
        self.ds, self.nodata, self.dtype = ds, nodata, np.dtype(dtype)

    def __setitem__(self, key, block):
        from rasterio.windows import Window
        rs, cs = key
        out = block
        if self.dtype.kind in "ui":
            info = np.iinfo(self.dtype)
            bad = ~np.isfinite(out)
            out = np.clip(np.round(np.where(bad, 0, out)), info.min, info.max)
            out = out.astype(self.dtype)
            out[bad] = self.nodata
        else:
            out = out.astype(self.dtype)
            if self.nodata is not None and not np.isnan(self.nodata):
                out[~np.isfinite(out)] = self.nodata
        self.ds.write(out, 1, window=Window(cs.start, rs.start, cs.stop - cs.start,
                                            rs.stop - rs.start))


def write_mosaic(layout: Layout, out, offsets, radiometric, feather: int = 64,
                 mode: str = "feather", tile: int = 1024, workers: int | None = None,
                 dtype=None, nodata=None, cog: bool = True, blocksize: int = 512) -> dict:
    """Render the mosaic tile by tile over dask (threads) into ``out`` (a COG with
    overviews when ``cog``), atomically. Memory is bounded by ``workers`` tiles."""
    import dask.array as da
    import rasterio
    from rasterio.shutil import copy as rio_copy
    dtypes = {s.dtype for s in layout.swings}
    if dtype is None:
        dtype = "float32" if len(dtypes) != 1 or next(iter(dtypes)).startswith("float") \
            else next(iter(dtypes))
    dtype = np.dtype(dtype)
    if nodata is None:
        nds = {s.nodata for s in layout.swings}
        nd = nds.pop() if len(nds) == 1 else None
        nodata = nd if nd is not None else (float("nan") if dtype.kind == "f" else 0)
    H, W = layout.shape
    offsets = np.asarray(offsets, float)
    radiometric = np.asarray(radiometric, float)
    handles = _Handles()

    def block(x, block_info=None):
        (a, b), (c, d) = block_info[None]["array-location"]
        v, _ = render_tile(layout, a, c, b, d, offsets, radiometric, handles, feather, mode)
        return v.astype(np.float32)

    arr = da.zeros((H, W), chunks=(tile, tile), dtype=np.float32).map_blocks(
        block, dtype=np.float32)
    profile = dict(driver="GTiff", width=W, height=H, count=1, dtype=dtype.name,
                   crs=layout.crs, transform=layout.transform, nodata=nodata, tiled=True,
                   blockxsize=blocksize, blockysize=blocksize, compress="deflate",
                   BIGTIFF="IF_SAFER")
    t0 = time.perf_counter()
    out = os.fspath(out)
    try:
        with atomic_path(out, suffix=".tif") as final:
            tmp = final + ".stage.tif" if cog else final
            try:
                with rasterio.open(tmp, "w", **profile) as ds:
                    da.store(arr, _Writer(ds, nodata, dtype), lock=threading.Lock(),
                             scheduler="threads", num_workers=workers)
                    ds.update_tags(product="mosaic", blend=mode, software="swathflow")
                t_render = time.perf_counter() - t0
                if cog:
                    with rasterio.Env(GDAL_NUM_THREADS=str(workers or os.cpu_count() or 1)):
                        rio_copy(tmp, final, driver="COG", COMPRESS="DEFLATE",
                                 BLOCKSIZE=blocksize, OVERVIEW_RESAMPLING="AVERAGE",
                                 PREDICTOR="YES", BIGTIFF="IF_SAFER")
            finally:
                if cog and os.path.exists(tmp):
                    os.remove(tmp)
    finally:
        handles.close()
    return {"seconds_render": t_render, "seconds_total": time.perf_counter() - t0,
            "shape": [H, W], "dtype": dtype.name}


def quicklook(src_path, png_path, max_side: int = 1024) -> None:
    """An 8-bit PNG preview (2-98 % stretch) read from the COG's overviews."""
    import rasterio
    with rasterio.open(src_path) as ds:
        f = max(1.0, max(ds.width, ds.height) / max_side)
        shape = (max(1, int(ds.height / f)), max(1, int(ds.width / f)))
        a = ds.read(1, out_shape=shape, masked=True).astype(float)
    data = a.filled(np.nan)
    ok = np.isfinite(data)
    img = np.zeros(shape, np.uint8)
    alpha = np.where(ok, 255, 0).astype(np.uint8)
    if ok.any():
        lo, hi = np.percentile(data[ok], [2, 98])
        img = np.clip((np.nan_to_num(data) - lo) / max(hi - lo, 1e-12) * 254 + 1, 1, 255)
        img = np.where(ok, img, 0).astype(np.uint8)
    import warnings
    with atomic_path(png_path, suffix=".png") as tmp, warnings.catch_warnings():
        warnings.simplefilter("ignore", rasterio.errors.NotGeoreferencedWarning)
        with rasterio.open(tmp, "w", driver="PNG", width=shape[1], height=shape[0], count=2,
                           dtype="uint8") as dst:
            dst.write(img, 1)
            dst.write(alpha, 2)
    aux = png_path + ".aux.xml"
    if os.path.exists(aux):
        os.remove(aux)


def mosaic(paths, out, per_image: bool = False, anchors=(), feather: int = 64,
           mode: str = "feather", balance: bool = True, match: bool = True,
           max_shift: int = 12, block: int = 128, min_texture: float = 1.0, tile: int = 1024,
           workers: int | None = None, png: bool = True, report: bool = True,
           cog: bool = True, strips: dict | None = None, log=None,
           cache_mb: int = 64) -> dict:
    """Match, adjust and blend rectified swings ``paths`` into the mosaic ``out``.

    GDAL's block cache is capped at ``cache_mb`` so memory stays bounded (GDAL's default is
    5 % of RAM). Returns the report (also written to ``<out>.json`` when ``report``): per-node offsets
    and radiometric offsets with their sigmas, every overlap with its measurement, status and
    residual, and the timing.
    """
    import rasterio
    with rasterio.Env(GDAL_CACHEMAX=int(cache_mb)):
        return _mosaic(paths, out, per_image, anchors, feather, mode, balance, match,
                       max_shift, block, min_texture, tile, workers, png, report, cog, strips,
                       log)


def _mosaic(paths, out, per_image, anchors, feather, mode, balance, match, max_shift, block,
            min_texture, tile, workers, png, report, cog, strips, log) -> dict:
    t0 = time.perf_counter()
    layout = scan_inputs(paths, strips)
    keys = _node_keys(layout, per_image)
    n_sw = len(layout.swings)
    rep: dict = {"format": "swathflow-mosaic/1", "inputs": n_sw, "grid": {
        "shape": list(layout.shape), "res": layout.res, "crs": layout.crs.to_string()
        if layout.crs else None, "transform": list(layout.transform)[:6]},
        "per_image": per_image, "blend": mode, "feather_px": feather}
    if match:
        net, pairs, matches, keys = plan(layout, per_image, anchors, max_shift, block,
                                         min_texture, workers, log)
        t_match = time.perf_counter() - t0
        node_of = {k: q for q, k in enumerate(net.nodes)}
        off = np.array([net.offsets[node_of[k]] for k in keys])
        rad = np.array([net.radiometric[node_of[k]] for k in keys]) if balance else np.zeros(n_sw)
        overlaps = []
        for q, ((i, j, win, n), m) in enumerate(zip(pairs, matches)):
            d = m.to_dict()
            d.update(ref=layout.swings[i].image_id, mov=layout.swings[j].image_id,
                     window=list(win), pixels=n, used=bool(net.used[q]),
                     residual=[None if not np.isfinite(v) else round(float(v), 4)
                               for v in net.residuals[q]])
            overlaps.append(d)
        skipped = [o for o in overlaps if not o["ok"]]
        rep.update({
            "nodes": [{"node": str(k), "offset": [round(float(v), 4) for v in net.offsets[q]],
                       "sigma": [None if not np.isfinite(v) else round(float(v), 4)
                                 for v in net.sigmas[q]],
                       "radiometric": round(float(net.radiometric[q]), 4)}
                      for q, k in enumerate(net.nodes)],
            "anchors": [str(a) for a in net.anchored],
            "free_groups": [[str(v) for v in g] for g in net.free_groups],
            "sigma0": None if not np.isfinite(net.sigma0) else round(net.sigma0, 4),
            "overlaps": overlaps,
            "skipped": [{"ref": o["ref"], "mov": o["mov"], "status": o["status"]}
                        for o in skipped],
            "rejected": [{"ref": o["ref"], "mov": o["mov"], "residual": o["offset"]}
                         for o in overlaps if o["ok"] and not o["used"]],
            "seconds_match": round(t_match, 3)})
        if log:
            log(f"matched {len(pairs)} overlaps ({len(skipped)} skipped) in {t_match:.1f} s")
            for s in skipped:
                log(f"  skipped {s['ref']} / {s['mov']}: {s['status']}")
    else:
        off = np.zeros((n_sw, 2))
        rad = np.zeros(n_sw)
    timing = write_mosaic(layout, out, off, rad, feather, mode, tile, workers, cog=cog)
    rep.update(timing)
    if png:
        t1 = time.perf_counter()
        quicklook(out, os.path.splitext(os.fspath(out))[0] + ".png")
        rep["seconds_quicklook"] = round(time.perf_counter() - t1, 3)
    rep["seconds"] = round(time.perf_counter() - t0, 3)
    rep["mpx_per_s"] = round(layout.shape[0] * layout.shape[1] / 1e6 / rep["seconds"], 3)
    if report:
        write_text(os.path.splitext(os.fspath(out))[0] + ".json", json.dumps(rep, indent=1))
    return rep


# --- seam metric --------------------------------------------------------------------------
def seam_lines(footprints, band: int = 1):
    """Every line where a mosaic of ``footprints`` (boolean masks on one grid) may show a
    seam: the edge of a footprint lying inside another one (where "first valid wins" and
    feathering change source) and the boundary of the nearest-centre partition (where a
    hard cut changes source). In-memory: for tests and benchmarks."""
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


# --- CLI ----------------------------------------------------------------------------------------
def find_inputs(source):
    """Rectified swings under ``source``: a folder of GeoTIFFs, or a mission/run folder
    with a ``rectified/`` subfolder."""
    source = os.fspath(source)
    if os.path.isfile(source):
        return [source]
    if not os.path.isdir(source):
        raise SwathflowError(f"{source}: no such folder; give a folder of rectified swings "
                             f"(GeoTIFF) or a mission folder with a rectified/ subfolder")
    for sub in ("rectified", os.path.join("out", "rectified"), ""):
        d = os.path.join(source, sub)
        if os.path.isdir(d):
            tifs = sorted(os.path.join(d, f) for f in os.listdir(d)
                          if f.lower().endswith((".tif", ".tiff")) and not f.startswith("."))
            if tifs:
                return tifs
    raise SwathflowError(f"{source}: no rectified swings found (looked for *.tif in "
                         f"{source}/rectified and {source}); run 'swathflow rectify' first")


def mission_strips(path) -> dict:
    """Image id -> strip number from a mission folder's ``mission.toml`` ([[images]])."""
    import tomllib
    path = os.fspath(path)
    toml = os.path.join(path, "mission.toml") if os.path.isdir(path) else path
    try:
        with open(toml, "rb") as f:
            cfg = tomllib.load(f)
    except (OSError, tomllib.TOMLDecodeError) as exc:
        raise FormatError(f"{toml}: cannot read mission file: {exc}") from None
    out = {}
    for k, e in enumerate(cfg.get("images", [])):
        if "id" in e and "strip" in e:
            try:
                out[str(e["id"])] = int(e["strip"])
            except (TypeError, ValueError):
                raise FormatError(f"{toml}: images[{k}].strip must be an integer, got "
                                  f"{e['strip']!r}") from None
    return out
