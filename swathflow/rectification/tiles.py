"""The exact method, tile by tile: lattice (:mod:`.lattice`) -> compiled kernels
(:mod:`.kernel`) -> a lazy dask array over the output grid.

Per tile: the lattice's leaves bound the raw window the tile needs (bilinear interpolation
stays inside its corners' box); that window is read once, in its native dtype, for the
selected bands; the coordinates are painted once (float32, window-relative) and every band
is resampled at them. Memory is bounded by the tile and its raw window, never by the swing.
"""
from __future__ import annotations

import json
import math
import os
import uuid
import warnings
import weakref

import numpy as np
from swathflow.errors import FormatError
from swathflow.geometry.terrain import open_terrain
from swathflow.rectification.kernel import resample_window
from swathflow.rectification.lattice import TOLERANCE_PX, leaves
from swathflow.rectification.paint import paint_leaves
from swathflow.rectification.rawimage import RawImage, open_raw_image

KERNELS = ("nearest", "bilinear", "cubic")
MARGIN = {"nearest": 1, "bilinear": 2, "cubic": 3}
#: output dtypes a user may ask for (``--dtype``)
DTYPES = ("uint8", "uint16", "int16", "uint32", "int32", "float32", "float64")


def output_plan(source: RawImage, dtype=None,
                mask_band: bool = False) -> tuple[np.dtype, float | None, bool]:
    """(output dtype, output nodata, mask band) for a raw image.

    The raw dtype is kept (uint8, uint16, int16, int32, uint32, float32); float64 and
    other types become float32 unless ``dtype`` says otherwise. Float output: NaN marks
    nodata. Integer output: the raw image's own nodata value when the output type can
    hold it, else the type's lowest value (0 unsigned, -32768 for int16...); a valid
    value that lands on the nodata value moves one unit inwards (as GDAL's warper does),
    so nodata cannot collide with data. With ``mask_band`` integer output carries no
    nodata value but a mask band (every value of the type stays data)."""
    if dtype is not None:
        dt = np.dtype(dtype)
        if dt.name not in DTYPES:
            raise FormatError(f"output dtype {dt.name!r} is not supported; use one of "
                              f"{', '.join(DTYPES)}")
    else:
        src = np.dtype(source.dtype)
        dt = src if src.name in DTYPES and src.name != "float64" else np.dtype(np.float32)
        if src.name == "int8":
            dt = np.dtype(np.int16)
    if dt.kind == "f":
        return dt, float("nan"), False
    if mask_band:
        return dt, None, True
    nd = source.nodata
    info = np.iinfo(dt)
    if nd is not None and not (isinstance(nd, float) and math.isnan(nd)):
        if float(nd) == int(nd) and info.min <= nd <= info.max:
            return dt, int(nd), False
    return dt, int(info.min), False


def _window(lv, kernel, nl, ne):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)       # all-NaN leaves
        b = lv.bounds(nl, ne)
    if b is None:
        return None
    m = MARGIN[kernel]
    l0 = max(math.floor(b[0]) - m, 0)
    l1 = min(math.ceil(b[1]) + m + 1, nl)
    e0 = max(math.floor(b[2]) - m, 0)
    e1 = min(math.ceil(b[3]) + m + 1, ne)
    return (l0, l1, e0, e1) if l1 > l0 and e1 > e0 else None


def tile_coords(model, source, grid, terrain, kernel="bilinear", tol=TOLERANCE_PX, step=32,
                stats=None):
    """(window-relative coordinates ``(2, h, w)`` float32, window ``(l0, l1, e0, e1)`` or
    None) of one output tile."""
    nl, ne = source.shape
    lv = leaves(model, grid, terrain, tol, step, raw_shape=(nl, ne))
    if stats is not None:
        stats["exact_evaluations"] = stats.get("exact_evaluations", 0) + lv.exact_evaluations
        stats["pixels"] = stats.get("pixels", 0) + grid.shape[0] * grid.shape[1]
    win = _window(lv, kernel, nl, ne)
    h, w = grid.shape
    if win is None:
        return np.full((2, h, w), np.nan, np.float32), None
    return paint_leaves(lv, win[0], win[2], nl, ne), win


def rectify_tile(model, source, grid, terrain, kernel: str = "bilinear",
                 tol: float = TOLERANCE_PX, step: int = 32, stats: dict | None = None,
                 return_coords: bool = False):
    """One window of the output grid (``grid`` is the window's own grid) as float32
    ``(rows, cols)`` of the first (selected) band, NaN = nodata; with ``return_coords``
    also the raw (line, element) ``(rows, cols, 2)`` (NaN off the image). The multi-band,
    native-dtype form is :func:`tile_values`."""
    src = open_raw_image(source)
    src = src.select([src.selected[0] + 1]) if src.count > 1 else src
    v, ok = tile_values(model, src, grid, terrain, kernel, tol, step, stats,
                        dtype=np.float32)
    out = np.where(ok, v[0], np.float32(np.nan))
    if not return_coords:
        return out
    co, win = tile_coords(model, src, grid, terrain, kernel, tol, step)
    if win is None:
        return out, np.full(grid.shape + (2,), np.nan)
    return out, np.stack([co[0] + win[0], co[1] + win[2]], axis=-1).astype(np.float64)


