"""Reading ``mission.toml``: TOML as :mod:`tomllib` reads it, with a UTF-8 byte-order mark
accepted (editors on Windows write one; TOML forbids it and tomllib then reports an
"Invalid statement" at line 1, column 1)."""
from __future__ import annotations

import os
import tomllib

BOM = b"\xef\xbb\xbf"


def load(path) -> dict:
    """The TOML document of ``path``; raises OSError, tomllib.TOMLDecodeError or
    UnicodeDecodeError as :func:`tomllib.load` does."""
    with open(os.fspath(path), "rb") as f:
        data = f.read()
    if data.startswith(BOM):
        data = data[len(BOM):]
    return tomllib.loads(data.decode("utf-8"))
