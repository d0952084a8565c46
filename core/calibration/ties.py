"""Tie points between overlapping swings of opposite directions: image-to-image matches
whose ground coordinates are unknowns of the adjustment.

Matching: both swings are rectified with the current parameters onto one grid over their
common footprint (the reference's pixel size), the second is histogram-matched to the
first, and well-textured blocks are matched with the mosaic's block matcher
(:func:`swathflow.mosaicking.matching.match_block`). A block centred at ``p`` in the first
swing's rendering is found at ``q`` in the second's; both are carried back to raw (line,
element) through their own model and terrain, and the ground point at ``p`` (on the terrain)
is the start value of the tie point's unknown ground coordinates.

Adjustment: :func:`tie_group` gives the observation group (observed minus computed image
coordinates of every tie observation, the partials with respect to the calibration unknowns
and to the tie point's own three ground-coordinate corrections, metres in ECEF) that
:func:`swathflow.calibration.control.calibrate` adds beside the control points when it is
given ``ties``. Left and right swings then see the same ground point through their own
boresights, which separates the direction-dependent boresight where control is sparse or
coarse.
"""
from __future__ import annotations

import numpy as np
import pandas as pd

from swathflow.calibration.partials import image_partials
from swathflow.calibration.reference import (MatchSettings, _footprint_window, _read_window,
                                             histogram_match, rectify_on)
from swathflow.mosaicking.matching import match_block

TIE_COLUMNS = ("tie_id", "image_id", "line", "element", "sigma_line", "sigma_element",
               "X", "Y", "Z")


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


