"""The adaptive lattice of exact raw coordinates under an output tile.

For each output tile the raw image coordinates (line, element) of the ground under the
output pixel centres (map x, y with terrain heights) come from the sensor model's
``ground_to_image``, evaluated on a coarse lattice of the tile. Every lattice cell is
checked at its centre and edge midpoints against the exact model; where bilinear
interpolation of the corners misses by ``tol / 2`` raw pixels or more there (the margin
keeps the error between test points below ``tol``) the cell is split in four and checked
again, down to single pixels (exact). All-NaN cells next to split cells are split too, so
the footprint's edge is traced at pixel resolution.

The result is a list of *leaves*: squares of output pixels with their four corner values,
in the order they must be painted (coarse first; finer leaves overwrite the shared
edges). :mod:`.kernel` paints them; no per-pixel array is built here.
"""
from __future__ import annotations

import math
import warnings
from dataclasses import dataclass

import numpy as np

#: default bound on the interpolated raw coordinates' error (raw pixels, line and element)
TOLERANCE_PX = 0.05
#: least distance (raw pixels) beyond the raw image's edge of a cell left unrefined
OFF_MARGIN_PX = 4.0


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
    """Leaves of a tile's lattice: ``cells`` ``(n, 3)`` int64 (row, col, size) and
    ``corners`` ``(n, 4, 2)`` float64 raw (line, element) at (r, c), (r, c + s),
    (r + s, c), (r + s, c + s); ``shape`` the tile's (rows, cols)."""

    cells: np.ndarray
    corners: np.ndarray
    shape: tuple[int, int]
    exact_evaluations: int

    def bounds(self, n_lines: int, n_elements: int):
        """``(lmin, lmax, emin, emax)`` of the corner coordinates of the leaves that can
        touch the raw image (bilinear interpolation stays inside its corners' box), or
        None when no leaf touches it."""
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


def _level(exact, cells, s, H, W, raw_shape=None):
    """One level of refinement: (error at the test points, all-NaN cells, corners, cells
    off the raw image (with ``raw_shape``, else None))."""
    hs = s // 2
    v = exact.values
    r, c = cells[:, 0], cells[:, 1]
    q00, q01 = v[r, c], v[r, c + s]
    q10, q11 = v[r + s, c], v[r + s, c + s]
    tests = [(r + hs, c + hs, (q00 + q01 + q10 + q11) / 4),
             (r, c + hs, (q00 + q01) / 2), (r + s, c + hs, (q10 + q11) / 2),
             (r + hs, c, (q00 + q10) / 2), (r + hs, c + s, (q01 + q11) / 2)]
    exact(np.concatenate([t[0] for t in tests]),            # one model call per level
          np.concatenate([t[1] for t in tests]))
    err = np.zeros(len(cells))
    all_nan = np.isnan(np.stack([q00, q01, q10, q11])).all(axis=(0, 2))
    exs = []
    for tr, tc, interp in tests:
        ex = v[tr, tc]
        exs.append(ex)
        d = np.abs(ex - interp).max(axis=-1)
        err = np.maximum(err, np.where(np.isnan(d), np.inf, d))
        all_nan &= np.isnan(ex).all(axis=-1)
    q = np.stack([q00, q01, q10, q11], axis=1)
    off = None
    if raw_shape is not None:
        off = _off_image(np.concatenate([q, np.stack(exs, axis=1)], axis=1), err, raw_shape)
    return err, all_nan, q, off


def _children_leaves(v, parents, hs, out_cells, out_corners) -> None:
    if not len(parents):
        return
    kids = np.concatenate([parents, parents + [hs, 0], parents + [0, hs], parents + [hs, hs]])
    r, c = kids[:, 0], kids[:, 1]
    out_cells.append(np.column_stack([kids, np.full(len(kids), hs)]))
    out_corners.append(np.stack([v[r, c], v[r, c + hs], v[r + hs, c], v[r + hs, c + hs]],
                                axis=1))


