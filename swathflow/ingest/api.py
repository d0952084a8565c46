"""A mission in xarray terms: :func:`open_mission` returns an ``xarray.DataTree`` whose
``pos`` node is the trajectory and whose ``images/<id>`` nodes are the raw images as lazy,
dask-backed Datasets (nothing is read until computed). :func:`as_mission` is how every API
function takes a mission: a folder, a loaded Mission or that tree (with its ``pos`` node as
edited); :func:`netcdf_attrs` keeps the attributes they return writable by ``to_netcdf`` and
``to_zarr``."""
from __future__ import annotations

import dataclasses
import json
import os
import warnings
from collections.abc import Mapping

import numpy as np
import xarray as xr

from swathflow.errors import FormatError
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
    raw.encoding.pop("grid_mapping", None)          # raw geometry: no CRS to point to
    nb, nl, ne = raw.shape
    coords = {"band": np.arange(1, nb + 1), "line": np.arange(nl), "element": np.arange(ne)}
    for k, v in mission.lines(image_id).items():
        if k != "line" and len(v) == nl:
            coords[k] = ("line", np.asarray(v))
    waves, units = _wavelengths(e.file)
    if waves is not None:
        coords["wavelength"] = ("band", np.asarray(waves))
    da = raw.assign_coords(coords)
    # the file's nodata, and its scale and offset unless they change nothing (the CF
    # decoding of to_netcdf / to_zarr's reader would turn the counts into floats)
    identity = {"scale_factor": 1.0, "add_offset": 0.0}
    da.attrs = {k: v for k, v in da.attrs.items()
                if k == "_FillValue" or (k in identity and v != identity[k])}
    ds = da.to_dataset(name="dn")
    if waves is not None and units:
        ds["wavelength"].attrs["units"] = units
    ds["time"].attrs.update(units="s", long_name="GPS time of the line")
    ds["dn"].attrs.update(long_name="raw digital number", units="1")
    ds.attrs = netcdf_attrs({"image_id": e.id, "direction": e.direction, "strip": e.strip,
                             "sensor": mission.sensor.get("model", ""), "file": str(e.file)})
    return ds


def open_mission(path, chunk_lines: int = CHUNK_LINES) -> xr.DataTree:
    """The mission folder ``path`` as a DataTree: ``pos`` (the trajectory over time: lat,
    lon, h, roll, pitch, heading) and ``images/<id>`` (lazy raw images, see
    :func:`image_dataset`); the root's attributes name the mission, its CRS, GSD and sensor.
    The mission is checked first (every problem listed at once, as ``swathflow validate``).
    :func:`swathflow.rectify` and :func:`swathflow.mosaic` take the tree; to rectify with an
    edited trajectory, replace its ``pos`` node (see :func:`as_mission`). Every attribute is
    a string or a number, so the tree writes with ``to_netcdf`` and ``to_zarr``.

    >>> tree = swathflow.open_mission(mission_folder)
    >>> sorted(tree.children), sorted(tree["images"].children)
    (['images', 'pos'], ['L1', 'R1'])
    >>> tree["images/L1"]["dn"].dims
    ('band', 'line', 'element')
    """
    m = load_mission(path)
    images = xr.DataTree.from_dict({iid: image_dataset(m, iid, chunk_lines)
                                    for iid in m.images})
    root = xr.Dataset(attrs={"mission": m.name, "crs": m.crs, "gsd": m.gsd,
                             "sensor": m.sensor.get("model", ""), "path": str(m.path)})
    pos = m.pos.copy()
    pos.attrs = netcdf_attrs(pos.attrs)
    return xr.DataTree.from_dict({"/": root, "pos": pos, "images": images})


def as_mission(mission) -> Mission:
    """The :class:`~swathflow.ingest.mission.Mission` that ``mission`` stands for: a mission
    folder (loaded and checked), a loaded Mission (as is), or the DataTree of
    :func:`open_mission` (its folder, loaded, with the tree's ``pos`` node as the
    trajectory). The tree is the one way to rectify with an edited trajectory: replace its
    ``pos`` node by a Dataset with the same variables over ``time`` (lat, lon, h, roll,
    pitch, heading), e.g. ``tree["pos"] = edited``.

    >>> tree = swathflow.open_mission(mission_folder)
    >>> pos = tree["pos"].to_dataset()
    >>> tree["pos"] = pos.assign(h=pos["h"] + 10.0)      # the aircraft 10 m higher
    >>> m = as_mission(tree)
    >>> float((m.pos["h"] - pos["h"]).mean())
    10.0
    """
    if isinstance(mission, Mission):
        return mission
    if isinstance(mission, xr.DataTree):
        root = mission.root
        if "path" not in root.attrs:
            raise FormatError("the DataTree is not a mission: its root has no 'path' "
                              "attribute (open the mission with swathflow.open_mission)")
        m = load_mission(root.attrs["path"])
        if "pos" not in root.children:
            return m
        pos = root["pos"].to_dataset()
        if pos.identical(m.pos):
            return m
        from swathflow.formats.pos import Trajectory
        traj = Trajectory.from_dataset(pos, max_gap=m.trajectory.max_gap)
        return dataclasses.replace(m, pos=pos, trajectory=traj)
    if isinstance(mission, (str, os.PathLike)):
        return load_mission(mission)
    raise FormatError(f"expected a mission folder, a Mission or the DataTree of "
                      f"swathflow.open_mission, not {type(mission).__name__}")


def netcdf_attrs(attrs: Mapping) -> dict:
    """``attrs`` as netCDF and Zarr store them: strings, numbers and numeric arrays kept,
    None as an empty string, booleans as 0/1, anything else (a dict, a list of strings)
    as JSON text.

    >>> netcdf_attrs({"a": 1, "b": None, "c": {"inputs": 2}, "d": True})
    {'a': 1, 'b': '', 'c': '{"inputs": 2}', 'd': 1}
    """
    out = {}
    for k, v in attrs.items():
        if isinstance(v, (bool, np.bool_)):
            v = int(v)
        elif v is None:
            v = ""
        elif isinstance(v, os.PathLike):
            v = os.fspath(v)
        elif isinstance(v, (list, tuple)) and v and all(
                isinstance(x, (int, float)) and not isinstance(x, bool) for x in v):
            v = np.asarray(v)
        elif not isinstance(v, (str, int, float, np.number, np.ndarray)):
            v = json.dumps(v, default=_json_default)
        out[k] = v
    return out


def _json_default(v):
    if isinstance(v, np.generic):
        return v.item()
    if isinstance(v, np.ndarray):
        return v.tolist()
    return str(v)
