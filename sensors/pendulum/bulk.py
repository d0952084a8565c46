"""Compiled bulk projection of the pendulum scanner for the adjustment (numba): every
observation of every swing in one call, the parameters of each swing given as its rotations
and lever arms, with the partial derivatives of (line, element) by the parameters and the
ground coordinates.

The geometry is that of ``PendulumModel`` (docs/geometry.md): the camera vector of a ground
point ``G`` seen from fractional line ``l`` is
``cam = R_HS^T (R_PH^T R_BP^T (R_NB^T R_EN^T (G - X_ant) - u_gps) - u_sen)``, the POS and
the gimbal angles interpolated linearly at the line's time. The line is the root of the
scan-plane condition ``F(l) = nvec . cam(l)`` (``nvec = (0, f, y0)``), solved exactly
(Illinois' regula falsi inside the bracketing pair of integer lines); the element is
``k0 + f cam_x / (-cam_z) / pixel_pitch``. The partials follow from the implicit function
theorem: ``dl/dq = -(nvec . dcam/dq) / (nvec . dcam/dl)``; ``dcam/dq`` are closed form
(lever arms, rotation derivatives, the rotation chain for the ground), ``dcam/dl`` a
central difference along the line.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

from swathflow.geometry.navkernel import pos_epoch

DEG = math.pi / 180.0
#: the line step (lines) of the derivative along the line (ECEF coordinates round off at
#: 1e-9 m: a shorter step would difference rounding noise)
LINE_STEP = 1e-3
#: the root's tolerance (lines)
LINE_TOL = 1e-10


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _to_body(x, y, z, pos):
    """``R_NB^T R_EN^T (x, y, z)`` with the POS row ``pos`` (angles in degrees)."""
    la, lo = pos[3] * DEG, pos[4] * DEG
    sl, cl, so, co = math.sin(la), math.cos(la), math.sin(lo), math.cos(lo)
    e_ = -so * x + co * y
    n_ = -sl * co * x - sl * so * y + cl * z
    d_ = -cl * co * x - cl * so * y - sl * z
    x, y, z = n_, e_, d_
    h = pos[7] * DEG
    sh, ch = math.sin(h), math.cos(h)
    x, y = ch * x + sh * y, -sh * x + ch * y
    p = pos[6] * DEG
    sp, cp = math.sin(p), math.cos(p)
    x, z = cp * x - sp * z, sp * x + cp * z
    r = pos[5] * DEG
    sr, cr = math.sin(r), math.cos(r)
    y, z = cr * y + sr * z, -sr * y + cr * z
    return x, y, z


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _head(x, y, z, rbp, sw):
    """``R_PH^T R_BP^T (x, y, z)``: body to scan head (``sw`` = sin, cos of swing and
    pitch compensation)."""
    x, y, z = (x * rbp[0, 0] + y * rbp[1, 0] + z * rbp[2, 0],
               x * rbp[0, 1] + y * rbp[1, 1] + z * rbp[2, 1],
               x * rbp[0, 2] + y * rbp[1, 2] + z * rbp[2, 2])
    ss, cs, sq, cq = sw[0], sw[1], sw[2], sw[3]
    y, z = cs * y + ss * z, -ss * y + cs * z
    x, z = cq * x - sq * z, sq * x + cq * z
    return x, y, z


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _cam(x, y, z, rhs, out):
    """``R_HS^T (x, y, z)`` into ``out``."""
    for k in range(3):
        out[k] = x * rhs[0, k] + y * rhs[1, k] + z * rhs[2, k]


@njit(cache=True, nogil=True, error_model="numpy")
def _chain(line, g, cols, time, table, max_gap, rbp, rhs, ugps, usen, pos, sw, a, c, cam):
    """The camera vector ``cam`` of ``g`` from fractional ``line``, with the body vector
    minus ``u_gps`` (``a``), the head vector minus ``u_sen`` (``c``), the POS row ``pos``
    and the gimbal's sines ``sw``. False where the POS cannot be interpolated."""
    n = cols.shape[0]
    line = min(max(line, 0.0), n - 1.0)
    i = min(int(line), n - 2)
    w = line - i
    t = cols[i, 0] * (1 - w) + cols[i + 1, 0] * w
    k0 = np.searchsorted(time, t) - 1
    if pos_epoch(time, table, max_gap, t, k0, pos) < 0:
        return False
    x, y, z = _to_body(g[0] - pos[0], g[1] - pos[1], g[2] - pos[2], pos)
    a[0], a[1], a[2] = x - ugps[0], y - ugps[1], z - ugps[2]
    s = cols[i, 1] * (1 - w) + cols[i + 1, 1] * w
    q = cols[i, 2] * (1 - w) + cols[i + 1, 2] * w
    sw[0], sw[1], sw[2], sw[3] = math.sin(s), math.cos(s), math.sin(q), math.cos(q)
    x, y, z = _head(a[0], a[1], a[2], rbp, sw)
    c[0], c[1], c[2] = x - usen[0], y - usen[1], z - usen[2]
    _cam(c[0], c[1], c[2], rhs, cam)
    return True


