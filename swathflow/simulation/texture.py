"""Ground truth for the simulator: a brightness texture and a terrain shape, both functions
of easting/northing (metres, the mission's output CRS).

The texture is a continuous function ``T(E, N)`` in [0, 1]; the truth orthophoto is the
same function area-averaged over each output pixel (:func:`area_average`), and raw images
integrate it over each detector pixel's ground footprint. Built in and procedural by
default (multi-scale noise, sharp-edged fields, roads, and bright survey targets at the
GCPs); or a given orthophoto placed under the flight.
"""
from __future__ import annotations

import os

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree


class Texture:
    """Base: a brightness function of (E, N) plus survey targets (bright disks in a dark ring)."""

    targets: np.ndarray | None = None
    target_radius: float = 1.0
    _tree: cKDTree | None = None

    def base(self, e, n) -> np.ndarray:  # pragma: no cover - interface
        raise NotImplementedError

    def with_targets(self, points, radius: float) -> "Texture":
        """A copy with a bright disk of ``radius`` m (value 1) inside a dark ring out to
        ``2 * radius`` (value 0) centred on every point ``(k, 2)`` E, N."""
        import copy
        t = copy.copy(self)
        t.targets = np.asarray(points, float).reshape(-1, 2)
        t.target_radius = float(radius)
        t._tree = cKDTree(t.targets) if len(t.targets) else None
        return t

    def __call__(self, e, n) -> np.ndarray:
        e, n = np.broadcast_arrays(np.asarray(e, float), np.asarray(n, float))
        if e.size > 2 * _CHUNK:
            # numpy and ndimage release the GIL: evaluate chunks on two threads
            ef, nf = e.ravel(), n.ravel()
            parts = [(i, min(i + _CHUNK, ef.size)) for i in range(0, ef.size, _CHUNK)]
            out = np.empty(ef.size, np.float32)

            def run(p):
                out[p[0]:p[1]] = self._eval(ef[p[0]:p[1]], nf[p[0]:p[1]])
            list(_pool().map(run, parts))
            return out.reshape(e.shape)
        return self._eval(e, n)

    def _eval(self, e, n) -> np.ndarray:
        v = self.base(e, n).astype(np.float32)
        tree = getattr(self, "_tree", None)
        if tree is not None:
            r = self.target_radius
            pts = np.stack([e.ravel(), n.ravel()], -1)
            d, _ = tree.query(pts, k=1, distance_upper_bound=2 * r)
            d = d.reshape(e.shape)
            v = np.where(d <= r, np.float32(1.0), np.where(d <= 2 * r, np.float32(0.0), v))
        return v


_CHUNK = 131_072
_POOL = None


def _pool():
    global _POOL
    if _POOL is None:
        from concurrent.futures import ThreadPoolExecutor
        _POOL = ThreadPoolExecutor(max_workers=min(2, os.cpu_count() or 1),
                                   thread_name_prefix="texture")
    return _POOL


def _rotate(e, n, angle, origin):
    c, s = np.cos(angle), np.sin(angle)
    de, dn = e - origin[0], n - origin[1]
    return c * de - s * dn, s * de + c * dn


