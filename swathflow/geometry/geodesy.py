"""Geodetic <-> ECEF through pyproj (EPSG:4979 <-> EPSG:4978).

Arrays carry coordinates on the last axis: geodetic ``(..., 3)`` as (lat deg, lon deg, h m),
ECEF ``(..., 3)`` as (X, Y, Z) m.
"""
from __future__ import annotations

from functools import lru_cache

import numpy as np
import pyproj

WGS84 = pyproj.CRS.from_epsg(4979)
ECEF = pyproj.CRS.from_epsg(4978)
_A = 6378137.0
_F = 1 / 298.257223563
_E2 = _F * (2 - _F)


@lru_cache(maxsize=None)
def _transformer(src: str, dst: str) -> pyproj.Transformer:
    return pyproj.Transformer.from_crs(src, dst, always_xy=True)


def geodetic_to_ecef(llh) -> np.ndarray:
    """``(..., 3)`` lat, lon (deg), ellipsoidal h (m) -> ECEF ``(..., 3)`` (m)."""
    llh = np.asarray(llh, dtype=float)
    x, y, z = _transformer("EPSG:4979", "EPSG:4978").transform(
        llh[..., 1], llh[..., 0], llh[..., 2])
    return np.stack(np.broadcast_arrays(x, y, z), axis=-1)


def ecef_to_geodetic(xyz) -> np.ndarray:
    """ECEF ``(..., 3)`` (m) -> ``(..., 3)`` lat, lon (deg), ellipsoidal h (m)."""
    xyz = np.asarray(xyz, dtype=float)
    lon, lat, h = _transformer("EPSG:4978", "EPSG:4979").transform(
        xyz[..., 0], xyz[..., 1], xyz[..., 2])
    return np.stack(np.broadcast_arrays(lat, lon, h), axis=-1)


def up_vector(lat_deg, lon_deg) -> np.ndarray:
    """Unit ellipsoid normal (local up) in ECEF, ``(..., 3)``."""
    lat = np.radians(lat_deg)
    lon = np.radians(lon_deg)
    return np.stack(np.broadcast_arrays(np.cos(lat) * np.cos(lon), np.cos(lat) * np.sin(lon),
                                        np.sin(lat)), axis=-1)


def utm_crs_for(lat_deg: float, lon_deg: float) -> pyproj.CRS:
    """The WGS84 UTM zone CRS that contains a point (``auto-utm``)."""
    zone = int(np.floor((lon_deg + 180.0) / 6.0)) % 60 + 1
    return pyproj.CRS.from_epsg((32600 if lat_deg >= 0 else 32700) + zone)


def transformer(src, dst) -> pyproj.Transformer:
    """A cached always-xy transformer between any two CRS given as strings or CRS objects
    (two strings: looked up as given, without parsing them again: 0.9 ms a call for a
    DEM's WKT, paid per image by the mission's check)."""
    if isinstance(src, str) and isinstance(dst, str):
        return _transformer_of(src, dst)
    return _transformer(pyproj.CRS.from_user_input(src).to_wkt(),
                        pyproj.CRS.from_user_input(dst).to_wkt())


@lru_cache(maxsize=64)
def _transformer_of(src: str, dst: str) -> pyproj.Transformer:
    return _transformer(pyproj.CRS.from_user_input(src).to_wkt(),
                        pyproj.CRS.from_user_input(dst).to_wkt())
