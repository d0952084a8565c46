"""Rotation builders and frame matrices of spec/geometry.md (version 1).

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
    lat = np.asarray(lat, dtype=float)
    lon = np.asarray(lon, dtype=float)
    sl, cl = np.sin(lat), np.cos(lat)
    so, co = np.sin(lon), np.cos(lon)
    zero = np.zeros(np.broadcast_shapes(lat.shape, lon.shape))
    return _stack([[-sl * co, -so, -cl * co],
                   [-sl * so, co + zero, -cl * so],
                   [cl + zero, zero, -sl + zero]])


def r_nb(roll, pitch, heading) -> np.ndarray:
    """IMU body frame B to navigation frame N: ``Rz(heading) @ Ry(pitch) @ Rx(roll)``."""
    return rz(heading) @ ry(pitch) @ rx(roll)


def r_ph(swing, pitch_comp) -> np.ndarray:
    """Gimbal: platform base P to scan head H, ``Rx(swing) @ Ry(pitch_comp)``."""
    return rx(swing) @ ry(pitch_comp)


def apply(r: np.ndarray, v: np.ndarray) -> np.ndarray:
    """``r @ v`` for stacks: ``r`` ``(..., 3, 3)``, ``v`` ``(..., 3)``."""
    return np.einsum("...ij,...j->...i", r, v)


def apply_t(r: np.ndarray, v: np.ndarray) -> np.ndarray:
    """``r.T @ v`` for stacks."""
    return np.einsum("...ji,...j->...i", r, v)
