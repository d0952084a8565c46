"""ECEF -> geodetic in compiled code (numba, ``cache=True``): Heikkinen's (1982) closed
form on WGS84, point by point without pyproj, for the compiled ray / DEM intersection
(:mod:`swathflow.geometry.march`) and the fit of a DEM's frame
(:mod:`swathflow.geometry.demframe`). :mod:`swathflow.geometry.geodesy` is the pyproj
reference it is tested against.
"""
from __future__ import annotations

import math

import numpy as np

from numba import njit

#: WGS84: semi-major axis (m), flattening, first eccentricity squared, semi-minor axis (m),
#: second eccentricity squared
WGS84_A = 6378137.0
_F = 1 / 298.257223563
_E2 = _F * (2 - _F)
WGS84_B = WGS84_A * (1 - _F)
_EP2 = (WGS84_A * WGS84_A - WGS84_B * WGS84_B) / (WGS84_B * WGS84_B)


@njit(cache=True, nogil=True)
def lat_lon_h(x, y, z):
    """Heikkinen (1982) closed-form ECEF -> geodetic (radians, metres)."""
    p = math.sqrt(x * x + y * y)
    if p < 1e-9:
        return math.copysign(math.pi / 2, z), 0.0, abs(z) - WGS84_B
    f = 54.0 * WGS84_B * WGS84_B * z * z
    g = p * p + (1 - _E2) * z * z - _E2 * (WGS84_A * WGS84_A - WGS84_B * WGS84_B)
    c = _E2 * _E2 * f * p * p / (g * g * g)
    s = (1 + c + math.sqrt(c * c + 2 * c)) ** (1.0 / 3.0)
    k = s + 1 + 1 / s
    pp = f / (3 * k * k * g * g)
    q = math.sqrt(1 + 2 * _E2 * _E2 * pp)
    r0 = (-pp * _E2 * p / (1 + q)
          + math.sqrt(max(0.5 * WGS84_A * WGS84_A * (1 + 1 / q) - pp * (1 - _E2) * z * z / (q * (1 + q))
                          - 0.5 * pp * p * p, 0.0)))
    t = p - _E2 * r0
    u = math.sqrt(t * t + z * z)
    v = math.sqrt(t * t + (1 - _E2) * z * z)
    z0 = WGS84_B * WGS84_B * z / (WGS84_A * v)
    h = u * (1 - WGS84_B * WGS84_B / (WGS84_A * v))
    lat = math.atan((z + _EP2 * z0) / p)
    lon = math.atan2(y, x)
    return lat, lon, h


@njit(cache=True, nogil=True)
def geodetic_of_points(pts):
    """ECEF ``(n, 3)`` -> lat, lon (degrees), h ``(n, 3)``."""
    out = np.empty_like(pts)
    for i in range(pts.shape[0]):
        la, lo, h = lat_lon_h(pts[i, 0], pts[i, 1], pts[i, 2])
        out[i, 0] = math.degrees(la)
        out[i, 1] = math.degrees(lo)
        out[i, 2] = h
    return out
