"""The mission's ``gcp.csv``: read, check every row, convert to geodetic and ECEF."""
from __future__ import annotations

import numpy as np
import pandas as pd

from swathflow.errors import SwathflowError
from swathflow.ingest.csvtable import finite_columns, read_table
from swathflow.ingest.keys import KNOWN_KEYS
from swathflow.ingest.problems import Collector, check_crs, check_keys, first_rows, rel

GCP_COLUMNS = ("gcp_id", "image_id", "line", "element", "x", "y", "z", "role")
GCP_ROLES = ("control", "check")


def check_gcps(cfg, root, toml, parts, c: Collector):
    """The GCP table with lat, lon, h and X, Y, Z added, or None (absent or bad)."""
    gc = cfg.get("gcp")
    if gc is None:
        if not (root / "gcp.csv").exists():
            return None
        gc = {"file": "gcp.csv", "crs": "EPSG:4979"}
    if not isinstance(gc, dict) or "file" not in gc:
        c.add(toml, "[gcp]", "needs file = \"gcp.csv\"", 'file = "gcp.csv", crs = "EPSG:4979"')
        return None
    check_keys(gc, KNOWN_KEYS["gcp"], toml, "[gcp]", c)
    gp = rel(root, gc["file"])
    crs = gc.get("crs", "EPSG:4979")
    err = check_crs(crs)
    if err:
        c.add(toml, "[gcp].crs", f"pyproj rejects CRS {crs!r}: {err}",
              'use "EPSG:4979" (lon, lat, ellipsoidal h) or a projected EPSG code')
    if not gp.exists():
        c.add(gp, "", "GCP file not found", "check [gcp].file in mission.toml")
        return None
    if not gp.is_file():        # a FIFO would hang the reader, a device fill memory
        c.add(gp, "", "not a regular file (a folder, device or FIFO)",
              "name the GCP table's CSV file in [gcp].file")
        return None
    df = read_table(gp, GCP_COLUMNS, c, "observation",
                    dtype={"gcp_id": str, "image_id": str, "role": str})
    if df is None:
        return None
    n0 = len(c.problems)
    _values(df, gp, c)
    _ids(df, gp, parts["images"], c)
    _inside(df, gp, parts["image_shapes"], c)
    if len(c.problems) > n0 or err:
        return None
    out = gcp_geodetic(df, crs)
    if not _located(out, df, gp, crs, parts.get("trajectory"), c):
        return None
    if not _heights(out, gp, parts, c):
        return None
    return out


def _heights(g, gp, parts, c) -> bool:
    """GCP heights must lie below the aircraft (an error otherwise: no image sees them;
    typically heights in millimetres or feet, or a wrong CRS); heights far from the
    terrain's (more than half the flying height above it) are warned of."""
    pos = parts.get("pos")
    if pos is None or "h" not in pos:
        return True
    h = g["h"].to_numpy(float)
    with np.errstate(all="ignore"):
        flight = float(np.nanmin(pos["h"].values))
        above = h >= flight
        if above.any():
            c.add(gp, f"column z, file row(s) {first_rows(above)}",
                  f"{int(above.sum())} GCP(s) at heights up to {np.nanmax(h[above]):.0f} m, "
                  f"at or above the aircraft (lowest POS height {flight:.0f} m): no image "
                  f"sees them", "give z as ellipsoidal heights in metres (not mm or feet), "
                  "or check [gcp].crs")
            return False
        terrain = parts.get("terrain")
        if terrain is None:
            return True
        try:
            th = np.asarray(terrain.height(g["lat"].to_numpy(float), g["lon"].to_numpy(float)),
                            float)
        except (ValueError, SwathflowError):
            return True
        agl = flight - np.nanmedian(th) if np.isfinite(th).any() else np.nan
        far = np.isfinite(th) & (np.abs(h - th) > 0.5 * agl) if agl > 0 else None
        if far is not None and far.any():
            c.warn(gp, f"column z, file row(s) {first_rows(far)}",
                   f"{int(far.sum())} GCP height(s) differ from the terrain's by more than "
                   f"half the flying height ({0.5 * agl:.0f} m)",
                   "check z (ellipsoidal metres) and [terrain] vertical/geoid")
    return True


def _values(df, gp, c) -> None:
    for col, v in finite_columns(df, gp, ("line", "element", "x", "y", "z"), c,
                                 "every GCP row needs finite numbers (delete unmeasured "
                                 "rows)").items():
        df[col] = v
    role = df["role"].astype(str).str.strip().str.lower()
    bad = ~role.isin(GCP_ROLES).to_numpy()
    if bad.any():
        c.add(gp, f"column role, file row(s) {first_rows(bad)}",
              f"role must be control or check, found {sorted(set(map(str, df['role'][bad])))}",
              "set role to control or check")
    df["role"] = role


