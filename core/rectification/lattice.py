"""The adaptive lattice of exact raw coordinates under an output tile.

For each output tile the raw image coordinates (line, element) of the ground under the
output pixel centres (map x, y with terrain heights) come from the sensor model's
``ground_to_image``, evaluated on a coarse lattice of the tile. Every lattice cell (a
rectangle of power-of-two sides) is checked at its centre and edge midpoints against the
exact model; where bilinear interpolation of the corners misses by ``TEST_SHARE * tol``
raw pixels or more there (the margin keeps the error between test points below ``tol``:
with 0.5, as before, one demo swing missed by 0.052 px; with 0.4 the worst of the eight
is 0.045 px) the cell is
halved across the failing direction (rows, columns, or both) and checked again, down to
single pixels (exact). All-NaN cells touching split cells are split too, so the
footprint's edge is traced at pixel resolution. Cells clearly off the raw image are not
refined when the caller gives the raw image's shape.

Why rectangles: with a real POS (noise at every epoch, interpolated linearly) the exact
mapping has a kink at every epoch, along curves of constant raw line (measured on the
demo mission: second differences up to 0.1 px every ~5 output pixels, so square cells
of 2 px already miss by 0.09-0.13 px and the lattice evaluated nearly every pixel).
Along those curves it stays smooth, and a rectangle one or two pixels across the kinks
and 8-32 long along them keeps the bound with a fraction of the calls.

The result is a list of *leaves*: rectangles of output pixels with their four corner
values, in the order they must be painted (coarse first; finer leaves overwrite the
shared edges). :mod:`.paint` paints them; no per-pixel array is built here.

Or, per tile, the exact model at every pixel, when that is cheaper. Where the mapping
kinks more densely than the output pixels (the survey preset: a 50 Hz POS, 2 m pixels,
a kink every 0.6 px) the lattice ends in unit cells nearly everywhere: 0.66 exact
evaluations per pixel, each costing about 2.5x a plain evaluation in bookkeeping (the
tests, the splits, one model call per level). The tile first tests a sample of 2 x 2
cells spread over it (:func:`_dense_cheaper`, about 600 evaluations): when at least
:data:`DENSE_SHARE` of them miss the bound, the adaptive refinement would go down to
single pixels over that share of the tile anyway, and the tile is evaluated exactly at
every pixel instead (:attr:`Leaves.pixels`; with the raw image's shape, 16-pixel cells
clearly off the image are skipped first, as the refinement skips them). Measured on the
survey's swings (2 x 2 cells missing: 97 %) and the demo's (19 %: the lattice, 0.2
evaluations per pixel, stays cheaper there).
"""
from __future__ import annotations

import math
import warnings
from dataclasses import dataclass

import numpy as np
from numba import njit

from swathflow.geometry.grid import tile_frame
from swathflow.rectification.paint import touching

#: default bound on the interpolated raw coordinates' error (raw pixels, line and element)
TOLERANCE_PX = 0.05
#: share of the bound that the interpolation may miss by at a cell's test points
TEST_SHARE = 0.4
#: least distance (raw pixels) beyond the raw image's edge of a cell left unrefined
OFF_MARGIN_PX = 4.0
#: share of a tile's sampled 2 x 2 cells missing the bound from which the tile is
#: evaluated exactly at every pixel instead of refined (:func:`_dense_cheaper`)
DENSE_SHARE = 0.5
#: cells (pixels a side) of the off-image check before a tile's exact evaluation
DENSE_CELL = 16


