"""Compiled ray / DEM intersection (numba): the bracketing, the march and the regula falsi
of :func:`swathflow.geometry.intersect.intersect` for a DEM in one kernel, without pyproj
per point.

The DEM's *frame* maps ECEF to (DEM column, DEM row, ellipsoidal height): a rotation into a
local east-north-up frame at the DEM's centre, then per tile of that frame a polynomial of
total degree 4 in (east, north, up), fitted once per DEM to exact values at nodes (Heikkinen
heights, pyproj for the DEM's CRS at the nodes only) and checked at other points against
the exact values (error below ``FRAME_TOL`` metres, else the tiles are halved). Along one
ray the kernel evaluates the frame at three nodes per 500 m of the ray (the start and end
of the ray's passage between the DEM's lowest and highest heights, and the middle) and
interpolates column, row and height quadratically in the ray parameter between them (over a
few hundred metres a straight line's height and map coordinates are quadratic to far below
a micrometre). The march then steps one DEM cell across the ground at a time (a near
vertical ray crosses few cells), a step whose ray stays above the highest DEM node it
passes over is skipped at once, one that may graze a ridge is cut into eighths, and the
first crossing from above is refined by the Illinois regula falsi to 1e-5 m in height.
"""
from __future__ import annotations

import math
import weakref
from dataclasses import dataclass

import numpy as np
from numba import njit

_A = 6378137.0
_F = 1 / 298.257223563
_E2 = _F * (2 - _F)
_B = _A * (1 - _F)
_EP2 = (_A * _A - _B * _B) / (_B * _B)


@njit(cache=True, nogil=True, inline="always")
def _lat_lon_h(x, y, z):
    """Heikkinen (1982) closed-form ECEF -> geodetic (radians, metres)."""
    p = math.sqrt(x * x + y * y)
    if p < 1e-9:
        return math.copysign(math.pi / 2, z), 0.0, abs(z) - _B
    f = 54.0 * _B * _B * z * z
    g = p * p + (1 - _E2) * z * z - _E2 * (_A * _A - _B * _B)
    c = _E2 * _E2 * f * p * p / (g * g * g)
    s = (1 + c + math.sqrt(c * c + 2 * c)) ** (1.0 / 3.0)
    k = s + 1 + 1 / s
    pp = f / (3 * k * k * g * g)
    q = math.sqrt(1 + 2 * _E2 * _E2 * pp)
    r0 = (-pp * _E2 * p / (1 + q)
          + math.sqrt(max(0.5 * _A * _A * (1 + 1 / q) - pp * (1 - _E2) * z * z / (q * (1 + q))
                          - 0.5 * pp * p * p, 0.0)))
    t = p - _E2 * r0
    u = math.sqrt(t * t + z * z)
    v = math.sqrt(t * t + (1 - _E2) * z * z)
    z0 = _B * _B * z / (_A * v)
    h = u * (1 - _B * _B / (_A * v))
    lat = math.atan((z + _EP2 * z0) / p)
    lon = math.atan2(y, x)
    return lat, lon, h


@njit(cache=True, nogil=True)
def geodetic_of_points(pts):
    """ECEF ``(n, 3)`` -> lat, lon (degrees), h ``(n, 3)``."""
    out = np.empty_like(pts)
    for i in range(pts.shape[0]):
        la, lo, h = _lat_lon_h(pts[i, 0], pts[i, 1], pts[i, 2])
        out[i, 0] = math.degrees(la)
        out[i, 1] = math.degrees(lo)
        out[i, 2] = h
    return out


