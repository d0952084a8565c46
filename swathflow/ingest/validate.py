"""Mission validation: one small check per concern, each collecting :class:`Problem` s.

:func:`inspect` runs them all in order and returns the problems with the parsed parts
(``load_mission`` builds a :class:`~swathflow.mission.Mission` from them). Problems have a
level: ``"error"`` makes the mission unusable, ``"warning"`` is reported and the mission
still loads. Plausibility checks (angles in radians, impossible motion, output size...) are
in :mod:`swathflow.plausible`, GCP tables in :mod:`swathflow.gcpfile`.
"""
from __future__ import annotations

import math
import os
import tomllib
from pathlib import Path
from typing import Any

import numpy as np

from swathflow.errors import SwathflowError
from swathflow.formats.pos import Trajectory, read_pos
from swathflow.geometry.terrain import DEM, ConstantHeight
from swathflow.ingest.images import ImageEntry, raster_check
from swathflow.ingest.keys import BASE_LINE_COLUMNS, IMAGE_KEYS, KNOWN_KEYS
from swathflow.ingest.problems import Collector, Problem, check_crs, check_keys, rel

# ------------------------------------------------------------------------------------------
# mission.toml

def read_toml(root: Path, c: Collector) -> dict | None:
    toml = root / "mission.toml"
    if not root.is_dir():
        c.add(root, "", "mission folder not found", "give the folder that holds mission.toml")
        return None
    if not toml.exists():
        c.add(toml, "", "mission.toml not found",
              "create mission.toml (see docs/mission-format.md)")
        return None
    if not toml.is_file():          # a FIFO would hang the reader, a device fill memory
        c.add(toml, "", "not a regular file", "mission.toml must be a text file")
        return None
    from swathflow.ingest.tomlfile import load
    try:
        return load(toml)
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        c.add(toml, "", f"not valid TOML: {exc}", "correct the syntax at the position shown")
    except OSError as exc:
        c.add(toml, "", f"cannot be read: {exc.strerror or exc}", "check the file's permissions")
    return None


def check_mission_table(cfg: dict, root: Path, toml: Path, c: Collector, parts: dict) -> None:
    m = cfg.get("mission")
    if not isinstance(m, dict):
        c.add(toml, "[mission]", "table missing", 'add [mission] with name, crs and gsd')
        m = {}
    check_keys(cfg, KNOWN_KEYS[""], toml, "", c)
    check_keys(cfg.get("rectify"), KNOWN_KEYS["rectify"], toml, "[rectify]", c)
    check_keys(m, KNOWN_KEYS["mission"], toml, "[mission]", c)
    if isinstance(cfg.get("reference"), dict):
        check_keys(cfg["reference"], KNOWN_KEYS["reference"], toml, "[reference]", c)
    parts["name"] = str(m.get("name", root.name))
    crs = m.get("crs", "auto-utm")
    n0 = len(c.problems)
    if not isinstance(crs, str):
        c.add(toml, "[mission].crs", f"must be a string, got {crs!r}",
              'crs = "EPSG:32651" or "auto-utm"')
    elif crs.lower() != "auto-utm":
        err = check_crs(crs)
        if err:
            c.add(toml, "[mission].crs", f"pyproj rejects CRS {crs!r}: {err}",
                  'use an EPSG code such as "EPSG:32651", or "auto-utm"')
        else:
            import pyproj
            if not pyproj.CRS.from_user_input(crs).is_projected:
                c.add(toml, "[mission].crs", f"{crs!r} is not a projected CRS",
                      "the output grid needs metres: use a projected CRS or auto-utm")
    parts["crs"] = crs
    parts["crs_ok"] = len(c.problems) == n0
    gsd = m.get("gsd")
    if not _positive(gsd):
        c.add(toml, "[mission].gsd", f"must be a positive number of metres, got {gsd!r}",
              "gsd = 0.5")
        gsd = None
    parts["gsd"] = gsd
    mp = m.get("max_pixels", 2e9)
    if not _positive(mp) or mp > MAX_PIXELS_LIMIT:
        c.add(toml, "[mission].max_pixels", f"must be a positive number up to "
              f"{MAX_PIXELS_LIMIT:g}, got {mp!r}", "max_pixels = 2e9")
        mp = 2e9
    parts["max_pixels"] = float(mp)
    parts["date"] = check_date(m.get("date"), toml, c)


