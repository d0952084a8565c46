"""The geometry test vectors (tests/data/vectors, docs/geometry.md) loaded into sensor models,
and the folder of real files the tests use (tests/data/real, PROVENANCE.md beside it)."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import xarray as xr

HERE = Path(__file__).resolve().parent
VECTORS = HERE / "data" / "vectors"
DATA = HERE / "data" / "real"


def load_cases(name: str) -> list[dict]:
    cases = json.loads((VECTORS / name).read_text())["cases"]
    assert cases, f"{name} holds no cases"
    return cases


def pos_dataset(pos: dict) -> xr.Dataset:
    return xr.Dataset({k: ("time", np.asarray(pos[k], float))
                       for k in ("lat", "lon", "h", "roll", "pitch", "heading")},
                      coords={"time": np.asarray(pos["time"], float)})