@njit(cache=True, nogil=True)
def shell_hits(o, d, h):
    """``lam`` where each ray meets the surface of constant ellipsoidal height ``h``
    (ellipsoid hit, then Newton on the exact height); NaN on a miss."""
    n = o.shape[0]
    out = np.full(n, np.nan)
    a = _A + h
    b = _B + h
    for i in range(n):
        ox, oy, oz = o[i, 0] / a, o[i, 1] / a, o[i, 2] / b
        dx, dy, dz = d[i, 0] / a, d[i, 1] / a, d[i, 2] / b
        qa = dx * dx + dy * dy + dz * dz
        qb = 2 * (ox * dx + oy * dy + oz * dz)
        qc = ox * ox + oy * oy + oz * oz - 1
        disc = qb * qb - 4 * qa * qc
        if disc < 0:
            continue
        sq = math.sqrt(disc)
        l1 = (-qb - sq) / (2 * qa)
        l2 = (-qb + sq) / (2 * qa)
        lam = l1 if l1 > 0 else (l2 if l2 > 0 else np.nan)
        if math.isnan(lam):
            continue
        for _ in range(6):
            px, py, pz = o[i, 0] + lam * d[i, 0], o[i, 1] + lam * d[i, 1], o[i, 2] + lam * d[i, 2]
            la, lo, hh = _lat_lon_h(px, py, pz)
            err = hh - h
            rate = (d[i, 0] * math.cos(la) * math.cos(lo) + d[i, 1] * math.cos(la) * math.sin(lo)
                    + d[i, 2] * math.sin(la))
            lam = lam - err / rate
            if abs(err) < 1e-7:
                break
        out[i] = lam
    return out




#: the frame's largest error (m) in position and height, checked when it is fitted
FRAME_TOL = 1e-6
#: total degree of the frame's polynomials
DEGREE = 4
#: metres of ray per quadratic piece of the march
PIECE = 500.0


@njit(cache=True, nogil=True, inline="always")
def _dem(data, col, row):
    """Bilinear DEM height at fractional (column, row) (pixel centres at integers); NaN
    outside."""
    nr, nc = data.shape
    if not (row >= 0 and row <= nr - 1 and col >= 0 and col <= nc - 1):
        return np.nan
    r0 = min(max(int(math.floor(row)), 0), max(nr - 2, 0))
    c0 = min(max(int(math.floor(col)), 0), max(nc - 2, 0))
    r1 = min(r0 + 1, nr - 1)
    c1 = min(c0 + 1, nc - 1)
    wr = row - r0
    wc = col - c0
    return (data[r0, c0] * (1 - wr) * (1 - wc) + data[r0, c1] * (1 - wr) * wc
            + data[r1, c0] * wr * (1 - wc) + data[r1, c1] * wr * wc)


# ----------------------------------------------------------------------------------------
# the DEM's frame: ECEF -> (column, row, ellipsoidal height)
# ----------------------------------------------------------------------------------------
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
    grid: np.ndarray        # e0, n0, tile width, tile height, tiles east, tiles north
    ubox: np.ndarray        # (ny, nx, 2) centre and inverse half-range of ``up`` per tile
    coef: np.ndarray        # (ny, nx, terms, 3)
    error_m: float          # largest error found at the check points (m)

    def arrays(self):
        return self.origin, self.rot, self.grid, self.ubox, self.coef


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
            grid = np.array([e0, n0, we, wn, nx, ny], float)
            return DemFrame(origin, np.ascontiguousarray(rot), grid, np.ascontiguousarray(ubox),
                            np.ascontiguousarray(coef), err_m)
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
    h_lo, h_hi = _bracket_heights(terrain)
    fr = _fit_frame(terrain, h_lo - 10.0, h_hi + 10.0)
    try:
        _FRAMES[terrain] = fr
    except TypeError:
        pass
    return fr


def _bracket_heights(terrain) -> tuple[float, float]:
    """Heights of the two shells (inflated ellipsoids) that bracket the DEM: below its
    lowest and above its highest point by more than an inflated ellipsoid strays from the
    surface of constant height."""
    h_min, h_max = float(terrain.h_min), float(terrain.h_max)
    return h_min - 2.0 - 0.01 * abs(h_min), h_max + 2.0 + 0.01 * abs(h_max)


@njit(cache=True, nogil=True, inline="always")
def _frame_at(x, y, z, origin, rot, grid, ubox, coef):
    """(column, row, height) of ECEF (x, y, z) through the frame's polynomial."""
    dx, dy, dz = x - origin[0], y - origin[1], z - origin[2]
    e = rot[0, 0] * dx + rot[0, 1] * dy + rot[0, 2] * dz
    n = rot[1, 0] * dx + rot[1, 1] * dy + rot[1, 2] * dz
    u = rot[2, 0] * dx + rot[2, 1] * dy + rot[2, 2] * dz
    fe = (e - grid[0]) / grid[2]
    fn = (n - grid[1]) / grid[3]
    tx = min(max(int(math.floor(fe)), 0), int(grid[4]) - 1)
    ty = min(max(int(math.floor(fn)), 0), int(grid[5]) - 1)
    s = 2.0 * (fe - tx) - 1.0
    t = 2.0 * (fn - ty) - 1.0
    w = (u - ubox[ty, tx, 0]) * ubox[ty, tx, 1]
    c = coef[ty, tx]
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
    """``(n, 3)`` column, row, height of ECEF points ``(n, 3)`` through the frame (tests)."""
    return _frame_points(np.ascontiguousarray(pts, dtype=float), *frame.arrays())


