"""Ground errors of the control and check points in metres (east, north, up), and their
accuracy table in the ASPRS layout (RMSE per axis, horizontal and vertical, mean, max,
count), beside the image residuals in pixels.

An observation's residual ``r = observed - computed`` (line, element; px) is carried to the
ground through the model's Jacobian ``J`` (px per metre of east, north, up at the surveyed
point): the image-derived position minus the surveyed one, ``d``, solves ``J d = r``. A
point seen in two or more images (left and right swings look from different sides) gets
``d`` in 3-D by least squares over its rays (a space intersection, linearised at the
surveyed point); a point seen once gets east and north where its ray meets the surveyed
height (:func:`mono_errors`, iterated to convergence; up is then not observable: NaN).
"""
from __future__ import annotations

import numpy as np
import pandas as pd

__all__ = ["JACOBIAN", "MONO", "enu_basis", "ground_jacobian", "mono_errors", "point_errors",
           "accuracy_table"]

#: the residual table's Jacobian columns: d(line, element) / d(east, north, up), px/m
JACOBIAN = ("dl_de", "dl_dn", "dl_du", "dp_de", "dp_dn", "dp_du")
#: the residual table's ground error of each observation on its own (m, at the surveyed
#: height: :func:`mono_errors`)
MONO = ("east_m", "north_m")
#: NSSDA / ASPRS factors from RMSE to accuracy at 95 % confidence: horizontal (radial,
#: for RMSE_E ~ RMSE_N) and vertical
H95, V95 = 1.7308, 1.9600
#: a multi-ray solution is kept when its weakest direction is at least this fraction of
#: the strongest (the rays cross at a useful angle)
MIN_CONDITION = 0.02


def enu_basis(lat_deg, lon_deg) -> np.ndarray:
    """``(..., 3, 3)`` rows: the east, north and up unit vectors in ECEF."""
    lat, lon = np.radians(lat_deg), np.radians(lon_deg)
    sl, cl, so, co = np.sin(lat), np.cos(lat), np.sin(lon), np.cos(lon)
    z = np.zeros_like(sl)
    east = np.stack([-so, co, z], -1)
    north = np.stack([-sl * co, -sl * so, cl], -1)
    up = np.stack([cl * co, cl * so, sl], -1)
    return np.stack([east, north, up], -2)


def ground_jacobian(d_ground: np.ndarray, lat, lon) -> np.ndarray:
    """``(n, 2, 3)``: d(line, element) / d(east, north, up) (px per m) from the partials
    ``d_ground`` ``(n, 2, 3)`` by the ECEF coordinates (a projector's, analytic) at points
    of geodetic ``lat``, ``lon`` (deg)."""
    basis = enu_basis(np.asarray(lat, float), np.asarray(lon, float))      # (n, 3, 3)
    return np.einsum("nax,nkx->nak", np.asarray(d_ground, float), basis)


def mono_errors(project, xyz: np.ndarray, lat, lon, image: np.ndarray, jac: np.ndarray,
                computed: np.ndarray, iterations: int = 8) -> np.ndarray:
    """``(n, 2)``: east, north (m) of where each observed ``image`` point (line, element)
    meets its surveyed point's height, minus the surveyed ECEF point ``xyz``: Newton-chord
    steps on ``project`` (ECEF points ``(n, 3)`` -> their image coordinates ``(n, 2)``, the
    same observations in the same order) in the point's horizontal plane with the Jacobian
    ``jac`` at the surveyed point (``computed``: its image position), one bulk call a step
    (a pendulum's line coordinate bends strongly near the swing's ends, where one linear
    step is off by decimetres)."""
    basis = enu_basis(np.asarray(lat, float), np.asarray(lon, float))
    J = jac[:, :, :2]
    ok = np.isfinite(J).all(axis=(1, 2)) & np.isfinite(image - computed).all(axis=1)
    inv = np.full(J.shape, np.nan)
    inv[ok] = np.linalg.pinv(J[ok])
    r = image - computed
    d = np.zeros((len(xyz), 2))
    for _ in range(iterations):
        step = (inv @ r[..., None])[..., 0]
        d = d + step
        if not np.nanmax(np.abs(step), initial=0.0) > 1e-4:
            break
        p = xyz + d[:, :1] * basis[:, 0, :] + d[:, 1:] * basis[:, 1, :]
        r = image - project(p)
    return d


