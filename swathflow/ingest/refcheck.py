"""The ``[reference]`` table of mission.toml (automatic control from a reference
orthophoto): checked by ``validate`` as the reference calibration reads it. ``c`` is the
validation's problem collector (``add(file, where, message, fix)``)."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from swathflow.errors import SwathflowError
from swathflow.geometry.terrain import DEM

def check_reference(cfg: dict, root: Path, toml: Path, c, pos=None) -> None:
    """``[reference]``: ortho (a north-up raster with a projected CRS) and dem (a DEM
    below the aircraft: heights in millimetres or feet are not) that exist and open; ties
    true or false."""
    ref = cfg.get("reference")
    if ref is None:
        return
    if not isinstance(ref, dict):
        c.add(toml, "[reference]", "must be a table", 'ortho = "reference.tif"')
        return
    if "ortho" not in ref or not isinstance(ref["ortho"], str):
        c.add(toml, "[reference].ortho", "missing or not a file name",
              'ortho = "<reference orthophoto file>"')
    else:
        _reference_ortho(rel(root, ref["ortho"]), c)
    if "dem" in ref:
        dp = rel(root, str(ref["dem"]))
        if not dp.is_file():
            c.add(dp, "[reference].dem", "reference DEM not found", "check [reference].dem")
        else:
            try:
                dem = DEM.open(dp, "ellipsoidal")
            except SwathflowError as exc:
                c.add(dp, "[reference].dem", str(exc).replace(str(dp) + ": ", ""),
                      "fix the reference DEM")
            else:
                _below_aircraft(dem, dp, pos, c)
    if not isinstance(ref.get("ties", False), bool):
        c.add(toml, "[reference].ties", f"must be true or false, got {ref['ties']!r}",
              "ties = true")


def _below_aircraft(dem, dp: Path, pos, c) -> None:
    """A reference DEM reaching the aircraft's height gives no usable point (typically
    heights in millimetres or feet)."""
    if pos is None or "h" not in pos:
        return
    with np.errstate(all="ignore"):
        top, flight = float(np.nanmax(dem.data)), float(np.nanmin(pos["h"].values))
    if np.isfinite(top) and top >= flight:
        c.add(dp, "[reference].dem", f"heights up to {top:.0f} m, at or above the aircraft "
              f"(lowest POS height {flight:.0f} m)", "give ellipsoidal heights in metres "
              "(not millimetres or feet)")


def _reference_ortho(p: Path, c) -> None:
    import rasterio
    if not p.is_file():
        c.add(p, "[reference].ortho", "reference orthophoto not found",
              "check [reference].ortho in mission.toml")
        return
    try:
        with rasterio.open(p) as src:
            crs, t = src.crs, src.transform
    except (rasterio.errors.RasterioError, OSError) as exc:
        c.add(p, "[reference].ortho", f"cannot be read: {str(exc).splitlines()[0][:200]}",
              "write the reference as a GeoTIFF")
        return
    if crs is None:
        c.add(p, "[reference].ortho", "has no CRS", "write it as a GeoTIFF with a CRS")
    elif not crs.is_projected:
        c.add(p, "[reference].ortho", f"its CRS ({crs.to_string()}) is not projected: "
              f"the matching's distances are metres", "warp it to the mission's CRS "
              "(gdalwarp -t_srs EPSG:...)")
    if t.b != 0 or t.d != 0 or t.e >= 0 or abs(abs(t.e) - t.a) > 1e-9 * abs(t.a):
        c.add(p, "[reference].ortho", "not north-up with square pixels",
              "warp it first (gdalwarp)")


def rel(root: Path, p) -> Path:
    """``p`` relative to the mission folder ``root`` (unless absolute)."""
    p = Path(str(p))
    return p if p.is_absolute() else root / p
