"""Rectification in xarray terms, the rasterio way: one lazy array, one writer.

:func:`rectify` returns a lazy, georeferenced ``xarray.DataArray`` (CRS, transform and
nodata through rioxarray, band descriptions and wavelengths as coordinates, the product
tags as attributes); nothing is read or computed until it is. :func:`to_cog` streams any
such array into a Cloud-Optimized GeoTIFF atomically, tile by tile on the current Dask
scheduler (a ``distributed.Client`` if one is active), in bounded memory, keeping its dtype,
nodata or mask band and band metadata. ``swathflow rectify`` and the flow's rectify task
are ``to_cog(rectify(...))``; :func:`geolocation` gives the GLT and IGM products the same
way."""
from __future__ import annotations

import contextlib
import hashlib
import json
import os
import sys
from collections.abc import Mapping

import numpy as np
import xarray as xr

from swathflow.arguments import tile_size
from swathflow.errors import ArgumentTypeError, FormatError
from swathflow.formats.calibfile import calibration_priors, read_calibration
from swathflow.geometry.grid import Grid, footprint_grid
from swathflow.ingest.api import as_mission, netcdf_attrs
from swathflow.ingest.mission import Mission

#: attributes that are not product tags (rioxarray's encoding, the mosaic's report)
_NOT_TAGS = {"_FillValue", "scale_factor", "add_offset", "grid_mapping", "units",
             "long_name", "report", "nodata"}
METHODS = ("exact", "polynomial")
#: the ``long_name`` of a rectified (or mosaicked) raw image: the sensor's counts
QUANTITY = "digital number"


def _parameters(mission: Mission, calibration):
    """(parameters, calibration tag) of ``calibration`` (a path, a parsed document or
    None: the mission's priors)."""
    if calibration is None:
        return mission.priors, "none: mission priors (mission.toml [calibration])"
    doc = calibration if isinstance(calibration, Mapping) else read_calibration(calibration)
    if doc.get("sensor") and doc["sensor"] != mission.sensor.get("model"):
        where = f"{calibration}: " if isinstance(calibration, (str, os.PathLike)) else ""
        raise FormatError(f"{where}calibration is for sensor {doc['sensor']!r}, the mission "
                          f"uses {mission.sensor.get('model')!r}")
    tag = "given as a document"
    if isinstance(calibration, (str, os.PathLike)):
        with open(calibration, "rb") as f:
            digest = hashlib.sha256(f.read()).hexdigest()[:16]
        tag = f"{os.path.abspath(calibration)} (sha256 {digest})"
    return mission.priors.updated(calibration_priors(doc)), tag


def grid_dataarray(data, grid: Grid, name: str, attrs: Mapping | None = None,
                   nodata=np.nan, band_info=None) -> xr.DataArray:
    """A (band, y, x) or (y, x) array over ``grid`` as a georeferenced DataArray: pixel
    centre coordinates, CRS, transform and nodata (None: none) written the rioxarray way
    (its ``spatial_ref`` coordinate, ``grid_mapping`` encoding and ``_FillValue``
    attribute, taken from :func:`_rio_template`: the CRS's CF attributes cost 3-4 ms a
    call, paid once per CRS, type and nodata rather than once per swing). ``band_info``
    (the raw bands' :class:`~swathflow.rectification.rawimage.BandInfo`): their
    coordinates (:func:`_band_coords`), made with the array (assigned after, xarray's
    alignment cost 3 ms a swing). ``x``/``y`` carry the CF attributes of the CRS's axes
    (``standard_name`` projection_x_coordinate, ``units`` metre... as rioxarray's
    ``write_coordinate_system``); ``attrs`` are made netCDF-safe
    (:func:`~swathflow.ingest.api.netcdf_attrs`: a dict becomes JSON text)."""
    t = grid.transform
    rows, cols = grid.shape
    coords = {"y": t.f + t.e * (np.arange(rows) + 0.5), "x": t.c + t.a * (np.arange(cols) + 0.5)}
    dims = ("y", "x")
    if data.ndim == 3:
        dims = ("band", "y", "x")
        coords["band"] = np.arange(1, data.shape[0] + 1)
    ref_attrs, fill, encoding, axes = _rio_template(str(grid.crs), np.dtype(data.dtype),
                                                    nodata)
    coords = {k: xr.Variable((k,), v, attrs=dict(axes[k])) if k in axes else v
              for k, v in coords.items()}
    ref_attrs = dict(ref_attrs, GeoTransform=" ".join(str(v) for v in t.to_gdal()))
    coords["spatial_ref"] = xr.Variable((), 0, attrs=ref_attrs)
    if band_info is not None:
        coords.update(_band_coords(band_info, data.ndim == 3))
    attrs = netcdf_attrs(attrs or {})
    if fill is not None:
        attrs["_FillValue"] = fill
    da = xr.DataArray(data, dims=dims, coords=coords, name=name, attrs=attrs)
    da.encoding.update(encoding)
    return da