@njit(cache=True, nogil=True, error_model="numpy")
def _condition(line, g, cols, time, table, max_gap, rbp, rhs, ugps, usen, nvec, pos, sw,
               a, c, cam):
    if not _chain(line, g, cols, time, table, max_gap, rbp, rhs, ugps, usen, pos, sw, a, c,
                  cam):
        return math.nan
    return cam[0] * nvec[0] + cam[1] * nvec[1] + cam[2] * nvec[2]


@njit(cache=True, nogil=True, error_model="numpy")
def _bracket(g, start, cols, time, table, max_gap, rbp, rhs, ugps, usen, nvec, pos, sw, a,
             c, cam):
    """The integer lines ``lo``, ``lo + 1`` (or, by bisection over the swing, ``lo``,
    ``hi``) between which ``g`` crosses the scan plane, and the condition at both:
    ``(lo, hi, f(lo), f(hi))``; ``lo`` -1 where it is not swept."""
    n = cols.shape[0]
    if math.isfinite(start):
        j = min(max(int(math.floor(start)), 0), n - 2)
        flo = _condition(j, g, cols, time, table, max_gap, rbp, rhs, ugps, usen, nvec, pos,
                         sw, a, c, cam)
        fhi = _condition(j + 1, g, cols, time, table, max_gap, rbp, rhs, ugps, usen, nvec,
                         pos, sw, a, c, cam)
        if (flo <= 0.0) != (fhi <= 0.0) and math.isfinite(flo) and math.isfinite(fhi):
            return j, j + 1, flo, fhi
    lo, hi = 0, n - 1
    flo = _condition(lo, g, cols, time, table, max_gap, rbp, rhs, ugps, usen, nvec, pos,
                     sw, a, c, cam)
    fhi = _condition(hi, g, cols, time, table, max_gap, rbp, rhs, ugps, usen, nvec, pos,
                     sw, a, c, cam)
    if not (math.isfinite(flo) and math.isfinite(fhi)) or (flo <= 0.0) == (fhi <= 0.0):
        return -1, -1, math.nan, math.nan
    while hi - lo > 1:
        mid = (lo + hi) // 2
        fm = _condition(mid, g, cols, time, table, max_gap, rbp, rhs, ugps, usen, nvec,
                        pos, sw, a, c, cam)
        if not math.isfinite(fm):
            return -1, -1, math.nan, math.nan
        if (fm <= 0.0) == (flo <= 0.0):
            lo, flo = mid, fm
        else:
            hi, fhi = mid, fm
    return lo, hi, flo, fhi


