"""Tie points between overlapping swings of opposite directions: image-to-image matches
whose ground coordinates are unknowns of the adjustment.

Matching: both swings are rectified with the current parameters onto one grid over their
common footprint at the raw pixel size (not the reference's: image-to-image matching does
not depend on how coarse the reference is), the second is histogram-matched to the first,
and well-textured blocks are matched with the mosaic's block matcher
(:func:`swathflow.mosaicking.matching.match_block`). A block centred at ``p`` in the first
swing's rendering is found at ``q`` in the second's; both are carried back to raw (line,
element) through their own model and terrain, and the ground point at ``p`` (on the terrain)
is the start value of the tie point's unknown ground coordinates. At most
``settings.tie_max`` per pair are kept, spread along the overlap.

Adjustment: :func:`tie_group` gives the observation group (observed minus computed image
coordinates of every tie observation, the partials with respect to the calibration unknowns
and to the tie point's own east, north, up corrections in metres, the up one with the
terrain's height as a prior: the two rays are nearly parallel) that
:func:`swathflow.calibration.control.calibrate` adds beside the control points when it is
given ``ties``. Left and right swings then see the same ground point through their own
boresights, which separates the direction-dependent boresight where control is sparse or
coarse.
"""
from __future__ import annotations

import time

import numpy as np
import pandas as pd
import scipy.sparse as sp

from swathflow.calibration.evaluation import BulkObservations
from swathflow.calibration.reference import (MatchSettings, _footprint_window, histogram_match,
                                             rectify_on)
from swathflow.geometry.geodesy import ecef_to_geodetic
from swathflow.geometry.grid import Grid
from swathflow.mosaicking.matching import match_block

TIE_COLUMNS = ("tie_id", "image_id", "line", "element", "sigma_line", "sigma_element",
               "X", "Y", "Z", "E", "N", "match_sigma")


def _direction(model) -> str:
    return str(model.image_attrs.get("direction", "")).upper()


def overlapping_pairs(models, terrain, ref) -> list[tuple[str, str]]:
    """Pairs (a, b) of swings of different directions whose footprints (on the reference's
    lattice) overlap."""
    boxes = {}
    for iid, m in models.items():
        w = _footprint_window(m, terrain, ref, 0)
        if w is not None:
            boxes[iid] = w
    ids = list(boxes)
    out = []
    for i, a in enumerate(ids):
        for b in ids[i + 1:]:
            if _direction(models[a]) == _direction(models[b]):
                continue
            (ra, ca), (rb, cb) = boxes[a], boxes[b]
            rows = min(ra[1], rb[1]) - max(ra[0], rb[0])
            cols = min(ca[1], cb[1]) - max(ca[0], cb[0])
            if rows > 8 and cols > 8:
                out.append((a, b))
    return out


def _common_grid(a, b, models, terrain, ref, res: float) -> Grid | None:
    """A grid of pixel size ``res`` (in the reference's CRS) over the common part of the
    footprints of swings a and b, or None when they do not overlap."""
    wa = _footprint_window(models[a], terrain, ref, 0)
    wb = _footprint_window(models[b], terrain, ref, 0)
    if wa is None or wb is None:
        return None
    r0, r1 = max(wa[0][0], wb[0][0]), min(wa[0][1], wb[0][1])
    c0, c1 = max(wa[1][0], wb[1][0]), min(wa[1][1], wb[1][1])
    if r1 <= r0 or c1 <= c0:
        return None
    x0, y0 = ref.grid.xy(r0, c0, offset="ul")
    x1, y1 = ref.grid.xy(r1, c1, offset="ul")
    return Grid.from_bounds(ref.grid.crs, (x0, y1, x1, y0), res, snap=True)


