"""A DEM's *frame*: ECEF -> (DEM column, DEM row, ellipsoidal height) without pyproj per
point, for the compiled ray / DEM intersection of :mod:`swathflow.geometry.march`.

A rotation into a local east-north-up frame at the DEM's centre, then per tile of that frame
a polynomial of total degree ``DEGREE`` in (east, north, up), fitted once per DEM to exact
values at Chebyshev nodes (Heikkinen heights; pyproj for the DEM's CRS at the nodes only)
and checked at other points of every tile against the exact values: the largest error must
stay below ``FRAME_TOL`` metres (in position and height), else the tiles are halved (and
after seven halvings no frame is made: the caller takes the numpy path). The frame also
keeps the highest and lowest node of every ``BLOCK`` x ``BLOCK`` block of DEM cells, which
lets the march start where the ray comes down to the terrain under it.
"""
from __future__ import annotations

import math
import weakref
from dataclasses import dataclass

import numpy as np
from numba import njit
from swathflow.geometry.geodesy_kernel import geodetic_of_points

#: the frame's largest error (m) in position and height, checked when it is fitted
FRAME_TOL = 1e-6
#: total degree of the frame's polynomials
DEGREE = 3
#: cells a side of the blocks whose highest and lowest node bound the terrain under a ray
BLOCK = 8


def _monomials(s, t, u) -> np.ndarray:
    """``(n, terms)`` monomials s^i t^j u^k, i + j + k <= DEGREE, in the kernel's order."""
    cols = []
    for k in range(DEGREE + 1):
        for j in range(DEGREE + 1 - k):
            for i in range(DEGREE + 1 - k - j):
                cols.append(s ** i * t ** j * u ** k)
    return np.stack(cols, axis=-1)


@dataclass(frozen=True)
class DemFrame:
    """ECEF -> (DEM column, row, ellipsoidal height) as tiled polynomials (see the module)."""

    origin: np.ndarray      # (3,) ECEF of the local frame's origin
    rot: np.ndarray         # (3, 3) rows: east, north, up (ECEF)
    grid: np.ndarray        # e0, n0, tile width, height, tiles east, north, 1/width, 1/height
    ubox: np.ndarray        # (ny, nx, 2) centre and inverse half-range of ``up`` per tile
    coef: np.ndarray        # (ny, nx, terms, 3)
    error_m: float          # largest error found at the check points (m)
    blocks: np.ndarray      # highest and lowest node of every BLOCK x BLOCK cells
    bracket: tuple          # heights of the shells below and above the DEM (the march's ends)

    def arrays(self):
        """The arrays the kernel takes: origin, rot, grid, ubox, coef, blocks."""
        return self.origin, self.rot, self.grid, self.ubox, self.coef, self.blocks


def _exact(terrain, enu, origin, rot, inv):
    """Column, row and ellipsoidal height of local ENU points (Heikkinen, pyproj)."""
    from swathflow.geometry.geodesy import transformer
    ecef = origin + enu @ rot
    llh = geodetic_of_points(np.ascontiguousarray(ecef))
    x, y = transformer("EPSG:4326", terrain.crs_wkt).transform(llh[:, 1], llh[:, 0])
    x, y = np.asarray(x), np.asarray(y)
    col = inv[0] * x + inv[1] * y + inv[2] - 0.5
    row = inv[3] * x + inv[4] * y + inv[5] - 0.5
    return np.stack([col, row, llh[:, 2]], axis=-1)


def _tile_points(tiles, s, t, u) -> np.ndarray:
    """Local ENU points ``(tiles * n, 3)`` at tile coordinates ``s, t, u`` in [-1, 1]."""
    ce, cn, we, wn, ubox = tiles
    return np.stack([ce[..., None] + s * we / 2, cn[..., None] + t * wn / 2,
                     ubox[..., 0:1] + u / ubox[..., 1:2]], axis=-1).reshape(-1, 3)


def _bracket_heights(h_min: float, h_max: float) -> tuple[float, float]:
    """Heights of the two shells (inflated ellipsoids) that bracket the DEM: below its
    lowest and above its highest point by more than an inflated ellipsoid strays from the
    surface of constant height (well under a metre up to 10 km)."""
    return h_min - 2.0 - 0.01 * abs(h_min), h_max + 2.0 + 0.01 * abs(h_max)


