"""Terrain: a constant ellipsoidal height or a DEM in any CRS, as ellipsoidal heights.

Orthometric DEMs are converted with a geoid grid or a stated constant undulation, never
silently: pyproj ships no geoid grids and would fall back to a no-op transformation.
"""
from __future__ import annotations

import math
import os
from dataclasses import dataclass, field

import numpy as np

from swathflow.errors import FormatError, SwathflowError
from swathflow.geometry.geodesy import transformer
from numba import njit

GEOID_GRIDS = {"egm96": "egm96_15.gtx", "egm2008": "egm08_25.gtx"}


class Terrain:
    """Interface: ellipsoidal terrain height at geodetic positions."""

    #: lowest and highest ellipsoidal height (m), to bracket ray intersections
    h_min: float
    h_max: float

    def height(self, lat, lon) -> np.ndarray:  # pragma: no cover - interface
        raise NotImplementedError

    def state(self) -> dict:  # pragma: no cover - interface
        raise NotImplementedError


@dataclass(frozen=True)
class ConstantHeight(Terrain):
    """A constant ellipsoidal height (m)."""

    h: float

    @property
    def h_min(self) -> float:
        return float(self.h)

    @property
    def h_max(self) -> float:
        return float(self.h)

    def height(self, lat, lon) -> np.ndarray:
        return np.full(np.broadcast_shapes(np.shape(lat), np.shape(lon)), float(self.h))

    def state(self) -> dict:
        return {"kind": "constant", "h": float(self.h)}


def _find_geoid_grid(name: str) -> str | None:
    import pyproj
    fname = GEOID_GRIDS.get(name.lower(), name)
    if os.path.isabs(fname) and os.path.exists(fname):
        return fname
    dirs = [os.environ.get("PROJ_DATA"), os.environ.get("PROJ_LIB"),
            pyproj.datadir.get_data_dir(), "/usr/share/proj", "/usr/local/share/proj"]
    dirs += [pyproj.datadir.get_user_data_dir()]
    for d in dirs:
        if d and os.path.exists(os.path.join(d, fname)):
            return os.path.join(d, fname)
    return None


def geoid_undulation(lat, lon, geoid: str) -> np.ndarray:
    """Geoid undulation N (m) from a PROJ grid: h_ellipsoidal = H_orthometric + N.

    Raises :class:`SwathflowError` when the grid is not installed (never a silent zero).
    """
    import pyproj
    grid = _find_geoid_grid(geoid)
    if grid is None:
        raise SwathflowError(
            f"geoid grid for {geoid!r} ({GEOID_GRIDS.get(geoid.lower(), geoid)}) is not "
            f"installed: install Debian's proj-data (apt-get install proj-data) or set "
            f"'undulation = <metres>' in [terrain] of mission.toml")
    t = pyproj.Transformer.from_pipeline(
        f"+proj=vgridshift +grids={grid} +multiplier=1")
    lat = np.asarray(lat, float)
    lon = np.asarray(lon, float)
    # vgridshift with multiplier=1 adds N: z_out = z_in + N (lon/lat in radians)
    _, _, z = t.transform(np.radians(lon), np.radians(lat), np.zeros_like(lat), radians=True)
    return np.asarray(z)


