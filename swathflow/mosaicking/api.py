"""The mosaic in xarray terms: :func:`mosaic` takes rectified swings (COG paths, or the
DataArrays of :func:`swathflow.rectify`) and returns the mosaic as a lazy, georeferenced
``xarray.DataArray``: the overlaps are matched and the offset network solved when it is
called (on the current Dask client if one is active; the result is in
``attrs["report"]``, as JSON text), the tiles are blended only when the array is computed, on the
current Dask scheduler. ``swathflow mosaic`` and the flow's mosaic task call it with
``out``, which also writes the COG, its quicklook, report picture and JSON with the
engine's streaming writer (:func:`swathflow.mosaicking.mosaic.finish_mosaic`).
:func:`write_mosaic` is that writing path alone, for COG files on disk: it returns the report
and imports neither xarray nor dask (``swathflow mosaic`` calls it; :func:`mosaic` with
``out`` runs the same code and builds the lazy array on top)."""
from __future__ import annotations

import os
import tempfile

from swathflow.errors import FormatError

SWING_TAGS = ("image_id", "strip", "direction", "mission", "sensor", "calibration")
#: the options of the matching (plan) and of the writing (finish)
_PLAN = ("per_image", "anchors", "balance", "match", "max_shift", "block", "min_texture",
         "workers", "strips", "log", "control")
_FINISH = ("tile", "workers", "png", "report", "cog")


def _as_paths(swings, folder: str) -> list[str]:
    """COG paths of ``swings``; DataArrays are written into ``folder`` first (with their
    tags, image id and strip among them, which the mosaic reads)."""
    from swathflow.rectification.api import to_cog
    import xarray as xr
    paths = []
    for i, s in enumerate(swings):
        if isinstance(s, xr.DataArray):
            name = str(s.attrs.get("image_id") or s.name or f"swing{i}")
            path = os.path.join(folder, f"{name}.tif")
            to_cog(s, path)
            paths.append(path)
        else:
            paths.append(os.path.abspath(os.fspath(s)))
    return paths


def _plan_and_write(paths, out, feather, mode, tile, cache_mb, options):
    """Match and solve the network for COG ``paths``, then (with ``out``) write the mosaic:
    ``(planned, report)``; the one code path of :func:`mosaic` and :func:`write_mosaic`."""
    import rasterio

    from swathflow.arguments import tile_size
    from swathflow.mosaicking.mosaic import finish_mosaic, plan_mosaic, swing_store
    tile = tile_size(tile)
    unknown = set(options) - set(_PLAN) - set(_FINISH)
    if unknown:
        raise FormatError(f"mosaic: unknown option(s) {', '.join(sorted(unknown))}")
    handles = swing_store()
    try:
        with rasterio.Env(GDAL_CACHEMAX=int(cache_mb)):
            planned = plan_mosaic(paths, feather=feather, mode=mode, handles=handles,
                                  **{k: v for k, v in options.items() if k in _PLAN})
        report = planned[3]
        if out is not None:
            report = finish_mosaic(planned, out, feather, mode, tile, cache_mb=cache_mb,
                                   handles=handles,
                                   **{k: v for k, v in options.items() if k in _FINISH})
    finally:
        handles.close()
    return planned, report


def write_mosaic(paths, out, *, feather: int = 64, mode: str = "feather", tile: int = 1024,
                 cache_mb: int = 64, **options) -> dict:
    """Write the mosaic of the rectified swing COGs ``paths`` to ``out`` (COG, ``.png``,
    ``.report.png``, ``.json``) and return its report: what :func:`mosaic` does with
    ``out``, without building the lazy array (no xarray or dask import)."""
    paths = [os.path.abspath(os.fspath(p)) for p in paths]
    if not paths:
        raise FormatError("mosaic: no swings given")
    return _plan_and_write(paths, out, feather, mode, tile, cache_mb, options)[1]


def _is_mission(swings) -> bool:
    """Whether ``swings`` is a mission (a Mission, the DataTree of ``open_mission``, or a
    folder holding a ``mission.toml``) rather than rectified swings."""
    import xarray as xr

    from swathflow.ingest.mission import Mission
    if isinstance(swings, (Mission, xr.DataTree)):
        return True
    return isinstance(swings, (str, os.PathLike)) and os.path.isfile(
        os.path.join(os.fspath(swings), "mission.toml"))


def mosaic(swings, out=None, *, calibration=None, feather: int = 64, mode: str = "feather",
           tile: int = 1024, cache_mb: int = 64, **options):
    """The mosaic of ``swings`` as a lazy float32 DataArray over (y, x) with NaN nodata,
    CRS and transform (rioxarray), ``long_name`` and ``units``; the matching report
    (offsets with sigmas, overlaps) is in ``attrs["report"]`` as JSON text
    (``json.loads`` it), so that ``to_netcdf`` and ``to_zarr`` write every attribute.
    ``swings``: rectified swings (COG paths, or the DataArrays of
    :func:`swathflow.rectify`), or a whole mission (a folder, a loaded Mission or the
    DataTree of :func:`swathflow.open_mission`), whose every image is rectified first with
    ``calibration`` (see :func:`swathflow.rectify`). With ``out`` the mosaic COG (and its
    ``.png``, ``.report.png`` and ``.json``) is also written there, and the full report
    (timings) returned. ``options`` go to :func:`swathflow.mosaicking.mosaic.plan_mosaic`
    (``per_image``, ``anchors``, ``balance``, ``match``, ``control``, ``strips``...) and to
    the writer (``png``, ``report``, ``cog``, ``workers``). DataArray swings are written to
    COGs first (beside ``out``, or in a temporary folder).

    >>> import json
    >>> mos = swathflow.mosaic(swathflow.open_mission(mission_folder))
    >>> mos.dims, mos.attrs["long_name"], json.loads(mos.attrs["report"])["inputs"]
    (('y', 'x'), 'mosaic of digital numbers', 2)
    """
    import xarray as xr

    from swathflow.geometry.grid import Grid
    from swathflow.mosaicking.mosaic import mosaic_array
    from swathflow.rectification.api import grid_dataarray, rectify
    if _is_mission(swings):
        from swathflow.ingest.api import as_mission
        m = as_mission(swings)
        swings = [rectify(m, iid, calibration) for iid in m.images]
    elif calibration is not None:
        raise FormatError("mosaic: calibration applies to a mission; these swings are "
                          "already rectified")
    swings = list(swings)
    if len(swings) == 0:
        raise FormatError("mosaic: no swings given")
    base = os.path.splitext(os.path.abspath(os.fspath(out)))[0] if out else os.path.join(
        tempfile.mkdtemp(prefix="swathflow-mosaic-"), "mosaic")
    folder = base + "-swings"
    if any(isinstance(s, xr.DataArray) for s in swings):
        os.makedirs(folder, exist_ok=True)
    paths = _as_paths(swings, folder)
    planned, report = _plan_and_write(paths, out, feather, mode, tile, cache_mb, options)
    layout, off, rad, _ = planned
    arr, _ = mosaic_array(layout, off, rad, feather, mode, tile)
    grid = Grid(layout.crs.to_string(), layout.transform, layout.shape)
    return grid_dataarray(arr, grid, "mosaic", {
        "product": "mosaic", "blend": mode, "long_name": "mosaic of digital numbers",
        "units": "1", "report": report})