def leaves(model, grid, terrain, tol: float = TOLERANCE_PX, step: int = 32,
           smooth: bool | None = None, raw_shape: tuple[int, int] | None = None) -> Leaves:
    """The adaptive lattice of ``grid`` (a tile's own grid) as :class:`Leaves`.

    ``smooth`` (default: the terrain is a constant height, so the mapping is analytic)
    lets cells whose parent missed by less than ``tol`` skip their own tests. With
    ``raw_shape`` (lines, elements) cells clearly off the raw image are not refined
    (:func:`_off_image`): their pixels are nodata whatever the interpolation, so the
    bound holds where the image is seen (the GLT and the rectified pixels), not on the
    coordinates of pixels off the image."""
    from swathflow.geometry.terrain import ConstantHeight
    if smooth is None:
        smooth = isinstance(terrain, ConstantHeight)
    h, w = grid.shape
    step = 1 << max(int(math.log2(max(step, 1))), 0)
    nr = max(math.ceil((h - 1) / step), 1)       # cells along rows
    nc = max(math.ceil((w - 1) / step), 1)
    H, W = nr * step + 1, nc * step + 1
    exact = _Exact(model, grid, terrain, H, W)
    rr, cc = np.meshgrid(np.arange(nr + 1) * step, np.arange(nc + 1) * step, indexing="ij")
    exact(rr.ravel(), cc.ravel())
    ci, cj = np.meshgrid(np.arange(nr), np.arange(nc), indexing="ij")
    cells = np.stack([ci.ravel() * step, cj.ravel() * step], axis=-1)
    out_cells, out_corners = [], []
    s = step
    while s > 1 and cells.size:
        hs = s // 2
        err, all_nan, q, off = _level(exact, cells, s, H, W, raw_shape)
        good = err < tol / 2        # half the bound at the test points
        if off is not None:
            good |= off
        bad = ~good & ~all_nan
        if good.any():
            g = cells[good]
            out_cells.append(np.column_stack([g, np.full(len(g), s)]))
            out_corners.append(q[good])
        # split bad cells and the all-NaN cells next to them
        r, c = cells[:, 0], cells[:, 1]
        lvl = np.zeros((H // s + 2, W // s + 2), bool)
        lvl[r[bad] // s + 1, c[bad] // s + 1] = True
        near = np.zeros_like(lvl)
        for di in (-1, 0, 1):
            for dj in (-1, 0, 1):
                near[1 + di:lvl.shape[0] - 1 + di, 1 + dj:lvl.shape[1] - 1 + dj] |= lvl[1:-1, 1:-1]
        split = bad | (all_nan & near[r // s + 1, c // s + 1])
        if smooth and hs > 1:
            # on a smooth mapping the interpolation error falls with the square of the
            # cell size: children of a cell that missed by less than ``tol`` miss by
            # about a quarter of it, half the acceptance threshold. They are leaves
            # without tests (their nine points are known already).
            sure = split & (err < tol)
            _children_leaves(exact.values, cells[sure], hs, out_cells, out_corners)
            split &= ~sure
        sel = cells[split]
        cells = np.concatenate([sel, sel + [hs, 0], sel + [0, hs], sel + [hs, hs]])
        s = hs
    if cells.size:                                  # s == 1: every corner is a pixel
        r, c = cells[:, 0], cells[:, 1]
        q = np.stack([exact(r, c), exact(r, c + 1), exact(r + 1, c), exact(r + 1, c + 1)],
                     axis=1)
        out_cells.append(np.column_stack([cells, np.ones(len(cells), np.int64)]))
        out_corners.append(q)
    if out_cells:
        cells_a = np.ascontiguousarray(np.concatenate(out_cells).astype(np.int64))
        corners_a = np.ascontiguousarray(np.concatenate(out_corners).astype(np.float64))
    else:
        cells_a = np.zeros((0, 3), np.int64)
        corners_a = np.zeros((0, 4, 2))
    return Leaves(cells_a, corners_a, (h, w), exact.count)


def inverse_map(model, grid, terrain, tol: float = TOLERANCE_PX, step: int = 32,
                stats: dict | None = None) -> np.ndarray:
    """Raw (line, element) ``(rows, cols, 2)`` float64 under every pixel centre of
    ``grid`` (NaN where the image does not see the ground; coordinates beyond the
    detector's ends are kept, the caller masks them). ``stats`` (a dict) receives the
    count of exact evaluations."""
    from swathflow.geometry.terrain import open_terrain
    from swathflow.rectification.kernel import lattice_coords_f64
    lv = leaves(model, grid, open_terrain(terrain), tol, step)
    if stats is not None:
        stats["exact_evaluations"] = stats.get("exact_evaluations", 0) + lv.exact_evaluations
        stats["pixels"] = stats.get("pixels", 0) + grid.shape[0] * grid.shape[1]
    return lattice_coords_f64(lv.cells, lv.corners, *grid.shape)