def exact_raw(model, grid, terrain, rows, cols, frame=None) -> np.ndarray:
    """Exact raw coordinates ``(n, 2)`` of grid pixel centres (rows, cols may lie off the
    grid; the grid's transform extends); with ``frame`` (a
    :class:`~swathflow.geometry.grid.TileFrame` of the grid) the ground points come from
    it (integer rows and columns inside its window)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        if frame is not None:
            g = frame.ecef(rows, cols)
        else:
            g = grid.to_ecef(*grid.xy(rows, cols), terrain)
        return model.ground_to_image(g, clip=False)


@dataclass(frozen=True)
class Leaves:
    """Leaves of a tile's lattice: ``cells`` ``(n, 4)`` int64 (row, col, rows, cols) and
    ``corners`` ``(n, 4, 2)`` float64 raw (line, element) at (r, c), (r, c + sc),
    (r + sr, c), (r + sr, c + sc); ``shape`` the tile's (rows, cols). A tile evaluated
    exactly at every pixel has no cells but ``pixels`` ``(rows, cols, 2)`` float64, the
    exact raw coordinates (NaN where the ray misses or the pixel is clearly off the
    image)."""

    cells: np.ndarray
    corners: np.ndarray
    shape: tuple[int, int]
    exact_evaluations: int
    pixels: np.ndarray | None = None

    def bounds(self, n_lines: int, n_elements: int):
        """``(lmin, lmax, emin, emax)`` of the corner coordinates of the leaves that can
        touch the raw image (bilinear interpolation stays inside its corners' box), or
        None when no leaf touches it; of the pixels on the image for an exact tile."""
        if self.pixels is not None:
            li, ei = self.pixels[..., 0], self.pixels[..., 1]
            with np.errstate(invalid="ignore"):
                on = ((li >= -0.5) & (li <= n_lines - 0.5)
                      & (ei >= -0.5) & (ei <= n_elements - 0.5))
            if not on.any():
                return None
            return (float(li[on].min()), float(li[on].max()),
                    float(ei[on].min()), float(ei[on].max()))
        q = self.corners
        with np.errstate(invalid="ignore"):
            lo = np.nanmin(q, axis=1) if q.size else np.zeros((0, 2))
            hi = np.nanmax(q, axis=1) if q.size else np.zeros((0, 2))
        touch = ((hi[:, 0] >= -0.5) & (lo[:, 0] <= n_lines - 0.5)
                 & (hi[:, 1] >= -0.5) & (lo[:, 1] <= n_elements - 0.5))
        if not touch.any():
            return None
        return (float(lo[touch, 0].min()), float(hi[touch, 0].max()),
                float(lo[touch, 1].min()), float(hi[touch, 1].max()))


class _Exact:
    """Memoised exact evaluations on the lattice points of one tile."""

    def __init__(self, model, grid, terrain, H, W):
        self.model, self.grid, self.terrain, self.W = model, grid, terrain, W
        self.values = np.empty((H, W, 2))      # read only where known (its pages stay
        self.known = np.zeros((H, W), bool)    # untouched where nothing is evaluated)
        self.count = 0
        self.frame = tile_frame(grid, terrain, H, W)      # ground points without pyproj

    def drop_frame(self):
        """Forget the values and evaluate from now on with the grid's own
        :meth:`~swathflow.geometry.grid.Grid.to_ecef` (pyproj) instead of the frame (which
        agrees with it to a few nm, not to the last bit)."""
        if self.frame is not None:
            self.frame = None
            self.known[:] = False

    def _evaluate(self, rr, cc):
        if rr.size:
            self.values[rr, cc] = exact_raw(self.model, self.grid, self.terrain, rr, cc,
                                            self.frame)
            self.count += rr.size

    def __call__(self, r, c):
        """The values at points ``r, c``, evaluating those not yet known (one model
        call)."""
        r = np.ascontiguousarray(r, np.int64).ravel()
        c = np.ascontiguousarray(c, np.int64).ravel()
        self._evaluate(*_unknown(r, c, self.known))
        return self.values[r, c]

    def cells(self, cells, tests: bool = True):
        """Evaluate the corners (and, with ``tests``, the test points) of ``cells`` not
        yet known, in one model call."""
        self._evaluate(*_cell_unknown(cells, self.known, tests))


@njit(cache=True, nogil=True)
def _unknown(r, c, known):
    """The points of ``r, c`` not yet ``known``, each once; marks them known (the caller
    evaluates them at once)."""
    rr = np.empty(r.shape[0], np.int64)
    cc = np.empty(r.shape[0], np.int64)
    k = 0
    for i in range(r.shape[0]):
        if not known[r[i], c[i]]:
            known[r[i], c[i]] = True
            rr[k], cc[k] = r[i], c[i]
            k += 1
    return rr[:k], cc[:k]


@njit(cache=True, nogil=True)
def _cell_unknown(cells, known, tests):
    """:func:`_unknown` of the corners of ``cells`` ``(n, 4)`` and, with ``tests``, of
    their test points (edge midpoints across a side of 2 or more, centre)."""
    n = cells.shape[0]
    r = np.empty(9 * n, np.int64)
    c = np.empty(9 * n, np.int64)
    k = 0
    for i in range(n):
        r0, c0, sr, sc = cells[i, 0], cells[i, 1], cells[i, 2], cells[i, 3]
        hr, hc = sr // 2, sc // 2
        r[k:k + 4] = (r0, r0, r0 + sr, r0 + sr)
        c[k:k + 4] = (c0, c0 + sc, c0, c0 + sc)
        k += 4
        if tests and sc >= 2:
            r[k], c[k], r[k + 1], c[k + 1] = r0, c0 + hc, r0 + sr, c0 + hc
            k += 2
        if tests and sr >= 2:
            r[k], c[k], r[k + 1], c[k + 1] = r0 + hr, c0, r0 + hr, c0 + sc
            k += 2
        if tests and sr >= 2 and sc >= 2:
            r[k], c[k] = r0 + hr, c0 + hc
            k += 1
    return _unknown(r[:k], c[:k], known)


@njit(cache=True, nogil=True, inline="always")
def _miss(v, r, c, a0, a1, pts, i, p):
    """The interpolation's miss at point (r, c) of ``v`` (the larger of line and element;
    inf where NaN) against the interpolated ``(a0, a1)``; ``pts[i, p]`` set to the exact
    value."""
    e0, e1 = v[r, c, 0], v[r, c, 1]
    pts[i, p, 0], pts[i, p, 1] = e0, e1
    d0, d1 = abs(e0 - a0), abs(e1 - a1)
    if math.isnan(d0) or math.isnan(d1):
        return math.inf
    return max(d0, d1)


@njit(cache=True, nogil=True)
def _cell_tests(cells, v):
    """Test the cells ``(n, 4)`` (r, c, sr, sc) at their edge midpoints and centre (all
    known in ``v``): the error of interpolation across columns (top and bottom
    midpoints), across rows (left and right midpoints) and both (centre), NaN as inf, 0
    where a size is 1; the points' values ``(n, 9, 2)``: the corners (r, c), (r, c + sc),
    (r + sr, c), (r + sr, c + sc), then the test points (NaN where a test does not
    exist)."""
    n = cells.shape[0]
    err_c, err_r, err_m = np.zeros(n), np.zeros(n), np.zeros(n)
    pts = np.full((n, 9, 2), np.nan)
    for i in range(n):
        r, c, sr, sc = cells[i, 0], cells[i, 1], cells[i, 2], cells[i, 3]
        hr, hc = sr // 2, sc // 2
        for q in range(2):
            pts[i, 0, q], pts[i, 1, q] = v[r, c, q], v[r, c + sc, q]
            pts[i, 2, q], pts[i, 3, q] = v[r + sr, c, q], v[r + sr, c + sc, q]
        q00, q01, q10, q11 = pts[i, 0], pts[i, 1], pts[i, 2], pts[i, 3]
        if sc >= 2:
            e1 = _miss(v, r, c + hc, (q00[0] + q01[0]) / 2, (q00[1] + q01[1]) / 2,
                       pts, i, 4)
            e2 = _miss(v, r + sr, c + hc, (q10[0] + q11[0]) / 2, (q10[1] + q11[1]) / 2,
                       pts, i, 5)
            err_c[i] = max(e1, e2)
        if sr >= 2:
            e1 = _miss(v, r + hr, c, (q00[0] + q10[0]) / 2, (q00[1] + q10[1]) / 2,
                       pts, i, 6)
            e2 = _miss(v, r + hr, c + sc, (q01[0] + q11[0]) / 2, (q01[1] + q11[1]) / 2,
                       pts, i, 7)
            err_r[i] = max(e1, e2)
        if sr >= 2 and sc >= 2:
            err_m[i] = _miss(v, r + hr, c + hc, (q00[0] + q01[0] + q10[0] + q11[0]) / 4,
                             (q00[1] + q01[1] + q10[1] + q11[1]) / 4, pts, i, 8)
    return err_c, err_r, err_m, pts


@njit(cache=True, nogil=True)
def _off_image(points, err, nl, ne):
    """Cells whose test points and corners ``points`` ``(k, 9, 2)`` all lie beyond one
    edge of the raw image (``nl`` lines x ``ne`` elements) by more than ``OFF_MARGIN_PX``
    plus twice the cell's interpolation error there: every pixel of such a cell is off
    the image (NaN), however its coordinates are interpolated. A NaN point (or a test
    that does not exist) never qualifies on its coordinate."""
    k = points.shape[0]
    out = np.zeros(k, np.bool_)
    for i in range(k):
        m = OFF_MARGIN_PX + 2 * err[i] if math.isfinite(err[i]) else math.inf
        off = False
        for q in range(2):
            lo, hi = math.inf, -math.inf
            nan = False
            for p in range(points.shape[1]):
                x = points[i, p, q]
                if math.isnan(x):
                    nan = True
                    break
                lo, hi = min(lo, x), max(hi, x)
            edge = (nl if q == 0 else ne) - 0.5
            if not nan and (lo > edge + m or hi < -0.5 - m):
                off = True
        out[i] = off
    return out


@njit(cache=True, nogil=True)
def _children(cells, split_r, split_c):
    """The halves (or quarters) of cells split across rows and / or columns (the
    cells with neither flag are kept whole): first every cell's top-left part, then the
    lower, right and lower-right parts, each in the cells' order."""
    n = cells.shape[0]
    m = n
    for i in range(n):
        m += int(split_r[i]) + int(split_c[i]) + int(split_r[i] and split_c[i])
    out = np.empty((m, 4), np.int64)
    k = 0
    for part in range(4):
        for i in range(n):
            if part == 1 and not split_r[i] or part == 2 and not split_c[i] or (
                    part == 3 and not (split_r[i] and split_c[i])):
                continue
            nsr = cells[i, 2] // 2 if split_r[i] else cells[i, 2]
            nsc = cells[i, 3] // 2 if split_c[i] else cells[i, 3]
            out[k, 0] = cells[i, 0] + (nsr if part == 1 or part == 3 else 0)
            out[k, 1] = cells[i, 1] + (nsc if part >= 2 else 0)
            out[k, 2], out[k, 3] = nsr, nsc
            k += 1
    return out


