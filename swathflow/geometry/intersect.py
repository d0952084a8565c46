"""Ray / terrain intersection in ECEF, vectorised over many rays.

A ray is ``X(lam) = origin + lam * direction`` with ``lam > 0``. The intersection is the
smallest such ``lam`` at which the ellipsoidal height of ``X`` equals the terrain height at
``X``'s latitude and longitude (docs/geometry.md). Rays that miss give NaN.
"""
from __future__ import annotations

import numpy as np

from swathflow.geometry.geodesy import _A, _E2, ecef_to_geodetic, up_vector
from swathflow.geometry.terrain import ConstantHeight, Terrain


def _ellipsoid_hit(origin, direction, h):
    """Smallest positive ``lam`` hitting the ellipsoid with semi-axes ``(a + h, b + h)``.

    A close first guess for the surface of constant ellipsoidal height ``h``. NaN on a miss.
    """
    a = _A + h
    b = _A * np.sqrt(1 - _E2) + h
    w = np.array([1 / a, 1 / a, 1 / b])
    o = origin * w
    d = direction * w
    qa = np.sum(d * d, axis=-1)
    qb = 2 * np.sum(o * d, axis=-1)
    qc = np.sum(o * o, axis=-1) - 1
    disc = qb * qb - 4 * qa * qc
    with np.errstate(invalid="ignore"):
        sq = np.sqrt(disc)
        l1 = (-qb - sq) / (2 * qa)
        l2 = (-qb + sq) / (2 * qa)
    lam = np.where(l1 > 0, l1, np.where(l2 > 0, l2, np.nan))
    return np.where(disc >= 0, lam, np.nan)


def _refine_constant(origin, direction, lam, h, iterations: int = 4):
    """Newton on the ellipsoidal height along the ray (converges to < 1e-7 m)."""
    for _ in range(iterations):
        x = origin + lam[..., None] * direction
        llh = ecef_to_geodetic(x)
        err = llh[..., 2] - h
        rate = np.sum(direction * up_vector(llh[..., 0], llh[..., 1]), axis=-1)
        lam = lam - err / rate
        if np.nanmax(np.abs(err), initial=0.0) < 1e-7:
            break
    return lam


def intersect(origin, direction, terrain: Terrain, step: float | None = None,
              max_iter: int = 40, compiled: bool = True) -> np.ndarray:
    """Intersect rays with the terrain; returns ECEF ``(..., 3)``, NaN where a ray misses.

    For a DEM the ray is marched downwards from the DEM's highest to its lowest height and
    the first crossing is bracketed and refined to below 0.1 mm in height. A raster DEM
    goes through the compiled kernel of :mod:`swathflow.geometry.march` (steps of at most
    one DEM cell across the ground, Newton's method on the bilinear DEM; ``step`` is not
    used); ``compiled=False`` takes the numpy reference, which steps ``step`` metres along
    the ray (default: about one DEM cell), asks ``terrain.height`` at every step and
    refines by regula falsi, as does any other :class:`Terrain`. A constant height is met
    by the compiled Newton of ``march.shell_hits`` (``compiled=False``: numpy and pyproj).
    Directions need not be unit vectors.
    """
    origin = np.asarray(origin, float)
    direction = np.asarray(direction, float)
    shape = np.broadcast_shapes(origin.shape, direction.shape)
    origin = np.broadcast_to(origin, shape).reshape(-1, 3)
    direction = np.broadcast_to(direction, shape).reshape(-1, 3)
    out = _intersect_compiled(origin, direction, terrain, max_iter) if compiled else None
    if out is not None:
        return out.reshape(shape)
    direction = direction / np.linalg.norm(direction, axis=-1, keepdims=True)
    if isinstance(terrain, ConstantHeight):
        lam = _ellipsoid_hit(origin, direction, terrain.h)
        lam = _refine_constant(origin, direction, lam, terrain.h)
        return (origin + lam[:, None] * direction).reshape(shape)
    return _intersect_dem(origin, direction, terrain, step, max_iter).reshape(shape)


def _intersect_compiled(origin, direction, terrain, max_iter):
    """The compiled kernels (directions of any length): a constant height through
    ``march.shell_hits``, a raster DEM through ``march.intersect_dem``; None for any other
    terrain, or a DEM whose frame cannot be fitted."""
    from swathflow.geometry import march
    if isinstance(terrain, ConstantHeight):
        o = np.ascontiguousarray(origin)
        d = np.ascontiguousarray(direction)
        return o + march.shell_hits(o, d, float(terrain.h))[:, None] * d
    if all(hasattr(terrain, k) for k in ("data", "transform", "crs_wkt")):
        return march.intersect_dem(origin, direction, terrain, max_iter)
    return None


def _height_gap(origin, direction, lam, terrain):
    x = origin + lam[:, None] * direction
    llh = ecef_to_geodetic(x)
    return llh[:, 2] - terrain.height(llh[:, 0], llh[:, 1])


def _intersect_dem(origin, direction, terrain, step, max_iter):
    n = origin.shape[0]
    lam_top = _refine_constant(origin, direction, _ellipsoid_hit(origin, direction, terrain.h_max),
                               terrain.h_max)
    # rays starting below the DEM's top start at the origin
    h0 = ecef_to_geodetic(origin)[:, 2]
    lam_top = np.where(h0 <= terrain.h_max, 0.0, lam_top)
    lam_bot = _refine_constant(origin, direction, _ellipsoid_hit(origin, direction, terrain.h_min),
                               terrain.h_min)
    if step is None:
        step = getattr(terrain, "cell_size_m", None) or 30.0
    span = lam_bot - lam_top
    ok = np.isfinite(lam_top) & np.isfinite(span)
    n_steps = int(np.ceil(np.nanmax(np.where(ok, span, 0.0), initial=0.0) / step)) + 1
    lo = np.full(n, np.nan)
    hi = np.full(n, np.nan)
    glo = np.full(n, np.nan)
    ghi = np.full(n, np.nan)
    prev_lam = np.where(ok, lam_top, np.nan)
    prev_g = np.full(n, np.nan)
    idx = np.flatnonzero(ok)
    prev_g[idx] = _height_gap(origin[idx], direction[idx], prev_lam[idx], terrain)
    active = idx
    for k in range(1, n_steps + 1):
        if active.size == 0:
            break
        lam_k = np.minimum(lam_top[active] + k * step, lam_bot[active] + 1e-3)
        g = _height_gap(origin[active], direction[active], lam_k, terrain)
        crossed = (prev_g[active] > 0) & (g <= 0)
        c = active[crossed]
        lo[c], hi[c] = prev_lam[c], lam_k[crossed]
        glo[c], ghi[c] = prev_g[c], g[crossed]
        prev_lam[active] = lam_k
        prev_g[active] = g
        done = crossed | (lam_k >= lam_bot[active])
        active = active[~done]
    # regula falsi, Illinois variant, inside the brackets
    b = np.flatnonzero(np.isfinite(lo))
    lam = np.full(n, np.nan)
    if b.size:
        a_l, fa, b_l, fb = lo[b], glo[b], hi[b], ghi[b]
        for _ in range(max_iter):
            x = b_l - fb * (b_l - a_l) / (fb - fa)
            fx = _height_gap(origin[b], direction[b], x, terrain)
            fx = np.where(np.isfinite(fx), fx, 0.0)
            flip = fx * fb < 0
            a_l, fa = np.where(flip, b_l, a_l), np.where(flip, fb, fa / 2)
            b_l, fb = x, fx
            if np.max(np.abs(fx)) < 1e-5:
                break
        lam[b] = b_l
    return origin + lam[:, None] * direction