#: :func:`_rio_template`'s results by (CRS, dtype, ``repr(nodata)``)
_RIO_TEMPLATES: dict = {}


def _rio_template(crs: str, dtype: np.dtype, nodata):
    """What rioxarray's ``write_crs``, ``write_transform`` and ``write_nodata(encoded=False)``
    write for ``crs``, ``dtype`` and ``nodata``, found on a 1 x 1 array once per
    combination: (the ``spatial_ref`` coordinate's attributes without ``GeoTransform``,
    the ``_FillValue`` attribute or None, the encoding, the attributes of ``x`` and ``y``
    that ``write_coordinate_system`` writes)."""
    key = (crs, dtype.str, repr(nodata))        # repr: NaN is one key
    if key not in _RIO_TEMPLATES:
        import rioxarray  # noqa: F401  (registers the .rio accessor)
        from affine import Affine
        one = xr.DataArray(np.zeros((1, 1), dtype), dims=("y", "x"),
                           coords={"y": [0.5], "x": [0.5]})
        one = one.rio.write_crs(crs).rio.write_transform(Affine.identity())
        if nodata is not None:
            one = one.rio.write_nodata(nodata, encoded=False)
        ref = {k: v for k, v in one.coords["spatial_ref"].attrs.items() if k != "GeoTransform"}
        axes = one.rio.write_coordinate_system()
        _RIO_TEMPLATES[key] = (ref, one.attrs.get("_FillValue"), dict(one.encoding),
                               {k: dict(axes[k].attrs) for k in ("x", "y")})
    return _RIO_TEMPLATES[key]


def _band_coords(infos, banded: bool) -> dict:
    """Band metadata as coordinates on ``band`` (scalars when not ``banded``): ``band`` the
    1-based band of the raw file, ``description``, ``wavelength``/``fwhm`` where known."""
    dim = ("band",) if banded else ()

    def val(v):
        return v if dim else v[0]
    coords = {"band": (dim, val(np.array([b.index for b in infos])))}
    if dim or infos[0].description:      # no empty "description = " in a plot's title
        coords["description"] = (dim, val(np.array([b.description for b in infos], object)))
    if any(b.wavelength is not None for b in infos):
        coords["wavelength"] = (dim, val(np.array([np.nan if b.wavelength is None
                                                   else b.wavelength for b in infos])),
                                {"units": next((b.units for b in infos if b.units), "")})
    if any(b.fwhm is not None for b in infos):
        coords["fwhm"] = (dim, val(np.array([np.nan if b.fwhm is None else b.fwhm
                                             for b in infos])))
    return coords


def _band_infos(da: xr.DataArray):
    """BandInfo of each band of ``da`` from its coordinates (see :func:`_band_coords`)."""
    from swathflow.rectification.rawimage import BandInfo
    if "description" not in da.coords and not ("band" in da.coords
                                               and da.coords["band"].ndim == 0):
        return ()
    n = da.sizes.get("band", 1)

    def col(name):
        if name not in da.coords:
            return [None] * n
        v = np.atleast_1d(da.coords[name].values)
        return [None if isinstance(x, float) and np.isnan(x) else x for x in v.tolist()]
    units = da.coords["wavelength"].attrs.get("units") if "wavelength" in da.coords else None
    return [BandInfo(int(i), str(d or ""), w, f, units or None)
            for i, d, w, f in zip(col("band"), col("description"), col("wavelength"),
                                  col("fwhm"))]


def _open(mission, image_id) -> Mission:
    m = as_mission(mission)
    if image_id not in m.images:
        raise FormatError(f"{m.path}: no image {image_id!r}; the mission has "
                          f"{', '.join(m.images)}")
    return m


