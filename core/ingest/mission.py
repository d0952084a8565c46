"""Mission bundles (shared/spec/mission-format.md, version 1): validation and loading.

:func:`validate_mission` lists every problem of a mission folder (never raises for bad
input); :func:`load_mission` returns a :class:`Mission` or raises one
:class:`~swathflow.errors.SwathflowError` listing all problems. Images load lazily as
dask-chunked ``xarray.Dataset`` objects ``(line, element)``.
"""
from __future__ import annotations

import math
import os
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import xarray as xr

from swathflow.errors import SwathflowError
from swathflow.formats.pos import Trajectory, read_pos
from swathflow.geometry.terrain import DEM, ConstantHeight, Terrain

GCP_COLUMNS = ("gcp_id", "image_id", "line", "element", "x", "y", "z", "role")
GCP_ROLES = ("control", "check")
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

    def __str__(self) -> str:
        loc = f"{self.file}: {self.where}: " if self.where else f"{self.file}: "
        return loc + self.message + (f" -> fix: {self.fix}" if self.fix else "")


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
    except rasterio.errors.RasterioIOError as exc:
        raise SwathflowError(f"{path}: cannot read image: {exc}") from None


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
        if image_id not in self._lines:
            df = pd.read_csv(self.images[image_id].lines_file)
            df.columns = [str(c).strip() for c in df.columns]
            self._lines[image_id] = {c: df[c].to_numpy(int if c == "line" else float)
                                     for c in df.columns}
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
        from swathflow.sensors import get_sensor
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


# ------------------------------------------------------------------------------------------
# inspection: one pass that collects problems and the parsed parts

class _Collector:
    def __init__(self):
        self.problems: list[Problem] = []

    def add(self, file, where, message, fix=""):
        self.problems.append(Problem(str(file), where, message, fix))


def _rel(root: Path, p) -> Path:
    p = Path(str(p))
    return p if p.is_absolute() else root / p


def _check_crs(crs) -> str | None:
    import pyproj
    try:
        pyproj.CRS.from_user_input(crs)
        return None
    except (pyproj.exceptions.CRSError, TypeError, ValueError) as exc:
        return str(exc).splitlines()[0][:200]


def _first_rows(mask, limit=5) -> str:
    idx = np.flatnonzero(mask)
    s = ", ".join(str(i + 2) for i in idx[:limit])
    return s + (f" (and {idx.size - limit} more)" if idx.size > limit else "")


