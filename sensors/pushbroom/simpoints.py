"""Ground points of the simulated push-broom mission: control, check and tie points seen by
several images well inside their edges, and their image observations."""
from __future__ import annotations

import math

import numpy as np
import pandas as pd

from swathflow.errors import SwathflowError
from swathflow.geometry.geodesy import geodetic_to_ecef, transformer

def _ground_xyz(en, terrain, crs) -> np.ndarray:
    en = np.asarray(en, float).reshape(-1, 2)
    lon, lat = transformer(crs, "EPSG:4326").transform(en[:, 0], en[:, 1])
    h = terrain.height(np.asarray(lat), np.asarray(lon))
    return geodetic_to_ecef(np.stack([lat, lon, h], -1))


def sample_points(cfg, plan, strips, models, terrain, n, rng, min_views=3,
                  min_sep=0.0, avoid=None, max_tries=30):
    """``n`` ground points (ECEF) under the common coverage of the strips, each seen by at
    least ``min_views`` images well inside their edges; returns (xyz, en, image points
    per image id: (point index, line, element))."""
    az = math.radians(cfg.heading)
    fwd = np.array([math.sin(az), math.cos(az)])
    right = np.array([fwd[1], -fwd[0]])
    got_en, got_xyz = [], []
    taken = np.empty((0, 2)) if avoid is None else np.asarray(avoid, float).reshape(-1, 2)
    for _ in range(max_tries):
        k = max(4 * (n - len(got_en)), 16)
        st = rng.integers(0, len(strips), k)
        off = np.array([s["offset_m"] for s in strips])[st]
        along = rng.uniform(-0.5, 0.5, k) * (cfg.common_length + 60.0)
        across = rng.uniform(-0.5, 0.5, k) * plan.swath * 0.95
        en = (np.asarray(plan.centre)[None] + along[:, None] * fwd[None]
              + (off + across)[:, None] * right[None])
        xyz = _ground_xyz(en, terrain, plan.crs)
        seen = np.zeros(k, int)
        for m in models.values():
            ij = m.ground_to_image(xyz)
            seen += _inside(ij, m, cfg.edge_margin)
        for i in np.flatnonzero(seen >= min_views):
            if min_sep > 0:
                allp = np.concatenate([taken, np.array(got_en).reshape(-1, 2)])
                if len(allp) and np.min(np.hypot(*(allp - en[i]).T)) < min_sep:
                    continue
            got_en.append(en[i])
            got_xyz.append(xyz[i])
            if len(got_en) == n:
                break
        if len(got_en) == n:
            break
    if len(got_en) < n:
        raise SwathflowError(f"could place only {len(got_en)} of {n} ground points seen by "
                             f"{min_views} images; lengthen the strip (common_length)")
    xyz = np.array(got_xyz)
    obs = {}
    for iid, m in models.items():
        ij = m.ground_to_image(xyz)
        ok = _inside(ij, m, cfg.edge_margin)
        obs[iid] = (np.flatnonzero(ok), ij[ok, 0], ij[ok, 1])
    return xyz, np.array(got_en), obs


def _inside(ij, m, margin) -> np.ndarray:
    with np.errstate(invalid="ignore"):
        return (np.isfinite(ij).all(-1) & (ij[:, 0] >= margin)
                & (ij[:, 0] <= m.n_lines - 1 - margin) & (ij[:, 1] >= margin)
                & (ij[:, 1] <= m.n_elements - 1 - margin))


def obs_frame(obs, ids, id_col) -> pd.DataFrame:
    rows = []
    for iid, (idx, li, el) in obs.items():
        rows.append(pd.DataFrame({id_col: np.asarray(ids)[idx], "image_id": iid,
                                  "line": li, "element": el, "_k": idx}))
    df = pd.concat(rows, ignore_index=True)
    return df.sort_values(["_k", "image_id"], kind="stable").reset_index(drop=True)


def write_points(out, cfg, seed: int, pts) -> tuple[pd.DataFrame, pd.DataFrame]:
    """``gcp.csv`` and ``ties.csv`` (observations with measurement noise) and their truth
    (``truth/gcp.csv``, ``truth/ties.csv``, exact image coordinates and ground); returns
    the noisy GCP and tie observations."""
    from swathflow.geometry.geodesy import ecef_to_geodetic
    from swathflow.simulation.bundle import write_csv
    grng = np.random.default_rng([int(seed), 83])
    llh = ecef_to_geodetic(pts.g_xyz)
    gobs = obs_frame(pts.g_obs, pts.gcp_ids, "gcp_id")
    k = gobs.pop("_k").to_numpy()
    gobs["x"], gobs["y"], gobs["z"] = llh[k, 1], llh[k, 0], llh[k, 2]
    gobs["role"] = pts.roles[k]
    truth_g = gobs.copy()
    truth_g["X"], truth_g["Y"], truth_g["Z"] = pts.g_xyz[k, 0], pts.g_xyz[k, 1], pts.g_xyz[k, 2]
    gobs["line"] += grng.normal(0, cfg.gcp_noise, len(gobs))
    gobs["element"] += grng.normal(0, cfg.gcp_noise, len(gobs))
    fmt = {"line": "%.4f", "element": "%.4f", "x": "%.10f", "y": "%.10f", "z": "%.4f"}
    write_csv(out / "gcp.csv", gobs[["gcp_id", "image_id", "line", "element", "x", "y", "z",
                                      "role"]], fmt)
    write_csv(out / "truth" / "gcp.csv", truth_g, {**fmt, "line": "%.6f", "element": "%.6f",
                                                     "X": "%.4f", "Y": "%.4f", "Z": "%.4f"})
    tobs = obs_frame(pts.t_obs, pts.tie_ids, "tie_id")
    k = tobs.pop("_k").to_numpy()
    truth_t = tobs.copy()
    tllh = ecef_to_geodetic(pts.t_xyz)
    truth_t["lon"], truth_t["lat"], truth_t["h"] = tllh[k, 1], tllh[k, 0], tllh[k, 2]
    truth_t["X"], truth_t["Y"], truth_t["Z"] = pts.t_xyz[k, 0], pts.t_xyz[k, 1], pts.t_xyz[k, 2]
    tobs["line"] += grng.normal(0, cfg.tie_noise, len(tobs))
    tobs["element"] += grng.normal(0, cfg.tie_noise, len(tobs))
    write_csv(out / "ties.csv", tobs, {"line": "%.4f", "element": "%.4f"})
    write_csv(out / "truth" / "ties.csv", truth_t,
              {"line": "%.6f", "element": "%.6f", "lon": "%.10f", "lat": "%.10f",
               "h": "%.4f", "X": "%.4f", "Y": "%.4f", "Z": "%.4f"})
    return gobs, tobs
