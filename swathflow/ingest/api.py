"""A mission in xarray terms: :func:`open_mission` returns an ``xarray.DataTree`` whose
``pos`` node is the trajectory and whose ``images/<id>`` nodes are the raw images as lazy,
dask-backed Datasets (nothing is read until computed)."""
from __future__ import annotations

import os
import warnings

import numpy as np
import xarray as xr

from swathflow.ingest.mission import Mission, load_mission

CHUNK_LINES = 2048


def _wavelengths(path) -> tuple[list[float] | None, str | None]:
    """Band centre wavelengths from the band tags (ENVI headers give them), if every band
    has one."""
    from swathflow.ingest.images import open_raw
    with open_raw(path) as src:
        tags = [{k.lower(): v for k, v in src.tags(b).items()} for b in range(1, src.count + 1)]
    if not tags or not all("wavelength" in t for t in tags):
        return None, None
    try:
        return [float(t["wavelength"]) for t in tags], tags[0].get("wavelength_units")
    except ValueError:
        return None, None


def image_dataset(mission: Mission, image_id: str, chunk_lines: int = CHUNK_LINES) -> xr.Dataset:
    """One raw image: ``dn`` over (band, line, element), lazy in blocks of whole lines, with
    the per-line table (time, and what the sensor records, e.g. swing) as line coordinates
    and ``wavelength`` over band where the file gives it."""
    import rioxarray
    from rasterio.errors import NotGeoreferencedWarning
    e = mission.images[image_id]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", NotGeoreferencedWarning)
        raw = rioxarray.open_rasterio(os.fspath(e.file), chunks={"band": 1, "y": chunk_lines,
                                                                 "x": -1}, lock=False,
                                      parse_coordinates=False)
    raw = raw.rename({"y": "line", "x": "element"}).drop_vars("spatial_ref", errors="ignore")
    nb, nl, ne = raw.shape
    coords = {"band": np.arange(1, nb + 1), "line": np.arange(nl), "element": np.arange(ne)}
    for k, v in mission.lines(image_id).items():
        if k != "line" and len(v) == nl:
            coords[k] = ("line", np.asarray(v))
    waves, units = _wavelengths(e.file)
    if waves is not None:
        coords["wavelength"] = ("band", np.asarray(waves))
    da = raw.assign_coords(coords)
    da.attrs = {k: v for k, v in da.attrs.items() if k in ("_FillValue", "scale_factor",
                                                           "add_offset")}
    ds = da.to_dataset(name="dn")
    if waves is not None and units:
        ds["wavelength"].attrs["units"] = units
    ds["time"].attrs["units"] = "s"
    ds.attrs = {"image_id": e.id, "direction": e.direction, "strip": e.strip,
                "sensor": mission.sensor.get("model", ""), "file": str(e.file)}
    return ds


def open_mission(path, chunk_lines: int = CHUNK_LINES) -> xr.DataTree:
    """The mission folder ``path`` as a DataTree: ``pos`` (the trajectory over time: lat,
    lon, h, roll, pitch, heading) and ``images/<id>`` (lazy raw images, see
    :func:`image_dataset`); the root's attributes name the mission, its CRS, GSD and sensor.
    The mission is checked first (every problem listed at once, as ``swathflow validate``)."""
    m = load_mission(path)
    images = xr.DataTree.from_dict({iid: image_dataset(m, iid, chunk_lines)
                                    for iid in m.images})
    root = xr.Dataset(attrs={"mission": m.name, "crs": m.crs, "gsd": m.gsd,
                             "sensor": m.sensor.get("model", ""), "path": str(m.path)})
    return xr.DataTree.from_dict({"/": root, "pos": m.pos, "images": images})