def _fit_frame(terrain, h_lo, h_hi):
    from swathflow.geometry.geodesy import geodetic_to_ecef, transformer
    a, b, c, dd, e, f = terrain.transform
    det = a * e - b * dd
    inv = np.array([e / det, -b / det, (b * f - e * c) / det,
                    -dd / det, a / det, (dd * c - a * f) / det])
    nr, nc = terrain.data.shape
    # the DEM's outline (pixel edges) at its lowest and highest height, in a local ENU frame
    k = np.linspace(0.0, 1.0, 17)
    pc = np.concatenate([k * nc, k * nc, np.zeros(17), np.full(17, nc)])
    pr = np.concatenate([np.zeros(17), np.full(17, nr), k * nr, k * nr])
    x, y = c + a * pc + b * pr, f + dd * pc + e * pr
    lon, lat = transformer(terrain.crs_wkt, "EPSG:4326").transform(x, y)
    lon, lat = np.asarray(lon, float), np.asarray(lat, float)
    if not (np.isfinite(lon).all() and np.isfinite(lat).all()):
        return None
    edge = np.concatenate([geodetic_to_ecef(np.stack([lat, lon, np.full_like(lat, h)], -1))
                           for h in (h_lo, h_hi)])
    centre = geodetic_of_points(edge.mean(axis=0)[None, :])[0]
    la, lo = np.radians(centre[0]), np.radians(centre[1])
    rot = np.array([[-np.sin(lo), np.cos(lo), 0.0],
                    [-np.sin(la) * np.cos(lo), -np.sin(la) * np.sin(lo), np.cos(la)],
                    [np.cos(la) * np.cos(lo), np.cos(la) * np.sin(lo), np.sin(la)]])
    origin = geodetic_to_ecef(np.array([centre[0], centre[1], 0.0]))
    enu = (edge - origin) @ rot.T
    # room for rays well off the vertical that pass over the DEM's edge
    pad = 200.0 + 4.0 * (h_hi - h_lo)
    e0, n0 = enu[:, 0].min() - pad, enu[:, 1].min() - pad
    ext_e, ext_n = enu[:, 0].max() + pad - e0, enu[:, 1].max() + pad - n0
    cell_m = max(float(terrain.cell_size_m), 1e-9)
    size = 16000.0
    cheb = np.cos(np.pi * (np.arange(7) + 0.5) / 7)
    cu = np.cos(np.pi * (np.arange(6) + 0.5) / 6)
    fs, ft, fu = (v.ravel() for v in np.meshgrid(cheb, cheb, cu, indexing="ij"))
    pinv = np.linalg.pinv(_monomials(fs, ft, fu))
    rng = np.random.default_rng(0)
    cs, ct, cu2 = (rng.uniform(-1, 1, 40) for _ in range(3))
    check = _monomials(cs, ct, cu2)
    for _ in range(7):
        nx, ny = max(int(np.ceil(ext_e / size)), 1), max(int(np.ceil(ext_n / size)), 1)
        we, wn = ext_e / nx, ext_n / ny
        ce = e0 + (np.arange(nx) + 0.5) * we
        cn = n0 + (np.arange(ny) + 0.5) * wn
        CE, CN = np.meshgrid(ce, cn)                              # (ny, nx)
        # the up coordinate of the heights h_lo..h_hi over the tile (the Earth curves away)
        far = (np.abs(CE) + we / 2) ** 2 + (np.abs(CN) + wn / 2) ** 2
        near = (np.maximum(np.abs(CE) - we / 2, 0.0) ** 2
                + np.maximum(np.abs(CN) - wn / 2, 0.0) ** 2)
        drop_far, drop_near = far / (2 * 6.33e6), near / (2 * 6.40e6)
        u_lo = h_lo - drop_far * 1.01 - 5.0
        u_hi = h_hi - drop_near * 0.99 + 5.0
        ubox = np.stack([(u_lo + u_hi) / 2, 2.0 / (u_hi - u_lo)], axis=-1)

        tiles = (CE, CN, we, wn, ubox)
        val = _exact(terrain, _tile_points(tiles, fs, ft, fu), origin, rot, inv)
        coef = np.einsum("tp,yxpk->yxtk", pinv, val.reshape(ny, nx, -1, 3))
        ref = _exact(terrain, _tile_points(tiles, cs, ct, cu2), origin, rot,
                     inv).reshape(ny, nx, -1, 3)
        err = np.abs(np.einsum("pt,yxtk->yxpk", check, coef) - ref)
        err_m = float(max(np.nanmax(err[..., :2]) * cell_m, np.nanmax(err[..., 2])))
        if np.isfinite(err_m) and err_m < FRAME_TOL:
            grid = np.array([e0, n0, we, wn, nx, ny, 1 / we, 1 / wn], float)
            return DemFrame(origin, np.ascontiguousarray(rot), grid, np.ascontiguousarray(ubox),
                            np.ascontiguousarray(coef), err_m,
                            _block_range(np.ascontiguousarray(terrain.data, dtype=float), BLOCK),
                            _bracket_heights(float(terrain.h_min), float(terrain.h_max)))
        size /= 2
    return None


_FRAMES: "weakref.WeakKeyDictionary" = weakref.WeakKeyDictionary()


def dem_frame(terrain) -> DemFrame | None:
    """The frame of a DEM terrain (fitted on first use, then kept with the terrain); None
    when no tiling meets ``FRAME_TOL`` (the caller then takes the numpy path)."""
    try:
        return _FRAMES[terrain]
    except (KeyError, TypeError):
        pass
    fr = _fit_frame(terrain, float(terrain.h_min) - 20.0 - 0.02 * abs(terrain.h_min),
                    float(terrain.h_max) + 20.0 + 0.02 * abs(terrain.h_max))
    try:
        _FRAMES[terrain] = fr
    except TypeError:
        pass
    return fr


