"""Compiled rays of the push-broom camera (numba): ``PushbroomModel.ray`` one point at a time
(the line's time, the POS there, the orientation fixes' corrections interpolated in time and
held outside them, ``R_EN R_NB R_opk(d_opk) R_BS (tan_psi_x, tan_psi_y, -1)`` with the
viewing tangents' cubic per element)."""
from __future__ import annotations

import math

import numpy as np

from swathflow.geometry.navkernel import body_to_ecef, line_at, nav_trig, pos_from
from numba import njit


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def fix_at(ft, val, t, c):
    """Column ``c`` of the fix corrections ``val`` at time ``t`` (``np.interp``: linear
    between fixes, held outside them)."""
    n = ft.shape[0]
    if t <= ft[0]:
        return val[0, c]
    if t >= ft[n - 1]:
        return val[n - 1, c]
    k = 0
    while ft[k + 1] < t:
        k += 1
    w = (t - ft[k]) / (ft[k + 1] - ft[k])
    return val[k, c] + (val[k + 1, c] - val[k, c]) * w


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _opk(x, y, z, om, ph, ka):
    """``R_opk(omega, phi, kappa) (x, y, z)`` = Rx(omega) Ry(phi) Rz(kappa) applied."""
    x, y = math.cos(ka) * x - math.sin(ka) * y, math.sin(ka) * x + math.cos(ka) * y
    x, z = math.cos(ph) * x + math.sin(ph) * z, -math.sin(ph) * x + math.cos(ph) * z
    y, z = math.cos(om) * y - math.sin(om) * z, math.sin(om) * y + math.cos(om) * z
    return x, y, z


@njit(cache=True, nogil=True, error_model="numpy")
def rays(image, lines, nav, fixes, cam, c_out, d_out):
    """Projection centres and unit directions (ECEF) of image points ``(n, 2)``.
    ``lines``: line times and the POS epoch of each; ``nav``: POS times, table, max gap;
    ``fixes``: fix times, d_ned (m), d_opk (rad); ``cam``: R_BS, u_gps and the viewing
    tangents' cubic coefficients ``(8, n_elements)``. False where a line is not finite or
    the POS cannot be interpolated at its time (the numpy path then reports it)."""
    ltime, epoch = lines
    time, table, max_gap = nav
    ft, d_ned, d_opk = fixes
    r_bs, u_gps, coef = cam
    pos = np.empty(8)
    n = ltime.shape[0]
    nel = coef.shape[1]
    for i in range(image.shape[0]):
        line = image[i, 0]
        if not math.isfinite(line):
            return False
        j, w = line_at(line, n)
        t = ltime[j] + (ltime[j + 1] - ltime[j]) * w
        if not pos_from(time, table, max_gap, t, epoch[j], pos):
            return False
        trig = nav_trig(pos)
        s = image[i, 1]
        e = min(max(math.floor(s if math.isfinite(s) else 0.0), 0.0), nel - 1.0)
        k = int(e)
        u = s - e
        tx = coef[0, k] + u * (coef[1, k] + u * (coef[2, k] + u * coef[3, k]))
        ty = coef[4, k] + u * (coef[5, k] + u * (coef[6, k] + u * coef[7, k]))
        x = r_bs[0, 0] * tx + r_bs[0, 1] * ty - r_bs[0, 2]
        y = r_bs[1, 0] * tx + r_bs[1, 1] * ty - r_bs[1, 2]
        z = r_bs[2, 0] * tx + r_bs[2, 1] * ty - r_bs[2, 2]
        lx, ly, lz = u_gps[0], u_gps[1], u_gps[2]
        px, py, pz = pos[0], pos[1], pos[2]
        if ft.shape[0]:
            om, ph, ka = fix_at(ft, d_opk, t, 0), fix_at(ft, d_opk, t, 1), fix_at(ft, d_opk, t, 2)
            x, y, z = _opk(x, y, z, om, ph, ka)
            lx, ly, lz = _opk(lx, ly, lz, om, ph, ka)
            # the position correction is north, east, down: R_EN of (d_n, d_e, d_d)
            sl, cl, so, co = trig[6], trig[7], trig[8], trig[9]
            dn, de, dd = fix_at(ft, d_ned, t, 0), fix_at(ft, d_ned, t, 1), fix_at(ft, d_ned, t, 2)
            px += -sl * co * dn - so * de - cl * co * dd
            py += -sl * so * dn + co * de - cl * so * dd
            pz += cl * dn - sl * dd
        ex, ey, ez = body_to_ecef(x, y, z, trig)
        norm = math.sqrt(ex * ex + ey * ey + ez * ez)
        d_out[i, 0], d_out[i, 1], d_out[i, 2] = ex / norm, ey / norm, ez / norm
        cx, cy, cz = body_to_ecef(lx, ly, lz, trig)
        c_out[i, 0], c_out[i, 1], c_out[i, 2] = px + cx, py + cy, pz + cz
    return True
