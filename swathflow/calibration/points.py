"""Where each observation sits, for the report's figures: the observed image position, its
acquisition time (the model's ``image_time``), its ground position, and every per-line
quantity the sensor records (read from the model's ``lines``, so no sensor is named here)."""
from __future__ import annotations

import numpy as np
import pandas as pd
from swathflow.geometry.geodesy import ecef_to_geodetic

SKIP = ("time", "line")


def point_context(model, grp: pd.DataFrame) -> dict[str, np.ndarray]:
    """Columns for the rows of ``grp`` (one image's observations): ``line``, ``element``
    (observed), ``time`` (s), ``lat``, ``lon`` (deg) and ``line_<name>`` for each numeric
    per-line array of the model (interpolated at the observed line)."""
    img = grp[["line", "element"]].to_numpy(float)
    out = {"line": img[:, 0], "element": img[:, 1]}
    llh = ecef_to_geodetic(grp[["X", "Y", "Z"]].to_numpy(float))
    out["lat"], out["lon"] = llh[:, 0], llh[:, 1]
    n = int(model.n_lines)
    idx = np.arange(n, dtype=float)
    out["time"] = np.asarray(model.image_time(img), dtype=float).reshape(-1)
    for name, values in model.lines.items():
        v = np.asarray(values)
        if name in SKIP or v.shape != (n,) or not np.issubdtype(v.dtype, np.number):
            continue
        out[f"line_{name}"] = np.interp(img[:, 0], idx, v.astype(float))
    return out
