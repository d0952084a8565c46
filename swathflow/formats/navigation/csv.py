"""The swathflow POS CSV: ``time,lat,lon,h,roll,pitch,heading`` with a header row."""
from __future__ import annotations

import os

import pandas as pd
import xarray as xr
from swathflow.errors import FormatError
from swathflow.formats.posdata import POS_VARIABLES, pos_dataset
from swathflow.io import atomic_path

from .registry import PosFormat


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
    return pos_dataset(cols["time"], *(cols[k] for k in POS_VARIABLES), source=path)


def write_pos_csv(ds: xr.Dataset, path) -> None:
    """Write a trajectory as swathflow POS CSV. Atomic."""
    df = pd.DataFrame({"time": ds["time"].values,
                       **{k: ds[k].values for k in POS_VARIABLES}})
    with atomic_path(path) as tmp:
        df.to_csv(tmp, index=False, float_format="%.10f")


FORMAT = PosFormat("csv", read_pos_csv, suffixes=("csv", "txt"), write=write_pos_csv,
                   description="swathflow CSV: time,lat,lon,h,roll,pitch,heading (degrees)")
