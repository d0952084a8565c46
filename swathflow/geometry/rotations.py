"""Rotation builders and frame matrices of docs/geometry.md (version 1).

Every builder is vectorised: angle arrays of shape ``(...)`` give matrices of shape
``(..., 3, 3)``. Angles are in radians here; degrees belong to files and configuration.
"""
from __future__ import annotations

import numpy as np

#: Photogrammetric flip between the scan-head frame H (z down) and the sensor frame S (z out of the lens).
T = np.diag([1.0, -1.0, -1.0])


def _stack(rows) -> np.ndarray:
    """Build ``(..., 3, 3)`` from a 3x3 nested list of broadcastable arrays."""
    shape = np.broadcast_shapes(*(np.shape(v) for row in rows for v in row))
    out = np.empty(shape + (3, 3))
    for i, row in enumerate(rows):
        for j, v in enumerate(row):
            out[..., i, j] = v
    return out


def rx(a) -> np.ndarray:
    a = np.asarray(a, dtype=float)
    c, s = np.cos(a), np.sin(a)
    one, zero = np.ones_like(a), np.zeros_like(a)
    return _stack([[one, zero, zero], [zero, c, -s], [zero, s, c]])


def ry(a) -> np.ndarray:
    a = np.asarray(a, dtype=float)
    c, s = np.cos(a), np.sin(a)
    one, zero = np.ones_like(a), np.zeros_like(a)
    return _stack([[c, zero, s], [zero, one, zero], [-s, zero, c]])


def rz(a) -> np.ndarray:
    a = np.asarray(a, dtype=float)
    c, s = np.cos(a), np.sin(a)
    one, zero = np.ones_like(a), np.zeros_like(a)
    return _stack([[c, -s, zero], [s, c, zero], [zero, zero, one]])


def r_opk(omega, phi, kappa) -> np.ndarray:
    """``Rx(omega) @ Ry(phi) @ Rz(kappa)``."""
    return rx(omega) @ ry(phi) @ rz(kappa)


def r_en(lat, lon) -> np.ndarray:
    """Local north-east-down frame N to ECEF E at geodetic latitude/longitude (radians)."""
    lat, lon = np.broadcast_arrays(np.asarray(lat, dtype=float), np.asarray(lon, dtype=float))
    sl, cl = np.sin(lat), np.cos(lat)
    so, co = np.sin(lon), np.cos(lon)
    out = np.empty(lat.shape + (3, 3))
    out[..., 0, 0] = -sl * co
    out[..., 0, 1] = -so
    out[..., 0, 2] = -cl * co
    out[..., 1, 0] = -sl * so
    out[..., 1, 1] = co
    out[..., 1, 2] = -cl * so
    out[..., 2, 0] = cl
    out[..., 2, 1] = 0.0
    out[..., 2, 2] = -sl
    return out


def r_nb(roll, pitch, heading) -> np.ndarray:
    """IMU body frame B to navigation frame N: ``Rz(heading) @ Ry(pitch) @ Rx(roll)``
    (written out in closed form: this is on the hot path of every projection)."""
    r, p, h = np.broadcast_arrays(np.asarray(roll, dtype=float), np.asarray(pitch, dtype=float),
                                  np.asarray(heading, dtype=float))
    sr, cr = np.sin(r), np.cos(r)
    sp, cp = np.sin(p), np.cos(p)
    sh, ch = np.sin(h), np.cos(h)
    out = np.empty(r.shape + (3, 3))
    out[..., 0, 0] = ch * cp
    out[..., 0, 1] = ch * sp * sr - sh * cr
    out[..., 0, 2] = ch * sp * cr + sh * sr
    out[..., 1, 0] = sh * cp
    out[..., 1, 1] = sh * sp * sr + ch * cr
    out[..., 1, 2] = sh * sp * cr - ch * sr
    out[..., 2, 0] = -sp
    out[..., 2, 1] = cp * sr
    out[..., 2, 2] = cp * cr
    return out


def r_ph(swing, pitch_comp) -> np.ndarray:
    """Gimbal: platform base P to scan head H, ``Rx(swing) @ Ry(pitch_comp)`` (closed form)."""
    s, q = np.broadcast_arrays(np.asarray(swing, dtype=float), np.asarray(pitch_comp, dtype=float))
    ss, cs = np.sin(s), np.cos(s)
    sq, cq = np.sin(q), np.cos(q)
    out = np.empty(s.shape + (3, 3))
    out[..., 0, 0] = cq
    out[..., 0, 1] = 0.0
    out[..., 0, 2] = sq
    out[..., 1, 0] = ss * sq
    out[..., 1, 1] = cs
    out[..., 1, 2] = -ss * cq
    out[..., 2, 0] = -cs * sq
    out[..., 2, 1] = ss
    out[..., 2, 2] = cs * cq
    return out


def apply(r: np.ndarray, v: np.ndarray) -> np.ndarray:
    """``r @ v`` for stacks: ``r`` ``(..., 3, 3)``, ``v`` ``(..., 3)``."""
    return np.einsum("...ij,...j->...i", r, v)


def apply_t(r: np.ndarray, v: np.ndarray) -> np.ndarray:
    """``r.T @ v`` for stacks."""
    return np.einsum("...ji,...j->...i", r, v)


def _d_rx(a):
    c, s = np.cos(a), np.sin(a)
    out = np.zeros(a.shape + (3, 3))
    out[..., 1, 1], out[..., 1, 2], out[..., 2, 1], out[..., 2, 2] = -s, -c, c, -s
    return out


def _d_ry(a):
    c, s = np.cos(a), np.sin(a)
    out = np.zeros(a.shape + (3, 3))
    out[..., 0, 0], out[..., 0, 2], out[..., 2, 0], out[..., 2, 2] = -s, c, -c, -s
    return out


def _d_rz(a):
    c, s = np.cos(a), np.sin(a)
    out = np.zeros(a.shape + (3, 3))
    out[..., 0, 0], out[..., 0, 1], out[..., 1, 0], out[..., 1, 1] = -s, -c, c, -s
    return out


def opk_derivatives(opk_deg) -> tuple[np.ndarray, np.ndarray]:
    """``r_opk`` of angles ``(m, 3)`` in degrees (as parameter vectors hold them),
    ``(m, 3, 3)``, and its derivatives by
    omega, phi, kappa (per radian), ``(m, 3, 3, 3)``."""
    w, p, k = np.radians(np.asarray(opk_deg, float)).T
    X, Y, Z = rx(w), ry(p), rz(k)
    d = np.stack([_d_rx(w) @ Y @ Z, X @ _d_ry(p) @ Z, X @ Y @ _d_rz(k)], axis=1)
    return X @ Y @ Z, d