@njit(cache=True, nogil=True, error_model="numpy")
def _root(g, start, cols, time, table, max_gap, rbp, rhs, ugps, usen, nvec, pos, sw, a, c,
          cam):
    """The fractional line where ``g`` crosses the scan plane (NaN: not swept): the
    bracketing integer lines next to ``start`` (or by bisection over the swing,
    :func:`_bracket`), then Illinois' regula falsi inside them."""
    lo, hi, flo, fhi = _bracket(g, start, cols, time, table, max_gap, rbp, rhs, ugps, usen,
                                nvec, pos, sw, a, c, cam)
    if lo < 0:
        return math.nan
    xa, fa, xb, fb = float(lo), flo, float(hi), fhi
    if fa == 0.0:
        return xa
    if fb == 0.0:
        return xb
    side = 0
    x = xa
    for _ in range(100):
        xn = (xa * fb - xb * fa) / (fb - fa)
        f = _condition(xn, g, cols, time, table, max_gap, rbp, rhs, ugps, usen, nvec, pos,
                       sw, a, c, cam)
        if not math.isfinite(f):
            return math.nan
        done = abs(xn - x) < LINE_TOL or f == 0.0
        x = xn
        if done:
            break
        if (f > 0.0) == (fb > 0.0):
            xb, fb = xn, f
            if side == -1:
                fa *= 0.5
            side = -1
        else:
            xa, fa = xn, f
            if side == 1:
                fb *= 0.5
            side = 1
        if xb - xa < LINE_TOL:
            break
    return x


@njit(cache=True, nogil=True, error_model="numpy")
def _smooth_piece(line, cols, time):
    """The ends of the difference along the line at ``line``: ``LINE_STEP`` either side,
    inside the piece where the camera vector is smooth (between the line centres and the
    POS epochs around it, where the linear interpolations kink); one-sided next to a kink."""
    j = min(int(line), cols.shape[0] - 2)
    t0, t1 = cols[j, 0], cols[j + 1, 0]
    t = t0 + (line - j) * (t1 - t0)
    lo, hi = float(j), j + 1.0
    k = np.searchsorted(time, t, side="right") - 1
    if 0 <= k < time.shape[0] and time[k] > t0:
        lo = max(lo, j + (time[k] - t0) / (t1 - t0))
    if 0 <= k + 1 < time.shape[0] and time[k + 1] < t1:
        hi = min(hi, j + (time[k + 1] - t0) / (t1 - t0))
    lm, lp = max(line - LINE_STEP, lo), min(line + LINE_STEP, hi)
    if lp - lm < LINE_STEP:              # next to a kink: the side with room
        if hi - line > line - lo:
            lm, lp = line, min(line + LINE_STEP, hi)
        else:
            lm, lp = max(line - LINE_STEP, lo), line
    return lm, lp