class ProceduralTexture(Texture):
    """Multi-scale, deterministic texture; ``scale`` is the finest feature size (m)."""

    def __init__(self, seed: int, scale: float, origin=(0.0, 0.0)):
        rng = np.random.default_rng([int(seed), 20240917])
        self.scale = float(scale)
        self.origin = (float(origin[0]), float(origin[1]))
        # smooth noise octaves: lattice spacing (m) and amplitude
        self.octaves = [(400.0, 0.22), (130.0, 0.18), (40.0, 0.14), (12.0, 0.10),
                        (4.0, 0.08), (1.6, 0.07)]
        self.tables = [rng.random((256, 256)) for _ in self.octaves]
        self.angles = rng.uniform(0, np.pi, len(self.octaves))
        self.shifts = rng.uniform(0, 256, (len(self.octaves), 2))
        # fields: piecewise-constant parcels (sharp edges), warped by low-frequency noise
        self.parcels = rng.random((256, 256)) ** 0.8
        self.parcel_size = 45.0
        self.parcel_angle = rng.uniform(0, np.pi)
        self.warp_phase = rng.uniform(0, 2 * np.pi, 2)
        # roads: straight bright lines
        k = 5
        self.road_angle = rng.uniform(0, np.pi, k)
        self.road_offset = rng.uniform(-600, 600, k)
        self.road_width = rng.uniform(3.0, 8.0, k)

    def _lookup(self, table, u, v, order=1):
        return ndimage.map_coordinates(table, [u.ravel(), v.ravel()], order=order,
                                       mode="grid-wrap", prefilter=False).reshape(u.shape)

    def base(self, e, n) -> np.ndarray:
        s = self.scale
        de = np.asarray(e, float) - self.origin[0]
        dn = np.asarray(n, float) - self.origin[1]
        out = np.zeros(de.shape, np.float32)
        for (spacing, amp), tab, ang, sh in zip(self.octaves, self.tables, self.angles,
                                                self.shifts):
            d = spacing * s
            c, si = np.cos(ang) / d, np.sin(ang) / d
            v = self._lookup(tab, si * de + c * dn + sh[0], c * de - si * dn + sh[1])
            out += np.float32(amp) * v.astype(np.float32)
        # warped parcels
        ps = self.parcel_size * s
        c, si = np.cos(self.parcel_angle) / ps, np.sin(self.parcel_angle) / ps
        y = si * de + c * dn
        x = c * de - si * dn
        a, b = self.warp_phase
        wx = 0.6 * np.sin(0.9 * y + 0.5 * x + a)
        wy = 0.6 * np.sin(0.7 * x - 0.4 * y + b)
        par = self._lookup(self.parcels, y + wy, x + wx, order=0)
        out = np.float32(0.6) * out + np.float32(0.35) * par.astype(np.float32) \
            - np.float32(0.02)
        # roads
        on = np.zeros(de.shape, bool)
        for ang, off, wid in zip(self.road_angle, self.road_offset, self.road_width):
            y = np.sin(ang) * de + np.cos(ang) * dn - off * s
            on |= np.abs(y) < 0.5 * wid * s
        out[on] = np.float32(0.85)
        return np.clip(out, 0.0, 1.0)


class ImageTexture(Texture):
    """A given orthophoto (any raster rasterio reads, e.g. GeoTIFF or JPEG + world file),
    converted to grey and placed with its centre at ``centre`` (E, N) with ``pixel_size``
    metres per pixel (default: its own pixel size in metres); mirrored beyond its edges."""

    def __init__(self, path, centre, pixel_size: float | None = None, rotation_deg: float = 0.0):
        from swathflow.formats.raster import read_raster
        r = read_raster(path, band=None)
        data = r.data.astype(np.float32)
        grey = data[:3].mean(0) if data.shape[0] >= 3 else data[0]
        lo, hi = np.percentile(grey, [0.5, 99.5])
        self.grey = np.clip((grey - lo) / max(hi - lo, 1e-6), 0, 1).astype(np.float32)
        if pixel_size is None:
            pixel_size = abs(r.transform.a)
            if r.crs:
                import pyproj
                crs = pyproj.CRS.from_user_input(r.crs)
                if crs.is_projected:
                    pixel_size *= crs.axis_info[0].unit_conversion_factor
                elif crs.is_geographic:
                    pixel_size *= 111_000.0
        self.pixel_size = float(pixel_size)
        self.centre = (float(centre[0]), float(centre[1]))
        self.rotation = np.radians(rotation_deg)
        self.source = str(path)

    def base(self, e, n) -> np.ndarray:
        x, y = _rotate(e, n, self.rotation, self.centre)
        rows, cols = self.grey.shape
        col = x / self.pixel_size + cols / 2 - 0.5
        row = -y / self.pixel_size + rows / 2 - 0.5
        return ndimage.map_coordinates(self.grey, [row.ravel(), col.ravel()], order=1,
                                       mode="mirror", prefilter=False).reshape(e.shape)