def _ids(df, gp, images, c) -> None:
    for col in ("gcp_id", "image_id"):
        bad = df[col].isna().to_numpy()
        if bad.any():
            c.add(gp, f"column {col}, file row(s) {first_rows(bad)}", "empty value",
                  f"give every row its {col}")
    df["gcp_id"] = df["gcp_id"].astype(str)
    df["image_id"] = df["image_id"].astype(str)
    unknown = ~df["image_id"].isin(list(images)).to_numpy()
    if unknown.any():
        c.add(gp, f"column image_id, file row(s) {first_rows(unknown)}",
              f"unknown image id(s) {sorted(set(map(str, df['image_id'][unknown])))}",
              f"use one of the [[images]] ids: {', '.join(images)}")
    dup = df.duplicated(["gcp_id", "image_id"]).to_numpy()
    if dup.any():
        c.add(gp, f"file row(s) {first_rows(dup)}", "the same gcp_id appears twice for one "
              "image", "one row per GCP and image")


def _inside(df, gp, shapes, c) -> None:
    li = df["line"].to_numpy(float)
    el = df["element"].to_numpy(float)
    for iid, (rows, cols) in shapes.items():
        sel = (df["image_id"] == iid).to_numpy()
        with np.errstate(invalid="ignore"):
            out = sel & ((li < -0.5) | (li > rows - 0.5) | (el < -0.5) | (el > cols - 0.5))
        if out.any():
            c.add(gp, f"file row(s) {first_rows(out)}",
                  f"{int(out.sum())} GCP(s) outside image {iid!r} ({rows} lines x {cols} "
                  f"elements; valid line -0.5..{rows - 0.5}, element -0.5..{cols - 0.5})",
                  "check the image_id and the (line, element) order of these rows")


def _axis_names(crs) -> tuple[str, str]:
    import pyproj
    src = pyproj.CRS.from_user_input(crs)
    return ("longitude", "latitude") if src.is_geographic else ("easting", "northing")


def _located(out, df, gp, crs, traj, c) -> bool:
    """GCPs must be real places near the flight; x/y swapped is named as such."""
    xn, yn = _axis_names(crs)
    with np.errstate(all="ignore"):
        bad = ~np.isfinite(out[["lat", "lon", "h"]].to_numpy()).all(-1)
        near = _far_from(out, traj)
        if not bad.any() and (near is None or not near.any()):
            return True
        swapped = df.rename(columns={"x": "y", "y": "x"})
        try:
            alt = gcp_geodetic(swapped, crs)
            alt_ok = np.isfinite(alt[["lat", "lon", "h"]].to_numpy()).all(-1)
            alt_near = _far_from(alt, traj)
            fixes = alt_ok.all() and (alt_near is None or not alt_near.any())
        except Exception:  # noqa: BLE001 - only a hint
            fixes = False
    rows = bad | (near if near is not None else False)
    what = "not valid coordinates" if bad.any() else "far (> 50 km) from the flight"
    fix = (f"x and y look swapped: with [gcp].crs {crs}, x is the {xn} and y the {yn}; "
           f"swap the x and y columns" if fixes else
           f"check x ({xn}), y ({yn}), z and [gcp].crs ({crs})")
    c.add(gp, f"columns x, y, file row(s) {first_rows(rows)}",
          f"{int(rows.sum())} GCP(s) are {what} in {crs}", fix)
    return False


def _far_from(g, traj):
    """Rows farther than 50 km from every sampled trajectory point (None: no trajectory)."""
    if traj is None:
        return None
    idx = np.linspace(0, traj.lat.size - 1, 50).astype(int)
    lat0 = np.radians(traj.lat[idx])[None]
    lon0 = np.radians(traj.lon[idx])[None]
    lat = np.radians(g["lat"].to_numpy(float))[:, None]
    lon = np.radians(g["lon"].to_numpy(float))[:, None]
    a = (np.sin((lat - lat0) / 2) ** 2
         + np.cos(lat) * np.cos(lat0) * np.sin((lon - lon0) / 2) ** 2)
    d = 2 * 6371000.0 * np.arcsin(np.sqrt(np.clip(a, 0, 1)))
    return ~(np.nanmin(d, axis=1) < 50000.0)


def gcp_geodetic(df: pd.DataFrame, crs: str) -> pd.DataFrame:
    """Add lat, lon, h (EPSG:4979) and X, Y, Z (ECEF) to a GCP table."""
    import pyproj

    from swathflow.geometry.geodesy import geodetic_to_ecef, transformer
    src = pyproj.CRS.from_user_input(crs)
    x, y, z = (df[k].to_numpy(float) for k in ("x", "y", "z"))
    if src.to_epsg() == 4979 or (src.is_geographic and len(src.axis_info) == 3):
        lon, lat, h = transformer(src, "EPSG:4979").transform(x, y, z)
    else:   # geographic 2-D or projected, with ellipsoidal heights (spec)
        lon, lat = transformer(src, "EPSG:4326").transform(x, y)
        h = z
    out = df.copy()
    out["lat"], out["lon"], out["h"] = np.asarray(lat), np.asarray(lon), np.asarray(h)
    with np.errstate(all="ignore"):
        xyz = geodetic_to_ecef(np.stack([out["lat"], out["lon"], out["h"]], axis=-1))
    out["X"], out["Y"], out["Z"] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    return out.reset_index(drop=True)
