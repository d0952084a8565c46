"""The adaptive lattice of exact raw coordinates under an output tile.

For each output tile the raw image coordinates (line, element) of the ground under the
output pixel centres (map x, y with terrain heights) come from the sensor model's
``ground_to_image`` on a lattice of the tile. It starts from one cell over the whole tile,
halved down to ``step`` pixels a side except where a cell lies clearly off the raw image
(its pixels are nodata: a few evaluations, not a lattice). Every cell (a rectangle of
power-of-two sides) is checked at its centre and edge midpoints against the exact model;
where bilinear interpolation of the corners misses by ``TEST_SHARE * tol`` raw pixels or
more there (the margin keeps the error between test points below ``tol``: with 0.5 one
demo swing missed by 0.052 px; with 0.4 the worst of the eight is 0.045 px) the cell is
halved across the failing direction (rows, columns, or both) and checked again, down to
single pixels (exact). All-NaN cells touching split cells are split too, so the
footprint's edge is traced at pixel resolution.

Why rectangles: with a real POS (noise at every epoch, interpolated linearly) the exact
mapping has a kink at every epoch, along curves of constant raw line (on the demo mission
second differences up to 0.1 px every ~5 output pixels). Along those curves it stays
smooth, and a rectangle one or two pixels across the kinks and 8-32 long along them keeps
the bound with a fraction of the calls.

The result is a list of *leaves*: rectangles of output pixels with their four corner
values, in the order they must be painted (coarse first; finer leaves overwrite the
shared edges). :mod:`.paint` paints them; no per-pixel array is built here.

Or, per tile, the exact model at every pixel, when that is cheaper: where the mapping
kinks more densely than the output pixels (the survey preset: a 50 Hz POS, 2 m pixels, a
kink every 0.6 px) the lattice ends in unit cells nearly everywhere, each evaluation
costing about 2.5x a plain one in bookkeeping. A sample of 2 x 2 cells among the cells of
``step`` (:func:`_dense_cheaper`) decides: when at least :data:`DENSE_SHARE` of them miss
the bound the tile is evaluated at every pixel instead (:attr:`Leaves.pixels`; 16-pixel
cells clearly off the image skipped first). Measured on the survey's swings (2 x 2 cells
missing: 97 %) and the demo's (19 %: the lattice, 0.2 evaluations per pixel, stays
cheaper there).
"""
from __future__ import annotations

import math
import warnings
from dataclasses import dataclass

import numpy as np

from swathflow.geometry.grid import tile_frame
from numba import njit
from swathflow.rectification.cells import (_cell_tests, _cell_unknown, _children, _inside,
                                           _items, _off_image, _rows, _store, _unknown,
                                           corner_bounds)
from swathflow.rectification.paint import touching

#: default bound on the interpolated raw coordinates' error (raw pixels, line and element)
TOLERANCE_PX = 0.05
#: share of the bound that the interpolation may miss by at a cell's test points
TEST_SHARE = 0.4
#: share of a tile's sampled 2 x 2 cells missing the bound from which the tile is
#: evaluated exactly at every pixel instead of refined (:func:`_dense_cheaper`)
DENSE_SHARE = 0.5
#: cells (pixels a side) of the off-image check before a tile's exact evaluation
DENSE_CELL = 16
#: a first sample of 16 cells settles :func:`_dense_cheaper` when its share of misses is
#: at most this or at least 1 minus this
SETTLED = 0.25