@njit(cache=True, nogil=True, error_model="numpy")
def project(points, image, start, cols_all, col_off, time_all, table_all, pos_off, pos_of,
            max_gap, rbp, rhs, ugps, usen, drbp, drhs, optics, partials, out, d_par,
            d_ground):
    """Image coordinates (``out`` (n, 2), line and element, NaN where not seen or behind
    the camera) of ``points`` (n, 3) in the swings ``image`` (n,), each starting near line
    ``start`` (NaN: search the swing). Per swing ``m``: its line table rows
    ``cols_all[col_off[m]:col_off[m + 1]]`` (time, swing, pitch_comp in radians), its POS
    ``pos_of[m]`` (rows ``pos_off[p]:pos_off[p + 1]`` of ``time_all``, ``table_all``),
    ``max_gap``, ``R_BP``, ``R_HS`` (3, 3), ``u_gps``, ``u_sen``, the derivatives of
    ``R_BP`` and ``R_HS`` by their three angles (radians, (3, 3, 3)) and ``optics``
    (k0, pixel pitch, y0, f). With ``partials``: ``d_par`` (n, 2, 12) by u_gps, u_sen,
    opk_sen, opk_pos (degrees), ``d_ground`` (n, 2, 3) by ECEF X, Y, Z."""
    pos = np.empty(8)
    sw = np.empty(4)
    a, c, cam = np.empty(3), np.empty(3), np.empty(3)
    a2, c2, cp, cm = np.empty(3), np.empty(3), np.empty(3), np.empty(3)
    dq = np.empty((15, 3))
    dl, e = np.empty(3), np.empty(3)
    nvec = np.empty(3)
    for i in range(points.shape[0]):
        m = image[i]
        cols = cols_all[col_off[m]:col_off[m + 1]]
        p = pos_of[m]
        time = time_all[pos_off[p]:pos_off[p + 1]]
        table = table_all[pos_off[p]:pos_off[p + 1]]
        k0, pp, y0, f = optics[m, 0], optics[m, 1], optics[m, 2], optics[m, 3]
        nvec[0], nvec[1], nvec[2] = 0.0, f, y0
        g = points[i]
        out[i, 0] = math.nan
        out[i, 1] = math.nan
        if not (math.isfinite(g[0]) and math.isfinite(g[1]) and math.isfinite(g[2])):
            continue
        line = _root(g, start[i], cols, time, table, max_gap[m], rbp[m], rhs[m], ugps[m],
                     usen[m], nvec, pos, sw, a, c, cam)
        if not math.isfinite(line):
            continue
        if not _chain(line, g, cols, time, table, max_gap[m], rbp[m], rhs[m], ugps[m],
                      usen[m], pos, sw, a, c, cam) or not cam[2] < 0.0:
            continue
        scale = f / pp
        out[i, 0] = line
        out[i, 1] = k0 + scale * cam[0] / (-cam[2])
        if not partials:
            continue
        lm, lp = _smooth_piece(line, cols, time)
        okp = _chain(lp, g, cols, time, table, max_gap[m], rbp[m], rhs[m], ugps[m],
                     usen[m], pos, sw, a2, c2, cp)
        okm = _chain(lm, g, cols, time, table, max_gap[m], rbp[m], rhs[m], ugps[m],
                     usen[m], pos, sw, a2, c2, cm)
        _chain(line, g, cols, time, table, max_gap[m], rbp[m], rhs[m], ugps[m], usen[m],
               pos, sw, a, c, cam)
        if not (okp and okm) or lp <= lm:
            out[i, 0] = math.nan
            out[i, 1] = math.nan
            continue
        for k in range(3):
            dl[k] = (cp[k] - cm[k]) / (lp - lm)
        # dcam/dq: rows 0-2 u_gps, 3-5 u_sen, 6-8 opk_sen, 9-11 opk_pos, 12-14 ground
        R, H = rbp[m], rhs[m]
        for k in range(3):
            e[0], e[1], e[2] = 0.0, 0.0, 0.0
            e[k] = 1.0
            x, y, z = _head(e[0], e[1], e[2], R, sw)
            _cam(-x, -y, -z, H, dq[k])
            for b in range(3):
                dq[3 + k, b] = -H[k, b]
            D = drhs[m, k]
            for b in range(3):
                dq[6 + k, b] = (c[0] * D[0, b] + c[1] * D[1, b] + c[2] * D[2, b]) * DEG
            D = drbp[m, k]
            x = a[0] * D[0, 0] + a[1] * D[1, 0] + a[2] * D[2, 0]
            y = a[0] * D[0, 1] + a[1] * D[1, 1] + a[2] * D[2, 1]
            z = a[0] * D[0, 2] + a[1] * D[1, 2] + a[2] * D[2, 2]
            ss, cs, sq, cq = sw[0], sw[1], sw[2], sw[3]
            y, z = cs * y + ss * z, -ss * y + cs * z
            x, z = cq * x - sq * z, sq * x + cq * z
            _cam(x * DEG, y * DEG, z * DEG, H, dq[9 + k])
            x, y, z = _to_body(e[0], e[1], e[2], pos)
            x, y, z = _head(x, y, z, R, sw)
            _cam(x, y, z, H, dq[12 + k])
        fl = dl[0] * nvec[0] + dl[1] * nvec[1] + dl[2] * nvec[2]
        inv_z = 1.0 / cam[2]
        for q in range(15):
            dline = -(dq[q, 0] * nvec[0] + dq[q, 1] * nvec[1] + dq[q, 2] * nvec[2]) / fl
            dx = dq[q, 0] + dl[0] * dline
            dz = dq[q, 2] + dl[2] * dline
            de = -scale * (dx * inv_z - cam[0] * dz * inv_z * inv_z)
            if q < 12:
                d_par[i, 0, q] = dline
                d_par[i, 1, q] = de
            else:
                d_ground[i, 0, q - 12] = dline
                d_ground[i, 1, q - 12] = de
