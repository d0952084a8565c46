"""Reuse of finished outputs, keyed by the content of their inputs and their parameters.

Every stage output ``OUT`` gets a manifest ``OUT.swathflow.json`` written (atomically) after
the output itself, with the output's size and sha256. A re-run recomputes the output unless
the manifest exists, the output is whole (the same size and content as when it was
written: a truncated or corrupted output is redone, not trusted) and the key (a hash of the
input files' content, the parameters and the software version) is unchanged. Inputs are
compared by content: a file rewritten with its size and modification time kept is seen.
An interrupted run leaves no manifest for a half-finished output, so it is redone; outputs
are themselves written atomically.
"""
from __future__ import annotations

import hashlib
import json
import os
from functools import lru_cache
from typing import Any, Iterable

from swathflow.io import write_text


@lru_cache(maxsize=4096)
def _file_digest(path: str, size: int, mtime_ns: int, ctime_ns: int = 0, ino: int = 0) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def _stamp(st) -> tuple:
    """What the in-process memo of a digest is keyed on: size, modification and change
    times and inode. The change time cannot be set back by a program (``os.utime`` sets
    it to now), so a file rewritten with its size and mtime restored hashes anew."""
    return st.st_size, st.st_mtime_ns, st.st_ctime_ns, st.st_ino


def file_digest(path) -> str:
    """sha256 of a file's content (memoised in this process on path and :func:`_stamp`)."""
    path = os.path.abspath(os.fspath(path))
    return _file_digest(path, *_stamp(os.stat(path)))


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
    """True when ``output`` exists, was finished with this ``key`` and is whole: its size
    and sha256 are those recorded when it was written."""
    m = manifest_path(output)
    if not (os.path.exists(output) and os.path.exists(m)):
        return False
    try:
        with open(m, encoding="utf-8") as f:
            doc = json.load(f)
        if not isinstance(doc, dict) or doc.get("key") != key:
            return False
        size, digest = doc.get("size"), doc.get("sha256")
        return _output_size(output) == size and _output_digest(output) == digest
    except (OSError, ValueError):
        return False


def mark_done(output, key: str, **info: Any) -> None:
    """Record that ``output`` is complete for ``key`` (call after writing the output),
    with its size and sha256 (:func:`is_fresh` checks the output is still whole)."""
    doc = {"key": key, "size": _output_size(output), "sha256": _output_digest(output),
           **info}
    write_text(manifest_path(output), json.dumps(doc, indent=2, default=str))


def _folder_files(folder) -> list[str]:
    """The files of an output folder (any depth, sorted), its temporaries aside."""
    out = []
    for root, _dirs, files in os.walk(folder):
        out += [os.path.join(root, f) for f in files if ".tmp" not in f]
    return sorted(out)


def _output_size(output) -> int:
    """Bytes of an output: a file's size, or the sum of a folder's files (a catalogue)."""
    if os.path.isdir(output):
        return sum(os.path.getsize(f) for f in _folder_files(output))
    return os.path.getsize(output)


def _output_digest(output) -> str:
    """sha256 of an output file, or of a folder's files (their relative names and
    contents)."""
    if not os.path.isdir(output):
        return file_digest(output)
    h = hashlib.sha256()
    for f in _folder_files(output):
        h.update(os.path.relpath(f, output).encode() + b"\0" + file_digest(f).encode())
    return h.hexdigest()


def fingerprints(paths: Iterable) -> dict[str, list]:
    """``{path: [size, mtime_ns, sha256]}`` of existing files (absolute paths)."""
    out = {}
    for p in paths:
        p = os.path.abspath(os.fspath(p))
        st = os.stat(p)
        out[p] = [st.st_size, st.st_mtime_ns, _file_digest(p, *_stamp(st))]
    return out


def unchanged(recorded: dict[str, list]) -> bool:
    """True when every file of :func:`fingerprints` still has the same content: compared
    by sha256 (a file changed with its size and modification time kept is seen; the size
    alone tells most changes apart without reading the file)."""
    for p, (size, _mtime_ns, digest) in recorded.items():
        try:
            st = os.stat(p)
            if st.st_size != size or _file_digest(p, *_stamp(st)) != digest:
                return False
        except OSError:
            return False
    return True
