"""Applanix SBET: 17 little-endian float64 per record, angles in radians."""
from __future__ import annotations

import os

import numpy as np
import xarray as xr
from swathflow.errors import FormatError
from swathflow.formats.posdata import pos_dataset
from swathflow.io import atomic_path

from .registry import PosFormat

#: Applanix SBET record: 17 little-endian float64.
SBET_FIELDS = ("time", "lat", "lon", "h", "vx", "vy", "vz", "roll", "pitch",
               "platform_heading", "wander", "ax", "ay", "az", "wx", "wy", "wz")
SBET_DTYPE = np.dtype([(name, "<f8") for name in SBET_FIELDS])


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
    return pos_dataset(rec["time"], np.degrees(rec["lat"]), np.degrees(rec["lon"]), rec["h"],
                    np.degrees(rec["roll"]), np.degrees(rec["pitch"]), heading, path)


def write_sbet(ds: xr.Dataset, path) -> None:
    """Write a trajectory as SBET (wander angle 0; velocities etc. zero). Atomic."""
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


FORMAT = PosFormat("sbet", read_sbet, suffixes=("sbet", "out"), write=write_sbet,
                   description="Applanix smoothed best estimate of trajectory (binary)")