@dataclass(frozen=True, eq=False)
class DEM(Terrain):
    """A DEM read into memory, bilinearly interpolated, heights converted to ellipsoidal.

    ``vertical``: ``"ellipsoidal"`` or ``"orthometric"``; the latter needs ``geoid`` (a grid
    name such as ``"egm96"``) or a constant ``undulation`` in metres.
    """

    path: str
    data: np.ndarray = field(repr=False)
    transform: tuple = field(repr=False)      # affine (a, b, c, d, e, f)
    crs_wkt: str = field(repr=False)
    vertical: str = "ellipsoidal"
    geoid: str | None = None
    undulation: float | None = None

    @classmethod
    def open(cls, path, vertical: str = "ellipsoidal", geoid: str | None = None,
             undulation: float | None = None) -> "DEM":
        import rasterio
        path = os.fspath(path)
        if not os.path.exists(path):
            raise FormatError(f"{path}: DEM file not found")
        if vertical not in ("ellipsoidal", "orthometric"):
            raise FormatError(f"{path}: vertical must be 'ellipsoidal' or 'orthometric', "
                              f"not {vertical!r}")
        if vertical == "orthometric" and geoid is None and undulation is None:
            raise FormatError(f"{path}: an orthometric DEM needs geoid = 'egm96' or "
                              f"undulation = <metres> (heights are never converted silently)")
        try:
            with rasterio.open(path) as src:
                if src.crs is None:
                    raise FormatError(f"{path}: the DEM has no CRS")
                data = src.read(1, masked=True).astype(float).filled(np.nan)
                tr = src.transform
                crs = src.crs.to_wkt()
        except rasterio.errors.RasterioIOError as exc:
            raise FormatError(f"{path}: cannot read DEM: {exc}") from None
        if vertical == "orthometric":
            rows, cols = np.indices(data.shape)
            xs = tr.c + (cols + 0.5) * tr.a + (rows + 0.5) * tr.b
            ys = tr.f + (cols + 0.5) * tr.d + (rows + 0.5) * tr.e
            lon, lat = transformer(crs, "EPSG:4326").transform(xs, ys)
            n = (np.full(data.shape, float(undulation)) if undulation is not None
                 else geoid_undulation(lat, lon, geoid))
            data = data + n
        return cls(path, data, tuple(tr)[:6], crs, vertical, geoid, undulation)

    @property
    def h_min(self) -> float:
        return float(np.nanmin(self.data))

    @property
    def h_max(self) -> float:
        return float(np.nanmax(self.data))

    @property
    def cell_size_m(self) -> float:
        """Approximate cell size in metres (the ray-marching step)."""
        import pyproj
        a, b, c, d, e, f = self.transform
        size = min(abs(a) or abs(b), abs(e) or abs(d))
        crs = pyproj.CRS.from_wkt(self.crs_wkt)
        if crs.is_geographic:
            size *= 111_000.0 * min(1.0, abs(np.cos(np.radians(f))) + 0.1)
        else:
            size *= crs.axis_info[0].unit_conversion_factor
        return float(size)

    def height(self, lat, lon) -> np.ndarray:
        """Bilinear ellipsoidal height; NaN outside the DEM or next to its nodata."""
        lat = np.asarray(lat, float)
        lon = np.asarray(lon, float)
        x, y = transformer("EPSG:4326", self.crs_wkt).transform(lon, lat)
        return self.height_xy(x, y)

    def height_xy(self, x, y) -> np.ndarray:
        """:meth:`height` at points given in the DEM's own CRS."""
        a, b, c, d, e, f = self.transform
        det = a * e - b * d
        col = (e * (x - c) - b * (y - f)) / det - 0.5
        row = (-d * (x - c) + a * (y - f)) / det - 0.5
        return bilinear(self.data, row, col)

    def state(self) -> dict:
        return {"kind": "dem", "path": self.path, "vertical": self.vertical,
                "geoid": self.geoid, "undulation": self.undulation}


def bilinear(data: np.ndarray, row, col) -> np.ndarray:
    """Bilinear interpolation at fractional pixel-centre coordinates; NaN outside
    (compiled: :func:`_bilinear`)."""
    row, col = np.broadcast_arrays(np.asarray(row, float), np.asarray(col, float))
    out = np.empty(row.shape)
    data = np.ascontiguousarray(data, dtype=float)
    _bilinear(data, np.ascontiguousarray(row).reshape(-1), np.ascontiguousarray(col).reshape(-1),
              out.reshape(-1))
    return out


@njit(cache=True, nogil=True, error_model="numpy")
def _bilinear(data, row, col, out):
    """:func:`bilinear` one point at a time (:func:`bilinear_one`)."""
    for i in range(row.shape[0]):
        out[i] = bilinear_one(data, row[i], col[i])


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def bilinear_one(data, r, c):
    """:func:`bilinear` of one point (the same arithmetic as its numpy form had)."""
    nr, nc = data.shape
    if not (r >= 0 and r <= nr - 1 and c >= 0 and c <= nc - 1):
        return np.nan
    r0 = min(max(int(math.floor(r)), 0), max(nr - 2, 0))
    c0 = min(max(int(math.floor(c)), 0), max(nc - 2, 0))
    r1, c1 = min(r0 + 1, nr - 1), min(c0 + 1, nc - 1)
    wr, wc = r - r0, c - c0
    return (data[r0, c0] * (1 - wr) * (1 - wc) + data[r0, c1] * (1 - wr) * wc
            + data[r1, c0] * wr * (1 - wc) + data[r1, c1] * wr * wc)


def open_terrain(spec) -> Terrain:
    """A :class:`Terrain` from a number (constant height), a path, or a ``[terrain]`` dict."""
    if isinstance(spec, Terrain):
        return spec
    if isinstance(spec, (int, float)):
        return ConstantHeight(float(spec))
    if isinstance(spec, (str, os.PathLike)):
        return DEM.open(spec)
    if isinstance(spec, dict):
        if spec.get("kind") == "constant" or "height" in spec or "h" in spec:
            h = float(spec.get("height", spec.get("h")))
            if spec.get("vertical", "ellipsoidal") == "orthometric":
                if spec.get("undulation") is not None:
                    h += float(spec["undulation"])
                else:
                    raise FormatError("[terrain]: an orthometric constant height needs "
                                      "undulation = <metres>")
            return ConstantHeight(h)
        return DEM.open(spec.get("dem", spec.get("path")), spec.get("vertical", "ellipsoidal"),
                        spec.get("geoid"), spec.get("undulation"))
    raise FormatError(f"cannot make a terrain from {spec!r}")