def area_average(texture, transform, shape, supersample: int = 3,
                 block_rows: int = 256) -> np.ndarray:
    """The texture averaged over each pixel of a north-up grid (``transform``: affine of the
    top-left corner, ``shape``: rows, cols), by ``supersample`` x ``supersample`` samples."""
    rows, cols = shape
    a, _, c, _, e, f = tuple(transform)[:6]
    out = np.empty(shape, np.float32)
    off = (np.arange(supersample) + 0.5) / supersample
    cc = (np.arange(cols)[:, None] + off[None, :]).ravel()
    for r0 in range(0, rows, block_rows):
        r1 = min(rows, r0 + block_rows)
        rr = (np.arange(r0, r1)[:, None] + off[None, :]).ravel()
        ee = c + a * cc[None, :]
        nn = f + e * rr[:, None]
        ee, nn = np.broadcast_arrays(ee, nn)
        v = texture(ee, nn)
        out[r0:r1] = v.reshape(r1 - r0, supersample, cols, supersample).mean(axis=(1, 3))
    return out


class ProceduralTerrain:
    """Gentle hills: ellipsoidal height (m) as a function of (E, N)."""

    def __init__(self, seed: int, base: float, relief: float, wavelength: float,
                 origin=(0.0, 0.0)):
        rng = np.random.default_rng([int(seed), 777])
        self.base, self.relief, self.origin = float(base), float(relief), origin
        k = 6
        self.kx = rng.normal(size=k)
        self.ky = rng.normal(size=k)
        norm = np.hypot(self.kx, self.ky)
        lam = wavelength * rng.uniform(0.5, 1.5, k)
        self.kx, self.ky = self.kx / norm * 2 * np.pi / lam, self.ky / norm * 2 * np.pi / lam
        self.phase = rng.uniform(0, 2 * np.pi, k)
        self.amp = rng.uniform(0.5, 1.0, k)
        self.amp /= self.amp.sum()

    def __call__(self, e, n) -> np.ndarray:
        x = np.asarray(e, float) - self.origin[0]
        y = np.asarray(n, float) - self.origin[1]
        h = np.zeros(np.broadcast_shapes(x.shape, y.shape))
        for kx, ky, ph, a in zip(self.kx, self.ky, self.phase, self.amp):
            h += a * np.sin(kx * x + ky * y + ph)
        return self.base + 0.5 * self.relief * h


class RasterTerrain:
    """A given DEM's shape placed under the flight: heights rescaled to
    ``base + (H - mean(H)) * vscale`` and its grid centred at ``centre`` with ``cell`` m."""

    def __init__(self, path, centre, cell: float, base: float, relief: float):
        from swathflow.formats.raster import read_raster
        r = read_raster(path, masked_to_nan=True)
        d = r.data.astype(float)
        if np.isnan(d).any():
            d = np.where(np.isnan(d), np.nanmean(d), d)
        span = float(np.nanmax(d) - np.nanmin(d)) or 1.0
        self.vscale = relief / span
        self.data = base + (d - d.mean()) * self.vscale
        self.centre, self.cell = centre, float(cell)
        self.source = str(path)
        self.source_range = (float(np.nanmin(r.data)), float(np.nanmax(r.data)))

    def __call__(self, e, n) -> np.ndarray:
        e, n = np.broadcast_arrays(np.asarray(e, float), np.asarray(n, float))
        rows, cols = self.data.shape
        col = (e - self.centre[0]) / self.cell + cols / 2 - 0.5
        row = -(n - self.centre[1]) / self.cell + rows / 2 - 0.5
        return ndimage.map_coordinates(self.data, [row.ravel(), col.ravel()], order=1,
                                       mode="mirror", prefilter=False).reshape(e.shape)
