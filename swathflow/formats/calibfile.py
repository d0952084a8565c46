"""Calibration files (``calibration.json``, format ``swathflow-calibration/1``).

See docs/mission-format.md. A calibration file is reusable: another mission of the
same installation names it in place of its ``[calibration]`` table.
"""
from __future__ import annotations

import json
import math
import os
from typing import Any, Mapping

from swathflow.errors import FormatError
from swathflow.io import write_text

FORMAT = "swathflow-calibration/1"


def _clean(x):
    if isinstance(x, float) and not math.isfinite(x):
        return None
    if isinstance(x, dict):
        return {k: _clean(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_clean(v) for v in x]
    if hasattr(x, "tolist"):
        return _clean(x.tolist())
    return x


def write_calibration(path, sensor: str, parameters: Mapping[str, Mapping[str, Any]],
                      **extra: Any) -> None:
    """Write ``calibration.json`` atomically. ``parameters``: name -> {value, sigma, units}."""
    doc = {"format": FORMAT, "sensor": sensor,
           "parameters": {k: {"value": list(v["value"]),
                              "sigma": list(v.get("sigma", [None] * len(v["value"]))),
                              "units": v.get("units", "")} for k, v in parameters.items()}}
    doc.update(extra)
    write_text(path, json.dumps(_clean(doc), indent=2) + "\n")


def read_calibration(path) -> dict:
    """Read and check a calibration file; returns the whole document.

    ``doc["parameters"]`` maps name -> {"value": [...], "sigma": [...], "units": str}.
    """
    path = os.fspath(path)
    if not os.path.exists(path):
        raise FormatError(f"{path}: calibration file not found")
    if not os.path.isfile(path):        # a FIFO would hang the reader, a device fill memory
        raise FormatError(f"{path}: not a regular file (a folder, device or FIFO); name a "
                          f"calibration.json")
    try:
        with open(path, encoding="utf-8") as f:
            doc = json.load(f)
    except (json.JSONDecodeError, UnicodeDecodeError, RecursionError) as exc:
        raise FormatError(f"{path}: not valid JSON: {str(exc)[:200]}") from None
    except OSError as exc:
        raise FormatError(f"{path}: cannot read the calibration file: {exc.strerror}") from None
    if not isinstance(doc, dict) or doc.get("format") != FORMAT:
        found = doc.get("format") if isinstance(doc, dict) else type(doc).__name__
        raise FormatError(f"{path}: format must be {FORMAT!r}, found {found!r}")
    params = doc.get("parameters")
    if not isinstance(params, dict) or not params:
        raise FormatError(f"{path}: 'parameters' must be a non-empty table")
    for name, p in params.items():
        if not isinstance(p, dict) or "value" not in p:
            raise FormatError(f"{path}: parameter {name!r} needs a 'value'")
        _check_numbers(path, name, p)
    return doc


def _check_numbers(path, name, p) -> None:
    """value: a list of finite numbers; sigma (optional): numbers or null, same length."""
    v, s = p["value"], p.get("sigma")
    num = (int, float)
    if not (isinstance(v, list) and v and all(isinstance(x, num) and not isinstance(x, bool)
                                               and math.isfinite(x) for x in v)):
        raise FormatError(f"{path}: parameter {name!r}: value must be a list of numbers, "
                          f"got {str(v)[:60]}")
    if s is not None and not (isinstance(s, list) and len(s) == len(v) and all(
            x is None or (isinstance(x, num) and not isinstance(x, bool)
                          and not math.isnan(x) and x >= 0) for x in s)):
        raise FormatError(f"{path}: parameter {name!r}: sigma must be a list of "
                          f"{len(v)} numbers >= 0 (or null: unknown), got {str(s)[:60]}")


def calibration_priors(doc: Mapping) -> dict:
    """``ParameterSet.updated`` input from a calibration document (sigma None -> inf).
    A document without parameters is refused: it would silently mean the priors."""
    params = doc.get("parameters") if isinstance(doc, Mapping) else None
    if not isinstance(params, Mapping) or not params:
        raise FormatError("the calibration gives no parameters ('parameters' missing or "
                          "empty): it would mean the mission's priors; pass a calibration "
                          "that 'swathflow calibrate' wrote")
    out = {}
    for name, p in params.items():
        entry = {"value": p["value"]}
        if p.get("sigma") is not None:
            entry["sigma"] = [math.inf if s is None else s for s in p["sigma"]]
        out[name] = entry
    return out