@njit(cache=True, nogil=True)
def _level(cells, v, half, tol, nl, ne, smooth, H, W):
    """One level of the refinement (every test point of ``cells`` known in ``v``):
    ``(leaves, corners, kids, sure)``: the unit cells, then the cells that pass (or lie
    clearly off the raw image, with ``nl`` > 0), as leaves with their corners; the
    children of the cells to refine; with ``smooth`` the children taken as leaves without
    tests (:func:`leaves`; their corners for the caller to look up)."""
    n = cells.shape[0]
    unit = (cells[:, 2] == 1) & (cells[:, 3] == 1)
    rest = cells[~unit]
    err_c, err_r, err_m, pts = _cell_tests(rest, v)
    err = np.maximum(np.maximum(err_c, err_r), err_m)
    good = err < half
    if nl > 0:
        good |= _off_image(pts, err, nl, ne)
    k = rest.shape[0]
    all_nan = np.ones(k, np.bool_)
    for i in range(k):
        for p in range(9):
            if not (math.isnan(pts[i, p, 0]) and math.isnan(pts[i, p, 1])):
                all_nan[i] = False
                break
    n_unit = n - k
    n_leaf = n_unit + good.sum()
    leaf = np.empty((n_leaf, 4), np.int64)
    corners = np.empty((n_leaf, 4, 2))
    j = 0
    for i in range(n):
        if unit[i]:
            r, c = cells[i, 0], cells[i, 1]
            leaf[j] = cells[i]
            corners[j, 0], corners[j, 1] = v[r, c], v[r, c + 1]
            corners[j, 2], corners[j, 3] = v[r + 1, c], v[r + 1, c + 1]
            j += 1
    for i in range(k):
        if good[i]:
            leaf[j] = rest[i]
            corners[j] = pts[i, :4]
            j += 1
    bad = ~good & ~all_nan
    near = np.zeros(k, np.bool_)
    if bad.any():           # all-NaN cells touching a refined one: the footprint's edge
        near = all_nan & touching(rest, rest[bad], H, W)
    split = bad | near
    can_r, can_c = rest[:, 2] >= 2, rest[:, 3] >= 2
    pick_r = (err_r >= half) & (err_c < half / 2)
    pick_c = (err_c >= half) & (err_r < half / 2)
    both = near | ~(pick_r | pick_c)
    split_r = split & can_r & (pick_r | both | ~can_c)
    split_c = split & can_c & (pick_c | both | ~can_r)
    sure = np.zeros(split.shape[0], np.bool_)
    if smooth:
        # on a smooth mapping the interpolation error falls with the square of the cell
        # size: children of a cell that missed by less than ``tol`` miss by about a
        # quarter of it, half the acceptance threshold. They are leaves without tests
        # (their corners are the parent's tested points).
        sure = split & (err < tol)
    go = split & ~sure
    kids = _children(rest[go], split_r[go], split_c[go])
    sure_kids = _children(rest[sure], split_r[sure], split_c[sure])
    return leaf, corners, kids, sure_kids