@njit(cache=True, nogil=True)
def _frame_points(pts, origin, rot, grid, ubox, coef):
    out = np.empty_like(pts)
    for i in range(pts.shape[0]):
        out[i, 0], out[i, 1], out[i, 2] = _frame_at(pts[i, 0], pts[i, 1], pts[i, 2], origin,
                                                    rot, grid, ubox, coef)
    return out


# ----------------------------------------------------------------------------------------
# the kernel: bracket, march and regula falsi, ray by ray
# ----------------------------------------------------------------------------------------
@njit(cache=True, nogil=True, inline="always")
def _shell(ox, oy, oz, dx, dy, dz, h):
    """Entry ``lam`` of a ray into the inflated ellipsoid (a + h, b + h) (NaN: missed),
    and whether the origin is inside it."""
    a = _A + h
    b = _B + h
    px, py, pz = ox / a, oy / a, oz / b
    qx, qy, qz = dx / a, dy / a, dz / b
    qa = qx * qx + qy * qy + qz * qz
    qb = 2 * (px * qx + py * qy + pz * qz)
    qc = px * px + py * py + pz * pz - 1
    disc = qb * qb - 4 * qa * qc
    if disc < 0:
        return np.nan, qc < 0
    sq = math.sqrt(disc)
    l1 = (-qb - sq) / (2 * qa)
    l2 = (-qb + sq) / (2 * qa)
    lam = l1 if l1 > 0 else (l2 if l2 > 0 else np.nan)
    return lam, qc < 0


@njit(cache=True, nogil=True, inline="always")
def _gap(t, q, data):
    """Ray height minus DEM height at ``t`` on one quadratic piece ``q`` (9 coefficients:
    column, row, height)."""
    col = q[0] + t * (q[1] + t * q[2])
    row = q[3] + t * (q[4] + t * q[5])
    h = q[6] + t * (q[7] + t * q[8])
    return h - _dem(data, col, row)


@njit(cache=True, nogil=True)
def _may_graze(t0, t1, q, data):
    """Whether the DEM may rise above the ray between ``t0`` and ``t1`` (at most one cell
    apart across the ground): the lower end of the ray against the highest DEM node of
    the cells the step passes over (a bilinear cell never exceeds its corners)."""
    nr, nc = data.shape
    c0 = q[0] + t0 * (q[1] + t0 * q[2])
    c1 = q[0] + t1 * (q[1] + t1 * q[2])
    r0 = q[3] + t0 * (q[4] + t0 * q[5])
    r1 = q[3] + t1 * (q[4] + t1 * q[5])
    h = min(q[6] + t0 * (q[7] + t0 * q[8]), q[6] + t1 * (q[7] + t1 * q[8]))
    ra = max(int(math.floor(min(r0, r1))), 0)
    rb = min(int(math.floor(max(r0, r1))) + 1, nr - 1)
    ca = max(int(math.floor(min(c0, c1))), 0)
    cb = min(int(math.floor(max(c0, c1))) + 1, nc - 1)
    for r in range(ra, rb + 1):
        for c in range(ca, cb + 1):
            if not data[r, c] < h:
                return True
    return False


@njit(cache=True, nogil=True)
def _falsi(ta, ga, tb, gb, q, data, max_iter):
    """Illinois regula falsi on ``[ta, tb]`` (gap > 0 at ``ta``, <= 0 at ``tb``)."""
    for _ in range(max_iter):
        x = tb - gb * (tb - ta) / (gb - ga)
        gx = _gap(x, q, data)
        if not math.isfinite(gx):
            gx = 0.0
        if gx * gb < 0:
            ta, ga = tb, gb
        else:
            ga = ga / 2
        tb, gb = x, gx
        if abs(gx) < 1e-5:
            break
    return tb


