"""Automatic control points from a reference orthophoto and DEM.

A swing is rectified with the current parameters onto the reference's own pixel lattice
(rendered finer, then area-averaged to the reference's pixels, so both images carry the
same blur), its radiometry mapped onto the reference's by histogram matching (gamma,
gain, offset, any monotonic difference), and its systematic displacement found coarse to
fine: a minimum-grey-difference search over the whole footprint on 4x averaged pixels,
then one subpixel match per well-textured block with
:func:`swathflow.mosaicking.matching.match_block` (the mosaic's matcher, with its texture,
contrast and divergence checks).

Each match is carried back to the raw image: the reference feature at map position ``p``
appears in the rectified swing at ``q``; the raw (line, element) under ``q`` follows from
the *same* model and terrain that rectified it (``ground_to_image``), so the observation
does not depend on the current parameters being right; the ground coordinates are those of
``p`` with the height of the reference DEM (or the mission's terrain). The point's a-priori
sigma in raw pixels is the match's formal sigma, floored, combined with the reference's
accuracy, and propagated through the local raw-per-reference-pixel Jacobian.

Only the :class:`~swathflow.sensormodel.base.SensorModel` interface is used (``shape``,
``ground_to_image``, ``image_to_ground``), so every sensor plugin gets it.
"""
from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np
import pandas as pd
from affine import Affine

from swathflow.errors import FormatError
from swathflow.geometry.grid import Grid, ecef_to_map
from swathflow.geometry.terrain import DEM, Terrain
from swathflow.mosaicking.matching import match_block, mmgd_search

#: columns of the automatic control-point table (the control-point table's, plus these)
POINT_COLUMNS = ("gcp_id", "image_id", "line", "element", "X", "Y", "Z", "role",
                 "sigma_line", "sigma_element", "E", "N", "quality", "texture", "peak",
                 "match_sigma", "shift_row", "shift_col")


@dataclass(frozen=True)
class MatchSettings:
    """How swings are matched against the reference (sizes in reference pixels)."""

    block: int = 16                 # block side
    search: int = 4                 # block search radius around the coarse shift
    margin_m: float = 40.0          # the reference window extends the footprint by this
    coarse: int = 4                 # averaging factor of the coarse global search
    step: float = 1.0               # block spacing as a fraction of the block side (blocks
    #                                 that overlap give correlated errors: sigmas too small)
    min_texture: float = 1.0        # match_block's texture threshold
    min_valid: float = 0.6          # fraction of the block's search window the swing covers
    sigma_floor: float = 0.05       # reference px, added in quadrature to the formal sigma
    accuracy_m: float | None = None  # the reference's absolute accuracy (default 0.25 px)
    tie_block: int = 16             # tie points (swing to swing): block side, raw pixels
    tie_search: int = 6             # tie points: search radius, raw pixels
    tie_max: int = 12               # tie points per pair of swings at most (spread along the
    #                                 overlap; each adds 3 unknowns to the adjustment)
    tie_sigma_factor: float = 2.0   # tie points: the block matcher's formal sigma times this
    #                                 (then with sigma_floor in quadrature: against simulator
    #                                 truth and a noise-free trajectory the transfer errors
    #                                 are 0.82-1.05 x the tie sigmas, 1.4 x without it:
    #                                 benchmarks/bench_calibration_tiesigma.py)


DEFAULT_SETTINGS = MatchSettings()


@dataclass(frozen=True, eq=False)
class Reference:
    """A north-up grey reference orthophoto in memory, and the heights for its points."""

    path: str
    image: np.ndarray               # float64, NaN = nodata
    grid: Grid
    dem: Terrain | None = None      # None: the mission's terrain

    @property
    def res(self) -> float:
        return float(self.grid.res[0])


def open_reference(path, dem=None, vertical: str = "ellipsoidal") -> Reference:
    """Read a reference orthophoto (any raster GDAL reads, bands averaged to grey; JPEG with
    a world file and a ``-srs.wkt`` beside it works) and an optional reference DEM."""
    from swathflow.formats.raster import read_raster
    path = os.fspath(path)
    r = read_raster(path, band=None, masked_to_nan=True)
    if r.crs is None:
        raise FormatError(f"{path}: the reference orthophoto has no CRS (add a .prj or "
                          f"-srs.wkt beside it, or write it as a GeoTIFF with a CRS)")
    import pyproj
    if not pyproj.CRS.from_user_input(r.crs).is_projected:
        raise FormatError(f"{path}: the reference orthophoto's CRS is not projected (its "
                          f"pixels are degrees; the matching's margins and blocks are "
                          f"metres): warp it to a projected CRS, e.g. the mission's "
                          f"(gdalwarp -t_srs EPSG:...)")
    t = r.transform
    if t.b != 0 or t.d != 0 or t.e >= 0 or abs(abs(t.e) - t.a) > 1e-9 * t.a:
        raise FormatError(f"{path}: the reference orthophoto must be north-up with square "
                          f"pixels (transform {tuple(t)[:6]}); warp it first (gdalwarp)")
    img = np.asarray(r.data, float)
    img = img.mean(axis=0) if img.ndim == 3 else img
    if not np.isfinite(img).any():
        raise FormatError(f"{path}: the reference orthophoto has no valid pixel")
    terrain = DEM.open(dem, vertical) if dem else None
    return Reference(path, img, Grid(r.crs, t, img.shape), terrain)


