"""Compiled ground-to-image solve of the push-broom camera for the adjustment (numba): every
observation of every image in one call, each image's parameters given as its lever arm,
boresight rotation, viewing-tangent cubics and orientation-fix corrections.

The geometry is that of ``PushbroomModel`` (docs/geometry.md, push-broom section): the
camera vector of a ground point ``G`` seen from fractional line ``l`` (time ``t`` linear
between the line times) is
``g = R_BS^T (R_opk(d_opk(t))^T R_NB^T R_EN^T (G - X_ant - R_EN d_ned(t)) - u_gps)``, the POS
interpolated linearly at ``t``, the fix corrections linear between fixes and held outside
them. The point is seen at the line and element where ``(g_x / -g_z - tan_psi_x(s),
g_y / -g_z - tan_psi_y(s)) = 0``, solved jointly in (line, element) by Newton (the
derivative along the line a difference inside the piece where the interpolations are
smooth: with a noisy POS the slope jumps at every epoch), from the caller's start or from the line
bracketed by the viewing plane of the middle element. The kernel returns, per point, the
line, the element, the 2x2 Jacobian of the conditions there and the POS row at its time:
the partial derivatives follow in numpy
(:class:`~swathflow.sensors.pushbroom.projection.PushbroomProjector`).
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

from swathflow.geometry.navkernel import pos_epoch
from swathflow.sensors.pushbroom.rays import fix_at

#: the line step of the derivative along the line (lines; 0.01 line is a few mm of
#: flight: ECEF rounding, 1e-9 m, stays far below it)
LINE_STEP = 1e-2
#: Newton's tolerance on the line (lines) and the element (elements): the conditions are
#: exact to about 1e-8 px (ECEF rounding); the step after one this short is far shorter
TOL = 1e-7
#: Newton iterations at most
MAX_ITER = 30


@njit(cache=True, nogil=True, error_model="numpy")
def camera_vector(line, g, ltime, time, table, max_gap, ft, dned, dopk, rbs, u, pos, out):
    """The camera vector ``out`` of ``g`` from fractional ``line`` (extrapolated linearly
    beyond the first and last line) and the POS row ``pos`` at its time; the time, or NaN
    where the POS cannot be interpolated there."""
    n = ltime.shape[0]
    j = min(max(int(math.floor(line)), 0), n - 2)
    t = ltime[j] + (ltime[j + 1] - ltime[j]) * (line - j)
    k = np.searchsorted(time, t) - 1
    if pos_epoch(time, table, max_gap, t, k, pos) < 0:
        return math.nan
    la, lo = pos[3] * math.pi / 180.0, pos[4] * math.pi / 180.0
    sl, cl, so, co = math.sin(la), math.cos(la), math.sin(lo), math.cos(lo)
    x, y, z = g[0] - pos[0], g[1] - pos[1], g[2] - pos[2]
    # R_EN^T: north, east, down
    x, y, z = (-sl * co * x - sl * so * y + cl * z, -so * x + co * y,
               -cl * co * x - cl * so * y - sl * z)
    if ft.shape[0]:
        x -= fix_at(ft, dned, t, 0)
        y -= fix_at(ft, dned, t, 1)
        z -= fix_at(ft, dned, t, 2)
    # R_NB^T = Rx(roll)^T Ry(pitch)^T Rz(heading)^T
    h = pos[7] * math.pi / 180.0
    sh, ch = math.sin(h), math.cos(h)
    x, y = ch * x + sh * y, -sh * x + ch * y
    p = pos[6] * math.pi / 180.0
    sp, cp = math.sin(p), math.cos(p)
    x, z = cp * x - sp * z, sp * x + cp * z
    r = pos[5] * math.pi / 180.0
    sr, cr = math.sin(r), math.cos(r)
    y, z = cr * y + sr * z, -sr * y + cr * z
    if ft.shape[0]:
        # R_opk(d_opk)^T = Rz(kappa)^T Ry(phi)^T Rx(omega)^T
        om, ph, ka = fix_at(ft, dopk, t, 0), fix_at(ft, dopk, t, 1), fix_at(ft, dopk, t, 2)
        so_, co_ = math.sin(om), math.cos(om)
        y, z = co_ * y + so_ * z, -so_ * y + co_ * z
        sp_, cp_ = math.sin(ph), math.cos(ph)
        x, z = cp_ * x - sp_ * z, sp_ * x + cp_ * z
        sk, ck = math.sin(ka), math.cos(ka)
        x, y = ck * x + sk * y, -sk * x + ck * y
    x, y, z = x - u[0], y - u[1], z - u[2]
    for c in range(3):
        out[c] = rbs[0, c] * x + rbs[1, c] * y + rbs[2, c] * z
    return t


@njit(cache=True, nogil=True, error_model="numpy")
def _smooth_piece(line, ltime, time, ft):
    """The ends (lines) of the difference along the line at ``line``: ``LINE_STEP`` either
    side, inside the piece where the camera vector is smooth (between the line times, the
    POS epochs and the fix times around it, where the linear interpolations kink); wider
    across a kink only when the piece is too short to difference over."""
    n = ltime.shape[0]
    j = min(max(int(math.floor(line)), 0), n - 2)
    t0, t1 = ltime[j], ltime[j + 1]
    t = t0 + (t1 - t0) * (line - j)
    lo_t, hi_t = -math.inf, math.inf
    if line >= 0.0:
        lo_t = t0
    if line <= n - 1.0:
        hi_t = t1
    k = np.searchsorted(time, t, side="right") - 1
    if 0 <= k < time.shape[0]:
        lo_t = max(lo_t, time[k])
    if 0 <= k + 1 < time.shape[0]:
        hi_t = min(hi_t, time[k + 1])
    f = np.searchsorted(ft, t, side="right") - 1
    if 0 <= f < ft.shape[0]:
        lo_t = max(lo_t, ft[f])
    if 0 <= f + 1 < ft.shape[0]:
        hi_t = min(hi_t, ft[f + 1])
    lo = j + (lo_t - t0) / (t1 - t0)
    hi = j + (hi_t - t0) / (t1 - t0)
    lm, lp = max(line - LINE_STEP, lo), min(line + LINE_STEP, hi)
    if lp - lm < 0.1 * LINE_STEP:          # a sliver between two kinks: difference across
        lm, lp = line - LINE_STEP, line + LINE_STEP
    return lm, lp


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _tangents(coef, s):
    """tan_psi_x, tan_psi_y and their derivatives by the element at element ``s`` (the
    cubic of its interval; the end intervals extrapolate)."""
    nel = coef.shape[1]
    e = min(max(math.floor(s), 0.0), nel - 1.0)
    k = int(e)
    v = s - e
    tx = coef[0, k] + v * (coef[1, k] + v * (coef[2, k] + v * coef[3, k]))
    ty = coef[4, k] + v * (coef[5, k] + v * (coef[6, k] + v * coef[7, k]))
    dtx = coef[1, k] + v * (2.0 * coef[2, k] + 3.0 * v * coef[3, k])
    dty = coef[5, k] + v * (2.0 * coef[6, k] + 3.0 * v * coef[7, k])
    return tx, ty, dtx, dty


@njit(cache=True, nogil=True, error_model="numpy")
def _along(line, g, ltime, time, table, max_gap, ft, dned, dopk, rbs, u, tx_mid, pos, cam):
    """The along-track condition of the middle element at ``line`` (NaN: no POS there or
    the point behind the camera)."""
    t = camera_vector(line, g, ltime, time, table, max_gap, ft, dned, dopk, rbs, u, pos, cam)
    if not (math.isfinite(t) and cam[2] < 0.0):
        return math.nan
    return cam[0] / -cam[2] - tx_mid


@njit(cache=True, nogil=True, error_model="numpy")
def _first_guess(g, ltime, time, table, max_gap, ft, dned, dopk, rbs, u, coef, tx_mid, pos,
                 cam):
    """A start (line, element): the integer lines between which the viewing plane of the
    middle element passes ``g`` (bisection), the line interpolated between them and the
    element whose nominal tan_psi_y points at it; the nearer end when the plane does not
    pass it inside the image (Newton then says whether the point is seen). NaN line where
    neither end can be evaluated."""
    n = ltime.shape[0]
    lo, hi = 0, n - 1
    flo = _along(lo, g, ltime, time, table, max_gap, ft, dned, dopk, rbs, u, tx_mid, pos, cam)
    fhi = _along(hi, g, ltime, time, table, max_gap, ft, dned, dopk, rbs, u, tx_mid, pos, cam)
    if not (math.isfinite(flo) and math.isfinite(fhi)):
        return math.nan, math.nan
    if (flo <= 0.0) == (fhi <= 0.0):
        line = 0.0 if abs(flo) < abs(fhi) else n - 1.0
    else:
        while hi - lo > 1:
            mid = (lo + hi) // 2
            fm = _along(mid, g, ltime, time, table, max_gap, ft, dned, dopk, rbs, u, tx_mid,
                        pos, cam)
            if not math.isfinite(fm):
                return math.nan, math.nan
            if (fm <= 0.0) == (flo <= 0.0):
                lo, flo = mid, fm
            else:
                hi, fhi = mid, fm
        line = lo + flo / (flo - fhi)
    camera_vector(line, g, ltime, time, table, max_gap, ft, dned, dopk, rbs, u, pos, cam)
    nel = coef.shape[1]
    ty0, ty1 = coef[4, 0], coef[4, nel - 1]
    s = (cam[1] / -cam[2] - ty0) / (ty1 - ty0) * (nel - 1)
    return line, s


@njit(cache=True, nogil=True, error_model="numpy")
def _newton(line, s, g, ltime, time, table, max_gap, ft, dned, dopk, rbs, u, coef, pos, cam,
            cp, cm, jac):
    """Newton jointly in (line, element) from ``(line, s)``: the solution and whether it
    converged, with the Jacobian of the conditions there in ``jac`` (2, 2)."""
    n = ltime.shape[0]
    for _ in range(MAX_ITER):
        lm, lp = _smooth_piece(line, ltime, time, ft)
        tp = camera_vector(lp, g, ltime, time, table, max_gap, ft, dned, dopk, rbs, u, pos, cp)
        tm = camera_vector(lm, g, ltime, time, table, max_gap, ft, dned, dopk, rbs, u, pos, cm)
        t = camera_vector(line, g, ltime, time, table, max_gap, ft, dned, dopk, rbs, u, pos,
                          cam)
        if not (math.isfinite(t) and math.isfinite(tp) and math.isfinite(tm)) \
                or not cam[2] < 0.0:
            return line, s, False
        tx, ty, dtx, dty = _tangents(coef, s)
        jac[0, 0] = (cp[0] / -cp[2] - cm[0] / -cm[2]) / (lp - lm)
        jac[1, 0] = (cp[1] / -cp[2] - cm[1] / -cm[2]) / (lp - lm)
        jac[0, 1], jac[1, 1] = -dtx, -dty
        f0, f1 = cam[0] / -cam[2] - tx, cam[1] / -cam[2] - ty
        det = jac[0, 0] * jac[1, 1] - jac[0, 1] * jac[1, 0]
        if det == 0.0 or not math.isfinite(det):
            return line, s, False
        # a step of more than the image is a miss far away: limit it (Newton then walks
        # there or the final test rejects the point)
        d_l = min(max((jac[1, 1] * f0 - jac[0, 1] * f1) / det, -float(n)), float(n))
        d_s = (jac[0, 0] * f1 - jac[1, 0] * f0) / det
        line -= d_l
        s -= d_s
        if abs(d_l) < TOL and abs(d_s) < TOL:
            return line, s, True
    return line, s, False


@njit(cache=True, nogil=True, error_model="numpy")
def project(points, image, start, ltime_all, line_off, time_all, table_all, pos_off, pos_of,
            max_gap, ft, dned, dopk, rbs, ugps, coef_all, coef_off, tx_mid, out, jac,
            times, pos_out):
    """Image coordinates (``out`` (n, 2): line, element; NaN where not seen or behind the
    camera; elements not clipped to the CCD) of ``points`` (n, 3) in the images ``image``
    (n,), each from ``start`` (n, 2) (NaN: search the image). Per image ``m``: its line
    times ``ltime_all[line_off[m]:line_off[m + 1]]``, its POS ``pos_of[m]`` (rows
    ``pos_off[p]:pos_off[p + 1]`` of ``time_all``, ``table_all``), ``max_gap[m]``, the fix
    times ``ft`` with ``dned[m]`` (m) and ``dopk[m]`` (rad), ``rbs[m]`` (R_BS), ``ugps[m]``,
    the viewing tangents' cubics ``coef_all[:, coef_off[m]:coef_off[m + 1]]`` (8, elements)
    and ``tx_mid[m]`` (tan_psi_x of the middle element). Also per point: ``jac`` (n, 2, 2)
    the Jacobian of the conditions in (line, element), ``times`` (n,) the line's time and
    ``pos_out`` (n, 8) the POS row there."""
    pos = np.empty(8)
    cam, cp, cm = np.empty(3), np.empty(3), np.empty(3)
    for i in range(points.shape[0]):
        m = image[i]
        ltime = ltime_all[line_off[m]:line_off[m + 1]]
        p = pos_of[m]
        time = time_all[pos_off[p]:pos_off[p + 1]]
        table = table_all[pos_off[p]:pos_off[p + 1]]
        coef = coef_all[:, coef_off[m]:coef_off[m + 1]]
        g = points[i]
        n = ltime.shape[0]
        out[i, 0] = math.nan
        out[i, 1] = math.nan
        if n < 2 or not (math.isfinite(g[0]) and math.isfinite(g[1]) and math.isfinite(g[2])):
            continue
        line, s = start[i, 0], start[i, 1]
        if not (math.isfinite(line) and math.isfinite(s)):
            line, s = _first_guess(g, ltime, time, table, max_gap[m], ft, dned[m], dopk[m],
                                   rbs[m], ugps[m], coef, tx_mid[m], pos, cam)
            if not math.isfinite(line):
                continue
        line, s, ok = _newton(line, s, g, ltime, time, table, max_gap[m], ft, dned[m],
                              dopk[m], rbs[m], ugps[m], coef, pos, cam, cp, cm, jac[i])
        if not ok or not (-1e-6 <= line <= n - 1 + 1e-6):
            continue
        t = camera_vector(line, g, ltime, time, table, max_gap[m], ft, dned[m], dopk[m],
                          rbs[m], ugps[m], pos, cam)
        if not (math.isfinite(t) and cam[2] < 0.0):
            continue
        out[i, 0] = line
        out[i, 1] = s
        times[i] = t
        for c in range(8):
            pos_out[i, c] = pos[c]
