"""The navigation (POS) format registry: built-in and third-party readers through one
entry-point group, ``swathflow.pos_formats``.

A format is a :class:`PosFormat`: a name, a reader ``read(path, **options) -> Dataset``
returning a trajectory (see :mod:`swathflow.formats.pos`), the file suffixes it claims, the options
it accepts and optionally a writer. Built-ins register through the group like any plugin and
are also known statically, so an editable install never loses them. A plugin that fails to
load, is not a :class:`PosFormat`, or clashes with a registered name warns and is skipped
(the sensor registry's rules: both use :func:`swathflow.entrypoints.discover`).
"""
from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import dataclass
from functools import lru_cache
from importlib.metadata import entry_points

from swathflow.entrypoints import discover
from swathflow.errors import FormatError, SwathflowWarning
from swathflow.formats.posdata import POS_VARIABLES, check_trajectory

GROUP = "swathflow.pos_formats"
_PKG = __name__.rpartition(".")[0]
BUILTINS = {
    "sbet": f"{_PKG}.sbet:FORMAT",
    "csv": f"{_PKG}.csv:FORMAT",
    "lcf": f"{_PKG}.lcf:FORMAT",
    "ascii": f"{_PKG}.ascii:FORMAT",
}


@dataclass(frozen=True)
class PosFormat:
    """One navigation format.

    ``read(path, **options)`` returns a trajectory Dataset; ``suffixes`` (lower case, no dot)
    pick the format when none is named; ``aliases`` are other names accepted as ``format=``;
    ``options`` names every keyword ``read`` accepts (others are refused with a clear line).
    """

    name: str
    read: Callable
    suffixes: tuple[str, ...] = ()
    aliases: tuple[str, ...] = ()
    options: tuple[str, ...] = ()
    write: Callable | None = None
    description: str = ""


class PosFormatWarning(SwathflowWarning):
    """A navigation-format plugin could not be registered."""


def _problem(fmt) -> str | None:
    if not isinstance(fmt, PosFormat) or not callable(fmt.read):
        return "is not a PosFormat"
    return None


@lru_cache(maxsize=1)
def _registry() -> dict[str, tuple[PosFormat, str]]:
    return discover(BUILTINS, entry_points(group=GROUP), _problem, PosFormatWarning,
                    "POS format")


def list_formats() -> dict[str, PosFormat]:
    """Registered navigation formats by name (built-ins first)."""
    return {k: v[0] for k, v in _registry().items()}


def refresh() -> None:
    """Forget the cached discovery (after installing a plugin in a running process)."""
    _registry.cache_clear()


def find_format(path, format: str | None = None) -> PosFormat:
    """The format named ``format`` (a name or an alias), else the one claiming the suffix."""
    formats = list_formats()
    if format is not None and not isinstance(format, str):
        raise FormatError(f"{os.fspath(path)}: format must be the name of a POS format "
                          f"(one of {', '.join(repr(n) for n in formats)}), got {format!r}")
    key = (format or os.path.splitext(os.fspath(path))[1].lstrip(".")).lower()
    if key in formats:
        return formats[key]
    for fmt in formats.values():
        if key in fmt.aliases or (format is None and key in fmt.suffixes):
            return fmt
    for fmt in formats.values():     # a suffix named as the format ("out", "txt")
        if key in fmt.suffixes:
            return fmt
    names = ", ".join(f"'{n}'" for n in formats)
    raise FormatError(f"{os.fspath(path)}: unknown POS format {key!r}; use format= one of "
                      f"{names}")


def read(path, format: str | None = None, **options):
    """Read a trajectory with the registered reader for ``format`` (default: the suffix)."""
    path = os.fspath(path)
    if not os.path.exists(path):
        raise FormatError(f"{path}: POS file not found")
    fmt = find_format(path, format)
    unknown = sorted(set(options) - set(fmt.options))
    if unknown:
        allowed = ", ".join(fmt.options) or "none"
        raise FormatError(f"{path}: option(s) {', '.join(unknown)} not understood by the "
                          f"{fmt.name!r} POS reader; it accepts: {allowed}")
    ds = fmt.read(path, **options)
    missing = [k for k in POS_VARIABLES if k not in ds]
    if missing:
        raise FormatError(f"{path}: the {fmt.name!r} reader returned no {', '.join(missing)}")
    return check_trajectory(ds, path)
