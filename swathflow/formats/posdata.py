"""The POS dataset every navigation reader returns: an ``xarray.Dataset`` over ``time`` (s)
with :data:`POS_VARIABLES` ``lat``, ``lon`` (deg), ``h`` (ellipsoidal m), ``roll``,
``pitch``, ``heading`` (deg, true heading clockwise from north); how one is built
(:func:`pos_dataset`) and checked (:func:`check_trajectory`).

Shared by the readers (:mod:`swathflow.formats.navigation`) and the trajectory
(:mod:`swathflow.formats.pos`).
"""
from __future__ import annotations

import numpy as np
import xarray as xr

from swathflow.errors import FormatError

#: the trajectory's variables besides ``time``, in the order the readers give them
POS_VARIABLES = ("lat", "lon", "h", "roll", "pitch", "heading")


def pos_dataset(time, lat, lon, h, roll, pitch, heading, source: str,
                check: bool = True) -> xr.Dataset:
    """The POS dataset of these columns, with units; checked (:func:`check_trajectory`)
    unless ``check`` is false, ``source`` naming the file in the attributes and errors."""
    # float64 ndarrays wrapped as they are (fastpath): xarray's general conversion asks
    # whether each array is a dask array, which imports dask.array (0.4-1 CPU-s) in a
    # process that needs no dask, e.g. the mission check of `swathflow run`
    data = {k: xr.Variable(("time",), np.asarray(v, dtype=float), fastpath=True) for k, v in
            zip(POS_VARIABLES, (lat, lon, h, roll, pitch, heading))}
    ds = xr.Dataset(data, coords={"time": xr.Variable(("time",), np.asarray(time, dtype=float),
                                                      fastpath=True)},
                    attrs={"source": source})
    for k in ("lat", "lon", "roll", "pitch", "heading"):
        ds[k].attrs["units"] = "deg"
    ds["h"].attrs["units"] = "m"
    ds["h"].attrs["long_name"] = "ellipsoidal height"
    ds["heading"].attrs["long_name"] = "true heading, clockwise from north"
    ds["time"].attrs["units"] = "s"
    return check_trajectory(ds, source) if check else ds


def check_trajectory(ds: xr.Dataset, source: str = "trajectory") -> xr.Dataset:
    """Raise :class:`FormatError` unless every time is a number, times increase strictly
    and values are finite (the file, the variable and the first bad epoch named)."""
    t = np.asarray(ds["time"].values, dtype=float)
    if t.size < 2:
        raise FormatError(f"{source}: a trajectory needs at least 2 epochs, found {t.size}")
    nan = np.flatnonzero(~np.isfinite(t))
    if nan.size:
        i = int(nan[0])
        after = f", after t={t[i - 1]:.3f} s" if i > 0 and np.isfinite(t[i - 1]) else ""
        raise FormatError(f"{source}: column time, epoch {i} (counted from 0{after}): time "
                          f"is {t[i]} ({nan.size} epoch(s) in all); every epoch needs a time")
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