def _dense_cheaper(exact, h: int, w: int, half: float) -> bool:
    """Whether at least :data:`DENSE_SHARE` of a sample of 2 x 2 cells (up to 8 x 8 of
    them, spread over the tile) miss ``half`` at their test points: the adaptive
    refinement would then end in single pixels over most of the tile, and evaluating
    every pixel is cheaper. Cells whose tests meet NaN (off the footprint) are left out
    of the share; none left: False."""
    if h < 3 or w < 3:
        return False
    r = np.unique(np.linspace(0, h - 3, min(8, h - 2)).astype(np.int64))
    c = np.unique(np.linspace(0, w - 3, min(8, w - 2)).astype(np.int64))
    rr, cc = np.meshgrid(r, c, indexing="ij")
    n = rr.size
    cells = np.stack([rr.ravel(), cc.ravel(), np.full(n, 2), np.full(n, 2)], axis=-1)
    exact.cells(cells)
    err_c, err_r, err_m, _ = _cell_tests(cells, exact.values)
    err = np.maximum(np.maximum(err_c, err_r), err_m)
    seen = np.isfinite(err)
    return bool(seen.any() and (err[seen] >= half).mean() >= DENSE_SHARE)


def _every_pixel(exact, h: int, w: int, step: int, raw_shape) -> np.ndarray:
    """Exact raw coordinates ``(h, w, 2)`` of every pixel of the tile; with ``raw_shape``
    cells of :data:`DENSE_CELL` pixels clearly off the raw image (:func:`_off_image`, on
    their corners and test points) are skipped (NaN), and so are cells whose corners and
    test points are all NaN unless they touch a kept cell (as the refinement splits
    all-NaN cells next to split ones: the footprint's edge)."""
    H, W = exact.known.shape
    keep = np.ones((H, W), bool)
    s = min(DENSE_CELL, step)                     # divides the lattice's step
    if raw_shape is not None and h > s and w > s:
        nr, nc = (H - 1) // s, (W - 1) // s       # step is a multiple of s: cells tile H x W
        ci, cj = np.meshgrid(np.arange(nr) * s, np.arange(nc) * s, indexing="ij")
        k = ci.size
        cells = np.stack([ci.ravel(), cj.ravel(), np.full(k, s), np.full(k, s)], axis=-1)
        exact.cells(cells)
        err_c, err_r, err_m, pts = _cell_tests(cells, exact.values)
        off = _off_image(pts, np.maximum(np.maximum(err_c, err_r), err_m), *raw_shape)
        blank = np.isnan(pts).all(axis=(1, 2)).reshape(nr, nc)
        kept = ~off.reshape(nr, nc) & ~blank
        # all-NaN cells next to a kept one are kept: the footprint's edge runs through them
        grown = np.pad(kept, 1)
        grown = np.logical_or.reduce([grown[1 + di:nr + 1 + di, 1 + dj:nc + 1 + dj]
                                      for di in (-1, 0, 1) for dj in (-1, 0, 1)])
        kept |= blank & grown
        # a pixel is kept when any cell whose closed rectangle holds it is kept
        i = np.arange(H)
        a, b = np.minimum(i // s, nr - 1), np.maximum((i - 1) // s, 0)
        j = np.arange(W)
        ca, cb = np.minimum(j // s, nc - 1), np.maximum((j - 1) // s, 0)
        keep = (kept[a][:, ca] | kept[b][:, ca] | kept[a][:, cb] | kept[b][:, cb])
    keep = keep[:h, :w]
    rr, cc = np.nonzero(keep)
    exact(rr, cc)
    out = exact.values[:h, :w].copy()
    out[~keep] = np.nan
    return out


def leaves(model, grid, terrain, tol: float = TOLERANCE_PX, step: int = 32,
           smooth: bool = False, raw_shape: tuple[int, int] | None = None,
           dense: bool | None = None) -> Leaves:
    """The adaptive lattice of ``grid`` (a tile's own grid) as :class:`Leaves`.

    Cells are rectangles of power-of-two sides, split across rows, across columns, or
    both, as their tests say: a mapping kinked along curves near one axis (the raw lines
    of a POS with noise, interpolated linearly between epochs) refines across the kinks
    only. ``smooth`` (only for a mapping known to be analytic: off by default) lets
    cells whose parent missed by less than ``tol`` skip their own tests. A real POS is not
    analytic even over a constant height: on the demo mission at its mean height that
    shortcut missed by up to 0.17 px (0.4 % of the pixels beyond 0.05 px).
    With ``raw_shape`` (lines, elements) cells clearly off the raw image are not refined
    (:func:`_off_image`): their pixels are nodata whatever the interpolation, so the
    bound holds where the image is seen (the GLT and the rectified pixels), not on the
    coordinates of pixels off the image.

    ``dense`` True evaluates the exact model at every pixel of the tile instead
    (:attr:`Leaves.pixels`), False always refines, None (default) chooses per tile by
    :func:`_dense_cheaper`."""
    h, w = grid.shape
    step = 1 << max(int(math.log2(max(step, 1))), 0)
    nr = max(math.ceil((h - 1) / step), 1)       # cells along rows
    nc = max(math.ceil((w - 1) / step), 1)
    H, W = nr * step + 1, nc * step + 1
    exact = _Exact(model, grid, terrain, H, W)
    rr, cc = np.meshgrid(np.arange(nr + 1) * step, np.arange(nc + 1) * step, indexing="ij")
    exact(rr.ravel(), cc.ravel())
    half = tol * TEST_SHARE                      # a share of the bound at the test points
    if dense is None:
        dense = _dense_cheaper(exact, h, w, half)
    if dense:           # the exact model itself at every pixel: ground points by pyproj
        exact.drop_frame()
        px = _every_pixel(exact, h, w, step, raw_shape)
        return Leaves(np.zeros((0, 4), np.int64), np.zeros((0, 4, 2)), (h, w), exact.count,
                      px)
    ci, cj = np.meshgrid(np.arange(nr), np.arange(nc), indexing="ij")
    n = ci.size
    cells = np.stack([ci.ravel() * step, cj.ravel() * step, np.full(n, step),
                      np.full(n, step)], axis=-1).astype(np.int64)
    out_cells, out_corners = [], []
    nl, ne = raw_shape if raw_shape is not None else (0, 0)
    while cells.size:                  # one model call and one compiled pass a level
        exact.cells(cells)
        leaf, corners, cells, sure = _level(cells, exact.values, half, tol, nl, ne, smooth,
                                            H, W)
        out_cells.append(leaf)
        out_corners.append(corners)
        if len(sure):
            exact.cells(sure, tests=False)
            out_cells.append(sure)
            out_corners.append(_cell_tests(sure, exact.values)[3][:, :4])
    if out_cells:
        cells_a = np.ascontiguousarray(np.concatenate(out_cells).astype(np.int64))
        corners_a = np.ascontiguousarray(np.concatenate(out_corners).astype(np.float64))
    else:
        cells_a = np.zeros((0, 4), np.int64)
        corners_a = np.zeros((0, 4, 2))
    return Leaves(cells_a, corners_a, (h, w), exact.count)


def inverse_map(model, grid, terrain, tol: float = TOLERANCE_PX, step: int = 32,
                stats: dict | None = None) -> np.ndarray:
    """Raw (line, element) ``(rows, cols, 2)`` float64 under every pixel centre of
    ``grid`` (NaN where the image does not see the ground; coordinates beyond the
    detector's ends are kept, the caller masks them). ``stats`` (a dict) receives the
    count of exact evaluations."""
    from swathflow.geometry.terrain import open_terrain
    from swathflow.rectification.paint import paint_f64
    lv = leaves(model, grid, open_terrain(terrain), tol, step)
    if stats is not None:
        stats["exact_evaluations"] = stats.get("exact_evaluations", 0) + lv.exact_evaluations
        stats["pixels"] = stats.get("pixels", 0) + grid.shape[0] * grid.shape[1]
    if lv.pixels is not None:
        return lv.pixels
    return paint_f64(lv.cells, lv.corners, *grid.shape)
