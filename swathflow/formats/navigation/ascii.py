"""Text exports of NovAtel Inertial Explorer and Applanix POSPac, with a configurable header.

Both programs write a free-form preamble, a row of column names (chosen in the export
profile), sometimes a row of units, then one record per epoch. The reader finds the column
names (or takes them from ``columns``), maps them onto the trajectory variables through the
names both programs use, and reads the records. Column mapping and options:
docs/navigation-formats.md.
"""
from __future__ import annotations

import os
import re

import numpy as np
import xarray as xr
from swathflow.errors import FormatError
from swathflow.formats.posdata import POS_VARIABLES, pos_dataset

from .registry import PosFormat

VARIABLES = ("time",) + POS_VARIABLES
#: Export column names (lower case, letters and digits only) -> trajectory variable.
ALIASES = {
    "time": ("gpstime", "time", "gpssec", "gpsseconds", "timegps", "gpstimesec", "sow",
             "secondsofweek"),
    "lat": ("latitude", "lat"),
    "lon": ("longitude", "long", "lon"),
    "h": ("hell", "ellipsoidheight", "heightell", "ellheight", "ellipsoidalheight", "helip",
          "height"),
    "roll": ("roll",),
    "pitch": ("pitch",),
    "heading": ("heading", "trueheading", "hdg"),
}
OPTIONS = ("columns", "header_line", "delimiter", "angle_units", "latlon_units")
_SCAN = 200     # lines searched for the header row


def _norm(name: str) -> str:
    return re.sub(r"[^a-z0-9]", "", name.lower())


def _split(line: str, delimiter: str | None) -> list[str]:
    if delimiter is None:
        delimiter = "," if "," in line else None
    return [f.strip() for f in line.strip().split(delimiter)]


def _map_header(names: list[str], columns: dict | None) -> dict[str, int]:
    """Trajectory variable -> column index, from header names (first match wins)."""
    norm = [_norm(n) for n in names]
    wanted = ({k: (_norm(v),) for k, v in columns.items()} if columns
              else ALIASES)
    found = {}
    for var, aliases in wanted.items():
        hits = [norm.index(a) for a in aliases if a in norm]   # the first alias wins
        if hits:
            found[var] = hits[0]
    return found


def _find_header(lines, delimiter, columns, header_line, path) -> tuple[int, dict[str, int]]:
    if header_line is not None:
        idx = int(header_line) - 1
        if not 0 <= idx < len(lines):
            raise FormatError(f"{path}: header_line={header_line} is beyond the file's "
                              f"{len(lines)} lines")
        return idx, _map_header(_split(lines[idx], delimiter), columns)
    for idx, line in enumerate(lines[:_SCAN]):
        mapping = _map_header(_split(line, delimiter), columns)
        if {"time", "lat", "lon"} <= set(mapping):
            return idx, mapping
    raise FormatError(f"{path}: no header row naming time, latitude and longitude in the "
                      f"first {_SCAN} lines; set header_line= (1-based) or columns= (see "
                      f"docs/navigation-formats.md)")


def _positional(columns: list) -> dict[str, int]:
    mapping = {str(c).strip().lower(): i for i, c in enumerate(columns)}
    return {v: mapping[v] for v in VARIABLES if v in mapping}


def _records(lines, start, mapping, delimiter, path) -> np.ndarray:
    """The numeric records from line index ``start`` on; leading non-numeric rows (units)
    are skipped, any later one is an error naming its line."""
    need = max(mapping.values()) + 1
    rows, seen = [], False
    for no in range(start, len(lines)):
        fields = _split(lines[no], delimiter)
        if not fields or fields == [""]:
            continue
        try:
            vals = [float(fields[i]) for i in range(need)] if len(fields) >= need else None
        except ValueError:
            vals = None
        if vals is None:
            if seen:
                raise FormatError(f"{path}: line {no + 1} is not a record of {need} numeric "
                                  f"columns ({lines[no].strip()[:50]!r})")
            continue
        seen = True
        rows.append([vals[mapping[v]] for v in VARIABLES])
    if not rows:
        raise FormatError(f"{path}: no numeric records after the header")
    return np.asarray(rows)


def _angles(values: np.ndarray, units: str, option: str, path: str) -> np.ndarray:
    if units not in ("deg", "rad"):
        raise FormatError(f"{path}: {option} must be 'deg' or 'rad', got {units!r}")
    return np.degrees(values) if units == "rad" else values


def read_pos_ascii(path, columns=None, header_line=None, delimiter=None, angle_units="deg",
                   latlon_units="deg") -> xr.Dataset:
    """Read an Inertial Explorer / POSPac ASCII export as a trajectory.

    ``columns``: ``None`` (find the header row and map its names), a list naming every
    column in order with the trajectory names (``time, lat, lon, h, roll, pitch, heading``;
    other names are ignored; records start at the first numeric line after ``header_line``,
    or at the top), or a mapping ``{variable: "export column name"}`` for unusual names.
    ``header_line``: 1-based line of the column names (default: searched). ``delimiter``:
    default comma if the header has one, else white space. ``angle_units`` (roll, pitch,
    heading) and ``latlon_units``: ``"deg"`` or ``"rad"``.
    """
    path = os.fspath(path)
    try:
        with open(path, encoding="utf-8", errors="strict") as f:
            lines = f.read().splitlines()
    except UnicodeDecodeError:
        raise FormatError(f"{path}: not a text export; use format='sbet' for binary "
                          f"SBET files") from None
    if isinstance(columns, (list, tuple)):
        mapping = _positional(columns)
        start = 0 if header_line is None else int(header_line)
    else:
        idx, mapping = _find_header(lines, delimiter, columns, header_line, path)
        start = idx + 1
    missing = [v for v in VARIABLES if v not in mapping]
    if missing:
        raise FormatError(f"{path}: no column for {', '.join(missing)}; name them with "
                          f"columns= (see docs/navigation-formats.md)")
    rec = _records(lines, start, mapping, delimiter, path)
    col = dict(zip(VARIABLES, rec.T))
    lat, lon = (_angles(col[k], latlon_units, "latlon_units", path) for k in ("lat", "lon"))
    roll, pitch, heading = (_angles(col[k], angle_units, "angle_units", path)
                            for k in ("roll", "pitch", "heading"))
    heading = (heading + 180.0) % 360.0 - 180.0
    ds = pos_dataset(col["time"], lat, lon, col["h"], roll, pitch, heading, path)
    ds.attrs["format"] = "ascii"
    return ds


FORMAT = PosFormat("ascii", read_pos_ascii, suffixes=("asc",),
                   aliases=("novatel", "inertial-explorer", "pospac"), options=OPTIONS,
                   description="NovAtel Inertial Explorer / Applanix POSPac text export")