@njit(cache=True, nogil=True)
def _one_ray(ox, oy, oz, dx, dy, dz, h_top, h_bot, origin, rot, grid, ubox, coef, data,
             max_iter, q):
    lt, inside = _shell(ox, oy, oz, dx, dy, dz, h_top)
    if inside:
        lt = 0.0
    lb, _ = _shell(ox, oy, oz, dx, dy, dz, h_bot)
    if not (math.isfinite(lt) and math.isfinite(lb) and lb > lt):
        return np.nan
    pieces = max(int(math.ceil((lb - lt) / PIECE)), 1)
    length = (lb - lt) / pieces
    lam = lt
    v0 = _frame_at(ox + lam * dx, oy + lam * dy, oz + lam * dz, origin, rot, grid, ubox, coef)
    g_prev = np.nan
    for p in range(pieces):
        lm = lam + 0.5 * length
        le = lam + length
        v1 = _frame_at(ox + lm * dx, oy + lm * dy, oz + lm * dz, origin, rot, grid, ubox, coef)
        v2 = _frame_at(ox + le * dx, oy + le * dy, oz + le * dz, origin, rot, grid, ubox, coef)
        for k in range(3):      # v(t) = q0 + q1 t + q2 t^2 through t = 0, 1/2, 1
            a0, a1, a2 = v0[k], v1[k], v2[k]
            q[3 * k] = a0
            q[3 * k + 1] = -3 * a0 + 4 * a1 - a2
            q[3 * k + 2] = 2 * a0 - 4 * a1 + 2 * a2
        # steps of at most one DEM cell across the ground
        move = max(abs(q[1]), abs(q[1] + 2 * q[2]), abs(q[4]), abs(q[4] + 2 * q[5]))
        n_steps = max(int(math.ceil(move)), 1)
        t_prev = 0.0
        if p == 0:
            g_prev = _gap(0.0, q, data)
        for s in range(1, n_steps + 1):
            t = s / n_steps
            g = _gap(t, q, data)
            if g_prev > 0 and g > 0 and _may_graze(t_prev, t, q, data):
                # a ridge may poke through the ray inside the step: look at eighths of it
                sa, sg = t_prev, g_prev
                for m in range(1, 8):
                    tm = t_prev + (t - t_prev) * m / 8
                    gm = _gap(tm, q, data)
                    if sg > 0 and gm <= 0:
                        return lam + length * _falsi(sa, sg, tm, gm, q, data, max_iter)
                    sa, sg = tm, gm
            if g_prev > 0 and g <= 0:
                return lam + length * _falsi(t_prev, g_prev, t, g, q, data, max_iter)
            t_prev, g_prev = t, g
        lam = le
        v0 = v2
    return np.nan


@njit(cache=True, nogil=True)
def hits(o, d, h_top, h_bot, origin, rot, grid, ubox, coef, data, max_iter):
    """``lam`` of the first crossing of every ray with the DEM from above (NaN: none)."""
    n = o.shape[0]
    out = np.empty(n)
    q = np.empty(9)
    for i in range(n):
        out[i] = _one_ray(o[i, 0], o[i, 1], o[i, 2], d[i, 0], d[i, 1], d[i, 2], h_top, h_bot,
                          origin, rot, grid, ubox, coef, data, max_iter, q)
    return out


def intersect_dem(origin, direction, terrain, max_iter: int = 40) -> np.ndarray | None:
    """ECEF ``(n, 3)`` intersections of rays ``(n, 3)`` (unit directions) with a DEM
    terrain (``data``, ``transform``, ``crs_wkt``, ``h_min``, ``h_max``); NaN on a miss.
    None when the DEM's frame cannot be fitted (the caller takes the numpy path)."""
    frame = dem_frame(terrain)
    if frame is None:
        return None
    o = np.ascontiguousarray(origin, dtype=float)
    d = np.ascontiguousarray(direction, dtype=float)
    h_bot, h_top = _bracket_heights(terrain)
    data = terrain.data
    if not (data.dtype == np.float64 and data.flags.c_contiguous):
        data = np.ascontiguousarray(data, dtype=float)
    lam = hits(o, d, h_top, h_bot, *frame.arrays(), data, int(max_iter))
    return o + lam[:, None] * d
