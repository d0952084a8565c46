"""A third-party navigation format: ``t;lat;lon;h;roll;pitch;heading`` rows, no header."""
import numpy as np

from swathflow import PosFormat


def read(path, scale=1.0):
    import xarray as xr
    rec = np.loadtxt(path, delimiter=";", ndmin=2)
    names = ("lat", "lon", "h", "roll", "pitch", "heading")
    ds = xr.Dataset({k: ("time", rec[:, i + 1] * (scale if k == "h" else 1.0))
                     for i, k in enumerate(names)}, coords={"time": rec[:, 0]},
                    attrs={"source": str(path)})
    return ds       # the registry checks it (times increasing, values finite)


FORMAT = PosFormat("semicolon", read, suffixes=("semi",), options=("scale",))
not_a_format = object()