def _inspect(path) -> tuple[list[Problem], dict]:
    from swathflow.sensors.registry import _registry
    c = _Collector()
    root = Path(os.fspath(path))
    parts: dict[str, Any] = {"root": root}
    toml = root / "mission.toml"
    if not root.is_dir():
        c.add(root, "", "mission folder not found", "give the folder that holds mission.toml")
        return c.problems, parts
    if not toml.exists():
        c.add(toml, "", "mission.toml not found",
              "create mission.toml (see spec/mission-format.md)")
        return c.problems, parts
    try:
        with open(toml, "rb") as f:
            cfg = tomllib.load(f)
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        c.add(toml, "", f"not valid TOML: {exc}", "correct the syntax at the position shown")
        return c.problems, parts
    parts["config"] = cfg

    # [mission]
    m = cfg.get("mission")
    if not isinstance(m, dict):
        c.add(toml, "[mission]", "table missing", 'add [mission] with name, crs and gsd')
        m = {}
    parts["name"] = str(m.get("name", root.name))
    crs = m.get("crs", "auto-utm")
    if not isinstance(crs, str):
        c.add(toml, "[mission].crs", f"must be a string, got {crs!r}",
              'crs = "EPSG:32651" or "auto-utm"')
    elif crs.lower() != "auto-utm":
        err = _check_crs(crs)
        if err:
            c.add(toml, "[mission].crs", f"pyproj rejects CRS {crs!r}: {err}",
                  'use an EPSG code such as "EPSG:32651", or "auto-utm"')
        else:
            import pyproj
            cc = pyproj.CRS.from_user_input(crs)
            if not cc.is_projected:
                c.add(toml, "[mission].crs", f"{crs!r} is not a projected CRS",
                      "the output grid needs metres: use a projected CRS or auto-utm")
    parts["crs"] = crs
    gsd = m.get("gsd")
    if not isinstance(gsd, (int, float)) or isinstance(gsd, bool) or not gsd > 0 \
            or not math.isfinite(gsd):
        c.add(toml, "[mission].gsd", f"must be a positive number of metres, got {gsd!r}",
              "gsd = 0.5")
        gsd = None
    parts["gsd"] = gsd

    # [sensor]
    sensor = cfg.get("sensor")
    cls = None
    if not isinstance(sensor, dict):
        c.add(toml, "[sensor]", "table missing",
              "add [sensor] with model = a name that 'swathflow sensors' lists")
        sensor = {}
    else:
        name = sensor.get("model")
        reg = _registry()
        if name not in reg:
            c.add(toml, "[sensor].model", f"unknown sensor plugin {name!r}",
                  f"use one of: {', '.join(sorted(reg)) or 'none'} (see 'swathflow sensors'),"
                  f" or install the plugin")
        else:
            cls = reg[name][0]
            try:
                bad = cls.check_config(sensor)
            except (TypeError, ValueError) as exc:
                bad = [f"invalid value: {exc}"]
            for b in bad:
                c.add(toml, "[sensor]", b, f"see the {name} plugin's documentation")
            if bad:
                cls = None
    parts["sensor"] = sensor
    parts["cls"] = cls

    # [pos]
    posc = cfg.get("pos", {}) if isinstance(cfg.get("pos", {}), dict) else {}
    pos_file = posc.get("file")
    if pos_file is None:
        for cand in ("pos.sbet", "pos.csv"):
            if (root / cand).exists():
                pos_file = cand
                break
    traj = None
    if pos_file is None:
        c.add(toml, "[pos].file", "no POS file named and neither pos.sbet nor pos.csv found",
              'add [pos] file = "pos.sbet", format = "sbet"')
    else:
        pp = _rel(root, pos_file)
        if not pp.exists():
            c.add(pp, "", "POS file not found", "check [pos].file in mission.toml")
        else:
            try:
                max_gap = float(posc.get("max_gap", 1.0))
            except (TypeError, ValueError):
                c.add(toml, "[pos].max_gap", f"must be a number of seconds, got "
                      f"{posc.get('max_gap')!r}", "max_gap = 1.0")
                max_gap = 1.0
            try:
                ds = read_pos(pp, posc.get("format"))
                traj = Trajectory.from_dataset(ds, max_gap=max_gap)
                parts["pos"] = ds
            except SwathflowError as exc:
                msg = str(exc).replace(str(pp) + ": ", "")
                c.add(pp, "[pos]" if "format" in msg else "", msg,
                      'set [pos] format = "sbet" or "csv"' if "unknown POS format" in msg
                      else "re-export the POS (times strictly increasing, finite values)")
    parts["trajectory"] = traj

    # [terrain]
    ter = cfg.get("terrain")
    terrain = None
    if not isinstance(ter, dict):
        c.add(toml, "[terrain]", "table missing",
              'add [terrain] dem = "dem.tif" or height = <ellipsoidal metres>')
    elif "dem" in ter:
        dp = _rel(root, ter["dem"])
        if not dp.exists():
            c.add(dp, "", "DEM file not found", "check [terrain].dem in mission.toml")
        else:
            try:
                terrain = DEM.open(dp, ter.get("vertical", "ellipsoidal"), ter.get("geoid"),
                                   ter.get("undulation"))
                if not np.isfinite(terrain.data).any():
                    c.add(dp, "", "the DEM holds no valid heights", "use a DEM with data")
                    terrain = None
            except SwathflowError as exc:
                c.add(dp, "[terrain]", str(exc).replace(str(dp) + ": ", ""),
                      "fix the DEM or its [terrain] keys")
    elif "height" in ter:
        try:
            h = float(ter["height"])
            if not math.isfinite(h):
                raise ValueError
            if ter.get("vertical", "ellipsoidal") == "orthometric":
                if "undulation" not in ter:
                    raise SwathflowError("an orthometric constant height needs undulation")
                h += float(ter["undulation"])
            terrain = ConstantHeight(h)
        except (TypeError, ValueError, SwathflowError) as exc:
            c.add(toml, "[terrain].height", f"not a usable height: {ter['height']!r} {exc}",
                  "height = <ellipsoidal metres> (or vertical = 'orthometric' + undulation)")
    else:
        c.add(toml, "[terrain]", "needs dem = \"...\" or height = <metres>",
              'add dem = "dem.tif" or height = 12.0')
    parts["terrain"] = terrain

    # [[images]]
    images: dict[str, ImageEntry] = {}
    shapes: dict[str, tuple[int, int]] = {}        # images whose line table is fine too
    image_shapes: dict[str, tuple[int, int]] = {}  # every readable image
    lines: dict[str, dict] = {}
    entries = cfg.get("images")
    if not isinstance(entries, list) or not entries:
        c.add(toml, "[[images]]", "no images listed", "add one [[images]] table per swing")
        entries = []
    need_cols = BASE_LINE_COLUMNS
    if cls is not None:
        need_cols = tuple(dict.fromkeys(BASE_LINE_COLUMNS + tuple(cls.line_columns)))
    n_el = None
    if "n_elements" in sensor:
        try:
            n_el = int(sensor["n_elements"])
        except (TypeError, ValueError):
            n_el = None
    for k, e in enumerate(entries):
        where = f"[[images]] #{k + 1}"
        if not isinstance(e, dict):
            c.add(toml, where, "must be a table", "")
            continue
        missing = [key for key in ("id", "file", "lines") if key not in e]
        if missing:
            c.add(toml, where, f"missing key(s) {', '.join(missing)}",
                  'each image needs id, file, lines (and direction, strip)')
            continue
        iid = str(e["id"])
        where = f"[[images]] id={iid!r}"
        if iid in images:
            c.add(toml, where, "duplicate image id", "give every image a unique id")
            continue
        direction = str(e.get("direction", ""))
        allowed = cls.directions if cls is not None else None
        if allowed and direction.upper() not in allowed:
            c.add(toml, where + ".direction", f"must be one of {', '.join(allowed)} for sensor "
                  f"{cls.name!r}, got {direction!r}",
                  f"direction = {allowed[0]!r} (see 'swathflow sensors' for the model)")
        try:
            strip = int(e.get("strip", 0))
        except (TypeError, ValueError):
            c.add(toml, where + ".strip", f"must be an integer, got {e.get('strip')!r}", "")
            strip = 0
        ip = _rel(root, e["file"])
        lp = _rel(root, e["lines"])
        attrs = {k2: v for k2, v in e.items() if k2 not in IMAGE_KEYS}
        entry = ImageEntry(iid, ip, lp, direction.upper(), strip, attrs)
        images[iid] = entry
        shape = None
        if not ip.exists():
            c.add(ip, where, "image file not found", "check the file key of this image")
        else:
            try:
                rows, cols, _, _ = raster_info(ip)
                shape = (rows, cols)
                image_shapes[iid] = shape
                if n_el is not None and cols != n_el:
                    c.add(ip, where, f"image has {cols} columns but [sensor].n_elements is "
                          f"{n_el}", "columns must be detector elements; fix n_elements or "
                          "the image")
            except SwathflowError as exc:
                c.add(ip, where, str(exc).replace(str(ip) + ": ", ""),
                      "write the image as GeoTIFF or ENVI")
        if not lp.exists():
            c.add(lp, where, "line table not found", "check the lines key of this image")
            continue
        try:
            df = pd.read_csv(lp)
        except (pd.errors.ParserError, pd.errors.EmptyDataError, UnicodeDecodeError) as exc:
            c.add(lp, "", f"cannot be read as CSV: {exc}", "write one header row and "
                  "one row per image line")
            continue
        df.columns = [str(col).strip() for col in df.columns]
        miss = [col for col in need_cols if col not in df.columns]
        if miss:
            c.add(lp, "header", f"missing column(s) {', '.join(miss)}",
                  f"the header must contain {','.join(need_cols)}")
            continue
        ok = True
        cols = {}
        check_cols = list(need_cols) + [col for col in df.columns if col not in need_cols
                                        and pd.api.types.is_numeric_dtype(df[col])]
        for col in check_cols:
            v = pd.to_numeric(df[col], errors="coerce").to_numpy(float)
            bad = ~np.isfinite(v)
            if bad.any():
                c.add(lp, f"column {col}, file row(s) {_first_rows(bad)}",
                      f"{int(bad.sum())} missing, NaN or non-numeric value(s)",
                      "every line needs finite numbers")
                ok = False
            cols[col] = v
        n = len(df)
        if shape is not None and n != shape[0]:
            c.add(lp, "", f"{n} rows but the image {ip.name} has {shape[0]} lines",
                  "the line table needs exactly one row per image line")
            ok = False
        if np.isfinite(cols["line"]).all() and not np.array_equal(cols["line"], np.arange(n)):
            bad = cols["line"] != np.arange(n)
            c.add(lp, f"column line, file row(s) {_first_rows(bad)}",
                  "line numbers must be 0, 1, 2, ... in order", "one row per line, in order")
            ok = False
        if ok and cls is not None:
            for msg in cls.check_lines({k2: v for k2, v in cols.items() if k2 != "line"}):
                c.add(lp, "", msg, "")
                ok = False
        t = cols["time"]
        if not np.isfinite(t).all():
            continue
        dec = np.diff(t) <= 0
        if dec.any():
            c.add(lp, f"column time, file row(s) {_first_rows(np.r_[False, dec])}",
                  "times must increase strictly from line to line",
                  "sort the lines by time; remove duplicate lines")
            ok = False
        if traj is not None:
            t0, t1 = traj.time[0], traj.time[-1]
            out = (t < t0) | (t > t1)
            if out.any():
                c.add(lp, f"column time, file row(s) {_first_rows(out)}",
                      f"{int(out.sum())} line time(s) outside the POS time span "
                      f"[{t0:.3f}, {t1:.3f}] s (e.g. {t[out][0]:.3f} s)",
                      "use a POS that covers the whole image (no extrapolation), or check "
                      "the time scale (GPS seconds of week)")
                ok = False
            else:
                i = np.clip(np.searchsorted(traj.time, t, side="right") - 1, 0,
                            traj.time.size - 2)
                gap = traj.time[i + 1] - traj.time[i]
                if (gap > traj.max_gap).any():
                    c.add(lp, f"column time, file row(s) {_first_rows(gap > traj.max_gap)}",
                          f"line times fall in a POS gap of {gap.max():.2f} s "
                          f"(> max_gap {traj.max_gap} s)",
                          "use a POS without gaps here, or raise [pos].max_gap")
                    ok = False
        if ok:
            lines[iid] = {col: cols[col] for col in need_cols if col != "line"}
            if shape is not None:
                shapes[iid] = shape
    parts["images"] = images
    parts["lines"] = lines
    parts["shapes"] = shapes

    # output CRS
    if isinstance(crs, str) and crs.lower() == "auto-utm" and traj is not None:
        from swathflow.geometry.geodesy import utm_crs_for
        parts["crs"] = utm_crs_for(float(np.mean(traj.lat)),
                                   float((np.mean(traj.lon) + 180) % 360 - 180)).to_string()

    # [calibration] priors
    priors = None
    if cls is not None:
        priors = _priors(cls, sensor, cfg.get("calibration"), root, toml, c)
    parts["priors"] = priors

    # [gcp]
    parts["gcps"] = _gcps(cfg, root, toml, images, image_shapes, c)

    # DEM coverage and model construction
    if cls is not None and traj is not None and priors is not None:
        for iid, lt in lines.items():
            if iid not in shapes:
                continue
            e = images[iid]
            try:
                model = cls.build(sensor, lt, traj, priors, image_id=iid, direction=e.direction,
                                  strip=e.strip, **e.attrs)
            except (SwathflowError, TypeError, ValueError, KeyError) as exc:
                c.add(toml, f"[[images]] id={iid!r}", f"the sensor model cannot be built: {exc}",
                      "fix the image's entry, its line table or the [sensor] values")
                continue
            if isinstance(terrain, DEM):
                _check_dem_cover(model, terrain, iid, c)
    return c.problems, parts


