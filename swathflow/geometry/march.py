"""Compiled ray / DEM intersection (numba): the bracketing, the march and the refinement
of :func:`swathflow.geometry.intersect.intersect` for a DEM in one kernel, without pyproj
per point.

Per ray: the shells (inflated ellipsoids) just above the DEM's highest and below its lowest
point bracket the ray's passage; the DEM's frame (:mod:`swathflow.geometry.demframe`:
ECEF -> DEM column, row and ellipsoidal height, fitted once per DEM) is evaluated at three
nodes per 500 m of that passage, and column, row and height are interpolated quadratically
in the ray parameter between them (over a few hundred metres a straight line's height and
map coordinates are quadratic to far below a micrometre). The highest and lowest DEM node
of the blocks under the ray's path narrow the passage to the heights where the terrain
can be; there the march steps at most one DEM cell across the ground, a step whose ends
are above the DEM but may graze a ridge (a DEM node under it reaches the ray) is cut into
eighths, and the first crossing from above is refined by Newton's method on the bilinear
DEM, kept inside its bracket, to 1e-5 m in height.
"""
from __future__ import annotations

import math

import numpy as np

from numba import njit

from swathflow.geometry.demframe import BLOCK, dem_frame, poly, poly3, tile_of
from swathflow.geometry.geodesy_kernel import WGS84_A, WGS84_B, lat_lon_h

@njit(cache=True, nogil=True)
def shell_hits(o, d, h):
    """``lam`` where each ray meets the surface of constant ellipsoidal height ``h``
    (ellipsoid hit, then Newton on the exact height); NaN on a miss."""
    n = o.shape[0]
    out = np.full(n, np.nan)
    a = WGS84_A + h
    b = WGS84_B + h
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
            la, lo, hh = lat_lon_h(px, py, pz)
            err = hh - h
            rate = (d[i, 0] * math.cos(la) * math.cos(lo) + d[i, 1] * math.cos(la) * math.sin(lo)
                    + d[i, 2] * math.sin(la))
            lam = lam - err / rate
            if abs(err) < 1e-7:
                break
        out[i] = lam
    return out


#: metres of ray per quadratic piece of the march
PIECE = 500.0


@njit(cache=True, nogil=True)
def _shell(ox, oy, oz, dx, dy, dz, h):
    """Entry ``lam`` of a ray into the inflated ellipsoid (a + h, b + h) (NaN: missed),
    and whether the origin is inside it."""
    a = WGS84_A + h
    b = WGS84_B + h
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
    """Ray height minus bilinear DEM height at ``t`` on a quadratic piece ``q`` (column,
    row, height: 3 coefficients each), and its derivative in ``t``; NaN off the DEM."""
    col = q[0] + t * (q[1] + t * q[2])
    row = q[3] + t * (q[4] + t * q[5])
    nr, nc = data.shape
    if not (row >= 0 and row <= nr - 1 and col >= 0 and col <= nc - 1):
        return np.nan, np.nan
    r0 = min(int(row), nr - 2)
    c0 = min(int(col), nc - 2)
    wr = row - r0
    wc = col - c0
    a, b = data[r0, c0], data[r0, c0 + 1]
    c, d = data[r0 + 1, c0], data[r0 + 1, c0 + 1]
    top = a + (b - a) * wc
    bot = c + (d - c) * wc
    dem = top + (bot - top) * wr
    dcol = (b - a) + ((d - c) - (b - a)) * wr
    drow = bot - top
    h = q[6] + t * (q[7] + t * q[8])
    slope = (q[7] + 2 * t * q[8]) - dcol * (q[1] + 2 * t * q[2]) - drow * (q[4] + 2 * t * q[5])
    return h - dem, slope


@njit(cache=True, nogil=True, _nrt=False)
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


@njit(cache=True, nogil=True, _nrt=False)
def _refine(ta, ga, tb, gb, q, data, max_iter):
    """The crossing in ``[ta, tb]`` (gap > 0 at ``ta``, <= 0 at ``tb``) to 1e-5 m: Newton
    steps on the bilinear DEM from the chord's root, bisection where one leaves the
    bracket."""
    t = tb - gb * (tb - ta) / (gb - ga)
    for _ in range(max_iter):
        g, slope = _gap(t, q, data)
        if not math.isfinite(g) or abs(g) < 1e-5:
            break
        if g > 0:
            ta = t
        else:
            tb = t
        tn = t - g / slope
        t = tn if (tn > ta and tn < tb) else 0.5 * (ta + tb)
    return t


