"""Compiled rays of the rotating-mirror scanner (numba): ``RotatingMirrorModel.ray`` one
point at a time (row time and start angle interpolated in the line, the pixel's own time,
the POS there, ``R_EN R_NB (u_gps + R_BM (0, -sin theta, cos theta))``)."""
from __future__ import annotations

import math

import numpy as np

from swathflow.geometry.navkernel import body_to_ecef, line_at, nav_trig, pos_from
from numba import njit


@njit(cache=True, nogil=True, error_model="numpy")
def rays(image, rows, nav, scan, c_out, d_out):
    """Mirror centres and unit directions (ECEF) of image points ``(n, 2)``. ``rows``:
    row times, row start angles (rad) and the POS epoch of every row time; ``nav``: POS
    times, table and max gap; ``scan``: ifov (rad), dwell (s), scan offset (rad), R_BM,
    u_gps. False where a line is not finite or the POS cannot be interpolated at a pixel's
    time (the caller then takes the numpy path, which reports it)."""
    rtime, rstart, epoch = rows
    time, table, max_gap = nav
    ifov, dwell, offset, r_bm, u_gps = scan
    pos = np.empty(8)
    n = rtime.shape[0]
    for i in range(image.shape[0]):
        line = image[i, 0]
        if not math.isfinite(line):
            return False
        j, w = line_at(line, n)
        e = image[i, 1]
        t = rtime[j] + (rtime[j + 1] - rtime[j]) * w + e * dwell
        th = rstart[j] + (rstart[j + 1] - rstart[j]) * w + e * ifov + offset
        if not pos_from(time, table, max_gap, t, epoch[j], pos):
            return False
        trig = nav_trig(pos)
        y, z = -math.sin(th), math.cos(th)
        x, y, z = (r_bm[0, 1] * y + r_bm[0, 2] * z, r_bm[1, 1] * y + r_bm[1, 2] * z,
                   r_bm[2, 1] * y + r_bm[2, 2] * z)
        d_out[i, 0], d_out[i, 1], d_out[i, 2] = body_to_ecef(x, y, z, trig)
        cx, cy, cz = body_to_ecef(u_gps[0], u_gps[1], u_gps[2], trig)
        c_out[i, 0], c_out[i, 1], c_out[i, 2] = pos[0] + cx, pos[1] + cy, pos[2] + cz
    return True