def _tags(m: Mission, image_id, model, method, kernel, tol, cal_tag, terrain) -> dict:
    from swathflow._version import __version__
    e = m.images[image_id]
    return {"software": f"swathflow {__version__}", "method": method, "kernel": kernel,
            "sensor": m.sensor.get("model", ""),
            "tolerance_px": tol if method == "exact" else "",
            "terrain": json.dumps(terrain.state()), "image_id": image_id, "strip": e.strip,
            "direction": e.direction, "mission": m.name, "calibration": cal_tag,
            "parameters": json.dumps(model.parameters.values_dict())}


def rectify(mission, image_id: str, calibration=None, *, gsd: float | None = None,
            crs: str | None = None, kernel: str = "bilinear", tile: int = 512,
            method: str = "exact", tol: float | None = None, bands=None,
            dtype: str | None = "float32", mask_band: bool = False) -> xr.DataArray:
    """The swing ``image_id`` of ``mission`` (a folder, a loaded Mission or the DataTree of
    :func:`swathflow.open_mission`, whose ``pos`` node, edited, is the trajectory used: see
    :func:`~swathflow.ingest.api.as_mission`) orthorectified onto its footprint grid,
    as a lazy DataArray over (y, x), or (band, y, x) when several bands are selected
    (``bands``: 1-based indices or wavelengths, see
    :func:`~swathflow.rectification.rawimage.parse_bands`; default every band).

    ``dtype`` (default float32, NaN outside the footprint; None: the raw image's own type,
    as ``swathflow rectify`` writes it, with an integer nodata value or, with
    ``mask_band``, none and a lazy ``mask`` coordinate over (y, x): 255 valid, 0 not).
    ``calibration``: a calibration.json path or its parsed document (default: the
    mission's priors); ``gsd``/``crs`` default to the mission's. ``method``: ``exact``
    (tile by tile, ``tol`` raw pixels) or ``polynomial`` (one band, float32, computed as
    one block). Band descriptions and wavelengths are coordinates; the product tags
    (image id, strip, calibration, parameters...) are attributes, with ``long_name`` and
    ``units``; ``x``/``y`` are in the CRS's units with their CF ``standard_name``. Every
    attribute is a string or a number (``to_netcdf`` and ``to_zarr`` write it) and the
    dask graph's tasks hold small arguments (it pickles, to any scheduler).

    >>> tree = swathflow.open_mission(mission_folder)
    >>> arr = swathflow.rectify(tree, "L1")
    >>> arr.dims, arr.attrs["long_name"], arr["x"].attrs["standard_name"]
    (('y', 'x'), 'digital number', 'projection_x_coordinate')
    >>> arr.rio.crs.to_string()
    'EPSG:32651'
    >>> import pickle
    >>> graph = dict(arr.data.__dask_graph__())
    >>> pickle.loads(pickle.dumps(graph)).keys() == graph.keys()
    True
    """
    from swathflow.rectification.lattice import TOLERANCE_PX
    from swathflow.rectification.rawimage import open_raw_image
    from swathflow.rectification.tiles import check_inputs, output_plan, rectify_blocks
    if method not in METHODS:
        raise FormatError(f"unknown rectification method {method!r}; use one of "
                          f"{', '.join(METHODS)}")
    tile = tile_size(tile)
    tol = TOLERANCE_PX if tol is None else tol
    m, model, terrain, grid, cal_tag = _swing(mission, image_id, calibration, gsd, crs)
    source = open_raw_image(m.images[image_id].file, bands=bands)
    check_inputs(model, source, kernel)
    attrs = dict(_tags(m, image_id, model, method, kernel, tol, cal_tag, terrain),
                 long_name=QUANTITY, units="1")
    if method == "polynomial":
        return _polynomial(model, source, grid, terrain, attrs)
    dt, nodata, use_mask = output_plan(source, dtype, mask_band)
    arr = rectify_blocks(model, source, grid, terrain, kernel, tol, tile, dtype=dtype,
                         mask_plane=use_mask)
    data = arr[:-1] if use_mask else arr
    if source.count == 1:
        data = data[0]
    out = grid_dataarray(data, grid, image_id, attrs, nodata, source.band_info)
    if use_mask:
        out = out.assign_coords(mask=(("y", "x"), arr[-1]))
    return out