@njit(cache=True, nogil=True)
def _t_at_height(q, h):
    """``t`` where the piece's (descending) height is ``h`` (one Newton step from the chord:
    the quadratic term is a curvature of millimetres)."""
    t = (h - q[6]) / q[7]
    return t - (q[6] + t * (q[7] + t * q[8]) - h) / (q[7] + 2 * t * q[8])


@njit(cache=True, nogil=True, inline="always")
def _narrow(q, blocks, nr, nc):
    """The part ``[t0, t1]`` of a piece where the ray is between the highest and the
    lowest DEM node of the blocks under its path (no crossing can lie outside it); the
    whole piece where the path is long or a node is NaN; empty off the DEM."""
    if not (q[7] < 0 and q[7] + 2 * q[8] < 0):
        return 0.0, 1.0                 # not descending all along
    c0, c1 = q[0], q[0] + q[1] + q[2]
    r0, r1 = q[3], q[3] + q[4] + q[5]
    ca, cb = int(math.floor(min(c0, c1))) - 1, int(math.floor(max(c0, c1))) + 1
    ra, rb = int(math.floor(min(r0, r1))) - 1, int(math.floor(max(r0, r1))) + 1
    if cb < 0 or ca > nc - 2 or rb < 0 or ra > nr - 2:
        return 1.0, 0.0
    ca, cb = max(ca, 0) // BLOCK, min(cb, nc - 2) // BLOCK
    ra, rb = max(ra, 0) // BLOCK, min(rb, nr - 2) // BLOCK
    if (cb - ca + 1) * (rb - ra + 1) > 9:
        return 0.0, 1.0
    hi, lo = -np.inf, np.inf
    for r in range(ra, rb + 1):
        for c in range(ca, cb + 1):
            hi = max(hi, blocks[r, c, 0])
            lo = min(lo, blocks[r, c, 1])
    if not (math.isfinite(hi) and math.isfinite(lo)):
        return 0.0, 1.0
    return max(_t_at_height(q, hi + 1e-3), 0.0), min(_t_at_height(q, lo - 1e-3), 1.0)


@njit(cache=True, nogil=True, _nrt=False)
def _march_piece(q, data, blocks, g_prev, max_iter):
    """The first crossing from above on one quadratic piece (``t`` in [0, 1], NaN: none)
    and the gap at its end: steps of at most one cell across the ground between the
    heights of the highest and the lowest DEM node under the path."""
    nr, nc = data.shape
    t0, t1 = _narrow(q, blocks, nr, nc)
    if t0 >= t1:
        return np.nan, _gap(1.0, q, data)[0]
    if t0 > 0:
        g_prev = _gap(t0, q, data)[0]
    move = max(abs(q[1]), abs(q[1] + 2 * q[2]), abs(q[4]), abs(q[4] + 2 * q[5])) * (t1 - t0)
    n_steps = max(int(math.ceil(move)), 1)
    t_prev = t0
    for k in range(1, n_steps + 1):
        t = t0 + (t1 - t0) * k / n_steps
        g = _gap(t, q, data)[0]
        if ((g_prev > 0 and g > 0 and _may_graze(t_prev, t, q, data))
                or (math.isnan(g_prev) and g <= 0)):
            # a ridge may poke through the ray inside the step, or the ray comes in over
            # nodata or the DEM's edge below the surface: look at eighths of the step
            sa, sg = t_prev, g_prev
            for m in range(1, 8):
                tm = t_prev + (t - t_prev) * m / 8
                gm = _gap(tm, q, data)[0]
                if sg > 0 and gm <= 0:
                    return _refine(sa, sg, tm, gm, q, data, max_iter), gm
                sa, sg = tm, gm
        if g_prev > 0 and g <= 0:
            return _refine(t_prev, g_prev, t, g, q, data, max_iter), g
        t_prev, g_prev = t, g
    return np.nan, (g_prev if t1 >= 1.0 else _gap(1.0, q, data)[0])


@njit(cache=True, nogil=True)
def _quadratic(a0, a1, a2):
    """Coefficients of v(t) = q0 + q1 t + q2 t^2 through (0, a0), (1/2, a1), (1, a2)."""
    return a0, -3 * a0 + 4 * a1 - a2, 2 * a0 - 4 * a1 + 2 * a2