def match_pair(a, b, models, sources, terrain, ref, settings: MatchSettings,
               raw_gsd: float | None, start: int = 0) -> pd.DataFrame:
    """Tie observations (two rows per tie point, :data:`TIE_COLUMNS`) of swings a and b."""
    wa = _footprint_window(models[a], terrain, ref, 0)
    wb = _footprint_window(models[b], terrain, ref, 0)
    pad = settings.search + 2
    rows = (max(wa[0][0], wb[0][0]) - pad, min(wa[0][1], wb[0][1]) + pad)
    cols = (max(wa[1][0], wb[1][0]) - pad, min(wa[1][1], wb[1][1]) + pad)
    grid, _ = _read_window(ref, rows, cols)
    sup = int(np.clip(np.ceil(ref.res / raw_gsd), 1, 6)) if raw_gsd else 2
    ia = rectify_on(models[a], sources[a], terrain, grid, sup)
    ib = histogram_match(rectify_on(models[b], sources[b], terrain, grid, sup), ia)
    bs, S = settings.block, settings.search
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
            m = match_block(np.where(blk_ok, ia[r:r + bs, c:c + bs], 0.0), blk_ok,
                            np.where(mov_ok, ib[r - S:r + bs + S, c - S:c + bs + S], 0.0),
                            mov_ok, S, min_texture=settings.min_texture,
                            min_pixels=min(256, bs * bs // 3))
            if m.ok:
                p = (r + (bs - 1) / 2.0, c + (bs - 1) / 2.0)
                pts.append((p, (p[0] + m.offset[0], p[1] + m.offset[1]), m.sigma))
    if not pts:
        return pd.DataFrame(columns=list(TIE_COLUMNS))
    out = []
    sig = np.array([np.hypot(np.asarray(s, float), settings.sigma_floor) for _, _, s in pts])
    for iid, k in ((a, 0), (b, 1)):
        q = np.array([t[k] for t in pts])
        qq = np.concatenate([q, q + [1.0, 0.0], q + [0.0, 1.0]])
        x, y = grid.xy(qq[:, 0], qq[:, 1])
        raw = models[iid].ground_to_image(grid.to_ecef(x, y, terrain), clip=False)
        n = len(q)
        d_row, d_col = raw[n:2 * n] - raw[:n], raw[2 * n:] - raw[:n]
        s = sig / np.sqrt(2.0)                # the match error, shared by the two images
        xa, ya = grid.xy(np.array([t[0][0] for t in pts]), np.array([t[0][1] for t in pts]))
        g0 = grid.to_ecef(xa, ya, terrain)
        out.append(pd.DataFrame({
            "tie_id": [f"T{start + i:05d}" for i in range(n)], "image_id": iid,
            "line": raw[:n, 0], "element": raw[:n, 1],
            "sigma_line": np.hypot(d_row[:, 0] * s[:, 0], d_col[:, 0] * s[:, 1]),
            "sigma_element": np.hypot(d_row[:, 1] * s[:, 0], d_col[:, 1] * s[:, 1]),
            "X": g0[:, 0], "Y": g0[:, 1], "Z": g0[:, 2]}))
    df = pd.concat(out, ignore_index=True)
    good = np.isfinite(df[["line", "element", "sigma_line", "sigma_element"]].to_numpy()).all(1)
    bad_ids = set(df.loc[~good, "tie_id"])
    return df[~df["tie_id"].isin(bad_ids)].reset_index(drop=True)


def match_ties(models, sources, terrain, ref, settings: MatchSettings,
               raw_gsd: float | None = None) -> pd.DataFrame:
    """Tie observations between every overlapping pair of opposite-direction swings."""
    tables = []
    n = 0
    for a, b in overlapping_pairs(models, terrain, ref):
        t = match_pair(a, b, models, sources, terrain, ref, settings, raw_gsd, n)
        n += t["tie_id"].nunique()
        tables.append(t)
    if not tables:
        return pd.DataFrame(columns=list(TIE_COLUMNS))
    return pd.concat(tables, ignore_index=True)


def tie_group(models, mats, unk, ties: pd.DataFrame, n_total: int, h: float = 0.05):
    """The tie observations' group for :class:`swathflow.adjustment.Problem`: returns
    ``(names, fn, sigma, point, point_names)``; ``names`` are the 3 ground corrections
    per tie point (appended after the calibration unknowns, ``n_total`` unknowns in all)."""
    n = len(unk.names)
    ids = list(dict.fromkeys(ties["tie_id"]))
    col = {t: n + 3 * k for k, t in enumerate(ids)}
    names = [f"{t}.{a}" for t in ids for a in ("dX", "dY", "dZ")]
    g0 = ties.groupby("tie_id", sort=False)[["X", "Y", "Z"]].first().loc[ids].to_numpy(float)
    start = ties["tie_id"].map(col).to_numpy(int)
    g0_rows = g0[(start - n) // 3]
    spans = []
    for iid, g in ties.groupby("image_id", sort=False):
        spans.append((iid, g.index.to_numpy(), g[["line", "element"]].to_numpy(float)))
    m_obs = len(ties)
    l_obs = np.empty((m_obs, 2))
    for _, idx, le in spans:
        l_obs[idx] = le

    def fn(x, jacobian=True):
        G = g0_rows + np.stack([x[start], x[start + 1], x[start + 2]], axis=1)
        comp = np.full((m_obs, 2), np.nan)
        J = np.zeros((m_obs, 2, n_total)) if jacobian else None
        for iid, idx, _ in spans:
            mod = models[iid].with_vector(mats[iid] @ x[:n])
            comp[idx] = mod.ground_to_image(G[idx], clip=False)
            if not jacobian:
                continue
            M = mats[iid]
            used = np.flatnonzero(np.any(M[:, ~unk.fixed] != 0, axis=1))
            names_used = [mod.parameters.flat_names()[i] for i in used]
            D = image_partials(mod, G[idx], comp[idx], names_used)
            J[idx, :, :n] = D @ M[used]
            for k in range(3):
                e = np.zeros(3)
                e[k] = h
                d = (mod.ground_to_image(G[idx] + e, clip=False)
                     - mod.ground_to_image(G[idx] - e, clip=False)) / (2 * h)
                J[idx, :, start[idx] + k] = d
        r = (l_obs - comp).ravel()
        return r, (J.reshape(2 * m_obs, n_total) if jacobian else None)

    sigma = ties[["sigma_line", "sigma_element"]].to_numpy(float).ravel()
    point = np.repeat(np.arange(m_obs), 2)
    pnames = np.array([f"{t}@{i}" for t, i in zip(ties["tie_id"], ties["image_id"])],
                      dtype=object)
    return names, fn, sigma, point, pnames
