"""Reading ``mission.toml``: TOML as :mod:`tomllib` reads it, with a UTF-8 byte-order mark
accepted (editors on Windows write one; TOML forbids it and tomllib then reports an
"Invalid statement" at line 1, column 1)."""
from __future__ import annotations

import os
import tomllib
from pathlib import Path

BOM = b"\xef\xbb\xbf"


def load(path) -> dict:
    """The TOML document of ``path``; raises OSError, tomllib.TOMLDecodeError or
    UnicodeDecodeError as :func:`tomllib.load` does."""
    with open(os.fspath(path), "rb") as f:
        data = f.read()
    if data.startswith(BOM):
        data = data[len(BOM):]
    return tomllib.loads(data.decode("utf-8"))


def named_paths(cfg: dict, root):
    """Every path a mission.toml may name: its string values at any depth (of plausible
    length, without NUL), relative to ``root`` unless absolute; existing or not."""
    stack = [cfg]
    while stack:
        v = stack.pop()
        if isinstance(v, dict):
            stack.extend(v.values())
        elif isinstance(v, list):
            stack.extend(v)
        elif isinstance(v, str) and v and len(v) < 4096 and "\0" not in v:
            yield Path(v) if Path(v).is_absolute() else Path(root) / v


def special_files(cfg: dict, root) -> list[Path]:
    """Paths a mission.toml names (:func:`named_paths`) that exist and are neither regular
    files nor folders: FIFOs, devices, sockets."""
    import stat
    found = []
    for p in named_paths(cfg, root):
        try:
            mode = os.stat(p).st_mode
        except (OSError, ValueError):
            continue
        if not (stat.S_ISREG(mode) or stat.S_ISDIR(mode)):
            found.append(p)
    return found