def exact_raw(model, grid, terrain, rows, cols, frame=None) -> np.ndarray:
    """Exact raw coordinates ``(n, 2)`` of grid pixel centres (rows, cols may lie off the
    grid; the grid's transform extends); with ``frame`` (a
    :class:`~swathflow.geometry.grid.TileFrame` of the grid) the ground points come from
    it (integer rows and columns inside its window)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        return _exact_raw(model, grid, terrain, rows, cols, frame)


def _exact_raw(model, grid, terrain, rows, cols, frame):
    """:func:`exact_raw` without its warnings filter (the caller holds one)."""
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
        b = corner_bounds(self.corners, n_lines, n_elements)
        return None if math.isnan(b[0]) else tuple(float(v) for v in b)


class _Exact:
    """Memoised exact evaluations on the lattice points of one tile."""

    def __init__(self, model, grid, terrain, H, W):
        self.model, self.grid, self.terrain, self.W = model, grid, terrain, W
        self.values = np.empty((H, W, 2))      # read only where known (its pages stay
        self.known = np.zeros((H, W), bool)    # untouched where nothing is evaluated)
        self.count = 0
        self.frame = tile_frame(grid, terrain, H, W)      # ground points without pyproj

    def _evaluate(self, rr, cc):
        if rr.size:
            _store(self.values, rr, cc, _exact_raw(self.model, self.grid, self.terrain, rr,
                                                   cc, self.frame))
            self.count += rr.size

    def __call__(self, r, c):
        """Evaluate the points ``r, c`` not yet known (one model call); their values are
        in :attr:`values`."""
        r = np.ascontiguousarray(r, np.int64).ravel()
        c = np.ascontiguousarray(c, np.int64).ravel()
        self._evaluate(*_unknown(r, c, self.known))

    def cells(self, cells, tests: bool = True):
        """Evaluate the corners (and, with ``tests``, the test points) of ``cells`` not
        yet known, in one model call."""
        self._evaluate(*_cell_unknown(cells, self.known, tests))


@njit(cache=True, nogil=True)
def _level(cells, v, half, tol, nl, ne, smooth, H, W, leaf_max, h, w):
    """One level of the refinement (every test point of ``cells`` known in ``v``):
    ``(leaves, corners, kids, sure)``: the unit cells, then the cells that pass (or lie
    clearly off the raw image, with ``nl`` > 0), as leaves with their corners; the
    children of the cells to refine; with ``smooth`` the children taken as leaves without
    tests (:func:`leaves`; their corners for the caller to look up). A cell longer than
    ``leaf_max`` on a side is a leaf only when it lies off the raw image; otherwise it is
    halved across that side (whatever its tests say), children that start beyond the
    tile's ``h`` x ``w`` pixels dropped.

    Written cell by cell: each whole-array expression (``a & ~b``, ``np.where``, a mask
    assigned through, a boolean index) is code numba compiles on its own; cell by cell
    this kernel's first compilation on a cold cache took 4.0 CPU-s instead of 6.9, with
    the same leaves."""
    larger = _not_unit(cells)
    rest = _rows(cells, larger)
    k = rest.shape[0]
    err_c, err_r, err_m, pts = _cell_tests(rest, v)
    err = np.empty(k)
    good = np.empty(k, np.bool_)
    for i in range(k):
        err[i] = max(max(err_c[i], err_r[i]), err_m[i])
        good[i] = err[i] < half and not (rest[i, 2] > leaf_max or rest[i, 3] > leaf_max)
    if nl > 0:
        off = _off_image(pts, err, nl, ne)
        for i in range(k):
            good[i] = good[i] or off[i]
    all_nan = _all_nan(pts)
    leaf, corners = _leaves_of(cells, larger, rest, good, v, pts)
    bad = np.empty(k, np.bool_)
    any_bad = any_nan = False
    for i in range(k):
        bad[i] = not good[i] and not all_nan[i]
        any_bad, any_nan = any_bad or bad[i], any_nan or all_nan[i]
    near = np.zeros(k, np.bool_)
    if any_bad and any_nan:    # all-NaN cells touching a refined one: the edge of the
        hit = touching(_rows(rest, all_nan), _rows(rest, bad), H, W)      # footprint
        t = 0
        for i in range(k):
            if all_nan[i]:
                near[i] = hit[t]
                t += 1
    split_r, split_c, go, sure = _splits(rest, err, err_r, err_c, bad, near, all_nan,
                                         half, tol, smooth, leaf_max)
    kids = _inside(_children(_rows(rest, go), _items(split_r, go), _items(split_c, go)),
                   h, w)
    sure_kids = _inside(_children(_rows(rest, sure), _items(split_r, sure),
                                  _items(split_c, sure)), h, w)
    return leaf, corners, kids, sure_kids


@njit(cache=True, nogil=True)
def _all_nan(pts):
    """Whether every corner and test point ``(k, 9, 2)`` of a cell is NaN."""
    k = pts.shape[0]
    out = np.ones(k, np.bool_)
    for i in range(k):
        for p in range(9):
            if not (math.isnan(pts[i, p, 0]) and math.isnan(pts[i, p, 1])):
                out[i] = False
                break
    return out


@njit(cache=True, nogil=True)
def _leaves_of(cells, larger, rest, good, v, pts):
    """The leaves of a level and their corners: its unit cells (not ``larger``; corners
    from ``v``), then the cells of ``rest`` that pass (corners from their tested points
    ``pts``)."""
    n, k = cells.shape[0], rest.shape[0]
    n_leaf = n - k
    for i in range(k):
        n_leaf += good[i]
    leaf = np.empty((n_leaf, 4), np.int64)
    corners = np.empty((n_leaf, 4, 2))
    j = 0
    for i in range(n):             # element by element: a row view (or a slice assigned)
        if not larger[i]:          # counts references, at every cell
            r, c = cells[i, 0], cells[i, 1]
            for q in range(4):
                leaf[j, q] = cells[i, q]
            for q in range(2):
                corners[j, 0, q], corners[j, 1, q] = v[r, c, q], v[r, c + 1, q]
                corners[j, 2, q], corners[j, 3, q] = v[r + 1, c, q], v[r + 1, c + 1, q]
            j += 1
    for i in range(k):
        if good[i]:
            for q in range(4):
                leaf[j, q] = rest[i, q]
                corners[j, q, 0], corners[j, q, 1] = pts[i, q, 0], pts[i, q, 1]
            j += 1
    return leaf, corners


@njit(cache=True, nogil=True)
def _splits(rest, err, err_r, err_c, bad, near, all_nan, half, tol, smooth, leaf_max):
    """:func:`_level`'s decision for each cell left (``rest``): split across rows,
    across columns, refined further (``go``) or halved into sure leaves."""
    k = rest.shape[0]
    split_r, split_c = np.empty(k, np.bool_), np.empty(k, np.bool_)
    go, sure = np.empty(k, np.bool_), np.empty(k, np.bool_)
    for i in range(k):
        big_r, big_c = rest[i, 2] > leaf_max, rest[i, 3] > leaf_max
        big = big_r or big_c
        split = bad[i] or near[i] or (big and all_nan[i])   # a big all-NaN cell may
        if big:                                            # hide the footprint
            split_r[i], split_c[i] = split and big_r, split and big_c
        else:
            r, c = _across(rest[i, 2] >= 2, rest[i, 3] >= 2, err_r[i], err_c[i], near[i],
                           half)
            split_r[i], split_c[i] = split and r, split and c
        # on a smooth mapping the interpolation error falls with the square of the cell
        # size: children of a cell that missed by less than ``tol`` miss by about a
        # quarter of it, half the acceptance threshold. They are leaves without tests
        # (their corners are the parent's tested points).
        sure[i] = smooth and split and err[i] < tol and not big
        go[i] = split and not sure[i]
    return split_r, split_c, go, sure


@njit(cache=True, nogil=True)
def _across(can_r, can_c, err_r, err_c, near, half):
    """Whether a cell to split is halved across rows, across columns (both where its
    tests do not single out one, or it borders the footprint's edge)."""
    pick_r = err_r >= half and err_c < half / 2
    pick_c = err_c >= half and err_r < half / 2
    both = near or not (pick_r or pick_c)
    return can_r and (pick_r or both or not can_c), can_c and (pick_c or both or not can_r)


@njit(cache=True, nogil=True)
def _not_unit(cells):
    """Whether each cell ``(n, 4)`` is larger than one pixel."""
    out = np.empty(cells.shape[0], np.bool_)
    for i in range(cells.shape[0]):
        out[i] = not (cells[i, 2] == 1 and cells[i, 3] == 1)
    return out


def _dense_cheaper(exact, cells, h: int, w: int, half: float) -> bool:
    """Whether at least :data:`DENSE_SHARE` of a sample of 2 x 2 cells miss ``half`` at
    their test points: the adaptive refinement would then end in single pixels over most
    of the tile, and evaluating every pixel is cheaper. The sample's cells sit at the
    top-left corners of up to 64 of the lattice's ``cells`` (those left to refine, spread
    over them: none off the raw image), 16 of them first, all 64 only where those 16 do
    not settle it (a share between :data:`SETTLED` and 1 - :data:`SETTLED`, or fewer
    than 8 seen). Cells whose tests meet NaN (off the footprint) are left out of the
    share; none left: False."""
    if h < 3 or w < 3 or not len(cells):
        return False
    pick = np.unique(np.linspace(0, len(cells) - 1, min(64, len(cells))).astype(np.int64))
    r = np.minimum(cells[pick, 0], h - 3)
    c = np.minimum(cells[pick, 1], w - 3)
    sample = np.stack([r, c, np.full(r.size, 2), np.full(r.size, 2)], axis=-1)
    share = None
    # both contiguous: a strided array is another type to numba, whose compiled
    # _cell_unknown and _cell_tests each forked worker would load again (17 ms)
    for part in (np.ascontiguousarray(sample[::4]), sample):
        exact.cells(part)
        err_c, err_r, err_m, _ = _cell_tests(part, exact.values)
        err = np.maximum(np.maximum(err_c, err_r), err_m)
        seen = np.isfinite(err)
        share = float((err[seen] >= half).mean()) if seen.any() else 0.0
        if len(part) == len(sample) or (seen.sum() >= 8 and not
                                         SETTLED < share < 1 - SETTLED):
            break
    return share >= DENSE_SHARE


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
        # step is a multiple of s: cells tile H x W; those past the tile's pixels left out
        nr = min((H - 1) // s, max(math.ceil((h - 1) / s), 1))
        nc = min((W - 1) // s, max(math.ceil((w - 1) / s), 1))
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
        i = np.arange(h)
        a, b = np.minimum(i // s, nr - 1), np.clip((i - 1) // s, 0, nr - 1)
        j = np.arange(w)
        ca, cb = np.minimum(j // s, nc - 1), np.clip((j - 1) // s, 0, nc - 1)
        keep = (kept[a][:, ca] | kept[b][:, ca] | kept[a][:, cb] | kept[b][:, cb])
    keep = keep[:h, :w]
    rr, cc = np.nonzero(keep)
    exact(rr, cc)
    out = exact.values[:h, :w].copy()
    out[~keep] = np.nan
    return out


def _dense_leaves(exact, h: int, w: int, step: int, raw_shape) -> Leaves:
    """:class:`Leaves` of the exact model at every pixel (:func:`_every_pixel`; the
    ground points from the tile's frame, as the lattice's: 16 M points a second on a
    256 x 256 tile of the survey's DEM, where pyproj's projection gave 2.4 M)."""
    px = _every_pixel(exact, h, w, step, raw_shape)
    return Leaves(np.zeros((0, 4), np.int64), np.zeros((0, 4, 2)), (h, w), exact.count, px)


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
    with warnings.catch_warnings():              # one filter a tile, not one a model call
        warnings.simplefilter("ignore", RuntimeWarning)
        return _leaves(model, grid, terrain, tol, step, smooth, raw_shape, dense)


def _leaves(model, grid, terrain, tol, step, smooth, raw_shape, dense) -> Leaves:
    """:func:`leaves` inside its warnings filter."""
    h, w = grid.shape
    step = 1 << max(int(math.log2(max(step, 1))), 0)
    half = tol * TEST_SHARE                      # a share of the bound at the test points
    if dense:           # the exact model itself at every pixel
        nr = max(math.ceil((h - 1) / step), 1)
        nc = max(math.ceil((w - 1) / step), 1)
        exact = _Exact(model, grid, terrain, nr * step + 1, nc * step + 1)
        return _dense_leaves(exact, h, w, step, raw_shape)
    # one cell over the whole tile (power-of-two sides, at least ``step``), halved down
    # to ``step`` where it does not lie off the raw image: a tile's parts off the image
    # cost a few evaluations, not a lattice of ``step`` cells each
    sr, sc = step, step
    while sr < h - 1:
        sr *= 2
    while sc < w - 1:
        sc *= 2
    H, W = sr + 1, sc + 1
    exact = _Exact(model, grid, terrain, H, W)
    cells = np.array([[0, 0, sr, sc]], np.int64)
    out_cells, out_corners = [], []
    nl, ne = raw_shape if raw_shape is not None else (0, 0)
    while cells.size:                  # one model call and one compiled pass a level
        if dense is None and cells[:, 2:].max() <= step:
            dense = False              # decided once, on the cells of ``step`` left
            if _dense_cheaper(exact, cells, h, w, half):
                return _dense_leaves(exact, h, w, step, raw_shape)
        exact.cells(cells)
        leaf, corners, cells, sure = _level(cells, exact.values, half, tol, nl, ne, smooth,
                                            H, W, step, h, w)
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