def check_date(value, toml, c: Collector):
    """``[mission] date``: the flight's UTC date (a TOML date or an ISO string), or None."""
    from swathflow.formats.gpstime import flight_date
    try:
        return flight_date(value)
    except ValueError:
        c.add(toml, "[mission].date", f"must be the flight's UTC date, got {value!r}",
              "date = 2024-06-05 (the UTC date of the first POS epoch)")
        return None


def check_date_against_pos(date, traj, toml, c: Collector) -> None:
    """The flight date must hold the POS's first epoch (GPS seconds of week)."""
    from swathflow.formats.gpstime import date_mismatch
    why = date_mismatch(float(traj.time[0]), date)
    if why:
        c.add(toml, "[mission].date", why,
              "give the UTC date of the flight's first POS epoch, or remove the date (the "
              "catalogue then dates the products by their processing time)")


#: the largest ``[mission] max_pixels`` a user may set: a swing's output grid of 10^12
#: pixels is terabytes of COG and days of work; beyond it the limit no longer bounds
#: anything (1e300 let a mistaken gsd allocate without end)
MAX_PIXELS_LIMIT = 1e12


def _positive(v) -> bool:
    return (isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)
            and v > 0)


def check_sensor(cfg: dict, toml: Path, c: Collector, parts: dict) -> None:
    from swathflow.sensormodel.registry import _registry
    sensor = cfg.get("sensor")
    cls = None
    if not isinstance(sensor, dict):
        c.add(toml, "[sensor]", "table missing",
              "add [sensor] with model = a name that 'swathflow sensors' lists")
        sensor = {}
    else:
        name = sensor.get("model")
        reg = _registry()
        if not isinstance(name, str) or name not in reg:
            c.add(toml, "[sensor].model", f"unknown sensor plugin {name!r}",
                  f"use one of: {', '.join(sorted(reg)) or 'none'} (see 'swathflow sensors'),"
                  f" or install the plugin")
        else:
            cls = reg[name][0]
            known = ("model",) + tuple(cls.required_keys) + tuple(
                getattr(cls, "optional_keys", ()) or ())
            check_keys(sensor, known, toml, "[sensor]",
                       c, strict=bool(getattr(cls, "optional_keys", None)))
            try:
                bad = cls.check_config(sensor)
            except (TypeError, ValueError, KeyError, AttributeError) as exc:
                bad = [f"invalid value: {exc}"]
            for b in bad:
                c.add(toml, "[sensor]", b, f"see the {name} plugin's documentation")
            if bad:
                cls = None
    n_el = sensor.get("n_elements")
    if n_el is not None and (isinstance(n_el, bool) or not isinstance(n_el, (int, float))
                             or (isinstance(n_el, float) and not n_el.is_integer())):
        c.add(toml, "[sensor].n_elements", f"must be a whole number of detector elements, "
              f"got {n_el!r}", "n_elements = the number of image columns, e.g. 1024")
        cls = None
    parts["sensor"] = sensor
    parts["cls"] = cls
    parts["n_elements"] = int(n_el) if cls is not None and n_el is not None else None


def _pos_format_options(posc: dict) -> tuple[str, ...]:
    """The options the [pos] format's reader takes (docs/navigation-formats.md)."""
    from swathflow.formats.navigation import find_format
    try:
        return tuple(find_format(str(posc.get("file") or ""), posc.get("format")).options)
    except SwathflowError:      # an unknown format is reported when the file is read
        return ()


def _pos_options(root: Path, posc: dict, options: tuple[str, ...]) -> dict:
    """The [pos] keys the reader takes; an LCF's ``times`` file is relative to the mission
    folder."""
    opts = {k: v for k, v in posc.items() if k in options}
    if isinstance(opts.get("times"), str):
        opts["times"] = str(rel(root, opts["times"]))
    return opts


