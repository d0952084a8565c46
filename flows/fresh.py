"""Nothing to recompute? Checked before Prefect, Dask or the mission's validation start.

A finished run leaves ``OUT/run.swathflow.json``: the fingerprint of every input (each file
of the mission folder, files its ``mission.toml`` names outside it, the calibration file),
the size and modification time of every output file, and the run's result. A later run
whose inputs have the same content (stamps equal, or contents hashing equal) and whose
outputs are all still there, unmodified, returns that result at once; anything else runs
the flow, whose stages then recompute exactly what depends on what changed
(:mod:`swathflow.cache`). No Prefect, Dask or numba is imported here.
"""
from __future__ import annotations

import json
import os
import time
from pathlib import Path

from swathflow.cache import fingerprints, unchanged
from swathflow.io import write_text

#: the run manifest, in the output folder
RUN_MANIFEST = "run.swathflow.json"
#: files in the output folder that are not products (the command's lock)
_NOT_OUTPUTS = (RUN_MANIFEST, ".swathflow.lock")


def _named_files(value, root: Path):
    """Files named by string values of mission.toml (any depth) that exist."""
    if isinstance(value, dict):
        for v in value.values():
            yield from _named_files(v, root)
    elif isinstance(value, list):
        for v in value:
            yield from _named_files(v, root)
    elif isinstance(value, str) and value and len(value) < 4096:
        p = root / value
        try:
            if p.is_file():
                yield p.resolve()
        except OSError:
            return


def inputs(mission, calibration=None) -> list[str]:
    """Every file the run reads: the mission folder's files (hidden ones aside), the files
    its mission.toml names (also outside the folder) and the calibration file."""
    import tomllib
    root = Path(mission).resolve()
    files = {p.resolve() for p in root.rglob("*")
             if p.is_file() and not any(part.startswith(".")
                                        for part in p.relative_to(root).parts)}
    try:
        with open(root / "mission.toml", "rb") as f:
            files.update(_named_files(tomllib.load(f), root))
    except (OSError, tomllib.TOMLDecodeError):
        pass
    if calibration:
        files.add(Path(calibration).resolve())
    return sorted(str(p) for p in files)


def outputs(out) -> dict[str, list]:
    """``{path: [size, mtime_ns]}`` of every file in the output folder (temporaries, the
    lock and the run manifest aside)."""
    root = Path(out).resolve()
    found = {}
    for p in root.rglob("*"):
        if p.name in _NOT_OUTPUTS or ".tmp" in p.name or p.name.endswith(".part"):
            continue
        try:
            if p.is_file():
                st = p.stat()
                found[str(p)] = [st.st_size, st.st_mtime_ns]
        except OSError:
            continue
    return found


def _params(mission, calibration) -> dict:
    from swathflow._version import __version__
    return {"version": __version__, "mission": str(Path(mission).resolve()),
            "calibration": str(Path(calibration).resolve()) if calibration else None}


def record(mission, out, calibration, result: dict) -> None:
    """Write the run manifest after a finished run (atomically)."""
    doc = {**_params(mission, calibration),
           "inputs": fingerprints(inputs(mission, calibration)),
           "outputs": outputs(out), "result": result}
    write_text(Path(out) / RUN_MANIFEST, json.dumps(doc, indent=1, default=str))


def fresh_result(mission, out, calibration=None) -> dict | None:
    """The recorded result when nothing is to be recomputed, else None (also when the
    mission or the calibration is missing or unreadable: the flow reports that)."""
    t0 = time.perf_counter()
    path = Path(out) / RUN_MANIFEST
    try:
        with open(path, encoding="utf-8") as f:
            doc = json.load(f)
        if {k: doc.get(k) for k in ("version", "mission", "calibration")} \
                != _params(mission, calibration):
            return None
        if set(doc["inputs"]) != set(inputs(mission, calibration)):
            return None
        recorded = doc["outputs"]
        if not recorded or outputs(out) != recorded or not unchanged(doc["inputs"]):
            return None
        result = dict(doc["result"])
    except (OSError, ValueError, KeyError, TypeError):
        return None
    result["fresh"] = True
    result["timings"] = {"fresh-check": time.perf_counter() - t0}
    return result


def forget(out) -> None:
    """Remove the run manifest (before a run changes the outputs)."""
    try:
        os.remove(Path(out) / RUN_MANIFEST)
    except FileNotFoundError:
        pass
