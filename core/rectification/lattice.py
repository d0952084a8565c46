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


def exact_raw(model, grid, terrain, rows, cols) -> np.ndarray:
    """Exact raw coordinates ``(n, 2)`` of grid pixel centres (rows, cols may lie off the
    grid; the grid's transform extends)."""
    x, y = grid.xy(rows, cols)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        g = grid.to_ecef(x, y, terrain)
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
        self.values = np.full((H, W, 2), np.nan)
        self.known = np.zeros((H, W), bool)
        self.count = 0

    def __call__(self, r, c):
        r = np.asarray(r, np.intp)
        c = np.asarray(c, np.intp)
        need = ~self.known[r, c]
        if need.any():
            mark = np.zeros(self.known.size, bool)      # sorted, unique: as np.unique,
            mark[r[need] * self.W + c[need]] = True      # without its hash table
            key = np.flatnonzero(mark)
            rr, cc = key // self.W, key % self.W
            self.values[rr, cc] = exact_raw(self.model, self.grid, self.terrain, rr, cc)
            self.known[rr, cc] = True
            self.count += key.size
        return self.values[r, c]


def _off_image(points, err, raw_shape):
    """Cells whose test points and corners ``points`` ``(k, n, 2)`` all lie beyond one edge
    of the raw image (``raw_shape`` lines x elements) by more than ``OFF_MARGIN_PX`` plus
    twice the cell's interpolation error there: every pixel of such a cell is off the
    image (NaN), however its coordinates are interpolated. NaN points never qualify."""
    nl, ne = raw_shape
    m = OFF_MARGIN_PX + 2 * np.where(np.isfinite(err), err, np.inf)
    lo = points.min(axis=1)                      # NaN propagates: never off
    hi = points.max(axis=1)
    with np.errstate(invalid="ignore"):
        return ((lo[:, 0] > nl - 0.5 + m) | (hi[:, 0] < -0.5 - m)
                | (lo[:, 1] > ne - 0.5 + m) | (hi[:, 1] < -0.5 - m))


def _tests(exact, cells):
    """Test the cells ``(n, 4)`` (r, c, sr, sc) at their edge midpoints and centre: the
    error of interpolation across columns (top and bottom midpoints), across rows (left
    and right midpoints) and both (centre), NaN as inf, 0 where a size is 1; the corners
    ``(n, 4, 2)``; the points' values ``(n, 9, 2)`` (NaN where a test does not exist)."""
    v = exact.values
    r, c, sr, sc = cells.T
    hr, hc = sr // 2, sc // 2
    q00, q01, q10, q11 = v[r, c], v[r, c + sc], v[r + sr, c], v[r + sr, c + sc]
    tc, tr = sc >= 2, sr >= 2
    tm = tc & tr
    groups = [(tc, r, c + hc, (q00 + q01) / 2), (tc, r + sr, c + hc, (q10 + q11) / 2),
              (tr, r + hr, c, (q00 + q10) / 2), (tr, r + hr, c + sc, (q01 + q11) / 2),
              (tm, r + hr, c + hc, (q00 + q01 + q10 + q11) / 4)]
    exact(np.concatenate([gr[m] for m, gr, _, _ in groups]),      # one model call
          np.concatenate([gc[m] for m, _, gc, _ in groups]))
    errs, pts = [], []
    for m, gr, gc, interp in groups:
        ex = np.where(m[:, None], v[gr, gc], np.nan)
        d = np.abs(ex - interp).max(axis=-1)
        errs.append(np.where(m, np.where(np.isnan(d), np.inf, d), 0.0))
        pts.append(ex)
    err_c = np.maximum(errs[0], errs[1])
    err_r = np.maximum(errs[2], errs[3])
    q = np.stack([q00, q01, q10, q11], axis=1)
    return err_c, err_r, errs[4], q, np.concatenate([q, np.stack(pts, axis=1)], axis=1)