def _priors(cls, sensor, cal, root, toml, c):
    from swathflow.formats.calibfile import calibration_priors, read_calibration
    try:
        base = cls.default_parameters(sensor)
    except (KeyError, TypeError, ValueError) as exc:
        c.add(toml, "[sensor]", f"default parameters fail: {exc}", "")
        return None
    if cal is None:
        return base
    if not isinstance(cal, dict):
        c.add(toml, "[calibration]", "must be a table", "")
        return None
    cal = dict(cal)
    if "file" in cal:
        fp = _rel(root, cal.pop("file"))
        try:
            doc = read_calibration(fp)
            if doc.get("sensor") not in (None, cls.name):
                c.add(fp, "sensor", f"calibration is for sensor {doc.get('sensor')!r}, the "
                      f"mission uses {cls.name!r}", "use a calibration of this sensor")
            base = base.updated(calibration_priors(doc))
        except SwathflowError as exc:
            c.add(fp, "[calibration].file", str(exc).replace(str(fp) + ": ", ""),
                  "name a valid calibration.json")
            return None
    try:
        return base.updated(cal)
    except (SwathflowError, TypeError, ValueError) as exc:
        c.add(toml, "[calibration]", str(exc),
              f"parameters of {cls.name}: {', '.join(base.names)}; each "
              "{ value = [...], sigma = [...] }")
        return None


