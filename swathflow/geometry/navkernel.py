"""Compiled POS interpolation and the IMU body -> ECEF rotation (numba), one point at a time,
for the sensor models' compiled rays: the linear interpolation of the POS table (ECEF, lat,
lon, roll, pitch, heading; :meth:`swathflow.formats.pos.Trajectory.interpolate`) and
``R_EN R_NB`` (:func:`swathflow.geometry.rotations.r_en`, :func:`~.rotations.r_nb`)."""
from __future__ import annotations

import math

import numpy as np
from numba import njit

DEG = math.pi / 180.0


def pos_table(trajectory) -> tuple[np.ndarray, np.ndarray, float]:
    """``(time, table, max_gap)`` of a trajectory, as the kernels take it (``pos_from``):
    the POS times, the table they interpolate (ECEF, lat, lon (deg), roll, pitch, heading
    (deg), one row per epoch: made once per trajectory, :meth:`Trajectory.table`) and the
    longest gap interpolated across."""
    return (np.ascontiguousarray(trajectory.time, dtype=float), trajectory.table(),
            float(trajectory.max_gap))


def epochs(time, t) -> np.ndarray:
    """The POS epoch of times ``t`` (the index of the last epoch not after it): start
    indices for :func:`pos_from`."""
    return np.searchsorted(time, np.asarray(t, float), side="right") - 1


@njit(cache=True, nogil=True, error_model="numpy")
def pos_from(time, table, max_gap, t, k, out):
    """POS at time ``t`` into ``out`` (8 columns), the search started at epoch ``k`` (a
    nearby one, e.g. the image line's: a random binary search costs more than a whole
    ray). False where ``t`` is outside the trajectory or inside a gap longer than
    ``max_gap`` (the numpy path then reports it)."""
    return pos_epoch(time, table, max_gap, t, k, out) >= 0


@njit(cache=True, nogil=True, error_model="numpy")
def pos_epoch(time, table, max_gap, t, k, out):
    """:func:`pos_from` that returns the epoch interpolated from (``t`` lies between it
    and the next one), or -1 where :func:`pos_from` is False."""
    n = time.shape[0]
    if not (t >= time[0] and t <= time[n - 1]):
        return -1
    k = min(max(k, 0), n - 2)
    while k > 0 and time[k] > t:
        k -= 1
    while k < n - 2 and time[k + 1] <= t:
        k += 1
    gap = time[k + 1] - time[k]
    if gap > max_gap:
        return -1
    w = (t - time[k]) / gap
    for c in range(8):
        a = table[k, c]
        out[c] = a + (table[k + 1, c] - a) * w
    return k


@njit(cache=True, nogil=True, error_model="numpy")
def line_at(line, n):
    """A fractional raw line clamped to the image's ``n`` lines: ``(j, w)``, the line
    below it (at most ``n - 2``) and the weight of the line after (the rays' line
    interpolation of every sensor model)."""
    line = min(max(line, 0.0), n - 1.0)
    j = min(int(line), n - 2)
    return j, line - j


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def nav_trig(pos):
    """Sines and cosines of roll, pitch, heading, latitude and longitude of a POS row."""
    r, p, h = pos[5] * DEG, pos[6] * DEG, pos[7] * DEG
    la, lo = pos[3] * DEG, pos[4] * DEG
    return (math.sin(r), math.cos(r), math.sin(p), math.cos(p), math.sin(h), math.cos(h),
            math.sin(la), math.cos(la), math.sin(lo), math.cos(lo))


@njit(cache=True, nogil=True, error_model="numpy")
def body_to_ecef(x, y, z, trig):
    """``R_EN R_NB (x, y, z)``: IMU body frame to ECEF (``trig`` from :func:`nav_trig`)."""
    sr, cr, sp, cp, sh, ch, sl, cl, so, co = trig
    y, z = cr * y - sr * z, sr * y + cr * z           # Rx(roll)
    x, z = cp * x + sp * z, -sp * x + cp * z          # Ry(pitch)
    x, y = ch * x - sh * y, sh * x + ch * y           # Rz(heading): north, east, down
    return (-sl * co * x - so * y - cl * co * z,
            -sl * so * x + co * y - cl * so * z,
            cl * x - sl * z)
