"""Output grids: an immutable, north-up raster grid (CRS, affine transform, shape).

Conventions follow rasterio: ``transform`` maps (col, row) of a pixel's top-left corner to
(x, y); ``xy(row, col)`` gives the pixel centre by default; ``rowcol(x, y)`` is its inverse
(integer pixel containing the point, or the continuous coordinate with ``op=None``, in which
pixel centres sit at integers).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache
from typing import Iterator

import numpy as np
import pyproj
from affine import Affine

from swathflow.errors import FormatError
from swathflow.geometry.geodesy import ecef_to_geodetic, transformer, utm_crs_for
from swathflow.geometry.terrain import bilinear_one
from numba import njit


def resolve_crs(spec, lat: float, lon: float) -> str:
    """``"auto-utm"`` -> the UTM zone of (lat, lon) as ``"EPSG:nnnn"``; else the CRS as given
    (checked to be projected)."""
    if str(spec).lower() == "auto-utm":
        return utm_crs_for(lat, lon).to_string()
    try:
        crs = pyproj.CRS.from_user_input(spec)
    except pyproj.exceptions.CRSError as exc:
        raise FormatError(f"output crs {spec!r} is not a valid CRS ({exc}); use 'EPSG:nnnn' "
                          f"or 'auto-utm'") from None
    if not crs.is_projected:
        raise FormatError(f"output crs {spec!r} is not projected; use a projected CRS in "
                          f"metres (for instance 'auto-utm')")
    return str(spec)


@dataclass(frozen=True)
class Grid:
    """A north-up output grid: ``crs`` (any pyproj input, kept as given), ``transform``
    (an :class:`affine.Affine`) and ``shape`` ``(rows, cols)``."""

    crs: str
    transform: Affine
    shape: tuple[int, int]

    def __post_init__(self):
        object.__setattr__(self, "transform", Affine(*tuple(self.transform)[:6]))
        object.__setattr__(self, "shape", (int(self.shape[0]), int(self.shape[1])))
        t = self.transform
        if t.b != 0 or t.d != 0 or t.a <= 0 or t.e >= 0:
            raise ValueError(f"Grid needs a north-up transform, got {tuple(t)[:6]}")

    # --- construction ---------------------------------------------------------------
    @classmethod
    def from_bounds(cls, crs, bounds, res: float, snap: bool = True) -> "Grid":
        """The grid covering ``bounds = (xmin, ymin, xmax, ymax)`` with square pixels of
        ``res``; with ``snap`` the edges fall on multiples of ``res`` (grids of one
        mission then share pixel edges)."""
        xmin, ymin, xmax, ymax = map(float, bounds)
        res = float(res)
        if not res > 0:
            raise FormatError(f"grid resolution must be positive, got {res}")
        if snap:
            xmin = math.floor(xmin / res) * res
            ymin = math.floor(ymin / res) * res
            xmax = math.ceil(xmax / res) * res
            ymax = math.ceil(ymax / res) * res
        cols = max(int(round((xmax - xmin) / res)), 1)
        rows = max(int(round((ymax - ymin) / res)), 1)
        return cls(str(crs), Affine(res, 0.0, xmin, 0.0, -res, ymax), (rows, cols))

    # --- properties -----------------------------------------------------------------------
    @property
    def height(self) -> int:
        return self.shape[0]

    @property
    def width(self) -> int:
        return self.shape[1]

    @property
    def res(self) -> tuple[float, float]:
        return (self.transform.a, -self.transform.e)

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        t = self.transform
        return (t.c, t.f + t.e * self.height, t.c + t.a * self.width, t.f)

    @property
    def pyproj_crs(self) -> pyproj.CRS:
        return pyproj.CRS.from_user_input(self.crs)

    # --- coordinates ------------------------------------------------------------------------
    def xy(self, row, col, offset: str = "center"):
        """Map coordinates of pixels (centre, or ``"ul"`` top-left corner)."""
        d = 0.5 if offset == "center" else 0.0
        if offset not in ("center", "ul"):
            raise ValueError("offset must be 'center' or 'ul'")
        row = np.asarray(row, float) + d
        col = np.asarray(col, float) + d
        t = self.transform
        return t.c + t.a * col, t.f + t.e * row

    def rowcol(self, x, y, op=np.floor):
        """Inverse of :meth:`xy`: the pixel containing (x, y) (``op=np.floor``) or, with
        ``op=None``, the continuous (row, col) with pixel centres at integers."""
        t = self.transform
        col = (np.asarray(x, float) - t.c) / t.a
        row = (np.asarray(y, float) - t.f) / t.e
        if op is None:
            return row - 0.5, col - 0.5
        return op(row).astype(np.intp), op(col).astype(np.intp)

    def centres(self, rows: slice = slice(None), cols: slice = slice(None)):
        """2-D arrays (x, y) of the pixel centres in a window (slices of the grid)."""
        r0, r1, _ = rows.indices(self.height)
        c0, c1, _ = cols.indices(self.width)
        x, y = self.xy(np.arange(r0, r1)[:, None], np.arange(c0, c1)[None, :])
        return np.broadcast_arrays(x, y)

    def window(self, rows: slice, cols: slice) -> "Grid":
        """The sub-grid of a window."""
        r0, r1, _ = rows.indices(self.height)
        c0, c1, _ = cols.indices(self.width)
        t = self.transform @ Affine.translation(c0, r0)
        return Grid(self.crs, t, (r1 - r0, c1 - c0))

    def tiles(self, size: int = 512) -> Iterator[tuple[slice, slice]]:
        """Row-major windows ``(row_slice, col_slice)`` of at most ``size`` x ``size``."""
        for r in range(0, self.height, size):
            for c in range(0, self.width, size):
                yield (slice(r, min(r + size, self.height)), slice(c, min(c + size, self.width)))

    def chunks(self, size: int = 512) -> tuple[tuple[int, ...], tuple[int, ...]]:
        """dask chunks matching :meth:`tiles`."""
        def split(n):
            return tuple(min(size, n - i) for i in range(0, n, size))
        return split(self.height), split(self.width)

    def to_ecef(self, x, y, terrain) -> np.ndarray:
        """ECEF ``(..., 3)`` of map points on the terrain (ellipsoidal heights)."""
        from swathflow.geometry.geodesy import geodetic_to_ecef
        x, y = np.asarray(x, float), np.asarray(y, float)
        h = _map_heights(self.crs, terrain, x, y)
        if h is not None:       # one projection call, not three (the same points to 1e-9 m)
            ex, ey, ez = _to_ecef(self.crs).transform(*np.broadcast_arrays(x, y, h))
            return np.stack([ex, ey, ez], axis=-1)
        lon, lat = _to_lonlat(self.crs).transform(x, y)
        h = terrain.height(lat, lon)
        return geodetic_to_ecef(np.stack(np.broadcast_arrays(lat, lon, h), axis=-1))

    def state(self) -> dict:
        return {"crs": self.crs, "transform": list(tuple(self.transform)[:6]),
                "shape": list(self.shape)}


@lru_cache(maxsize=64)
def _to_lonlat(crs: str):
    return transformer(crs, "EPSG:4326")


@lru_cache(maxsize=64)
def _to_ecef(crs: str):
    """Map x, y and ellipsoidal height in ``crs`` -> ECEF, in one transformation."""
    return transformer(pyproj.CRS.from_user_input(crs).to_3d(), "EPSG:4978")


@lru_cache(maxsize=64)
def _wgs84_projected(crs: str) -> bool:
    """A projected 2-D CRS on WGS 84 (its 3-D form then carries WGS 84 ellipsoidal
    heights, as :func:`~swathflow.geometry.geodesy.geodetic_to_ecef` takes them)."""
    c = pyproj.CRS.from_user_input(crs)
    return (c.is_projected and not c.is_compound and len(c.axis_info) == 2
            and c.geodetic_crs is not None and c.geodetic_crs.equals("EPSG:4326"))


@lru_cache(maxsize=64)
def _same_crs(crs: str, wkt: str) -> bool:
    return pyproj.CRS.from_user_input(crs).equals(pyproj.CRS.from_wkt(wkt))


def _map_heights(crs: str, terrain, x, y):
    """Ellipsoidal heights at map points of ``crs`` straight from the map coordinates (a
    constant height, or a DEM in the same CRS), None where that needs longitude and
    latitude (another terrain, a DEM in another CRS, a CRS not on WGS 84)."""
    from swathflow.geometry.terrain import ConstantHeight
    if not _heights_from_map(crs, terrain):
        return None
    if type(terrain) is ConstantHeight:
        return np.full(np.broadcast_shapes(x.shape, y.shape), float(terrain.h))
    return terrain.height_xy(x, y)


def _heights_from_map(crs: str, terrain) -> bool:
    """Whether :func:`_map_heights` gives heights (not None) in ``crs`` on ``terrain``."""
    from swathflow.geometry.terrain import DEM, ConstantHeight
    return _wgs84_projected(crs) and (type(terrain) is ConstantHeight or (
        type(terrain) is DEM and _same_crs(crs, terrain.crs_wkt)))


#: degree in rows and in columns of the polynomials of :class:`TileFrame` (5 x 5
#: Chebyshev nodes: within 1e-8 m of pyproj on 545-pixel windows at 0.05 to 40 m)
FRAME_DEGREE = 4


class TileFrame:
    """ECEF of the pixel centres (integer rows ``0..H-1``, columns ``0..W-1``) of a grid
    on the terrain, without a projection call a point: ``P + h U``, where ``P`` (the
    point on the ellipsoid) and ``U`` (the ellipsoid normal; ECEF is linear in the
    ellipsoidal height) are the polynomials of degree :data:`FRAME_DEGREE` in row and
    column through pyproj's values at Chebyshev nodes of the window, and ``h`` the
    terrain's height at the map point (:func:`_map_heights`). Use :func:`tile_frame`."""

    def __init__(self, grid: "Grid", terrain, H: int, W: int):
        self.grid, self.terrain = grid, terrain
        d = FRAME_DEGREE
        (rn, self.b_rows), (cn, self.b_cols) = _nodes_basis(H), _nodes_basis(W)
        x, y, h = np.empty((3, rn.size, cn.size, 2))    # filled by broadcasting (cheaper
        x[...], y[...] = grid.xy(rn[:, None, None], cn[None, :, None])   # than views)
        h[...] = (0.0, 1000.0)
        p = np.stack(_to_ecef(grid.crs).transform(x, y, h), axis=-1)    # one call
        p0, p1 = p[:, :, 0], p[:, :, 1]
        self.origin = p0[d // 2, d // 2].copy()    # the polynomials carry offsets from it
        self.nodes = np.ascontiguousarray(np.concatenate([p0 - self.origin, (p1 - p0) / 1000.0],
                                                         axis=-1))
        # the heights as _map_heights takes them: a constant, or the DEM in the grid's CRS
        t = grid.transform
        self.heights = ((t.a, t.c, t.e, t.f), np.zeros((0, 0)), (0.0,) * 6,
                        float(getattr(terrain, "h", 0.0)))
        if hasattr(terrain, "data"):
            self.heights = ((t.a, t.c, t.e, t.f), np.ascontiguousarray(terrain.data, float),
                            tuple(float(v) for v in terrain.transform), 0.0)

    def ecef(self, rows, cols) -> np.ndarray:
        """ECEF ``(n, 3)`` of the pixel centres at integer ``rows, cols`` (NaN where the
        terrain has no height)."""
        rows = np.ascontiguousarray(rows, np.int64).ravel()
        cols = np.ascontiguousarray(cols, np.int64).ravel()
        out = np.empty((rows.size, 3))
        _frame_ecef(self.nodes, self.b_rows, self.b_cols, rows, cols, self.heights,
                    self.origin, out)
        return out


@lru_cache(maxsize=16)
def _nodes_basis(n: int) -> tuple[np.ndarray, np.ndarray]:
    """The :data:`FRAME_DEGREE` + 1 Chebyshev nodes over ``0 .. n - 1`` and their
    Lagrange basis there (:func:`_basis`; shared by every tile of a size: not to be
    written)."""
    k = np.arange(FRAME_DEGREE + 1)
    nodes = (n - 1) / 2 * (1 - np.cos(np.pi * k / FRAME_DEGREE))
    b = _basis(nodes, n)
    return nodes, b


def _basis(nodes, n) -> np.ndarray:
    """Lagrange basis ``(n, len(nodes))`` of the ``nodes`` at 0 .. n - 1."""
    d = np.arange(n, dtype=float)[:, None, None] - nodes[None, None, :]   # (n, 1, m)
    den = nodes[:, None] - nodes[None, :]                                # (m, m)
    off = ~np.eye(nodes.size, dtype=bool)
    ratio = np.where(off, d / np.where(off, den, 1.0), 1.0)              # (n, m, m)
    return ratio.prod(axis=-1)


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _frame_height(r, cl, ga, gc, ge, gf, dem, a, b, c, d, e, f, det, h_const):
    """The terrain's height under pixel (r, cl): the constant, or the DEM's (as
    Grid.xy, then DEM.height_xy)."""
    if not dem.size:
        return h_const
    x, y = gc + ga * (cl + 0.5), gf + ge * (r + 0.5)
    return bilinear_one(dem, (-d * (x - c) + a * (y - f)) / det - 0.5,
                        (e * (x - c) - b * (y - f)) / det - 0.5)


@njit(cache=True, nogil=True, error_model="numpy")
def _frame_ecef(nodes, b_rows, b_cols, rows, cols, heights, origin, out):
    """``origin + sum_kl B_row[r, k] B_col[c, l] (P[k, l] + h U[k, l])`` a point, ``h``
    the constant height or the DEM's (``heights``: the grid's a, c, e, f; the DEM's
    data, or an empty array, and transform; the constant). Where points come in row order
    (a tile's pixels) the sums over ``k`` are kept along the row (30 products a point
    instead of 150); a point alone on its row (the lattice's nodes) takes the double sum."""
    (ga, gc, ge, gf), dem, (a, b, c, d, e, f), h_const = heights
    det = a * e - b * d
    nk, nm = nodes.shape[0], nodes.shape[1]
    q = np.zeros((nm, 6))
    row = -1
    for i in range(rows.shape[0]):
        r, cl = rows[i], cols[i]
        if r != row and (i + 1 == rows.shape[0] or rows[i + 1] != r):
            # a point alone on its row (the lattice's order): the double sum directly
            x = y = z = 0.0
            hi = _frame_height(r, cl, ga, gc, ge, gf, dem, a, b, c, d, e, f, det, h_const)
            for k in range(nk):
                px = py = pz = 0.0
                for m in range(nm):
                    w = b_cols[cl, m]
                    px += w * (nodes[k, m, 0] + hi * nodes[k, m, 3])
                    py += w * (nodes[k, m, 1] + hi * nodes[k, m, 4])
                    pz += w * (nodes[k, m, 2] + hi * nodes[k, m, 5])
                w = b_rows[r, k]
                x += w * px
                y += w * py
                z += w * pz
            out[i, 0], out[i, 1], out[i, 2] = origin[0] + x, origin[1] + y, origin[2] + z
            continue
        if r != row:                 # the row's polynomials in the column
            row = r
            for m in range(nm):
                for j in range(6):
                    s = 0.0
                    for k in range(nk):
                        s += b_rows[r, k] * nodes[k, m, j]
                    q[m, j] = s
        hi = _frame_height(r, cl, ga, gc, ge, gf, dem, a, b, c, d, e, f, det, h_const)
        x = y = z = 0.0
        for m in range(nm):
            w = b_cols[cl, m]
            x += w * (q[m, 0] + hi * q[m, 3])
            y += w * (q[m, 1] + hi * q[m, 4])
            z += w * (q[m, 2] + hi * q[m, 5])
        out[i, 0], out[i, 1], out[i, 2] = origin[0] + x, origin[1] + y, origin[2] + z


def tile_frame(grid: "Grid", terrain, H: int, W: int) -> "TileFrame | None":
    """A :class:`TileFrame` of the window ``H`` x ``W`` from the grid's origin, or None
    where the heights need longitude and latitude (:func:`_map_heights`: then
    :meth:`Grid.to_ecef`)."""
    if H < 2 or W < 2 or not _heights_from_map(grid.crs, terrain):
        return None
    return TileFrame(grid, terrain, H, W)


@lru_cache(maxsize=64)
def _from_lonlat(crs: str):
    return transformer("EPSG:4326", crs)


def ecef_to_map(ground, crs) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(x, y, ellipsoidal h) in ``crs`` of ECEF points ``(..., 3)``."""
    llh = ecef_to_geodetic(ground)
    x, y = _from_lonlat(crs).transform(llh[..., 1], llh[..., 0])
    return np.asarray(x), np.asarray(y), llh[..., 2]


def footprint_grid(model, terrain, gsd: float, crs="auto-utm", samples: int = 64,
                   margin: float = 0.0, interior: int = 8) -> Grid:
    """The grid (``gsd`` pixels, snapped) covering a sensor model's ground footprint.

    The image border (``samples`` points per side) and an ``interior`` x ``interior``
    lattice (its points among those of a ``samples`` x ``samples`` one when
    ``samples - 1`` is a multiple of ``interior - 1``: 64 and 8 are) are projected onto the
    terrain; ``margin`` metres are added on every side. The footprint of a swing whose rays
    all reach the terrain is bounded by the border's image; the interior lattice is for
    relief that hides parts of it and for border rays that miss the terrain. (The whole
    64 x 64 lattice gave the same grid on the survey's 240 swings and the demo's 8, in 4.7x
    the time: 6.5 ms a swing.)
    """
    from swathflow.geometry.terrain import open_terrain
    terrain = open_terrain(terrain)
    nl, ne = model.shape
    lines = np.linspace(-0.5, nl - 0.5, samples)
    elems = np.linspace(-0.5, ne - 0.5, samples)
    il, ie = np.meshgrid(np.linspace(-0.5, nl - 0.5, interior)[1:-1],
                         np.linspace(-0.5, ne - 0.5, interior)[1:-1], indexing="ij")
    img = np.concatenate([
        np.stack([lines, np.full(samples, elems[0])], axis=-1),
        np.stack([lines, np.full(samples, elems[-1])], axis=-1),
        np.stack([np.full(samples, lines[0]), elems], axis=-1),
        np.stack([np.full(samples, lines[-1]), elems], axis=-1),
        np.stack([il.ravel(), ie.ravel()], axis=-1)])
    import warnings
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")          # rays off the terrain are NaN
        g = model.image_to_ground(img, terrain)
    ok = np.isfinite(g).all(axis=-1)
    if not ok.any():
        raise FormatError("the image's footprint misses the terrain everywhere: check the "
                          "terrain heights, the POS and the calibration")
    llh = ecef_to_geodetic(g[ok])
    crs = resolve_crs(crs, float(np.median(llh[:, 0])), float(np.median(llh[:, 1])))
    x, y, _ = ecef_to_map(g[ok], crs)
    return Grid.from_bounds(crs, (x.min() - margin, y.min() - margin, x.max() + margin,
                                  y.max() + margin), gsd)


def union_grid(grids, res: float | None = None) -> Grid:
    """The snapped grid covering several grids of one CRS."""
    grids = list(grids)
    crs = grids[0].crs
    b = np.array([g.bounds for g in grids])
    return Grid.from_bounds(crs, (b[:, 0].min(), b[:, 1].min(), b[:, 2].max(), b[:, 3].max()),
                            res or grids[0].res[0])