def _gcps(cfg, root, toml, images, shapes, c):
    gc = cfg.get("gcp")
    if gc is None:
        if (root / "gcp.csv").exists():
            gc = {"file": "gcp.csv", "crs": "EPSG:4979"}
        else:
            return None
    if not isinstance(gc, dict) or "file" not in gc:
        c.add(toml, "[gcp]", "needs file = \"gcp.csv\"", 'file = "gcp.csv", crs = "EPSG:4979"')
        return None
    gp = _rel(root, gc["file"])
    crs = gc.get("crs", "EPSG:4979")
    err = _check_crs(crs)
    if err:
        c.add(toml, "[gcp].crs", f"pyproj rejects CRS {crs!r}: {err}",
              'use "EPSG:4979" (lon, lat, ellipsoidal h) or a projected EPSG code')
    if not gp.exists():
        c.add(gp, "", "GCP file not found", "check [gcp].file in mission.toml")
        return None
    try:
        df = pd.read_csv(gp, dtype={"gcp_id": str, "image_id": str, "role": str})
    except (pd.errors.ParserError, pd.errors.EmptyDataError, UnicodeDecodeError) as exc:
        c.add(gp, "", f"cannot be read as CSV: {exc}", "")
        return None
    df.columns = [str(col).strip() for col in df.columns]
    miss = [col for col in GCP_COLUMNS if col not in df.columns]
    if miss:
        c.add(gp, "header", f"missing column(s) {', '.join(miss)}",
              f"the header must contain {','.join(GCP_COLUMNS)}")
        return None
    ok = True
    for col in ("line", "element", "x", "y", "z"):
        v = pd.to_numeric(df[col], errors="coerce")
        bad = ~np.isfinite(v.to_numpy(float))
        if bad.any():
            c.add(gp, f"column {col}, file row(s) {_first_rows(bad)}",
                  f"{int(bad.sum())} missing, NaN or non-numeric value(s)",
                  "every GCP row needs finite numbers (delete unmeasured rows)")
            ok = False
        df[col] = v.astype(float)
    for col in ("gcp_id", "image_id"):
        bad = df[col].isna().to_numpy()
        if bad.any():
            c.add(gp, f"column {col}, file row(s) {_first_rows(bad)}", "empty value", "")
            ok = False
    df["gcp_id"] = df["gcp_id"].astype(str)
    df["image_id"] = df["image_id"].astype(str)
    role = df["role"].astype(str).str.strip().str.lower()
    bad = ~role.isin(GCP_ROLES).to_numpy()
    if bad.any():
        c.add(gp, f"column role, file row(s) {_first_rows(bad)}",
              f"role must be control or check, found {sorted(set(df['role'][bad].astype(str)))}",
              "set role to control or check")
        ok = False
    df["role"] = role
    unknown = ~df["image_id"].isin(list(images)).to_numpy()
    if unknown.any():
        c.add(gp, f"column image_id, file row(s) {_first_rows(unknown)}",
              f"unknown image id(s) {sorted(set(df['image_id'][unknown]))}",
              f"use one of the [[images]] ids: {', '.join(images)}")
        ok = False
    dup = df.duplicated(["gcp_id", "image_id"]).to_numpy()
    if dup.any():
        c.add(gp, f"file row(s) {_first_rows(dup)}", "the same gcp_id appears twice for one image",
              "one row per GCP and image")
        ok = False
    for iid, (rows, cols) in shapes.items():
        sel = (df["image_id"] == iid).to_numpy()
        li = df["line"].to_numpy()
        el = df["element"].to_numpy()
        with np.errstate(invalid="ignore"):
            out = sel & ((li < -0.5) | (li > rows - 0.5) | (el < -0.5) | (el > cols - 0.5))
        if out.any():
            c.add(gp, f"file row(s) {_first_rows(out)}",
                  f"{int(out.sum())} GCP(s) outside image {iid!r} ({rows} lines x {cols} "
                  f"elements; valid line -0.5..{rows - 0.5}, element -0.5..{cols - 0.5})",
                  "check the image_id and the (line, element) order of these rows")
            ok = False
    if not ok or err:
        return None
    return _gcp_geodetic(df, crs)


