"""Loading the shared spec vectors (../shared/spec/vectors) into sensor models."""
from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import xarray as xr

ROOT = Path(__file__).resolve().parents[1]
SHARED = Path(os.environ.get("SWATHFLOW_SHARED", ROOT.parent / "shared"))
VECTORS = SHARED / "spec" / "vectors"
DATA = SHARED / "data" / "real"


def load_cases(name: str) -> list[dict]:
    path = VECTORS / name
    if not path.exists():
        return []
    return json.loads(path.read_text())["cases"]


def pos_dataset(pos: dict) -> xr.Dataset:
    return xr.Dataset({k: ("time", np.asarray(pos[k], float))
                       for k in ("lat", "lon", "h", "roll", "pitch", "heading")},
                      coords={"time": np.asarray(pos["time"], float)})