def tile_values(model, source, grid, terrain, kernel: str = "bilinear",
                tol: float = TOLERANCE_PX, step: int = 32, stats: dict | None = None,
                dtype=None, mask_band: bool = False):
    """Rectify one window of the output grid (``grid`` is the window's own grid).

    Returns ``(values (bands, h, w), valid (h, w) bool)`` in the output dtype of
    :func:`output_plan` (nodata pixels hold the output nodata, or 0 with a mask)."""
    source = open_raw_image(source)
    dt, ond, _ = output_plan(source, dtype, mask_band)
    co, win = tile_coords(model, source, grid, terrain, kernel, tol, step, stats)
    if win is None:
        h, w = grid.shape
        fill = ond if ond is not None else 0
        return np.full((source.count, h, w), fill, dt), np.zeros((h, w), bool)
    raw = source.read(*win)
    return resample_window(raw, co, kernel, source.nodata, dt, ond)


def glt_tile(co, win):
    """ENVI GLT ``(2, h, w)`` int32 (element + 1, line + 1; 0 = none) of a tile."""
    g = np.zeros((2,) + co.shape[1:], np.int32)
    if win is None:
        return g
    ok = np.isfinite(co[0])
    g[0] = np.where(ok, np.floor(np.where(ok, co[1], 0) + win[2] + 0.5) + 1, 0)
    g[1] = np.where(ok, np.floor(np.where(ok, co[0], 0) + win[0] + 0.5) + 1, 0)
    return g


#: a token of each sensor model object for the tiles' task names: models are immutable
#: (``with_parameters`` makes a new one), so a random token per object names the same
#: tiles the same, without the model's content hash (``token()``: its POS as JSON, 6 ms
#: a call, a seventh of the kernel benchmark's 1x grid)
_MODEL_TOKENS: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def _model_token(model) -> str:
    try:
        return _MODEL_TOKENS[model]
    except KeyError:
        tok = _MODEL_TOKENS[model] = uuid.uuid4().hex
        return tok
    except TypeError:                    # not weakly referable: its content hash
        return model.token()


def _token(*args) -> str:
    from dask.base import tokenize
    return tokenize(*[_model_token(a) if hasattr(a, "to_state") else
                      a.token() if hasattr(a, "token") else
                      (a.state() if hasattr(a, "state") else a) for a in args])


def check_inputs(model, source, kernel):
    if kernel not in KERNELS:
        raise FormatError(f"unknown resampling kernel {kernel!r}; use one of {', '.join(KERNELS)}")
    if tuple(source.shape) != tuple(model.shape):
        raise FormatError(f"raw image is {source.shape[0]} x {source.shape[1]} but the sensor "
                          f"model expects {model.shape[0]} x {model.shape[1]} (lines x elements)")


def tiled(block, bands: int, chunks, dtype, name: str, args=(), shared=None):
    """A lazy ``(bands, rows, cols)`` dask array whose block ``(0, i, j)`` is
    ``block(*args, r0, r1, c0, c1)`` (its rows and columns in the whole array), one task a
    tile. ``shared``: graph keys -> objects that ``args`` name by key (a task argument
    that is a key is its object: a sensor model travels once a graph, not once a tile);
    the tiles depend on them alone. ``block`` is a module-level function and ``args``
    small, so that the graph pickles (plain ``pickle``), small. Built as a graph of its
    own, not with ``da.map_blocks``: its
    ``block_info`` dictionaries (every block's location, shape and chunk counts), built
    and parsed into tasks, cost about 0.1 ms a tile (the 0.05 m demo job's eight swings,
    442 tiles, in one process: 2.69-2.70 against 2.73-2.74 CPU-s, two alternated pairs)."""
    import dask.array as da
    from dask.highlevelgraph import HighLevelGraph
    rows, cols = chunks
    r_at = np.concatenate([[0], np.cumsum(rows)]).tolist()
    c_at = np.concatenate([[0], np.cumsum(cols)]).tolist()
    dsk = {(name, 0, i, j): (block, *args, r_at[i], r_at[i + 1], c_at[j], c_at[j + 1])
           for i in range(len(rows)) for j in range(len(cols))}
    dsk.update(shared or {})
    graph = HighLevelGraph.from_collections(name, dsk, dependencies=())
    return da.Array(graph, name, ((bands,), tuple(rows), tuple(cols)), dtype=dtype,
                    meta=np.empty((0, 0, 0), dtype))