def check_pos(cfg: dict, root: Path, toml: Path, c: Collector, parts: dict) -> None:
    from swathflow.ingest.plausible import check_pos_plausible
    posc = cfg.get("pos", {}) if isinstance(cfg.get("pos", {}), dict) else {}
    parts["trajectory"] = None
    if not isinstance(posc.get("format", ""), str):
        c.add(toml, "[pos].format", f"must be the name of a POS format, got "
              f"{posc['format']!r}", 'format = "sbet" (docs/navigation-formats.md)')
        return
    options = _pos_format_options(posc)
    check_keys(posc, KNOWN_KEYS["pos"] + options, toml, "[pos]", c)
    pos_file = posc.get("file")
    if pos_file is None:
        pos_file = next((n for n in ("pos.sbet", "pos.csv") if (root / n).exists()), None)
    parts["trajectory"] = None
    if pos_file is None:
        c.add(toml, "[pos].file", "no POS file named and neither pos.sbet nor pos.csv found",
              'add [pos] file = "pos.sbet", format = "sbet"')
        return
    pp = rel(root, pos_file)
    if not pp.exists():
        c.add(pp, "", "POS file not found", "check [pos].file in mission.toml")
        return
    max_gap = posc.get("max_gap", 1.0)
    if not _positive(max_gap):
        c.add(toml, "[pos].max_gap", f"must be a positive number of seconds, got "
              f"{max_gap!r}", "max_gap = 1.0")
        max_gap = 1.0
    try:
        ds = read_pos(pp, posc.get("format"), **_pos_options(root, posc, options))
    except SwathflowError as exc:
        msg = str(exc).replace(str(pp) + ": ", "")
        c.add(pp, "[pos]" if "format" in msg else "", msg,
              "set [pos] format to a registered format (docs/navigation-formats.md)"
              if "unknown POS format" in msg
              else "re-export the POS (times strictly increasing, finite values)")
        return
    parts["pos"] = ds
    fmt = (posc.get("format") or pp.suffix.lstrip(".")).lower()
    if not check_pos_plausible(ds, pp, fmt, c):
        return
    parts["trajectory"] = Trajectory.from_dataset(ds, max_gap=float(max_gap))


def check_terrain(cfg: dict, root: Path, toml: Path, c: Collector, parts: dict) -> None:
    ter = cfg.get("terrain")
    terrain = None
    if not isinstance(ter, dict):
        c.add(toml, "[terrain]", "table missing",
              'add [terrain] dem = "dem.tif" or height = <ellipsoidal metres>')
    else:
        check_keys(ter, KNOWN_KEYS["terrain"], toml, "[terrain]", c)
        if ter.get("vertical", "ellipsoidal") not in ("ellipsoidal", "orthometric"):
            c.add(toml, "[terrain].vertical", f"must be 'ellipsoidal' or 'orthometric', "
                  f"got {ter.get('vertical')!r}", 'vertical = "ellipsoidal"')
        elif "dem" in ter:
            terrain = _open_dem(ter, root, c)
        elif "height" in ter:
            terrain = _constant_height(ter, toml, c)
        else:
            c.add(toml, "[terrain]", "needs dem = \"...\" or height = <metres>",
                  'add dem = "dem.tif" or height = 12.0')
    parts["terrain"] = terrain


def _open_dem(ter: dict, root: Path, c: Collector):
    dp = rel(root, ter["dem"])
    if not dp.exists():
        c.add(dp, "", "DEM file not found", "check [terrain].dem in mission.toml")
        return None
    try:
        terrain = DEM.open(dp, ter.get("vertical", "ellipsoidal"), ter.get("geoid"),
                           ter.get("undulation"))
    except SwathflowError as exc:
        c.add(dp, "[terrain]", str(exc).replace(str(dp) + ": ", ""),
              "fix the DEM or its [terrain] keys")
        return None
    if not np.isfinite(terrain.data).any():
        c.add(dp, "", "the DEM holds no valid heights", "use a DEM with data")
        return None
    return terrain


