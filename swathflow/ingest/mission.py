"""Mission bundles (docs/mission-format.md, version 1): validation and loading.

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
from swathflow.ingest.images import ImageEntry, lazy_image
from swathflow.ingest.linetable import plain_table
from swathflow.ingest.problems import Problem
from swathflow.ingest.validate import inspect

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
    def date(self):
        """The flight's UTC date (``[mission] date``, a ``datetime.date``), or None."""
        from swathflow.formats.gpstime import flight_date
        return flight_date(self.config.get("mission", {}).get("date"))

    def acquisition_span(self, image_id: str):
        """The UTC times (start, end) of an image's first and last lines, or None without
        a flight date (line times are GPS seconds of week; see
        :mod:`swathflow.formats.gpstime`)."""
        from swathflow.formats.gpstime import gps_seconds_of_week_to_utc
        day = self.date
        if day is None:
            return None
        t = self.lines(image_id)["time"]
        return (gps_seconds_of_week_to_utc(float(np.min(t)), day),
                gps_seconds_of_week_to_utc(float(np.max(t)), day))

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
    try:
        with np.errstate(all="ignore"):
            return inspect(path)
    except SwathflowError as exc:  # defensive: a check raised instead of collecting
        return [Problem(os.fspath(path), "", str(exc), "")], {}
    except Exception as exc:  # noqa: BLE001 - bad input must never end in a traceback
        return [Problem(os.fspath(path), "", f"unexpected content ({type(exc).__name__}: "
                        f"{exc})", "check mission.toml against docs/mission-format.md; if "
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
        warnings.warn(MissionWarning(pr.text()), stacklevel=2)
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