def _directions(cells, split, near, err_r, err_c, half):
    """Which cells to halve across rows and across columns: across the one direction
    that misses where the other passes with a margin of two; across both otherwise
    (both miss, only the centre missed, or the cell traces the footprint's edge)."""
    can_r, can_c = cells[:, 2] >= 2, cells[:, 3] >= 2
    r_fail, c_fail = err_r >= half, err_c >= half
    pick_r = r_fail & (err_c < half / 2)
    pick_c = c_fail & (err_r < half / 2)
    both = near | ~(pick_r | pick_c)
    split_r = split & can_r & (pick_r | both | ~can_c)
    split_c = split & can_c & (pick_c | both | ~can_r)
    return split_r, split_c


def _children(cells, split_r, split_c):
    """The halves (or quarters) of cells split across rows and / or columns."""
    r, c, sr, sc = cells.T
    nsr = np.where(split_r, sr // 2, sr)
    nsc = np.where(split_c, sc // 2, sc)
    kids = [np.column_stack([r, c, nsr, nsc])]
    kids.append(np.column_stack([r + nsr, c, nsr, nsc])[split_r])
    kids.append(np.column_stack([r, c + nsc, nsr, nsc])[split_c])
    kids.append(np.column_stack([r + nsr, c + nsc, nsr, nsc])[split_r & split_c])
    return np.concatenate(kids)


def _corners(exact, cells):
    r, c, sr, sc = cells.T
    n = len(cells)
    v = exact(np.concatenate([r, r, r + sr, r + sr]),            # one model call
              np.concatenate([c, c + sc, c, c + sc]))
    return np.stack([v[:n], v[n:2 * n], v[2 * n:3 * n], v[3 * n:]], axis=1)


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
    _corners(exact, cells)
    err_c, err_r, err_m, _, _ = _tests(exact, cells)
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
        _corners(exact, cells)
        err_c, err_r, err_m, _, pts = _tests(exact, cells)
        off = _off_image(pts, np.maximum(np.maximum(err_c, err_r), err_m), raw_shape)
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
    from swathflow.rectification.paint import touching
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
    if dense:
        px = _every_pixel(exact, h, w, step, raw_shape)
        return Leaves(np.zeros((0, 4), np.int64), np.zeros((0, 4, 2)), (h, w), exact.count,
                      px)
    ci, cj = np.meshgrid(np.arange(nr), np.arange(nc), indexing="ij")
    n = ci.size
    cells = np.stack([ci.ravel() * step, cj.ravel() * step, np.full(n, step),
                      np.full(n, step)], axis=-1).astype(np.int64)
    out_cells, out_corners = [], []
    while cells.size:
        unit = (cells[:, 2] == 1) & (cells[:, 3] == 1)
        if unit.any():                           # every corner a pixel: exact
            out_cells.append(cells[unit])
            out_corners.append(_corners(exact, cells[unit]))
            cells = cells[~unit]
            if not cells.size:
                break
        err_c, err_r, err_m, q, pts = _tests(exact, cells)
        err = np.maximum(np.maximum(err_c, err_r), err_m)
        all_nan = np.isnan(pts).all(axis=(1, 2))
        good = err < half
        if raw_shape is not None:
            good |= _off_image(pts, err, raw_shape)
        if good.any():
            out_cells.append(cells[good])
            out_corners.append(q[good])
        bad = ~good & ~all_nan
        # all-NaN cells touching a refined one are refined too: the footprint's edge
        near = all_nan & touching(cells, cells[bad], H, W) if bad.any() else all_nan & False
        split = bad | near
        split_r, split_c = _directions(cells, split, near, err_r, err_c, half)
        kids = _children(cells[split], split_r[split], split_c[split])
        if smooth:
            # on a smooth mapping the interpolation error falls with the square of the
            # cell size: children of a cell that missed by less than ``tol`` miss by
            # about a quarter of it, half the acceptance threshold. They are leaves
            # without tests (their corners are the parent's tested points).
            sure_p = (err[split] < tol)
            sure = _children(cells[split][sure_p], split_r[split][sure_p],
                             split_c[split][sure_p])
            if len(sure):
                out_cells.append(sure)
                out_corners.append(_corners(exact, sure))
            kids = _children(cells[split][~sure_p], split_r[split][~sure_p],
                             split_c[split][~sure_p])
        cells = kids
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
