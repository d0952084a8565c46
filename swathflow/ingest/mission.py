"""Mission bundles (shared/spec/mission-format.md, version 1): validation and loading.

:func:`validate_mission` lists every problem of a mission folder (never raises for bad
input); :func:`load_mission` returns a :class:`Mission` or raises one
:class:`~swathflow.errors.SwathflowError` listing all problems. Images load lazily as
dask-chunked ``xarray.Dataset`` objects ``(line, element)``.
"""
from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import xarray as xr

from swathflow.errors import SwathflowError, SwathflowWarning
from swathflow.formats.pos import Trajectory
from swathflow.geometry.terrain import Terrain

#: per-line columns every line table needs; plugins may ask for more (``line_columns``)
BASE_LINE_COLUMNS = ("line", "time")
IMAGE_KEYS = ("id", "file", "lines", "direction", "strip")


@dataclass(frozen=True)
class Problem:
    """One thing wrong with a mission: where it is and how to fix it."""

    file: str
    where: str
    message: str
    fix: str = ""
    level: str = "error"      # "error": the mission is unusable; "warning": it loads

    def __str__(self) -> str:
        loc = f"{self.file}: {self.where}: " if self.where else f"{self.file}: "
        head = "warning: " if self.level == "warning" else ""
        return head + loc + self.message + (f" -> fix: {self.fix}" if self.fix else "")


@dataclass(frozen=True)
class ImageEntry:
    id: str
    file: Path
    lines_file: Path
    direction: str
    strip: int
    attrs: dict = field(default_factory=dict)


# ------------------------------------------------------------------------------------------
# lazy raster access (GeoTIFF, ENVI, anything rasterio reads)

class _RasterBand:
    """An array-like over band 1 of a raster file that reads only the requested window."""

    def __init__(self, path: str, shape: tuple[int, int], dtype: str):
        self.path = path
        self.shape = shape
        self.dtype = np.dtype(dtype)
        self.ndim = 2

    def __getitem__(self, key):
        from rasterio.windows import Window
        if not isinstance(key, tuple):
            key = (key,)
        key = key + (slice(None),) * (2 - len(key))
        sl = []
        for k, n in zip(key, self.shape):
            if not isinstance(k, slice) or (k.step not in (None, 1)):
                with _open_raw(self.path) as src:
                    return src.read(1)[key]
            start, stop, _ = k.indices(n)
            sl.append((start, max(stop, start)))
        (r0, r1), (c0, c1) = sl
        if r1 == r0 or c1 == c0:
            return np.empty((r1 - r0, c1 - c0), self.dtype)
        with _open_raw(self.path) as src:
            return src.read(1, window=Window(c0, r0, c1 - c0, r1 - r0))


def _open_raw(path):
    """rasterio.open for raw (non-georeferenced) images, without the warning."""
    import warnings

    import rasterio
    from rasterio.errors import NotGeoreferencedWarning
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", NotGeoreferencedWarning)
        return rasterio.open(os.fspath(path))


def raster_info(path) -> tuple[int, int, int, str]:
    """(rows, cols, bands, dtype) of a raster; raises SwathflowError when unreadable."""
    import rasterio
    try:
        with _open_raw(path) as src:
            return src.height, src.width, src.count, src.dtypes[0]
    except (rasterio.errors.RasterioError, OSError, ValueError) as exc:
        raise SwathflowError(f"{path}: cannot read image: {exc}") from None


def raster_check(path) -> tuple[int, int, int, str]:
    """(rows, cols, bands, note) of a raw image after checking that all of its pixels
    are there: a raw (ENVI) data file shorter than its header says, or a GeoTIFF whose
    last line cannot be read, is refused. ``note`` says which band is used when there
    are several (empty otherwise)."""
    import rasterio
    from rasterio.windows import Window
    try:
        with _open_raw(path) as src:
            rows, cols, bands = src.height, src.width, src.count
            if np.dtype(src.dtypes[0]).kind == "c":
                raise SwathflowError(f"{path}: complex-valued pixels ({src.dtypes[0]}); a "
                                     f"raw image holds real numbers: write its magnitude "
                                     f"(or the real part) as the image")
            need = rows * cols * bands * np.dtype(src.dtypes[0]).itemsize
            if src.driver == "ENVI":
                data = _envi_data_file(src, path)
                have = os.path.getsize(data)
                offset = _envi_offset(src)
                if have < need + offset:
                    raise SwathflowError(
                        f"{data}: truncated: {have:,} bytes where the header "
                        f"({rows} lines x {cols} samples x {bands} band(s), "
                        f"{src.dtypes[0]}) needs {need + offset:,}; re-copy or re-export "
                        f"the image")
                if have > need + offset:
                    raise SwathflowError(
                        f"{data}: {have:,} bytes where the header ({rows} lines x {cols} "
                        f"samples x {bands} band(s), {src.dtypes[0]}, header offset "
                        f"{offset}) accounts for {need + offset:,}: the header does not "
                        f"describe the file (its bands, samples, lines or data type are "
                        f"wrong, and the pixels would be read scrambled); correct the "
                        f".hdr")
            end = _tiff_blocks_end(src) if src.driver == "GTiff" else None
            if end is None:              # not told: read the last line (0.003 s each)
                src.read(1, window=Window(0, rows - 1, cols, 1))
            elif end > os.path.getsize(path):
                raise SwathflowError(
                    f"{path}: truncated: {os.path.getsize(path):,} bytes where its image "
                    f"blocks end at byte {end:,}; re-copy or re-export the image")
    except rasterio.errors.RasterioError as exc:
        raise SwathflowError(f"{path}: cannot read image (truncated or damaged?): "
                             f"{str(exc).splitlines()[0][:200]}") from None
    except (OSError, ValueError) as exc:
        raise SwathflowError(f"{path}: cannot read image: {exc}") from None
    _has_data(path)
    note = (f"the image has {bands} bands; every band is rectified, the mosaic uses band 1"
            if bands > 1 else "")
    return rows, cols, bands, note