# --- geometry helpers ---------------------------------------------------------------------
def _footprint_window(model, terrain, ref: Reference, margin_px: int):
    """Row/column slices of the reference covering the swing's footprint plus a margin,
    or None when the footprint misses the reference."""
    nl, ne = model.shape
    s = 24
    ll, ee = np.meshgrid(np.linspace(-0.5, nl - 0.5, s), np.linspace(-0.5, ne - 0.5, s),
                         indexing="ij")
    import warnings
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        g = model.image_to_ground(np.stack([ll, ee], -1), terrain)
    g = g[np.isfinite(g).all(axis=-1)]
    if not len(g):
        return None
    x, y, _ = ecef_to_map(g, ref.grid.crs)
    r, c = ref.grid.rowcol(np.array([x.min(), x.max()]), np.array([y.max(), y.min()]))
    r0, r1 = int(r[0]) - margin_px, int(r[1]) + margin_px + 1
    c0, c1 = int(c[0]) - margin_px, int(c[1]) + margin_px + 1
    if r1 <= 0 or c1 <= 0 or r0 >= ref.grid.height or c0 >= ref.grid.width:
        return None
    return (r0, r1), (c0, c1)


def _read_window(ref: Reference, rows, cols) -> tuple[Grid, np.ndarray]:
    """The reference over rows/cols ``(start, stop)`` (may pass its edges: NaN there)."""
    (r0, r1), (c0, c1) = rows, cols
    grid = Grid(ref.grid.crs, ref.grid.transform @ Affine.translation(c0, r0),
                (r1 - r0, c1 - c0))
    out = np.full(grid.shape, np.nan)
    H, W = ref.image.shape
    a0, a1, b0, b1 = max(r0, 0), min(r1, H), max(c0, 0), min(c1, W)
    out[a0 - r0:a1 - r0, b0 - c0:b1 - c0] = ref.image[a0:a1, b0:b1]
    return grid, out