def _constant_height(ter: dict, toml: Path, c: Collector):
    try:
        h = float(ter["height"])
        if not math.isfinite(h):
            raise ValueError("not finite")
        if ter.get("vertical", "ellipsoidal") == "orthometric":
            if "undulation" not in ter:
                raise SwathflowError("an orthometric constant height needs undulation")
            h += float(ter["undulation"])
        return ConstantHeight(h)
    except (TypeError, ValueError, SwathflowError) as exc:
        c.add(toml, "[terrain].height", f"not a usable height: {ter['height']!r} {exc}",
              "height = <ellipsoidal metres> (or vertical = 'orthometric' + undulation)")
        return None


# ------------------------------------------------------------------------------------------
# [[images]] and their line tables

def check_images(cfg: dict, root: Path, toml: Path, c: Collector, parts: dict) -> None:
    from swathflow.ingest.linetable import line_table
    from swathflow.ingest.plausible import check_lines_plausible
    images: dict[str, ImageEntry] = {}
    parts.update(images=images, lines={}, tables={}, shapes={}, image_shapes={})
    entries = cfg.get("images")
    if not isinstance(entries, list) or not entries:
        c.add(toml, "[[images]]", "no images listed", "add one [[images]] table per swing")
        entries = []
    cls = parts["cls"]
    need = BASE_LINE_COLUMNS
    if cls is not None:
        need = tuple(dict.fromkeys(BASE_LINE_COLUMNS + tuple(cls.line_columns)))
    files: dict[tuple, str] = {}
    for k, e in enumerate(entries):
        entry = _image_entry(e, k, root, toml, images, c, cls)
        if entry is None:
            continue
        images[entry.id] = entry
        for key, p in (("file", entry.file), ("lines", entry.lines_file)):
            other = files.setdefault((key, os.path.realpath(p)), entry.id)
            if other != entry.id:
                c.add(toml, f"[[images]] id={entry.id!r}.{key}", f"{p.name} is also the "
                      f"{key} of image {other!r}", "give every image its own file")
        shape = _image_shape(entry, parts, c)
        if shape is not None:
            from swathflow.ingest.bands import check_envi
            check_envi(entry, c)
        cols = line_table(entry, need, shape, parts.get("trajectory"), c)
        if cols is None:
            continue
        if cls is not None:
            check_lines_plausible(cls, entry, cols, c)
        parts["lines"][entry.id] = {col: cols[col] for col in need if col != "line"}
        parts["tables"][entry.id] = cols
        if shape is not None:
            parts["shapes"][entry.id] = shape


def _image_entry(e, k, root, toml, images, c, cls) -> ImageEntry | None:
    where = f"[[images]] #{k + 1}"
    if not isinstance(e, dict):
        c.add(toml, where, "must be a table", "")
        return None
    check_keys(e, KNOWN_KEYS["images"], toml, where, c, strict=False)
    missing = [key for key in ("id", "file", "lines") if key not in e]
    if missing:
        c.add(toml, where, f"missing key(s) {', '.join(missing)}",
              'each image needs id, file, lines (and direction, strip)')
        return None
    iid = str(e["id"])
    where = f"[[images]] id={iid!r}"
    from swathflow.ingest.names import id_problem
    bad = id_problem(iid if isinstance(e["id"], (str, int)) and not isinstance(
        e["id"], bool) else e["id"])
    if bad:
        c.add(toml, where + ".id", bad, 'an id is a plain name: letters, digits, "_", "-" '
              'and "." (not first), e.g. id = "L1"')
        return None
    if iid in images:
        c.add(toml, where, "duplicate image id", "give every image a unique id")
        return None
    direction = str(e.get("direction", ""))
    allowed = cls.directions if cls is not None else None
    if allowed and direction.upper() not in allowed:
        c.add(toml, where + ".direction", f"must be one of {', '.join(allowed)} for sensor "
              f"{cls.name!r}, got {direction!r}",
              f"direction = {allowed[0]!r} (see 'swathflow sensors' for the model)")
    strip = e.get("strip", 0)
    try:
        if isinstance(strip, bool) or (isinstance(strip, float) and not strip.is_integer()):
            raise ValueError
        strip = int(strip)
    except (TypeError, ValueError):
        c.add(toml, where + ".strip", f"must be an integer, got {strip!r}", "strip = 1")
        strip = 0
    attrs = {k2: v for k2, v in e.items() if k2 not in IMAGE_KEYS}
    return ImageEntry(iid, rel(root, e["file"]), rel(root, e["lines"]), direction.upper(),
                      strip, attrs)


