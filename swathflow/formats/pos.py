"""POS trajectories: the reader entry point and interpolation to scan-line times.

The readers are plugins (:mod:`swathflow.formats.navigation`, entry-point group
``swathflow.pos_formats``): SBET, CSV, Resonon LCF, Inertial Explorer / POSPac text.

A trajectory is an ``xarray.Dataset`` over ``time`` with ``lat``, ``lon`` (deg), ``h``
(ellipsoidal m), ``roll``, ``pitch``, ``heading`` (deg, true heading clockwise from north).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import xarray as xr

from swathflow.errors import OutOfRangeError
from swathflow.formats.navigation import read
from swathflow.formats.navigation.csv import read_pos_csv, write_pos_csv
from swathflow.formats.navigation.sbet import SBET_DTYPE, SBET_FIELDS, read_sbet, write_sbet
from swathflow.formats.posdata import POS_VARIABLES, check_trajectory, pos_dataset
from swathflow.geometry.geodesy import geodetic_to_ecef

def read_pos(path, format: str | None = None, **options) -> xr.Dataset:
    """Read a POS trajectory with the registered reader for ``format`` (a name such as
    ``"sbet"``, ``"csv"``, ``"lcf"``, ``"ascii"`` or a plugin's; default: from the suffix).
    ``options`` go to the reader (docs/navigation-formats.md)."""
    return read(path, format, **options)


@dataclass(frozen=True, eq=False)
class Trajectory:
    """A trajectory prepared for fast interpolation (numpy only).

    Positions are interpolated linearly in ECEF, attitude angles linearly in time with the
    heading unwrapped (docs/geometry.md, POS interpolation). Times outside the trajectory,
    or inside a gap longer than ``max_gap`` seconds, raise :class:`OutOfRangeError`.
    """

    time: np.ndarray
    ecef: np.ndarray      # (n, 3)
    lat: np.ndarray       # deg
    lon: np.ndarray       # deg, unwrapped
    attitude: np.ndarray  # (n, 3) roll, pitch, heading (deg, heading unwrapped)
    max_gap: float = 1.0
    source: dict | None = None  # the columns as given (to_dataset returns them unchanged)

    @classmethod
    def from_dataset(cls, ds: xr.Dataset, max_gap: float = 1.0) -> "Trajectory":
        ds = check_trajectory(ds, ds.attrs.get("source", "trajectory"))
        lat, lon, h = (ds[k].values.astype(float) for k in ("lat", "lon", "h"))
        ecef = geodetic_to_ecef(np.stack([lat, lon, h], axis=-1))
        att = np.stack([ds["roll"].values, ds["pitch"].values,
                        np.degrees(np.unwrap(np.radians(ds["heading"].values)))], axis=-1)
        lon_u = np.degrees(np.unwrap(np.radians(lon)))
        src = {k: ds[k].values.astype(float) for k in POS_VARIABLES}
        return cls(ds["time"].values.astype(float), ecef, lat, lon_u, att, float(max_gap), src)

    def _locate(self, t) -> tuple[np.ndarray, np.ndarray]:
        t = np.asarray(t, dtype=float)
        tt = self.time
        bad = ~((t >= tt[0]) & (t <= tt[-1]))
        if np.any(bad):
            tb = t[bad]
            raise OutOfRangeError(
                f"{np.count_nonzero(bad)} time(s) outside the trajectory "
                f"[{tt[0]:.3f}, {tt[-1]:.3f}] s, e.g. {tb.flat[0]:.3f} s: the POS must cover "
                f"every scan line (no extrapolation)")
        i = np.clip(np.searchsorted(tt, t, side="right") - 1, 0, tt.size - 2)
        gap = tt[i + 1] - tt[i]
        if np.any(gap > self.max_gap):
            g = gap[gap > self.max_gap]
            raise OutOfRangeError(
                f"{g.size} time(s) fall in POS gaps longer than max_gap={self.max_gap} s "
                f"(longest {g.max():.3f} s); raise max_gap only if interpolating across "
                f"the gap is acceptable")
        w = (t - tt[i]) / gap
        return i, w

    def interpolate(self, t) -> dict[str, np.ndarray]:
        """Position (ECEF and lat/lon) and attitude at times ``t`` (any shape)."""
        i, w = self._locate(t)
        tab = self.table()          # one gather per end instead of one per column
        a = tab[i]
        v = a + (tab[i + 1] - a) * w[..., None]
        return {"ecef": v[..., 0:3], "lat": v[..., 3], "lon": v[..., 4], "roll": v[..., 5],
                "pitch": v[..., 6], "heading": v[..., 7]}

    def table(self) -> np.ndarray:
        """The columns ECEF x, y, z, lat, lon, roll, pitch, heading ``(n, 8)`` side by side
        (made once per trajectory; read only by convention)."""
        tab = self.__dict__.get("_table")
        if tab is None:
            tab = np.column_stack([self.ecef, self.lat, self.lon, self.attitude])
            object.__setattr__(self, "_table", tab)
        return tab

    def typical_step(self) -> float:
        """The median interval between epochs (s), made once per trajectory (each image's
        line-time check asks for it: 0.6 ms a time for the survey's 50 Hz POS)."""
        step = self.__dict__.get("_step")
        if step is None:
            step = float(np.median(np.diff(self.time))) if self.time.size > 1 else 0.0
            object.__setattr__(self, "_step", step)
        return step

    def to_dataset(self) -> xr.Dataset:
        if self.source is not None:
            return pos_dataset(self.time, *(self.source[k] for k in POS_VARIABLES), "trajectory")
        from swathflow.geometry.geodesy import ecef_to_geodetic
        llh = ecef_to_geodetic(self.ecef)
        heading = (self.attitude[:, 2] + 180.0) % 360.0 - 180.0
        return pos_dataset(self.time, llh[:, 0], llh[:, 1], llh[:, 2], self.attitude[:, 0],
                        self.attitude[:, 1], heading, "trajectory")


def interpolate_pos(ds: xr.Dataset | Trajectory, times, max_gap: float = 1.0) -> xr.Dataset:
    """Interpolate a trajectory (a POS Dataset, or a :class:`Trajectory` already built from
    one, e.g. ``Mission.trajectory``) to ``times``; returns a Dataset over ``time``
    (:func:`pos_columns` wrapped)."""
    cols = pos_columns(ds, times, max_gap)
    return pos_dataset(np.asarray(times, dtype=float), *(cols[k] for k in POS_VARIABLES),
                    "interpolated", check=False)


def pos_columns(ds: xr.Dataset | Trajectory, times, max_gap: float = 1.0) -> dict:
    """:func:`interpolate_pos` as numpy arrays: ``{name: values}`` of
    :data:`POS_VARIABLES` at ``times`` (longitude and heading in [-180, 180))."""
    traj = ds if isinstance(ds, Trajectory) else Trajectory.from_dataset(ds, max_gap=max_gap)
    r = traj.interpolate(np.asarray(times, dtype=float))
    from swathflow.geometry.geodesy import ecef_to_geodetic
    return {"lat": r["lat"], "lon": (r["lon"] + 180.0) % 360.0 - 180.0,
            "h": ecef_to_geodetic(r["ecef"])[..., 2], "roll": r["roll"], "pitch": r["pitch"],
            "heading": (r["heading"] + 180.0) % 360.0 - 180.0}


__all__ = ["POS_VARIABLES", "SBET_DTYPE", "SBET_FIELDS", "Trajectory", "check_trajectory",
           "interpolate_pos", "pos_columns", "read_pos", "read_pos_csv", "read_sbet",
           "write_pos_csv", "write_sbet"]