def rectify_blocks(model, source: RawImage, grid, terrain, kernel="bilinear",
                   tol=TOLERANCE_PX, tile=512, step=32, dtype=None, mask_plane=False):
    """Lazy ``(bands [+ 1 mask plane], rows, cols)`` dask array of the rectified image in
    the output dtype; the mask plane (255 valid, 0 not) only with ``mask_plane``."""
    terrain = open_terrain(terrain)
    dt, _, _ = output_plan(source, dtype, mask_plane)
    nb = source.count + (1 if mask_plane else 0)
    token = _token(model, grid, kernel, tol, source, dt.name, mask_plane)
    key = f"swing-model-{token}"
    return tiled(_rectify_block, nb, grid.chunks(tile), dt, f"rectify-{token}",
                 (key, source, grid, terrain_arg(terrain), kernel, tol, step, dtype,
                  mask_plane), {key: model})


def _rectify_block(model, source, grid, terrain, kernel, tol, step, dtype, mask_plane,
                   r0, r1, c0, c1):
    """One tile of :func:`rectify_blocks` (rows ``r0:r1``, columns ``c0:c1`` of ``grid``)."""
    sub = grid.window(slice(r0, r1), slice(c0, c1))
    v, ok = tile_values(model, source, sub, terrain_of(terrain), kernel, tol, step,
                        dtype=dtype, mask_band=mask_plane)
    if not mask_plane:
        return v
    return np.concatenate([v, np.where(ok, 255, 0).astype(v.dtype)[None]])


#: terrains opened in this process by :func:`terrain_of`, by their JSON state (the last few)
_TERRAINS: dict = {}


def terrain_arg(terrain):
    """What a task carries for ``terrain``: a DEM read from a file as its state in JSON
    (its absolute path, vertical datum...: a few hundred bytes, where its heights are
    megabytes), reopened once a process by :func:`terrain_of`; another terrain as is."""
    st = terrain.state()
    if st.get("kind") != "dem" or not st.get("path") or not os.path.isfile(st["path"]):
        return terrain
    return json.dumps(dict(st, path=os.path.abspath(st["path"])), sort_keys=True)


def terrain_of(arg):
    """The terrain a task's argument of :func:`terrain_arg` stands for."""
    if not isinstance(arg, str):
        return arg
    t = _TERRAINS.pop(arg, None) or open_terrain(json.loads(arg))
    _TERRAINS[arg] = t                           # the most recent last
    while len(_TERRAINS) > 4:
        _TERRAINS.pop(next(iter(_TERRAINS)))
    return t


def glt_blocks(model, source, grid, terrain, kernel="bilinear", tol=TOLERANCE_PX, tile=512,
               step=32):
    """Lazy ENVI GLT ``(2, rows, cols)`` int32 dask array (the lattice alone, no reads)."""
    terrain = open_terrain(terrain)
    token = _token(model, grid, kernel, tol, source)
    key = f"swing-model-{token}"
    return tiled(_glt_block, 2, grid.chunks(tile), np.dtype(np.int32), f"rectify-glt-{token}",
                 (key, source, grid, terrain_arg(terrain), kernel, tol, step), {key: model})


def _glt_block(model, source, grid, terrain, kernel, tol, step, r0, r1, c0, c1):
    """One tile of :func:`glt_blocks`."""
    sub = grid.window(slice(r0, r1), slice(c0, c1))
    return glt_tile(*tile_coords(model, source, sub, terrain_of(terrain), kernel, tol, step))


def rectify(model, image, grid, terrain, kernel: str = "bilinear",
            tol: float = TOLERANCE_PX, tile: int = 512, step: int = 32, glt: bool = False,
            dtype=None, bands=None):
    """The rectified image as a lazy dask array over ``grid`` (tiles of ``tile`` pixels):
    ``(rows, cols)`` for a 2-D raw image, ``(bands, rows, cols)`` for a multi-band one
    (``bands`` selects a subset: see :func:`.rawimage.parse_bands`), in the output dtype
    of :func:`output_plan` (``dtype`` overrides). With ``glt`` a tuple ``(image, glt)``,
    the GLT an int32 ``(2, rows, cols)`` dask array. Compute it with any dask scheduler,
    or pass it to :func:`write_cog`."""
    source = open_raw_image(image, bands=bands)
    check_inputs(model, source, kernel)
    img = rectify_blocks(model, source, grid, terrain, kernel, tol, tile, step, dtype)
    if source.two_d:
        img = img[0]
    if not glt:
        return img
    return img, glt_blocks(model, source, grid, terrain, kernel, tol, tile, step)
