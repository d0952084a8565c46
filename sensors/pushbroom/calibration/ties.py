"""Tie points of a push-broom calibration: the table (``tie_id,image_id,line,element``) and
the least-squares intersection of their rays (the tie coordinates' starting values)."""
from __future__ import annotations

import os
from typing import Mapping, Sequence

import numpy as np
import pandas as pd

from swathflow.errors import FormatError

TIE_COLUMNS = ("tie_id", "image_id", "line", "element")


def read_ties(path, images: Sequence[str] | None = None) -> pd.DataFrame:
    """Read a tie-point table (``tie_id,image_id,line,element``; see
    docs/mission-format-pushbroom.md). Raises FormatError naming the file, row and fix."""
    path = os.fspath(path)
    if not os.path.exists(path):
        raise FormatError(f"{path}: tie-point file not found (check [ties].file in "
                          f"mission.toml)")
    try:
        df = pd.read_csv(path, dtype={"tie_id": str, "image_id": str})
    except (pd.errors.ParserError, pd.errors.EmptyDataError, UnicodeDecodeError) as exc:
        raise FormatError(f"{path}: cannot be read as CSV: {exc}") from None
    df.columns = [str(c).strip() for c in df.columns]
    miss = [c for c in TIE_COLUMNS if c not in df.columns]
    if miss:
        raise FormatError(f"{path}: missing column(s) {', '.join(miss)}; the header must "
                          f"contain {','.join(TIE_COLUMNS)}")
    for c in ("line", "element"):
        v = pd.to_numeric(df[c], errors="coerce").to_numpy(float)
        bad = ~np.isfinite(v)
        if bad.any():
            raise FormatError(f"{path}: file row {int(np.flatnonzero(bad)[0]) + 2}, column "
                              f"{c}: not a finite number; delete unmeasured rows")
        df[c] = v
    for c in ("tie_id", "image_id"):
        bad = df[c].isna().to_numpy()
        if bad.any():
            raise FormatError(f"{path}: file row {int(np.flatnonzero(bad)[0]) + 2}: empty "
                              f"{c}")
    df["tie_id"] = df["tie_id"].astype(str)
    df["image_id"] = df["image_id"].astype(str)
    if images is not None:
        bad = ~df["image_id"].isin(list(images)).to_numpy()
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            raise FormatError(f"{path}: file row {i + 2}: unknown image id "
                              f"{df['image_id'][i]!r}; use one of {', '.join(images)}")
    dup = df.duplicated(["tie_id", "image_id"]).to_numpy()
    if dup.any():
        raise FormatError(f"{path}: file row {int(np.flatnonzero(dup)[0]) + 2}: tie point "
                          f"measured twice in one image; keep one row per tie and image")
    return df.reset_index(drop=True)


def mission_ties(mission) -> pd.DataFrame | None:
    """The mission's tie points (``[ties] file = "ties.csv"``), or None."""
    tc = mission.config.get("ties")
    if tc is None:
        return None
    if not isinstance(tc, dict) or "file" not in tc:
        raise FormatError(f"{mission.path / 'mission.toml'}: [ties] needs file = "
                          f"\"ties.csv\"")
    p = mission.path / tc["file"]
    return read_ties(p, list(mission.images))


def intersect_rays(models: Mapping, obs: pd.DataFrame, id_col: str = "tie_id"):
    """Least-squares intersection of the rays of every point's image observations:
    ``(ids, ECEF (n, 3), rays per point)``; points with fewer than two rays are left out."""
    o_all, d_all, k_all = [], [], []
    ids, inv = np.unique(obs[id_col].to_numpy(str), return_inverse=True)
    for iid, g in obs.groupby("image_id", sort=False):
        o, d = models[iid].ray(g[["line", "element"]].to_numpy(float))
        o_all.append(o)
        d_all.append(d)
        k_all.append(inv[g.index.to_numpy()])
    o, d, k = np.concatenate(o_all), np.concatenate(d_all), np.concatenate(k_all)
    ok = np.isfinite(o).all(1) & np.isfinite(d).all(1)
    o, d, k = o[ok], d[ok], k[ok]
    M = np.eye(3)[None] - d[:, :, None] * d[:, None, :]
    A = np.zeros((ids.size, 3, 3))
    b = np.zeros((ids.size, 3))
    np.add.at(A, k, M)
    np.add.at(b, k, np.einsum("nij,nj->ni", M, o))
    n = np.bincount(k, minlength=ids.size)
    good = n >= 2
    X = np.full((ids.size, 3), np.nan)
    X[good] = np.linalg.solve(A[good], b[good][..., None])[..., 0]
    return ids, X, n
