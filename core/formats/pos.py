"""POS trajectories: readers (Applanix SBET, CSV) and interpolation to scan-line times.

A trajectory is an ``xarray.Dataset`` over ``time`` with ``lat``, ``lon`` (deg), ``h``
(ellipsoidal m), ``roll``, ``pitch``, ``heading`` (deg, true heading clockwise from north).
"""
from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np
import pandas as pd
import xarray as xr

from swathflow.errors import FormatError, OutOfRangeError
from swathflow.geometry.geodesy import geodetic_to_ecef

POS_VARIABLES = ("lat", "lon", "h", "roll", "pitch", "heading")

#: Applanix SBET record: 17 little-endian float64.
SBET_FIELDS = ("time", "lat", "lon", "h", "vx", "vy", "vz", "roll", "pitch",
               "platform_heading", "wander", "ax", "ay", "az", "wx", "wy", "wz")
SBET_DTYPE = np.dtype([(name, "<f8") for name in SBET_FIELDS])


def _dataset(time, lat, lon, h, roll, pitch, heading, source: str, check: bool = True) -> xr.Dataset:
    data = {k: ("time", np.asarray(v, dtype=float)) for k, v in
            zip(POS_VARIABLES, (lat, lon, h, roll, pitch, heading))}
    ds = xr.Dataset(data, coords={"time": np.asarray(time, dtype=float)},
                    attrs={"source": source})
    for k in ("lat", "lon", "roll", "pitch", "heading"):
        ds[k].attrs["units"] = "deg"
    ds["h"].attrs["units"] = "m"
    ds["h"].attrs["long_name"] = "ellipsoidal height"
    ds["heading"].attrs["long_name"] = "true heading, clockwise from north"
    ds["time"].attrs["units"] = "s"
    return check_trajectory(ds, source) if check else ds


def check_trajectory(ds: xr.Dataset, source: str = "trajectory") -> xr.Dataset:
    """Raise :class:`FormatError` unless times increase strictly and values are finite."""
    t = ds["time"].values
    if t.size < 2:
        raise FormatError(f"{source}: a trajectory needs at least 2 epochs, found {t.size}")
    bad = np.flatnonzero(np.diff(t) <= 0)
    if bad.size:
        raise FormatError(f"{source}: times must increase strictly; epoch {bad[0] + 1} "
                          f"(t={t[bad[0] + 1]!r}) does not follow {t[bad[0]]!r}")
    for k in POS_VARIABLES:
        nan = np.flatnonzero(~np.isfinite(ds[k].values))
        if nan.size:
            raise FormatError(f"{source}: {k} is not finite at epoch {nan[0]} "
                              f"({nan.size} epochs in all)")
    return ds


def read_sbet(path) -> xr.Dataset:
    """Read an Applanix SBET file (17 little-endian float64 per record, angles in radians).

    True heading: SBET stores the platform heading in the wander-angle frame and the wander
    angle; ``true_heading = platform_heading - wander_angle`` (Applanix POS output record
    description, as reproduced in the POS/SBET reader of the PFM/ABE hydrographic software,
    ``FilePOSOutput.h``: "To get a true heading the following equation should be used:
    true_heading = platform_heading - wander_angle").
    """
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise FormatError(f"{path}: not a file; name the SBET file")
    size = os.path.getsize(path)
    if size == 0 or size % SBET_DTYPE.itemsize:
        raise FormatError(
            f"{path}: not a valid SBET file: {size} bytes is not a whole number of "
            f"{SBET_DTYPE.itemsize}-byte records (17 float64); the file is truncated or "
            f"not an SBET")
    rec = np.fromfile(path, dtype=SBET_DTYPE)
    heading = np.degrees(rec["platform_heading"] - rec["wander"])
    heading = (heading + 180.0) % 360.0 - 180.0
    return _dataset(rec["time"], np.degrees(rec["lat"]), np.degrees(rec["lon"]), rec["h"],
                    np.degrees(rec["roll"]), np.degrees(rec["pitch"]), heading, path)


def write_sbet(ds: xr.Dataset, path) -> None:
    """Write a trajectory as SBET (wander angle 0; velocities etc. zero). Atomic."""
    from swathflow.io import atomic_path
    rec = np.zeros(ds.sizes["time"], dtype=SBET_DTYPE)
    rec["time"] = ds["time"].values
    rec["lat"] = np.radians(ds["lat"].values)
    rec["lon"] = np.radians(ds["lon"].values)
    rec["h"] = ds["h"].values
    rec["roll"] = np.radians(ds["roll"].values)
    rec["pitch"] = np.radians(ds["pitch"].values)
    rec["platform_heading"] = np.radians(ds["heading"].values)
    with atomic_path(path) as tmp:
        rec.tofile(tmp)