def _gcp_geodetic(df: pd.DataFrame, crs: str) -> pd.DataFrame:
    """Add lat, lon, h (EPSG:4979) and X, Y, Z (ECEF) to a GCP table."""
    import pyproj
    from swathflow.geometry.geodesy import geodetic_to_ecef, transformer
    src = pyproj.CRS.from_user_input(crs)
    x, y, z = (df[k].to_numpy(float) for k in ("x", "y", "z"))
    if src.to_epsg() == 4979 or (src.is_geographic and len(src.axis_info) == 3):
        lon, lat, h = transformer(src, "EPSG:4979").transform(x, y, z)
    elif src.is_geographic:
        lon, lat = transformer(src, "EPSG:4326").transform(x, y)
        h = z
    else:  # projected + ellipsoidal height (spec)
        lon, lat = transformer(src, "EPSG:4326").transform(x, y)
        h = z
    out = df.copy()
    out["lat"], out["lon"], out["h"] = np.asarray(lat), np.asarray(lon), np.asarray(h)
    xyz = geodetic_to_ecef(np.stack([out["lat"], out["lon"], out["h"]], axis=-1))
    out["X"], out["Y"], out["Z"] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    return out.reset_index(drop=True)


def image_border(shape, n: int = 24) -> np.ndarray:
    """Image coordinates ``(m, 2)`` around an image's outer edge (pixel-centre units)."""
    rows, cols = shape
    li = np.linspace(-0.5, rows - 0.5, n)
    el = np.linspace(-0.5, cols - 0.5, max(n // 4, 3))
    pts = [np.stack([li, np.full_like(li, -0.5)], -1), np.stack([li, np.full_like(li, cols - 0.5)], -1),
           np.stack([np.full_like(el, -0.5), el], -1), np.stack([np.full_like(el, rows - 0.5), el], -1)]
    return np.concatenate(pts)


def _check_dem_cover(model, dem: DEM, iid: str, c: _Collector) -> None:
    """The ground seen by the image's border, at the DEM's lowest and highest heights,
    must lie on valid DEM cells."""
    from swathflow.geometry.geodesy import ecef_to_geodetic
    from swathflow.geometry.intersect import intersect
    pts = image_border(model.shape)
    origin, direction = model.ray(pts)
    miss = []
    for h in (dem.h_min, dem.h_max):
        g = intersect(origin, direction, ConstantHeight(h))
        llh = ecef_to_geodetic(g)
        ok = np.isfinite(llh).all(-1)
        hh = np.full(ok.shape, np.nan)
        hh[ok] = dem.height(llh[ok, 0], llh[ok, 1])
        bad = ~np.isfinite(hh)
        if bad.any():
            miss.append(llh[bad])
    if miss:
        m = np.concatenate(miss)
        m = m[np.isfinite(m).all(-1)]
        eg = f" e.g. lat {m[0, 0]:.6f}, lon {m[0, 1]:.6f}" if len(m) else ""
        c.add(dem.path, f"image {iid!r}",
              f"the DEM does not cover the ground this image sees ({len(m)} sampled border "
              f"points off the DEM or on nodata{eg})",
              "use a DEM that covers the whole flight area (with a margin), or a constant "
              "[terrain].height")


# ------------------------------------------------------------------------------------------
# public entry points

def inspect_mission(path) -> tuple[list[Problem], dict]:
    """Every problem found in a mission folder and the parts read (config, images...)."""
    try:
        return _inspect(path)
    except SwathflowError as exc:  # defensive: a check raised instead of collecting
        return [Problem(os.fspath(path), "", str(exc), "")], {}
    except Exception as exc:  # noqa: BLE001 - bad input must never end in a traceback
        return [Problem(os.fspath(path), "", f"unexpected content ({type(exc).__name__}: "
                        f"{exc})", "check mission.toml against spec/mission-format.md; if "
                        "the mission is fine, report this as a swathflow bug")], {}


def validate_mission(path) -> list[Problem]:
    """Every problem found in a mission folder (empty list: the mission is usable)."""
    return inspect_mission(path)[0]


def load_mission(path) -> Mission:
    """Read a mission folder; raises SwathflowError listing every problem."""
    problems, p = inspect_mission(path)
    if problems:
        raise SwathflowError(format_problems(path, problems))
    return Mission(path=p["root"], name=p["name"], config=p["config"], crs=p["crs"],
                   gsd=float(p["gsd"]), sensor=dict(p["sensor"]), pos=p["pos"],
                   trajectory=p["trajectory"], images=p["images"], gcps=p["gcps"],
                   terrain=p["terrain"], priors=p["priors"])


def format_problems(path, problems: list[Problem]) -> str:
    head = f"mission {os.fspath(path)} has {len(problems)} problem(s):"
    return "\n".join([head] + [f"  - {pr}" for pr in problems])