def warm_up(mission, image_id: str | None = None, calibration=None, *,
            kernel: str = "bilinear", tile: int = 512, tol: float | None = None,
            bands=None, dtype: str | None = None, mask_band: bool = False,
            compress: str = "deflate") -> None:
    """Import the engine and load the compiled kernels (numba's on-disk cache) that
    rectifying ``image_id`` of ``mission`` (default its first image) calls, by rectifying
    an 8 x 8 px window in the middle of its footprint grid and discarding it. A process
    that forks workers calls it first, so that each worker starts with them loaded (a
    survey swing's first rectification in a forked worker: 0.45 -> 0.16 CPU-s; arguments
    as :func:`rectify`'s exact method), and what writing its COG (``compress``) makes once a
    process (:func:`_warm_writer`). It also keeps freed heap memory in this process and
    the ones it forks (:func:`~swathflow.rectification.heap.keep_freed_memory`). On a new
    install the processes warming up together take turns (:func:`taking_turns`), and
    the grid's corner tile is rectified too (the kernels of a swing's tiles compiled)."""
    from dask.local import get_sync

    from swathflow.rectification.heap import keep_freed_memory

    import rioxarray  # noqa: F401  (the .rio accessor of every rectified array)
    from swathflow.rectification.lattice import TOLERANCE_PX
    from swathflow.rectification.rawimage import open_raw_image
    from swathflow.rectification.tiles import output_plan, rectify_blocks
    keep_freed_memory()
    m = as_mission(mission)
    iid = image_id if image_id is not None else next(iter(m.images))
    with taking_turns() as cold:
        m, model, terrain, grid, _ = _swing(m, iid, calibration, None, None)
        src = open_raw_image(m.images[iid].file, bands=bands)
        dt, nodata, use_mask = output_plan(src, dtype, mask_band)
        r, c = grid.height // 2, grid.width // 2
        wins = [grid.window(slice(max(r - 4, 0), r + 4), slice(max(c - 4, 0), c + 4))]
        if cold:    # a new install: also the corner tile (off the footprint in part: the
            # lattice refines there), so that a swing's tiles find their kernels compiled
            wins.append(grid.window(slice(0, min(tile, grid.height)),
                                    slice(0, min(tile, grid.width))))
        for win in wins:
            rectify_blocks(model, src, win, terrain, kernel,
                           TOLERANCE_PX if tol is None else tol, tile, dtype=dtype,
                           mask_plane=use_mask).compute(scheduler=get_sync)
        _warm_writer(grid, dt, nodata, use_mask, tile, compress)


#: whether a block of :func:`taking_turns` has ended in this process
_TURN_TAKEN = False


@contextlib.contextmanager
def taking_turns():
    """A process's rectifications on a new install (numba's cache without the lattice's
    cell tests, which every tile calls), until one has ended: inside
    :func:`swathflow.kernelcache.compiling_alone`, so that the processes rectifying together (a
    local cluster's workers, and the threads of each) take turns: the first compiles the
    engine's kernels, the others wait and load what it cached instead of compiling them
    again side by side (25-50 CPU-s each). Afterwards, and with the cache full, the block
    runs at once. Yields whether the kernels were missing."""
    global _TURN_TAKEN
    from swathflow.kernelcache import compiling_alone
    from swathflow.rectification.cells import _cell_tests
    if _TURN_TAKEN:
        yield False
        return
    with compiling_alone(_cell_tests) as cold:
        yield cold
    _TURN_TAKEN = True


def _warm_writer(grid, dt, nodata, use_mask: bool, tile: int, compress: str) -> None:
    """What :func:`to_cog` makes once a process for a swing's output (``dt``, ``nodata``):
    rioxarray's attributes (:func:`_rio_template`) and the writer's modules, imported.
    (``use_mask``, ``tile`` and ``compress`` are GDAL's to use: nothing is made for them
    here.)"""
    from swathflow.formats import raster  # noqa: F401  (the writer's CRS, imported)
    from swathflow.rectification import writing  # noqa: F401  (the writer, imported)
    grid_dataarray(np.zeros((1, 1), dt), grid.window(slice(0, 1), slice(0, 1)), "warm",
                   nodata=nodata)