def read_pos_csv(path) -> xr.Dataset:
    """Read ``time,lat,lon,h,roll,pitch,heading`` (degrees, metres); extra columns ignored."""
    path = os.fspath(path)
    try:
        df = pd.read_csv(path)
    except (pd.errors.ParserError, pd.errors.EmptyDataError, UnicodeDecodeError,
            ValueError, OSError) as exc:
        raise FormatError(f"{path}: cannot be read as CSV: "
                          f"{str(exc).splitlines()[0][:200] if str(exc) else exc!r}") from None
    df.columns = [str(c).strip() for c in df.columns]
    missing = [c for c in ("time",) + POS_VARIABLES if c not in df.columns]
    if missing:
        raise FormatError(f"{path}: missing column(s) {', '.join(missing)}; the header must "
                          f"contain time,lat,lon,h,roll,pitch,heading")
    try:
        cols = {c: pd.to_numeric(df[c]).to_numpy(float) for c in ("time",) + POS_VARIABLES}
    except (ValueError, TypeError) as exc:
        raise FormatError(f"{path}: non-numeric value: {exc}") from None
    return _dataset(cols["time"], *(cols[k] for k in POS_VARIABLES), source=path)


def write_pos_csv(ds: xr.Dataset, path) -> None:
    from swathflow.io import atomic_path
    df = pd.DataFrame({"time": ds["time"].values,
                       **{k: ds[k].values for k in POS_VARIABLES}})
    with atomic_path(path) as tmp:
        df.to_csv(tmp, index=False, float_format="%.10f")


def read_pos(path, format: str | None = None) -> xr.Dataset:
    """Read a POS trajectory, ``format`` ``"sbet"`` or ``"csv"`` (default: from the suffix)."""
    path = os.fspath(path)
    if not os.path.exists(path):
        raise FormatError(f"{path}: POS file not found")
    fmt = (format or os.path.splitext(path)[1].lstrip(".")).lower()
    if fmt in ("sbet", "out"):
        return read_sbet(path)
    if fmt in ("csv", "txt"):
        return read_pos_csv(path)
    raise FormatError(f"{path}: unknown POS format {fmt!r}; use format='sbet' or 'csv'")


@dataclass(frozen=True, eq=False)
class Trajectory:
    """A trajectory prepared for fast interpolation (numpy only).

    Positions are interpolated linearly in ECEF, attitude angles linearly in time with the
    heading unwrapped (spec/geometry.md, POS interpolation). Times outside the trajectory,
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
        tab = self.__dict__.get("_table")
        if tab is None:         # one gather per end instead of one per column
            tab = np.column_stack([self.ecef, self.lat, self.lon, self.attitude])
            object.__setattr__(self, "_table", tab)
        a = tab[i]
        v = a + (tab[i + 1] - a) * w[..., None]
        return {"ecef": v[..., 0:3], "lat": v[..., 3], "lon": v[..., 4], "roll": v[..., 5],
                "pitch": v[..., 6], "heading": v[..., 7]}

    def to_dataset(self) -> xr.Dataset:
        if self.source is not None:
            return _dataset(self.time, *(self.source[k] for k in POS_VARIABLES), "trajectory")
        from swathflow.geometry.geodesy import ecef_to_geodetic
        llh = ecef_to_geodetic(self.ecef)
        heading = (self.attitude[:, 2] + 180.0) % 360.0 - 180.0
        return _dataset(self.time, llh[:, 0], llh[:, 1], llh[:, 2], self.attitude[:, 0],
                        self.attitude[:, 1], heading, "trajectory")


def interpolate_pos(ds: xr.Dataset, times, max_gap: float = 1.0) -> xr.Dataset:
    """Interpolate a trajectory Dataset to ``times``; returns a Dataset over ``time``."""
    traj = Trajectory.from_dataset(ds, max_gap=max_gap)
    t = np.asarray(times, dtype=float)
    r = traj.interpolate(t)
    from swathflow.geometry.geodesy import ecef_to_geodetic
    h = ecef_to_geodetic(r["ecef"])[..., 2]
    heading = (r["heading"] + 180.0) % 360.0 - 180.0
    lon = (r["lon"] + 180.0) % 360.0 - 180.0
    return _dataset(t, r["lat"], lon, h, r["roll"], r["pitch"], heading, "interpolated",
                    check=False)