@njit(cache=True, nogil=True)
def _block_range(data, b):
    """The highest and lowest node of every ``b`` x ``b`` block of DEM cells, ``(rows,
    cols, 2)`` (+inf and -inf where a node is NaN: the march then takes the whole ray)."""
    nr, nc = data.shape
    nbr, nbc = max(nr - 2, 0) // b + 1, max(nc - 2, 0) // b + 1
    out = np.empty((nbr, nbc, 2))
    out[:, :, 0] = -np.inf
    out[:, :, 1] = np.inf
    for r in range(nr):
        for c in range(nc):
            v = data[r, c]
            for br in range(max(r - 1, 0) // b, min(r // b, nbr - 1) + 1):
                for bc in range(max(c - 1, 0) // b, min(c // b, nbc - 1) + 1):
                    if math.isnan(v):
                        out[br, bc, 0], out[br, bc, 1] = np.inf, -np.inf
                    else:
                        out[br, bc, 0] = max(out[br, bc, 0], v)
                        out[br, bc, 1] = min(out[br, bc, 1], v)
    return out


@njit(cache=True, nogil=True, inline="always")
def tile_of(e, n, u, grid, ubox):
    """Tile (row, column) and tile coordinates (s, t, w) in [-1, 1] of local ENU (e, n, u)."""
    fe = (e - grid[0]) * grid[6]
    fn = (n - grid[1]) * grid[7]
    tx = min(max(int(math.floor(fe)), 0), int(grid[4]) - 1)
    ty = min(max(int(math.floor(fn)), 0), int(grid[5]) - 1)
    return ty, tx, 2.0 * (fe - tx) - 1.0, 2.0 * (fn - ty) - 1.0, (u - ubox[ty, tx, 0]) * ubox[ty, tx, 1]


@njit(cache=True, nogil=True, inline="always")
def poly3(c, s0, t0, w0, s1, t1, w1, s2, t2, w2):
    """The tile polynomial ``c`` at three points of one tile: a 9-tuple, point by point
    (column, row, height); the sums stay in registers."""
    a0 = b0 = h0 = a1 = b1 = h1 = a2 = b2 = h2 = 0.0
    m = 0
    pw0 = pw1 = pw2 = 1.0
    for k in range(DEGREE + 1):
        pt0, pt1, pt2 = pw0, pw1, pw2
        for j in range(DEGREE + 1 - k):
            ps0, ps1, ps2 = pt0, pt1, pt2
            for _i in range(DEGREE + 1 - k - j):
                ca, cb, ch = c[m, 0], c[m, 1], c[m, 2]
                a0 += ca * ps0
                b0 += cb * ps0
                h0 += ch * ps0
                a1 += ca * ps1
                b1 += cb * ps1
                h1 += ch * ps1
                a2 += ca * ps2
                b2 += cb * ps2
                h2 += ch * ps2
                m += 1
                ps0 *= s0
                ps1 *= s1
                ps2 *= s2
            pt0 *= t0
            pt1 *= t1
            pt2 *= t2
        pw0 *= w0
        pw1 *= w1
        pw2 *= w2
    return a0, b0, h0, a1, b1, h1, a2, b2, h2


@njit(cache=True, nogil=True, inline="always")
def poly(c, s, t, w):
    """The tile polynomial ``c`` (terms, 3) at tile coordinates (s, t, w)."""
    v0 = 0.0
    v1 = 0.0
    v2 = 0.0
    m = 0
    pw = 1.0
    for k in range(DEGREE + 1):
        pt = pw
        for j in range(DEGREE + 1 - k):
            ps = pt
            for _i in range(DEGREE + 1 - k - j):
                v0 += c[m, 0] * ps
                v1 += c[m, 1] * ps
                v2 += c[m, 2] * ps
                m += 1
                ps *= s
            pt *= t
        pw *= w
    return v0, v1, v2


def frame_points(frame: DemFrame, pts) -> np.ndarray:
    """``(n, 3)`` column, row, height of ECEF points ``(n, 3)`` through the frame."""
    return _frame_points(np.ascontiguousarray(pts, dtype=float), frame.origin, frame.rot,
                         frame.grid, frame.ubox, frame.coef)


@njit(cache=True, nogil=True)
def _frame_points(pts, origin, rot, grid, ubox, coef):
    out = np.empty_like(pts)
    for i in range(pts.shape[0]):
        dx, dy, dz = pts[i, 0] - origin[0], pts[i, 1] - origin[1], pts[i, 2] - origin[2]
        e = rot[0, 0] * dx + rot[0, 1] * dy + rot[0, 2] * dz
        n = rot[1, 0] * dx + rot[1, 1] * dy + rot[1, 2] * dz
        u = rot[2, 0] * dx + rot[2, 1] * dy + rot[2, 2] * dz
        ty, tx, s, t, w = tile_of(e, n, u, grid, ubox)
        out[i, 0], out[i, 1], out[i, 2] = poly(coef[ty, tx], s, t, w)
    return out
