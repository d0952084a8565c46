"""Reuse of finished outputs, keyed by the content of their inputs and their parameters.

Every stage output ``OUT`` gets a manifest ``OUT.swathflow.json`` written (atomically) after
the output itself. A re-run recomputes the output unless the manifest exists, the output
exists and the key (a hash of the input files' content, the parameters and the software
version) is unchanged. An interrupted run leaves no manifest for a half-finished output,
so it is redone; outputs are themselves written atomically.
"""
from __future__ import annotations

import hashlib
import json
import os
from functools import lru_cache
from typing import Any, Iterable

from swathflow.io import write_text


@lru_cache(maxsize=4096)
def _file_digest(path: str, size: int, mtime_ns: int) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def file_digest(path) -> str:
    """sha256 of a file's content (memoised on path, size and modification time)."""
    path = os.path.abspath(os.fspath(path))
    st = os.stat(path)
    return _file_digest(path, st.st_size, st.st_mtime_ns)


def stage_key(stage: str, files: Iterable = (), **params: Any) -> str:
    """A key for a stage output from its input files' content and its parameters."""
    from swathflow._version import __version__
    doc = {"stage": stage, "version": __version__,
           "files": sorted(file_digest(f) for f in files if f is not None and os.path.exists(f)),
           "params": params}
    return hashlib.sha256(json.dumps(doc, sort_keys=True, default=str).encode()).hexdigest()


def manifest_path(output) -> str:
    return os.fspath(output) + ".swathflow.json"


def is_fresh(output, key: str) -> bool:
    """True when ``output`` exists and was finished with this ``key``."""
    m = manifest_path(output)
    if not (os.path.exists(output) and os.path.exists(m)):
        return False
    try:
        with open(m, encoding="utf-8") as f:
            return json.load(f).get("key") == key
    except (OSError, json.JSONDecodeError):
        return False


def mark_done(output, key: str, **info: Any) -> None:
    """Record that ``output`` is complete for ``key`` (call after writing the output)."""
    write_text(manifest_path(output), json.dumps({"key": key, **info}, indent=2, default=str))


def fingerprints(paths: Iterable) -> dict[str, list]:
    """``{path: [size, mtime_ns, sha256]}`` of existing files (absolute paths)."""
    out = {}
    for p in paths:
        p = os.path.abspath(os.fspath(p))
        st = os.stat(p)
        out[p] = [st.st_size, st.st_mtime_ns, _file_digest(p, st.st_size, st.st_mtime_ns)]
    return out


def unchanged(recorded: dict[str, list]) -> bool:
    """True when every file of :func:`fingerprints` still has the same content: the stamp
    (size, mtime) is trusted when equal; a file touched but not changed hashes equal."""
    for p, (size, mtime_ns, digest) in recorded.items():
        try:
            st = os.stat(p)
        except OSError:
            return False
        if (st.st_size, st.st_mtime_ns) == (size, mtime_ns):
            continue
        if st.st_size != size or _file_digest(p, st.st_size, st.st_mtime_ns) != digest:
            return False
    return True
