"""Resonon LCF navigation files and their ``.times`` line-time files.

LCF: one record per line, space separated: system time (s), roll, pitch, heading (radians),
longitude, latitude (degrees), ellipsoidal height (m), two placeholders, a use flag. The
``.times`` file beside the image holds one time per image line on the same clock. Records
whose use flag is 0 are dropped. Column mapping: docs/navigation-formats.md.
"""
from __future__ import annotations

import os

import numpy as np
import xarray as xr
from swathflow.errors import FormatError
from swathflow.formats.posdata import pos_dataset
from swathflow.io import atomic_path

from .registry import PosFormat

LCF_COLUMNS = ("time", "roll", "pitch", "heading", "lon", "lat", "h", "spare1", "spare2",
               "use")
TIMES_SUFFIXES = (".times", ".bil.times", ".bip.times", ".bsq.times", ".raw.times")


def _numbers(path: str, min_fields: int, what: str) -> list[list[float]]:
    """The numeric rows of a whitespace-separated text file (blank and ``#`` lines skipped);
    a short or non-numeric row raises a FormatError naming its line number."""
    rows = []
    try:
        with open(path, encoding="utf-8") as f:
            lines = f.readlines()
    except UnicodeDecodeError:
        raise FormatError(f"{path}: not a text file; expected {what}") from None
    for no, line in enumerate(lines, 1):
        text = line.split("#", 1)[0].strip()
        if not text:
            continue
        fields = text.replace(",", " ").split()
        if len(fields) < min_fields:
            raise FormatError(f"{path}: line {no} has {len(fields)} field(s), {what} needs "
                              f"{min_fields}; re-export the file")
        try:
            rows.append([float(v) for v in fields[:min_fields]])
        except ValueError:
            raise FormatError(f"{path}: line {no} is not numeric ({text[:40]!r}); {what} has "
                              f"no header") from None
    if not rows:
        raise FormatError(f"{path}: no records; expected {what}")
    return rows


def read_times(path) -> np.ndarray:
    """Line times of a Resonon ``.times`` file (one per image line, increasing)."""
    path = os.fspath(path)
    t = np.asarray(_numbers(path, 1, "a .times file (one time per image line)"))[:, 0]
    bad = np.flatnonzero(np.diff(t) <= 0)
    if bad.size:
        raise FormatError(f"{path}: line times must increase; record {bad[0] + 2} "
                          f"(t={t[bad[0] + 1]!r}) does not follow {t[bad[0]]!r}")
    return t


def find_times(path) -> str | None:
    """The ``.times`` file beside an LCF (same stem), if there is one."""
    stem = os.path.splitext(os.fspath(path))[0]
    for suffix in TIMES_SUFFIXES:
        if os.path.exists(stem + suffix):
            return stem + suffix
    return None


def read_lcf(path, times=None) -> xr.Dataset:
    """Read a Resonon LCF file as a trajectory (degrees, metres, true heading).

    ``times``: the ``.times`` file (default: the one beside the LCF with the same stem, if
    any). Its line times come back as ``line_time`` over a ``line`` dimension.
    """
    path = os.fspath(path)
    rec = np.asarray(_numbers(path, len(LCF_COLUMNS), "an LCF record (10 columns: time, "
                              "roll, pitch, heading, lon, lat, h, 2 spares, use flag)"))
    col = dict(zip(LCF_COLUMNS, rec.T))
    use = col["use"] != 0
    if not use.any():
        raise FormatError(f"{path}: every record has use flag 0; nothing to read")
    col = {k: v[use] for k, v in col.items()}
    att = {k: np.degrees(col[k]) for k in ("roll", "pitch", "heading")}
    heading = (att["heading"] + 180.0) % 360.0 - 180.0
    ds = pos_dataset(col["time"], col["lat"], col["lon"], col["h"], att["roll"], att["pitch"],
                  heading, path)
    ds.attrs["format"] = "lcf"
    times = find_times(path) if times is None else os.fspath(times)
    if times:
        if not os.path.exists(times):
            raise FormatError(f"{times}: .times file not found; check the times= option")
        ds["line_time"] = ("line", read_times(times))
        ds["line_time"].attrs.update(units="s", source=times,
                                     long_name="image line times on the LCF clock")
    return ds


def write_lcf(ds: xr.Dataset, path, times_path=None) -> None:
    """Write a trajectory as LCF (use flag 1, spares 0) and, if the Dataset has
    ``line_time`` and ``times_path`` is given, its ``.times`` file. Atomic."""
    n = ds.sizes["time"]
    cols = [ds["time"].values, *(np.radians(ds[k].values) for k in ("roll", "pitch",
                                                                    "heading")),
            ds["lon"].values, ds["lat"].values, ds["h"].values, np.zeros(n), np.zeros(n),
            np.ones(n)]
    with atomic_path(path) as tmp:
        np.savetxt(tmp, np.column_stack(cols), fmt="%.12f")
    if times_path is not None and "line_time" in ds:
        with atomic_path(times_path) as tmp:
            np.savetxt(tmp, ds["line_time"].values, fmt="%.9f")


FORMAT = PosFormat("lcf", read_lcf, suffixes=("lcf",), aliases=("resonon",),
                   options=("times",), write=write_lcf,
                   description="Resonon LCF (+ .times line times)")