def _intersections(r: pd.DataFrame, keys: list, cols: list) -> pd.DataFrame:
    """The ground error of every point seen in two or more images (rows of ``r``; points
    in order of first appearance), all at once: east, north, up by least squares over the
    point's rays (the normal equations of its stacked rays, 3x3) when they cross at a
    useful angle (:data:`MIN_CONDITION`), else east and north with up held (up NaN; the
    mean of its single rays' own east and north when the table has them)."""
    code = r.groupby(keys, sort=False).ngroup().to_numpy()
    k = int(code.max()) + 1
    J = np.stack([r[list(JACOBIAN[:3])].to_numpy(float),
                  r[list(JACOBIAN[3:])].to_numpy(float)], 1)                 # (m, 2, 3)
    v = np.stack([r["y"].to_numpy(float), r["x"].to_numpy(float)], 1)      # (m, 2)
    A = np.zeros((k, 3, 3))
    b = np.zeros((k, 3))
    np.add.at(A, code, np.einsum("mai,maj->mij", J, J))
    np.add.at(b, code, np.einsum("mai,ma->mi", J, v))
    ev = np.linalg.eigvalsh(A)                       # squared singular values of the rays
    crossed = (np.sqrt(np.clip(ev[:, 0], 0, None)) >= MIN_CONDITION * np.sqrt(ev[:, -1])) & (
        ev[:, -1] > 0)
    d = np.full((k, 3), np.nan)
    if crossed.any():
        d[crossed] = np.linalg.solve(A[crossed], b[crossed][..., None])[..., 0]
    flat = ~crossed
    if flat.any():
        d[flat, :2] = (np.linalg.pinv(A[flat][:, :2, :2]) @ b[flat][:, :2, None])[..., 0]
        if set(MONO) <= set(r.columns):              # the exact single rays
            mono = np.zeros((k, 2))
            np.add.at(mono, code, r[list(MONO)].to_numpy(float))
            mono /= np.bincount(code, minlength=k)[:, None]
            d[flat, :2] = mono[flat]
    first = np.unique(code, return_index=True)[1]
    head = r.iloc[first]
    return pd.DataFrame({"stage": head["stage"].to_numpy(), "role": head["role"].to_numpy(),
                         "gcp_id": head["gcp_id"].to_numpy(),
                         "rays": np.bincount(code, minlength=k), "east": d[:, 0],
                         "north": d[:, 1], "up": d[:, 2]}, columns=cols)


def point_errors(res: pd.DataFrame) -> pd.DataFrame:
    """One row per stage, role and point: the ground error ``east``, ``north``, ``up`` (m,
    image-derived minus surveyed), ``horizontal`` (m), the number of ``rays`` (images)
    and whether ``up`` was observed, from the residual table's rows with the Jacobian
    columns (:data:`JACOBIAN`)."""
    need = {"gcp_id", "stage", "role", "x", "y", *JACOBIAN}
    cols = ["stage", "role", "gcp_id", "rays", "east", "north", "up", "horizontal"]
    if not need <= set(res.columns):
        return pd.DataFrame(columns=cols)
    ok = res[list(("x", "y") + JACOBIAN)].notna().all(axis=1)
    r = res[ok]
    keys = ["stage", "role", "gcp_id"]
    rays = r.groupby(keys, sort=False)["x"].transform("size").to_numpy()
    one = r[rays == 1]                       # most points: one ray, no loop
    if set(MONO) <= set(one.columns):
        en = one[list(MONO)].to_numpy(float)
    else:
        J = one[list(JACOBIAN)].to_numpy(float).reshape(-1, 2, 3)[:, :, :2]
        en = np.linalg.solve(J, one[["y", "x"]].to_numpy(float)[..., None])[..., 0]
    single = pd.DataFrame({"stage": one["stage"].to_numpy(), "role": one["role"].to_numpy(),
                           "gcp_id": one["gcp_id"].to_numpy(), "rays": 1, "east": en[:, 0],
                           "north": en[:, 1], "up": np.nan})
    parts = [single]
    many = r[rays > 1]
    if len(many):
        parts.append(_intersections(many, keys, cols[:-1]))
    out = pd.concat(parts, ignore_index=True).astype(
        {"rays": int, "east": float, "north": float, "up": float})
    out["horizontal"] = np.hypot(out["east"].to_numpy(float), out["north"].to_numpy(float))
    return out[cols]


def _rmse(v: np.ndarray) -> float:
    v = v[np.isfinite(v)]
    return float(np.sqrt(np.mean(v ** 2))) if v.size else np.nan


def _mean(v: np.ndarray) -> float:
    v = v[np.isfinite(v)]
    return float(v.mean()) if v.size else np.nan


def accuracy_table(points: pd.DataFrame, res: pd.DataFrame | None = None) -> pd.DataFrame:
    """The ASPRS-style table per stage and role from :func:`point_errors`: point count,
    mean and RMSE of east, north and up (m), RMSE_H = sqrt(RMSE_E^2 + RMSE_N^2), the
    largest horizontal and vertical error, the NSSDA accuracies at 95 % (1.7308 RMSE_H,
    1.96 RMSE_U) and, from ``res``, the RMS of the image residuals x and y (px) beside
    them."""
    rows = []
    for (stage, role), g in points.groupby(["stage", "role"], sort=False):
        e, n, u = (g[c].to_numpy(float) for c in ("east", "north", "up"))
        rmse_e, rmse_n, rmse_u = _rmse(e), _rmse(n), _rmse(u)
        rmse_h = float(np.hypot(rmse_e, rmse_n))
        row = {"stage": stage, "role": role, "points": len(g),
               "with_up": int(np.isfinite(u).sum()),
               "mean_E": _mean(e), "mean_N": _mean(n), "mean_U": _mean(u),
               "RMSE_E": rmse_e, "RMSE_N": rmse_n, "RMSE_H": rmse_h, "RMSE_U": rmse_u,
               "max_H": float(np.nanmax(np.hypot(e, n))) if len(g) else np.nan,
               "max_U": float(np.nanmax(np.abs(u))) if np.isfinite(u).any() else np.nan,
               "H95": H95 * rmse_h, "V95": V95 * rmse_u}
        if res is not None:
            q = res[(res["stage"] == stage) & (res["role"] == role)]
            row["rms_x_px"] = _rmse(q["x"].to_numpy(float))
            row["rms_y_px"] = _rmse(q["y"].to_numpy(float))
        rows.append(row)
    return pd.DataFrame(rows)