def _average(a: np.ndarray, f: int) -> np.ndarray:
    """``f`` x ``f`` block means (NaN where any input is NaN); the array is cropped to a
    multiple of ``f``."""
    h, w = (a.shape[0] // f) * f, (a.shape[1] // f) * f
    return a[:h, :w].reshape(h // f, f, w // f, f).mean(axis=(1, 3))


def rectify_on(model, source, terrain, grid: Grid, supersample: int) -> np.ndarray:
    """The swing on ``grid``: rendered on a ``supersample`` times finer grid, then
    area-averaged (NaN where the footprint does not cover the whole pixel)."""
    from swathflow.rectification.rectify import rectify_tile
    f = max(int(supersample), 1)
    fine = Grid(grid.crs, grid.transform @ Affine.scale(1.0 / f),
                (grid.height * f, grid.width * f))
    v = rectify_tile(model, source, fine, terrain, kernel="bilinear").astype(float)
    return _average(v, f)


def histogram_match(values: np.ndarray, target: np.ndarray) -> np.ndarray:
    """``values`` mapped monotonically so that their distribution is that of ``target``
    (valid pixels of each; NaN stays NaN)."""
    ok = np.isfinite(values)
    tv = target[np.isfinite(target)]
    if ok.sum() < 16 or tv.size < 16:
        return values
    q = np.linspace(0, 100, 257)
    src_q = np.percentile(values[ok], q)
    dst_q = np.percentile(tv, q)
    src_q, keep = np.unique(src_q, return_index=True)
    out = np.full(values.shape, np.nan)
    out[ok] = np.interp(values[ok], src_q, dst_q[keep])
    return out


def coarse_shift(rect: np.ndarray, ref: np.ndarray, margin: int, factor: int):
    """Integer shift ``s`` (reference pixels) with the swing's content at ``x`` found in the
    reference at ``x + s``: minimum grey difference on ``factor`` x ``factor`` averages.
    ``rect`` and ``ref`` share one grid; ``margin`` pixels around the grid are searched.
    Returns ``(s, contrast)`` or ``(None, 0)``."""
    f = max(int(factor), 1)
    m = (margin // f) * f
    inner = rect[m:rect.shape[0] - m, m:rect.shape[1] - m]
    h, w = (inner.shape[0] // f) * f, (inner.shape[1] // f) * f
    tc = _average(inner[:h, :w], f)
    rc = _average(ref[:h + 2 * m, :w + 2 * m], f)
    tok, rok = np.isfinite(tc), np.isfinite(rc)
    if tok.sum() < 32:
        return None, 0.0
    s, cost = mmgd_search(np.where(tok, tc, 0.0), tok, np.where(rok, rc, 0.0), rok, m // f,
                          min_pixels=max(16, int(0.5 * tok.sum())))
    if s is None:
        return None, 0.0
    fin = cost[np.isfinite(cost)]
    contrast = float((np.median(fin) - fin.min()) / max(np.median(fin), 1e-12))
    return (s[0] * f, s[1] * f), contrast


#: the last :func:`coarsened` reference: {(id of the original, factor): (original, coarse)}
_COARSE: dict = {}


def coarsened(ref: Reference, raw_gsd: float | None) -> Reference:
    """``ref`` on a lattice no finer than half the swing's raw pixel (``raw_gsd``, metres):
    a finer reference holds nothing the swing can match, and its windows grow with the
    square of the ratio (a 0.02 m reference for 0.4 m pixels: 400 times the pixels, a
    runaway). Its pixels are averaged ``f`` x ``f``; the result is kept for the next call."""
    if not raw_gsd or ref.res <= 0:
        return ref
    f = int(0.5 * float(raw_gsd) // ref.res)
    if f < 2:
        return ref
    key = (id(ref), f)
    hit = _COARSE.get(key)
    if hit is not None and hit[0] is ref:
        return hit[1]
    img = _average(ref.image, f)
    grid = Grid(ref.grid.crs, ref.grid.transform @ Affine.scale(f), img.shape)
    out = Reference(ref.path, img, grid, ref.dem)
    _COARSE.clear()
    _COARSE[key] = (ref, out)
    return out


# --- one swing ---------------------------------------------------------------------------
def match_swing(image_id: str, model, source, terrain, ref: Reference,
                settings: MatchSettings = DEFAULT_SETTINGS,
                raw_gsd: float | None = None) -> tuple[pd.DataFrame, dict]:
    """Automatic control points of one swing (table with :data:`POINT_COLUMNS`) and
    statistics of the matching (blocks tried, matched, reasons, coarse shift)."""
    st = settings
    ref = coarsened(ref, raw_gsd)
    stats: dict = {"image_id": image_id, "blocks": 0, "matched": 0, "reasons": {}}
    margin = int(np.ceil(st.margin_m / ref.res / st.coarse)) * st.coarse
    win = _footprint_window(model, terrain, ref, margin)
    if win is None:
        stats["status"] = "outside_reference"
        return _empty(), stats
    grid, refw = _read_window(ref, *win)
    sup = int(np.clip(np.ceil(ref.res / raw_gsd), 1, 6)) if raw_gsd else 2
    # the swing itself only within its footprint (the margin is for the reference)
    pad = margin - 2
    core = np.zeros(refw.shape, bool)
    core[pad:-pad, pad:-pad] = True
    rect = np.full(refw.shape, np.nan)
    rect[core] = rectify_on(model, source, terrain, grid.window(slice(pad, -pad),
                                                                slice(pad, -pad)), sup).ravel()
    rect = histogram_match(rect, np.where(core & np.isfinite(rect), refw, np.nan))
    s, contrast = coarse_shift(rect, refw, margin, st.coarse)
    stats.update(coarse_shift=s, coarse_contrast=contrast)
    if s is None or contrast < 0.05:
        stats["status"] = "no_coarse_match"
        return _empty(), stats
    rows = _match_blocks(rect, refw, s, st, stats, (win[0][0], win[1][0]))
    stats["status"] = "ok"
    if not rows:
        return _empty(), stats
    return _points(image_id, model, terrain, ref, grid, rows, st), stats


def _match_blocks(rect, refw, s, st: MatchSettings, stats, origin) -> list[tuple]:
    """(p_row, p_col, q_row, q_col, BlockMatch) for every matched block. The blocks sit on
    a lattice anchored to the reference's pixels (``origin``: the window's first row and
    column there), so that successive rounds match the same blocks."""
    b, S = st.block, st.search
    H, W = refw.shape
    out = []
    ok_rect = np.isfinite(rect)
    step = max(int(b * st.step), 4)
    for r in range(-origin[0] % step, H - b + 1, step):
        for c in range(-origin[1] % step, W - b + 1, step):
            r0, c0 = r - s[0] - S, c - s[1] - S
            if r0 < 0 or c0 < 0 or r0 + b + 2 * S > H or c0 + b + 2 * S > W:
                continue
            mov_ok = ok_rect[r0:r0 + b + 2 * S, c0:c0 + b + 2 * S]
            if mov_ok.mean() < st.min_valid:
                continue
            blk = refw[r:r + b, c:c + b]
            blk_ok = np.isfinite(blk)
            if not blk_ok.all():
                continue
            stats["blocks"] += 1
            mov = rect[r0:r0 + b + 2 * S, c0:c0 + b + 2 * S]
            m = match_block(blk, blk_ok, np.where(mov_ok, mov, 0.0), mov_ok, S,
                            min_texture=st.min_texture, min_pixels=min(256, b * b // 3))
            if not m.ok:
                stats["reasons"][m.reason] = stats["reasons"].get(m.reason, 0) + 1
                continue
            stats["matched"] += 1
            pr, pc = r + (b - 1) / 2.0, c + (b - 1) / 2.0
            out.append((pr, pc, pr - s[0] + m.offset[0], pc - s[1] + m.offset[1], m))
    return out


def _points(image_id, model, terrain, ref: Reference, grid: Grid, rows, st) -> pd.DataFrame:
    p = np.array([[r[0], r[1]] for r in rows])
    q = np.array([[r[2], r[3]] for r in rows])
    # the raw pixel under q (and one reference pixel on in row and column): the swing's
    # own model and terrain, exactly as it was rectified
    qq = np.concatenate([q, q + [1.0, 0.0], q + [0.0, 1.0]])
    xq, yq = grid.xy(qq[:, 0], qq[:, 1])
    raw = model.ground_to_image(grid.to_ecef(xq, yq, terrain), clip=False)
    n = len(q)
    lin_el, d_row, d_col = raw[:n], raw[n:2 * n] - raw[:n], raw[2 * n:] - raw[:n]
    xp, yp = grid.xy(p[:, 0], p[:, 1])
    ground = grid.to_ecef(xp, yp, ref.dem if ref.dem is not None else terrain)
    if ref.dem is not None and n and not np.isfinite(ground).all(axis=1).any():
        raise FormatError(f"{getattr(ref.dem, 'path', 'the reference DEM')}: the reference "
                          f"DEM has no height under any of the {n} points matched in swing "
                          f"{image_id} (it misses the swath); give a reference DEM that "
                          f"covers the flight (--reference-dem or [reference] dem), or none "
                          f"(the mission's terrain is used)")
    acc = (st.accuracy_m / ref.res) if st.accuracy_m is not None else 0.25
    msig = np.array([r[4].sigma for r in rows], float)
    sig = np.sqrt(msig ** 2 + st.sigma_floor ** 2 + acc ** 2)          # reference px
    # raw covariance J diag(sig^2) J^T, J columns = raw change per reference row / col
    var_line = (d_row[:, 0] * sig[:, 0]) ** 2 + (d_col[:, 0] * sig[:, 1]) ** 2
    var_elem = (d_row[:, 1] * sig[:, 0]) ** 2 + (d_col[:, 1] * sig[:, 1]) ** 2
    nl, ne = model.shape
    df = pd.DataFrame({
        "gcp_id": [f"A{image_id}-{k:04d}" for k in range(n)], "image_id": image_id,
        "line": lin_el[:, 0], "element": lin_el[:, 1],
        "X": ground[:, 0], "Y": ground[:, 1], "Z": ground[:, 2], "role": "control",
        "sigma_line": np.sqrt(var_line), "sigma_element": np.sqrt(var_elem),
        "E": xp, "N": yp,
        "quality": [float(r[4].peak) for r in rows],
        "texture": [float(r[4].texture) for r in rows],
        "match_sigma": np.hypot(msig[:, 0], msig[:, 1]),
        "shift_row": q[:, 0] - p[:, 0], "shift_col": q[:, 1] - p[:, 1]})
    keep = (np.isfinite(df[["line", "element", "X", "Y", "Z", "sigma_line",
                            "sigma_element"]].to_numpy()).all(axis=1)
            & (df["line"] > -0.5) & (df["line"] < nl - 0.5)
            & (df["element"] > -0.5) & (df["element"] < ne - 0.5))
    return df[keep].reset_index(drop=True)


def _empty() -> pd.DataFrame:
    return pd.DataFrame({c: pd.Series(dtype=object if c in ("gcp_id", "image_id", "role")
                                      else float) for c in POINT_COLUMNS})