@njit(cache=True, nogil=True, inline="always")
def _piece(e, n, u, de, dn, du, l0, length, grid, ubox, coef):
    """The quadratic piece of the ray from ``l0`` over ``length`` (local ENU origin and
    direction ``e, n, u`` and ``de, dn, du``): 9 coefficients, 3 each for column, row and
    height in ``t`` in [0, 1]."""
    l2 = l0 + length
    ty, tx, s0, t0, w0 = tile_of(e + l0 * de, n + l0 * dn, u + l0 * du, grid, ubox)
    ty2, tx2, s2, t2, w2 = tile_of(e + l2 * de, n + l2 * dn, u + l2 * du, grid, ubox)
    if ty == ty2 and tx == tx2:         # the tile coordinates are linear along the ray
        c0, r0, h0, c1, r1, h1, c2, r2, h2 = poly3(
            coef[ty, tx], s0, t0, w0, 0.5 * (s0 + s2), 0.5 * (t0 + t2), 0.5 * (w0 + w2),
            s2, t2, w2)
    else:
        lm = l0 + 0.5 * length
        ty1, tx1, s1, t1, w1 = tile_of(e + lm * de, n + lm * dn, u + lm * du, grid, ubox)
        c0, r0, h0 = poly(coef[ty, tx], s0, t0, w0)
        c1, r1, h1 = poly(coef[ty1, tx1], s1, t1, w1)
        c2, r2, h2 = poly(coef[ty2, tx2], s2, t2, w2)
    return _quadratic(c0, c1, c2) + _quadratic(r0, r1, r2) + _quadratic(h0, h1, h2)


@njit(cache=True, nogil=True, _nrt=False)
def _one_ray(o, d, h_top, h_bot, origin, rot, grid, ubox, coef, blocks, data, max_iter):
    """``lam`` of the first crossing of the ray ``o + lam d`` (3-tuples, ``d`` a unit
    vector) with the DEM from above; NaN where none."""
    lt, inside = _shell(o[0], o[1], o[2], d[0], d[1], d[2], h_top)
    if inside:
        lt = 0.0
    lb, _ = _shell(o[0], o[1], o[2], d[0], d[1], d[2], h_bot)
    if not (math.isfinite(lt) and math.isfinite(lb) and lb > lt):
        return np.nan
    x, y, z = o[0] - origin[0], o[1] - origin[1], o[2] - origin[2]
    e = rot[0, 0] * x + rot[0, 1] * y + rot[0, 2] * z
    n = rot[1, 0] * x + rot[1, 1] * y + rot[1, 2] * z
    u = rot[2, 0] * x + rot[2, 1] * y + rot[2, 2] * z
    de = rot[0, 0] * d[0] + rot[0, 1] * d[1] + rot[0, 2] * d[2]
    dn = rot[1, 0] * d[0] + rot[1, 1] * d[1] + rot[1, 2] * d[2]
    du = rot[2, 0] * d[0] + rot[2, 1] * d[1] + rot[2, 2] * d[2]
    pieces = max(int(math.ceil((lb - lt) / PIECE)), 1)
    length = (lb - lt) / pieces
    g_prev = np.nan
    for p in range(pieces):
        l0 = lt + p * length
        q = _piece(e, n, u, de, dn, du, l0, length, grid, ubox, coef)
        if p == 0:
            g_prev = _gap(0.0, q, data)[0]
        t, g_prev = _march_piece(q, data, blocks, g_prev, max_iter)
        if math.isfinite(t):
            return l0 + length * t
    return np.nan


@njit(cache=True, nogil=True, _nrt=False)
def hits(o, d, h_top, h_bot, origin, rot, grid, ubox, coef, blocks, data, max_iter, out):
    """ECEF points ``out`` where the rays (``d`` any length) first meet the DEM from above
    (NaN: never)."""
    for i in range(o.shape[0]):
        norm = math.sqrt(d[i, 0] ** 2 + d[i, 1] ** 2 + d[i, 2] ** 2)
        u = (d[i, 0] / norm, d[i, 1] / norm, d[i, 2] / norm)
        p = (o[i, 0], o[i, 1], o[i, 2])
        lam = _one_ray(p, u, h_top, h_bot, origin, rot, grid, ubox, coef, blocks, data,
                       max_iter)
        for k in range(3):
            out[i, k] = p[k] + lam * u[k]
    return out


def intersect_dem(origin, direction, terrain, max_iter: int = 40) -> np.ndarray | None:
    """ECEF ``(n, 3)`` intersections of rays ``(n, 3)`` with a DEM terrain (``data``,
    ``transform``, ``crs_wkt``, ``h_min``, ``h_max``); NaN on a miss. None when the DEM's
    frame cannot be fitted (the caller takes the numpy path)."""
    frame = dem_frame(terrain)
    if frame is None:
        return None
    o = np.ascontiguousarray(origin, dtype=float)
    d = np.ascontiguousarray(direction, dtype=float)
    data = terrain.data
    if not (data.dtype == np.float64 and data.flags.c_contiguous):
        data = np.ascontiguousarray(data, dtype=float)
    h_bot, h_top = frame.bracket
    return hits(o, d, h_top, h_bot, *frame.arrays(), data, int(max_iter), np.empty_like(o))
