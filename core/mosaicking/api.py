"""The mosaic in xarray terms: :func:`mosaic` takes rectified swings (COG paths, or the
DataArrays of :func:`swathflow.rectify`) and returns the mosaic as a lazily read,
georeferenced ``xarray.DataArray``. A thin wrapper over :func:`swathflow.mosaicking.mosaic.mosaic`:
the matching and blending run when called (overlaps matched on the current Dask client if
one is active) and write the mosaic COG; the result is read back lazily through rioxarray."""
from __future__ import annotations

import os
import tempfile

import xarray as xr

from swathflow.errors import FormatError

SWING_TAGS = ("image_id", "strip", "direction", "mission", "sensor", "calibration")


def _as_paths(swings, folder: str) -> list[str]:
    """COG paths of ``swings``; DataArrays are written into ``folder`` first (with their
    image id and strip as tags, which the mosaic reads)."""
    paths = []
    for i, s in enumerate(swings):
        if isinstance(s, xr.DataArray):
            name = str(s.attrs.get("image_id") or s.name or f"swing{i}")
            path = os.path.join(folder, f"{name}.tif")
            tags = {k: str(s.attrs[k]) for k in SWING_TAGS if k in s.attrs}
            s.rio.to_raster(path, driver="COG", tags=tags)
            paths.append(path)
        else:
            paths.append(os.path.abspath(os.fspath(s)))
    return paths


def mosaic(swings, out=None, **options) -> xr.DataArray:
    """Strip-match and blend ``swings`` into the mosaic COG ``out`` (default: a new
    temporary folder) and return it as a lazy DataArray over (y, x) with NaN nodata; the
    mosaic report (offsets with sigmas, overlaps) is in ``attrs["report"]``. ``options`` go
    to :func:`swathflow.mosaicking.mosaic.mosaic` (``feather``, ``per_image``, ``anchors``,
    ``balance``, ``match``...)."""
    import rioxarray

    from swathflow.mosaicking.mosaic import mosaic as run
    swings = list(swings)
    if len(swings) == 0:
        raise FormatError("mosaic: no swings given")
    out = os.path.abspath(os.fspath(out)) if out else os.path.join(
        tempfile.mkdtemp(prefix="swathflow-mosaic-"), "mosaic.tif")
    folder = os.path.splitext(out)[0] + "-swings"
    if any(isinstance(s, xr.DataArray) for s in swings):
        os.makedirs(folder, exist_ok=True)
    report = run(_as_paths(swings, folder), out, **options)
    da = rioxarray.open_rasterio(out, chunks={"band": 1, "y": 1024, "x": 1024},
                                 masked=True).squeeze("band", drop=True)
    da.name = "mosaic"
    da.attrs["report"] = report
    return da