def _envi_offset(src) -> int:
    """The ``header offset`` of an open ENVI image (bytes before its pixels; 0 if none)."""
    for f in src.files:
        if f.lower().endswith(".hdr"):
            try:
                with open(f, encoding="latin-1") as h:
                    for line in h:
                        k, _, v = line.partition("=")
                        if k.strip().lower() == "header offset":
                            return max(int(v.strip()), 0)
            except (OSError, ValueError):
                return 0
    return 0


#: lines of a raw image read to tell it holds data (all of it only when none of these has)
SAMPLE_LINES = 32


def _has_data(path) -> None:
    """Refuse a raw image without one valid pixel (all NaN, or all its nodata value): its
    products would be empty. A few lines spread over the image are read; all of it only
    when none of those holds a valid pixel."""
    from rasterio.windows import Window
    with _open_raw(path) as src:
        rows, cols = src.height, src.width
        nodata = src.nodata

        def valid(a) -> bool:
            ok = np.isfinite(a) if a.dtype.kind == "f" else np.ones(a.shape, bool)
            if nodata is not None:
                ok &= a != nodata
            return bool(ok.any())
        for r in np.unique(np.linspace(0, rows - 1, min(SAMPLE_LINES, rows)).astype(int)):
            if valid(src.read(window=Window(0, int(r), cols, 1))):
                return
        step = max(1, (64 << 20) // max(cols * src.count * 8, 1))
        for r0 in range(0, rows, step):
            if valid(src.read(window=Window(0, r0, cols, min(step, rows - r0)))):
                return
    what = "NaN" if nodata is None else f"NaN or its nodata value {nodata}"
    raise SwathflowError(f"{path}: no valid pixel (every pixel is {what}): its products "
                         f"would be empty; check the export of the image")


def _tiff_blocks_end(src) -> int | None:
    """The byte where the last image block of an open GeoTIFF ends (from its block
    offsets and sizes, without decompressing anything), or None when GDAL does not say."""
    pixel = str(getattr(src.interleaving, "name", "")).upper() == "PIXEL"
    bands = (1,) if pixel else range(1, src.count + 1)   # pixel-interleaved: shared blocks
    bh, bw = src.block_shapes[0]
    end = 0
    for b in bands:
        for y in range(-(-src.height // bh)):
            for x in range(-(-src.width // bw)):
                off = src.get_tag_item(f"BLOCK_OFFSET_{x}_{y}", "TIFF", bidx=b)
                size = src.get_tag_item(f"BLOCK_SIZE_{x}_{y}", "TIFF", bidx=b)
                if off is None or size is None:
                    return None
                end = max(end, int(off) + int(size))
    return end


def _envi_data_file(src, path) -> str:
    """The binary file of an ENVI image (the path itself, or the one beside its header)."""
    path = os.fspath(path)
    if not path.lower().endswith(".hdr"):
        return path
    for f in src.files:
        if not f.lower().endswith(".hdr"):
            return f
    return path


def lazy_image(path, chunk_lines: int = 2048):
    """A dask array over band 1 of a raster, chunked in blocks of whole lines."""
    import dask.array as da
    rows, cols, _, dtype = raster_info(path)
    arr = _RasterBand(os.fspath(path), (rows, cols), dtype)
    return da.from_array(arr, chunks=(min(chunk_lines, rows), cols), lock=False,
                         asarray=True, name=f"raw-{os.fspath(path)}-{os.path.getmtime(path)}")


# ------------------------------------------------------------------------------------------
# the Mission

@dataclass(frozen=True, eq=False)
class Mission:
    path: Path
    name: str
    config: dict
    crs: str
    gsd: float
    sensor: dict
    pos: xr.Dataset
    trajectory: Trajectory
    images: dict[str, ImageEntry]
    gcps: pd.DataFrame | None
    terrain: Terrain
    priors: Any  # ParameterSet
    _lines: dict = field(default_factory=dict, repr=False)

    def lines(self, image_id: str) -> dict[str, np.ndarray]:
        """The per-line table of an image: column -> array (``line`` as int)."""
        if image_id not in self._lines:   # (filled by load_mission from its check)
            from swathflow.ingest.linetable import plain_table
            path = self.images[image_id].lines_file
            cols = plain_table(path)
            if cols is None:
                df = pd.read_csv(path)
                df.columns = [str(c).strip() for c in df.columns]
                cols = {c: df[c].to_numpy(float) for c in df.columns}
            self._lines[image_id] = _typed(cols)
        return dict(self._lines[image_id])

    def image(self, image_id: str, chunk_lines: int = 2048) -> xr.Dataset:
        """The raw image as a lazy, dask-chunked Dataset with ``dn`` over (line, element)."""
        e = self.images[image_id]
        arr = lazy_image(e.file, chunk_lines)
        lt = self.lines(image_id)
        coords = {"line": np.arange(arr.shape[0]), "element": np.arange(arr.shape[1])}
        for k, v in lt.items():
            if k != "line":
                coords[k] = ("line", v)
        attrs = {"image_id": e.id, "direction": e.direction, "strip": e.strip,
                 "sensor": self.sensor.get("model", ""), "file": str(e.file)}
        ds = xr.Dataset({"dn": (("line", "element"), arr)}, coords=coords, attrs=attrs)
        return ds

    @property
    def sensor_class(self):
        """The registered sensor-model class (plugin) of the mission's ``[sensor] model``."""
        from swathflow.sensormodel import get_sensor
        return get_sensor(self.sensor["model"])

    def model(self, image_id: str, params=None):
        """The sensor model of one image (``params`` default: the mission's priors)."""
        e = self.images[image_id]
        cls = self.sensor_class
        lt = {k: v for k, v in self.lines(image_id).items() if k != "line"}
        return cls.build(self.sensor, lt, self.trajectory,
                         self.priors if params is None else params,
                         image_id=e.id, direction=e.direction, strip=e.strip, **e.attrs)

    @property
    def image_ids(self) -> list[str]:
        return list(self.images)

    def __repr__(self) -> str:
        n = 0 if self.gcps is None else len(self.gcps)
        return (f"<Mission {self.name!r} {len(self.images)} images, {n} GCP rows, "
                f"crs={self.crs}, gsd={self.gsd}>")


def _typed(cols: dict) -> dict[str, np.ndarray]:
    """A line table's columns as :meth:`Mission.lines` gives them (``line`` as int)."""
    return {c: (np.asarray(v).astype(int) if c == "line" else np.asarray(v, float))
            for c, v in cols.items()}


# ------------------------------------------------------------------------------------------
# public entry points

class MissionWarning(SwathflowWarning):
    """Something in a mission that loads but deserves a look (a POS gap, an unknown key)."""


def inspect_mission(path) -> tuple[list[Problem], dict]:
    """Every problem found in a mission folder and the parts read (config, images...)."""
    from swathflow.ingest.validate import inspect
    try:
        with np.errstate(all="ignore"):
            return inspect(path)
    except SwathflowError as exc:  # defensive: a check raised instead of collecting
        return [Problem(os.fspath(path), "", str(exc), "")], {}
    except Exception as exc:  # noqa: BLE001 - bad input must never end in a traceback
        return [Problem(os.fspath(path), "", f"unexpected content ({type(exc).__name__}: "
                        f"{exc})", "check mission.toml against spec/mission-format.md; if "
                        "the mission is fine, report this as a swathflow bug")], {}


def _errors(problems: list[Problem]) -> list[Problem]:
    return [p for p in problems if p.level != "warning"]


def validate_mission(path) -> list[Problem]:
    """Every problem found in a mission folder, warnings included (no error: usable)."""
    return inspect_mission(path)[0]


def load_mission(path) -> Mission:
    """Read a mission folder; raises SwathflowError listing every problem. Warnings are
    issued as :class:`MissionWarning`."""
    import warnings
    problems, p = inspect_mission(path)
    if _errors(problems):
        raise SwathflowError(format_problems(path, _errors(problems)))
    for pr in problems:
        warnings.warn(MissionWarning(str(pr)), stacklevel=2)
    return Mission(path=p["root"], name=p["name"], config=p["config"], crs=p["crs"],
                   gsd=float(p["gsd"]), sensor=dict(p["sensor"]), pos=p["pos"],
                   trajectory=p["trajectory"], images=p["images"], gcps=p["gcps"],
                   terrain=p["terrain"], priors=p["priors"],
                   _lines={iid: _typed(cols) for iid, cols in p.get("tables", {}).items()})


def format_problems(path, problems: list[Problem]) -> str:
    n = len(_errors(problems))
    w = len(problems) - n
    head = (f"mission {os.fspath(path)} has {n} problem(s)"
            + (f" and {w} warning(s)" if w else "") + ":")
    return "\n".join([head] + [f"  - {pr}" for pr in problems])


def __getattr__(name):   # moved names, kept importable from here
    if name in ("GCP_COLUMNS", "GCP_ROLES"):
        from swathflow.ingest import gcpfile
        return getattr(gcpfile, name)
    if name == "image_border":
        from swathflow.ingest.plausible import image_border
        return image_border
    raise AttributeError(name)