def _image_shape(entry: ImageEntry, parts: dict, c: Collector):
    where = f"[[images]] id={entry.id!r}"
    ip = entry.file
    if not ip.exists():
        c.add(ip, where, "image file not found", "check the file key of this image")
        return None
    try:
        rows, cols, _, note = raster_check(ip)
    except SwathflowError as exc:
        c.add(ip, where, str(exc).replace(str(ip) + ": ", ""),
              "write the image as GeoTIFF or ENVI")
        return None
    if note:
        c.warn(ip, where, note, "[rectify] bands = \"1,4-6\" in mission.toml (or --bands of "
               "'swathflow rectify') selects some; for a mosaic of each band, write one band "
               "per image file")
    parts["image_shapes"][entry.id] = (rows, cols)
    n_el = parts.get("n_elements")
    if n_el is not None and cols != n_el:
        c.add(ip, where, f"image has {cols} columns but [sensor].n_elements is "
              f"{n_el}", "columns must be detector elements; fix n_elements or the image")
    return rows, cols


# ------------------------------------------------------------------------------------------
# the whole mission

def inspect(path) -> tuple[list[Problem], dict]:
    from swathflow.ingest.gcpfile import check_gcps
    from swathflow.ingest.plausible import check_models
    c = Collector()
    root = Path(os.fspath(path))
    toml = root / "mission.toml"
    parts: dict[str, Any] = {"root": root}
    cfg = read_toml(root, c)
    if cfg is None:
        return c.problems, parts
    parts["config"] = cfg
    from swathflow.ingest.tomlfile import special_files
    for sp in special_files(cfg, root):     # a FIFO would hang a reader, a device fill memory
        c.add(sp, "", "not a regular file (a device or FIFO): reading it would hang or "
              "never end", "name the data file itself in mission.toml")
    if len(c.problems):
        return c.problems, parts
    check_mission_table(cfg, root, toml, c, parts)
    check_sensor(cfg, toml, c, parts)
    check_pos(cfg, root, toml, c, parts)
    check_terrain(cfg, root, toml, c, parts)
    check_images(cfg, root, toml, c, parts)
    from swathflow.ingest.refcheck import check_reference
    check_reference(cfg, root, toml, c, parts.get("pos"))
    traj = parts["trajectory"]
    if parts.get("date") is not None and traj is not None:
        check_date_against_pos(parts["date"], traj, toml, c)
    crs = parts["crs"]
    if isinstance(crs, str) and crs.lower() == "auto-utm" and traj is not None:
        from swathflow.geometry.geodesy import utm_crs_for
        parts["crs"] = utm_crs_for(float(np.mean(traj.lat)),
                                   float((np.mean(traj.lon) + 180) % 360 - 180)).to_string()
    cls = parts["cls"]
    parts["priors"] = None
    if cls is not None:
        parts["priors"] = priors(cls, parts["sensor"], cfg.get("calibration"), root, toml, c)
    parts["gcps"] = check_gcps(cfg, root, toml, parts, c)
    if cls is not None and traj is not None and parts["priors"] is not None:
        check_models(parts, toml, c)
    return c.problems, parts


def priors(cls, sensor, cal, root, toml, c: Collector):
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
        fp = rel(root, cal.pop("file"))
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
    check_keys(cal, base.names, toml, "[calibration]", c, strict=False)
    n0 = len(c.problems)
    from swathflow.ingest.priorcheck import check_prior, held
    for name, v in cal.items():
        check_prior(name, v, toml, c)
    if len(c.problems) > n0:
        return None
    try:
        out = base.updated(cal)
    except (SwathflowError, TypeError, ValueError) as exc:
        c.add(toml, "[calibration]", str(exc),
              f"parameters of {cls.name}: {', '.join(base.names)}; each "
              "{ value = [...], sigma = [...] }")
        return None
    return held(out, toml, c)