def _swing(mission, image_id: str, calibration, gsd, crs):
    """The loaded mission, the swing's sensor model with the calibration, the opened
    terrain, the footprint grid and the calibration's tag."""
    from swathflow.geometry.terrain import open_terrain
    m = _open(mission, image_id)
    params, cal_tag = _parameters(m, calibration)
    model = m.model(image_id, params)
    terrain = open_terrain(m.terrain)
    return m, model, terrain, footprint_grid(model, terrain, gsd or m.gsd, crs or m.crs), cal_tag


def _polynomial(model, source, grid, terrain, attrs) -> xr.DataArray:
    """The forward (polynomial) method as a lazy DataArray of one block (the method holds
    the whole output grid in memory by design)."""
    import dask
    import dask.array as dsa

    from swathflow.rectification.rectify import rectify_polynomial
    if source.count != 1:
        raise FormatError(f"the polynomial method rectifies one band; the raw image has "
                          f"{source.count}: select one (bands) or use the exact method")
    block = dask.delayed(rectify_polynomial, pure=True)(model, source, grid, terrain)
    data = dsa.from_delayed(block, shape=grid.shape, dtype=np.float32)
    return grid_dataarray(data, grid, attrs["image_id"], attrs, band_info=source.band_info)


def geolocation(mission, image_id: str, calibration=None, product: str = "glt", *,
                gsd: float | None = None, crs: str | None = None, kernel: str = "bilinear",
                tile: int = 512, tol: float | None = None) -> xr.DataArray:
    """A geolocation product of the swing as a lazy DataArray. ``glt``: the ENVI GLT over
    the rectified grid (int32 (band, y, x): element + 1, line + 1; 0 = none). ``igm``: map
    x, y and ellipsoidal height of every raw pixel centre, float64 (band, line, element)
    in raw geometry (no CRS on the array; the map CRS is in ``attrs["crs"]``)."""
    import dask.array as dsa

    from swathflow.rectification.lattice import TOLERANCE_PX
    from swathflow.rectification.rawimage import open_raw_image
    from swathflow.rectification.tiles import check_inputs, glt_blocks
    if product not in ("glt", "igm"):
        raise FormatError(f"unknown product {product!r}; use glt, igm")
    tile = tile_size(tile)
    tol = TOLERANCE_PX if tol is None else tol
    m, model, terrain, grid, cal_tag = _swing(mission, image_id, calibration, gsd, crs)
    attrs = _tags(m, image_id, model, "exact", kernel, tol, cal_tag, terrain)
    if product == "glt":
        source = open_raw_image(m.images[image_id].file)
        check_inputs(model, source, kernel)
        arr = glt_blocks(model, source, grid, terrain, kernel, tol, tile)
        attrs.update(product="GLT", bands="element+1,line+1",
                     convention="ENVI GLT, 1-based, 0 = none",
                     long_name="raw element + 1, raw line + 1 (0: none)", units="1")
        return grid_dataarray(arr, grid, f"{image_id}.glt", attrs, nodata=0)
    from swathflow.rectification.rectify import igm_block
    import dask
    nl, ne = model.shape
    blk = max(1, min(nl, 2_000_000 // max(ne, 1)))
    parts = [dsa.from_delayed(dask.delayed(igm_block, pure=True)(
        model, terrain, grid.crs, l0, min(l0 + blk, nl)),
        shape=(3, min(l0 + blk, nl) - l0, ne), dtype=np.float64) for l0 in range(0, nl, blk)]
    attrs.update(product="IGM", crs=grid.pyproj_crs.to_string(), bands="x,y,h_ellipsoidal",
                 geometry="raw (line, element)", long_name="map x, map y, ellipsoidal height",
                 units="m" if grid.pyproj_crs.is_projected else "deg, deg, m")
    data = dsa.concatenate(parts, axis=1).rechunk((3, tile, tile))
    return xr.DataArray(data, dims=("band", "line", "element"), name=f"{image_id}.igm",
                        attrs={**netcdf_attrs(attrs), "_FillValue": np.nan})


def _grid_of(da: xr.DataArray) -> Grid | None:
    """The output grid of a georeferenced DataArray (None: not georeferenced)."""
    if "x" not in da.dims or "y" not in da.dims or da.rio.crs is None:
        return None
    return Grid(da.rio.crs.to_string(), da.rio.transform(), (da.rio.height, da.rio.width))


def local_scheduler(collection):
    """The scheduler function dask would use for ``collection`` (the configured one, else
    the collection's default) when ``distributed`` was never imported, so no Client can
    be active; None otherwise (dask then looks for a Client). Passing it to ``compute``
    spares dask's own lookup, which imports ``distributed`` (0.2-0.4 CPU-s)."""
    import dask
    from dask.base import named_schedulers
    if "distributed" in sys.modules:
        return None
    name = dask.config.get("scheduler", None)
    if name is None:
        return collection.__dask_scheduler__
    if callable(name):
        return name
    return named_schedulers.get(name.lower()) if isinstance(name, str) else None


def to_cog(da: xr.DataArray, path, *, tags: Mapping | None = None, blocksize: int = 512,
           compress: str = "deflate", overview_resampling: str = "average",
           scheduler=None, valid: np.ndarray | None = None) -> dict:
    """Write ``da`` (lazy or not; (y, x) or (band, y, x), or a raw-geometry array without
    CRS) as a Cloud-Optimized GeoTIFF at ``path``, atomically: its blocks are computed on
    the current Dask scheduler and streamed window by window in THIS process (memory
    bounded by the blocks in flight), then laid out by GDAL's COG driver with overviews
    (:mod:`.writing`). Keeps the dtype, the nodata value (``da.rio.nodata``) or the
    ``mask`` coordinate as an internal mask band, band descriptions (``band <n>`` where
    none) and wavelengths, and the attributes as GDAL tags (with ``tags`` added; values
    that are not strings as JSON), with the software's version and the TIFF date and
    software tags. ``valid``: a (rows, cols) uint8 array to fill with the
    written data's valid mask (255 valid, 0 not: what rasterio's ``dataset_mask`` reads
    back), e.g. to trace its footprint without reading the file again. Returns a summary
    (path, grid, bands, dtype, nodata)."""
    import dask.array as dsa

    from swathflow.rectification.writing import write_cogs
    if not isinstance(da, xr.DataArray):
        raise ArgumentTypeError(
            f"to_cog: da must be an xarray.DataArray (e.g. swathflow.rectify(...)), got "
            f"{type(da).__module__}.{type(da).__qualname__}: wrap an array as "
            f"xarray.DataArray(a, dims=('y', 'x')) with its CRS and transform "
            f"(da.rio.write_crs, da.rio.write_transform), or none for raw geometry")
    blocksize = tile_size(blocksize, "blocksize")
    grid = _grid_of(da)
    nodata = da.rio.nodata if grid is not None else da.attrs.get("_FillValue")
    data = da.data if hasattr(da.data, "chunks") else dsa.from_array(np.asarray(da.data),
                                                                    chunks=blocksize,
                                                                    name=False)
    bands = data if data.ndim == 3 else data[None]
    use_mask = "mask" in da.coords and da.coords["mask"].dims == ("y", "x")
    if use_mask:
        mask = da.coords["mask"].data
        mask = mask if hasattr(mask, "chunks") else dsa.from_array(mask, chunks=blocksize,
                                                                   name=False)
        bands = dsa.concatenate([bands, mask.astype(bands.dtype)[None]], axis=0)
        bands = bands.rechunk({0: -1})         # one block per tile: the tile computed once
        nodata = None
    elif data.ndim == 2:
        bands = data
    out_tags = {k: v for k, v in da.attrs.items() if k not in _NOT_TAGS}
    out_tags.update(tags or {})
    named = da.attrs.get("bands")           # the GLT's and the IGM's bands, by name
    names = named.split(",") if isinstance(named, str) else None
    if scheduler is None:
        scheduler = local_scheduler(bands)
    write_cogs([{"path": path, "array": bands, "grid": grid, "nodata": nodata,
                 "tags": out_tags, "mask": use_mask, "bands": _band_infos(da),
                 "descriptions": names, "valid": valid}],
               blocksize=blocksize, compress=compress,
               overview_resampling=overview_resampling, scheduler=scheduler)
    nd = "mask band" if use_mask else str(nodata)
    return {"path": os.fspath(path), "grid": grid.state() if grid else None,
            "bands": int(da.sizes.get("band", 1)), "dtype": np.dtype(da.dtype).name,
            "nodata": nd}