def _match_grid(ia, ib, settings: MatchSettings, stats: dict) -> list[tuple]:
    """((row, col) in a, (row, col) in b, sigma) of every well-textured block of ``ia``
    found in ``ib`` (both on one grid)."""
    bs, S = settings.tie_block, settings.tie_search
    H, W = ia.shape
    ok_a, ok_b = np.isfinite(ia), np.isfinite(ib)
    pts = []
    step = max(int(bs * settings.step), 4)
    for r in range(S, H - bs - S + 1, step):
        for c in range(S, W - bs - S + 1, step):
            blk_ok = ok_a[r:r + bs, c:c + bs]
            mov_ok = ok_b[r - S:r + bs + S, c - S:c + bs + S]
            if blk_ok.mean() < 0.95 or mov_ok.mean() < settings.min_valid:
                continue
            stats["blocks"] += 1
            m = match_block(np.where(blk_ok, ia[r:r + bs, c:c + bs], 0.0), blk_ok,
                            np.where(mov_ok, ib[r - S:r + bs + S, c - S:c + bs + S], 0.0),
                            mov_ok, S, min_texture=settings.min_texture,
                            min_pixels=min(256, bs * bs // 3))
            if not m.ok:
                stats["reasons"][m.reason] = stats["reasons"].get(m.reason, 0) + 1
                continue
            p = (r + (bs - 1) / 2.0, c + (bs - 1) / 2.0)
            pts.append((p, (p[0] + m.offset[0], p[1] + m.offset[1]), m.sigma))
    stats["matched"] = len(pts)
    kept = _spread(pts, settings.tie_max)
    stats["kept"] = len(kept)
    return kept


def _spread(pts: list[tuple], k: int) -> list[tuple]:
    """At most ``k`` of ``pts``: the best (smallest sigma) in each of ``k`` equal bins
    along the longer axis of their extent."""
    if len(pts) <= k:
        return pts
    p = np.array([t[0] for t in pts])
    axis = int(np.ptp(p[:, 1]) > np.ptp(p[:, 0]))
    edges = np.linspace(p[:, axis].min(), p[:, axis].max() + 1e-9, k + 1)
    b = np.clip(np.searchsorted(edges, p[:, axis], side="right") - 1, 0, k - 1)
    s = np.array([np.hypot(*np.asarray(t[2], float)) for t in pts])
    keep = [min(np.flatnonzero(b == i), key=lambda j: s[j]) for i in range(k)
            if np.any(b == i)]
    return [pts[j] for j in sorted(keep)]


def match_pair(a, b, models, sources, terrain, ref, settings: MatchSettings,
               raw_gsd: float | None, start: int = 0,
               stats: dict | None = None) -> pd.DataFrame:
    """Tie observations (two rows per tie point, :data:`TIE_COLUMNS`) of swings a and b.

    The two swings are rendered at the raw pixel size (``raw_gsd``; the reference's half
    pixel without it), not the reference's: image-to-image matching does not depend on
    how coarse the reference is."""
    stats = {"pair": f"{a}-{b}", "blocks": 0, "matched": 0, "kept": 0, "reasons": {}} \
        if stats is None else stats
    res = float(raw_gsd) if raw_gsd else ref.res / 2.0
    grid = _common_grid(a, b, models, terrain, ref, res)
    if grid is None:
        return pd.DataFrame(columns=list(TIE_COLUMNS))
    ia = rectify_on(models[a], sources[a], terrain, grid, 2)
    ib = histogram_match(rectify_on(models[b], sources[b], terrain, grid, 2), ia)
    pts = _match_grid(ia, ib, settings, stats)
    if not pts:
        return pd.DataFrame(columns=list(TIE_COLUMNS))
    out = []
    sig = np.array([np.hypot(settings.tie_sigma_factor * np.asarray(s, float),
                             settings.sigma_floor) for _, _, s in pts])
    s = sig / np.sqrt(2.0)                # the match error, shared by the two images
    xa, ya = grid.xy(np.array([t[0][0] for t in pts]), np.array([t[0][1] for t in pts]))
    g0 = grid.to_ecef(xa, ya, terrain)
    for iid, k in ((a, 0), (b, 1)):
        q = np.array([t[k] for t in pts])
        qq = np.concatenate([q, q + [1.0, 0.0], q + [0.0, 1.0]])
        x, y = grid.xy(qq[:, 0], qq[:, 1])
        raw = models[iid].ground_to_image(grid.to_ecef(x, y, terrain), clip=False)
        n = len(q)
        d_row, d_col = raw[n:2 * n] - raw[:n], raw[2 * n:] - raw[:n]
        out.append(pd.DataFrame({
            "tie_id": [f"T{start + i:05d}" for i in range(n)], "image_id": iid,
            "line": raw[:n, 0], "element": raw[:n, 1],
            "sigma_line": np.hypot(d_row[:, 0] * s[:, 0], d_col[:, 0] * s[:, 1]),
            "sigma_element": np.hypot(d_row[:, 1] * s[:, 0], d_col[:, 1] * s[:, 1]),
            "X": g0[:, 0], "Y": g0[:, 1], "Z": g0[:, 2],
            "E": xa, "N": ya, "match_sigma": np.hypot(sig[:, 0], sig[:, 1])}))
    df = pd.concat(out, ignore_index=True)
    good = np.isfinite(df[["line", "element", "sigma_line", "sigma_element"]].to_numpy()).all(1)
    for iid in (a, b):
        nl, ne = models[iid].shape
        inside = ((df["line"] > -0.5) & (df["line"] < nl - 0.5) & (df["element"] > -0.5)
                  & (df["element"] < ne - 0.5))
        good &= inside | (df["image_id"] != iid)
    bad_ids = set(df.loc[~good, "tie_id"])
    return df[~df["tie_id"].isin(bad_ids)].reset_index(drop=True)


def match_ties(models, sources, terrain, ref, settings: MatchSettings,
               raw_gsd: float | None = None, stats: list | None = None) -> pd.DataFrame:
    """Tie observations between every overlapping pair of opposite-direction swings;
    ``stats``, when given, receives one dict per pair (blocks tried, matched, reasons)."""
    tables = []
    n = 0
    for a, b in overlapping_pairs(models, terrain, ref):
        st = {"pair": f"{a}-{b}", "blocks": 0, "matched": 0, "kept": 0, "reasons": {}}
        t0 = time.perf_counter()
        t = match_pair(a, b, models, sources, terrain, ref, settings, raw_gsd, n, st)
        st["seconds"] = round(time.perf_counter() - t0, 3)
        n += t["tie_id"].nunique()
        tables.append(t)
        if stats is not None:
            stats.append(st)
    tables = [t for t in tables if len(t)]
    if not tables:
        return pd.DataFrame(columns=list(TIE_COLUMNS))
    return pd.concat(tables, ignore_index=True)


def _enu_axes(g0: np.ndarray) -> np.ndarray:
    """(k, 3, 3): columns east, north, up (ECEF unit vectors) at each point."""
    llh = ecef_to_geodetic(g0)
    lat, lon = np.radians(llh[:, 0]), np.radians(llh[:, 1])
    sl, cl, sp, cp = np.sin(lon), np.cos(lon), np.sin(lat), np.cos(lat)
    east = np.stack([-sl, cl, np.zeros_like(sl)], -1)
    north = np.stack([-sp * cl, -sp * sl, cp], -1)
    up = np.stack([cp * cl, cp * sl, sp], -1)
    return np.stack([east, north, up], axis=-1)


def tie_group(models, mats, unk, ties: pd.DataFrame, n_total: int,
              height_sigma: float = 1.0):
    """The tie observations' group for :class:`swathflow.adjustment.Problem`: returns
    ``(names, prior_sigma, fn, sigma, point, point_names)``. ``names`` are the 3 ground
    corrections per tie point (east, north, up in metres, appended after the calibration
    unknowns, ``n_total`` unknowns in all); ``prior_sigma`` their priors: none on east and
    north, ``height_sigma`` on up (the terrain's height). Two swings see a ground point
    from nearly the same place (rays a few degrees apart), so the height along the ray is
    taken from the terrain, and the horizontal position from the images."""
    n = len(unk.names)
    ids = list(dict.fromkeys(ties["tie_id"]))
    col = {t: n + 3 * k for k, t in enumerate(ids)}
    names = [f"{t}.{a}" for t in ids for a in ("dE", "dN", "dU")]
    prior_sigma = np.tile([np.inf, np.inf, float(height_sigma)], len(ids))
    g0 = ties.groupby("tie_id", sort=False)[["X", "Y", "Z"]].first().loc[ids].to_numpy(float)
    start = ties["tie_id"].map(col).to_numpy(int)
    g0_rows = g0[(start - n) // 3]
    axes = _enu_axes(g0_rows)                                    # (m, 3, 3)
    m_obs = len(ties)
    l_obs = ties[["line", "element"]].to_numpy(float)
    bulk = BulkObservations(models, mats, ties["image_id"].astype(str).to_numpy())
    rows = np.repeat(np.arange(2 * m_obs), n + 3)
    cols = np.concatenate([np.tile(np.arange(n), (2 * m_obs, 1)),
                           np.repeat(start, 2)[:, None] + np.arange(3)], axis=1).ravel()

    def fn(x, jacobian=True):
        d = np.stack([x[start], x[start + 1], x[start + 2]], axis=1)
        G = g0_rows + np.einsum("mij,mj->mi", axes, d)
        comp, d_x, d_g = bulk.evaluate(x[:n], G, jacobian)
        r = (l_obs - comp).ravel()
        if not jacobian:
            return r, None
        d_t = np.einsum("mag,mgk->mak", d_g, axes)          # by east, north, up
        vals = np.concatenate([d_x, d_t], axis=2).ravel()
        J = sp.csr_matrix((vals, (rows, cols)), shape=(2 * m_obs, n_total))
        return r, J

    sigma = ties[["sigma_line", "sigma_element"]].to_numpy(float).ravel()
    point = np.repeat((start - n) // 3, 2)          # a tie point is tested (and rejected) whole
    return names, prior_sigma, fn, sigma, point, np.array(ids, dtype=object)
