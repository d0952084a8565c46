"""Rectification in xarray terms: :func:`rectify` returns a lazy, georeferenced
``xarray.DataArray`` (CRS, transform and nodata through rioxarray), so ``.rio.to_raster()``,
``.plot()`` and ``.compute()`` work; computing runs the engine tile by tile on the current
Dask scheduler (a ``distributed.Client`` if one is active). A thin wrapper over the engine's
lazy :func:`~swathflow.rectification.rectify.rectify` and the footprint grid."""
from __future__ import annotations

import os
from collections.abc import Mapping

import numpy as np
import xarray as xr

from swathflow.errors import FormatError
from swathflow.formats.calibfile import calibration_priors, read_calibration
from swathflow.geometry.grid import Grid, footprint_grid
from swathflow.ingest.mission import Mission, load_mission


def _engine():
    """The engine's lazy rectify (its module is being split: take it where it is)."""
    try:
        from swathflow.rectification.tiles import rectify as run
    except ImportError:
        from swathflow.rectification.rectify import rectify as run
    return run


def _parameters(mission: Mission, calibration):
    if calibration is None:
        return mission.priors
    doc = calibration if isinstance(calibration, Mapping) else read_calibration(calibration)
    if doc.get("sensor") and doc["sensor"] != mission.sensor.get("model"):
        raise FormatError(f"calibration is for sensor {doc['sensor']!r}, the mission uses "
                          f"{mission.sensor.get('model')!r}")
    return mission.priors.updated(calibration_priors(doc))


def grid_dataarray(data, grid: Grid, name: str, attrs: Mapping | None = None) -> xr.DataArray:
    """A (band, y, x) or (y, x) array over ``grid`` as a georeferenced DataArray: pixel
    centre coordinates, CRS, transform and NaN nodata written the rioxarray way."""
    import rioxarray  # noqa: F401  (registers the .rio accessor)
    t = grid.transform
    rows, cols = grid.shape
    coords = {"y": t.f + t.e * (np.arange(rows) + 0.5), "x": t.c + t.a * (np.arange(cols) + 0.5)}
    dims = ("y", "x")
    if data.ndim == 3:
        dims = ("band", "y", "x")
        coords["band"] = np.arange(1, data.shape[0] + 1)
    da = xr.DataArray(data, dims=dims, coords=coords, name=name, attrs=dict(attrs or {}))
    da = da.rio.write_crs(grid.crs).rio.write_transform(t)
    return da.rio.write_nodata(np.nan, encoded=False)


def rectify(mission, image_id: str, calibration=None, *, gsd: float | None = None,
            crs: str | None = None, kernel: str = "bilinear", tile: int = 512,
            **options) -> xr.DataArray:
    """The swing ``image_id`` of ``mission`` (a folder or a loaded Mission) orthorectified
    onto its footprint grid, as a lazy float32 DataArray over (y, x) with NaN outside the
    footprint. ``calibration``: a calibration.json path or its parsed document (default: the
    mission's priors); ``gsd``/``crs`` default to the mission's. ``options`` go to the
    engine (e.g. ``tol``)."""
    m = mission if isinstance(mission, Mission) else load_mission(mission)
    if image_id not in m.images:
        raise FormatError(f"{m.path}: no image {image_id!r}; the mission has "
                          f"{', '.join(m.images)}")
    model = m.model(image_id, _parameters(m, calibration))
    grid = footprint_grid(model, m.terrain, gsd or m.gsd, crs or m.crs)
    options.setdefault("dtype", "float32")     # NaN nodata, as documented (the engine
    data = _engine()(model, m.image(image_id), grid, m.terrain, kernel=kernel, tile=tile,
                     **options)                # would keep the raw integer type)
    e = m.images[image_id]
    attrs = {"image_id": image_id, "direction": e.direction, "strip": e.strip,
             "mission": m.name, "sensor": m.sensor.get("model", ""), "kernel": kernel}
    if isinstance(calibration, (str, os.PathLike)):
        attrs["calibration"] = os.fspath(calibration)
    return grid_dataarray(data, grid, image_id, attrs)
