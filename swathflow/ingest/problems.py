"""What the mission checks report and the small helpers they share: a :class:`Problem`
(file, place, message, fix, level), the :class:`Collector` every check adds to, and the
checks used by several parts of the mission (unknown keys of a table, a CRS pyproj
accepts, the file rows of a CSV column named in a message, paths relative to the mission
folder).
"""
from __future__ import annotations

import difflib
from dataclasses import dataclass
from pathlib import Path

import numpy as np


@dataclass(frozen=True)
class Problem:
    """One thing wrong with a mission: where it is and how to fix it."""

    file: str
    where: str
    message: str
    fix: str = ""
    level: str = "error"      # "error": the mission is unusable; "warning": it loads

    def text(self) -> str:
        """The problem without its level: file, place, message and fix."""
        loc = f"{self.file}: {self.where}: " if self.where else f"{self.file}: "
        return loc + self.message + (f" -> fix: {self.fix}" if self.fix else "")

    def __str__(self) -> str:
        return ("warning: " if self.level == "warning" else "") + self.text()



class Collector:
    """Problems found so far."""

    def __init__(self):
        self.problems: list[Problem] = []

    def add(self, file, where, message, fix="", level="error"):
        self.problems.append(Problem(str(file), where, message, fix, level))

    def warn(self, file, where, message, fix=""):
        self.add(file, where, message, fix, "warning")


def rel(root: Path, p) -> Path:
    """A path of mission.toml: as given when absolute, else in the mission folder."""
    p = Path(str(p))
    return p if p.is_absolute() else root / p


def check_crs(crs) -> str | None:
    """Why pyproj rejects ``crs`` (its first line), or None when it accepts it."""
    import pyproj
    try:
        pyproj.CRS.from_user_input(crs)
        return None
    except (pyproj.exceptions.CRSError, TypeError, ValueError) as exc:
        return str(exc).splitlines()[0][:200]


def first_rows(mask, limit=5) -> str:
    """The file rows of a CSV where ``mask`` (over its data rows) is true, as a message
    gives them: 1-based with the header as row 1, the first ``limit`` and how many more."""
    idx = np.flatnonzero(mask)
    s = ", ".join(str(i + 2) for i in idx[:limit])
    return s + (f" (and {idx.size - limit} more)" if idx.size > limit else "")


def check_keys(table, known, file, where: str, c: Collector, strict: bool = True) -> None:
    """Unknown keys of a table: a near miss of a known key is an error naming it (a typo
    silently changes the result), any other unknown key a warning (``strict``) or nothing."""
    if not isinstance(table, dict):
        return
    for key in table:
        if key in known:
            continue
        near = difflib.get_close_matches(str(key), known, n=1, cutoff=0.75)
        loc = f"{where}.{key}" if where else str(key)
        if near:
            c.add(file, loc, f"unknown key {key!r}", f"did you mean {near[0]!r}? rename it")
        elif strict:
            c.warn(file, loc, f"unknown key {key!r}, ignored",
                   f"known keys here: {', '.join(known)}")
