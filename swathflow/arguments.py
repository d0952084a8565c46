"""The bounds of the arguments a user gives, one definition for the command line and the
Python API (the command line words the reason as argparse does, the API raises
:class:`~swathflow.errors.ArgumentError` naming the argument)."""
from __future__ import annotations

import numbers

from swathflow.errors import ArgumentError, ArgumentTypeError

#: output tile sizes in pixels (lo, hi, step): TIFF tiles are multiples of 16; beyond 4096
#: a tile (and its compression buffer) no longer fits a worker's share of memory
TILE = (16, 4096, 16)


def out_of_range(value: int, lo: int, hi: int, step: int = 1) -> str | None:
    """Why the whole number ``value`` is not one from ``lo`` to ``hi`` (a multiple of
    ``step``), or None when it is."""
    if value < 1 <= lo:
        return f"must be 1 or more, got {value}"
    if not lo <= value <= hi:
        return f"must be from {lo} to {hi}, got {value}"
    if value % step:
        return f"must be a multiple of {step} (a TIFF tile size), got {value}"
    return None


def whole_between(name: str, value, lo: int, hi: int, step: int = 1) -> int:
    """``value`` (argument ``name`` of an API call) as an int from ``lo`` to ``hi``, a
    multiple of ``step``; :class:`ArgumentTypeError` when it is not a whole number,
    :class:`ArgumentError` when it is out of range."""
    if isinstance(value, bool) or not isinstance(value, numbers.Integral):
        raise ArgumentTypeError(f"{name}={value!r}: must be a whole number from {lo} to "
                                f"{hi}" + (f", a multiple of {step}" if step > 1 else ""))
    why = out_of_range(int(value), lo, hi, step)
    if why is not None:
        raise ArgumentError(f"{name}={value!r}: {why}")
    return int(value)


def tile_size(value, name: str = "tile") -> int:
    """An output tile size (:data:`TILE`) given to the Python API."""
    return whole_between(name, value, *TILE)
