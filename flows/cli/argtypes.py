"""The command line's argument types (argparse ``type=``): whole and finite numbers in
their bounds, refused with a message that says what is accepted. The tile bounds are the
Python API's (:mod:`swathflow.arguments`), so both refuse the same values."""
from __future__ import annotations

import argparse

from swathflow import arguments


def positive_int(text: str) -> int:
    """argparse type: a whole number above zero."""
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a whole number") from None
    if v <= 0:
        raise argparse.ArgumentTypeError(f"must be 1 or more, got {v}")
    return v


def int_between(lo: int, hi: int, step: int = 1):
    """argparse type: a whole number from ``lo`` to ``hi`` (a multiple of ``step``)."""
    def parse(text: str) -> int:
        try:
            v = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not a whole number") from None
        why = arguments.out_of_range(v, lo, hi, step)
        if why is not None:
            raise argparse.ArgumentTypeError(why)
        return v
    parse.__name__ = "number"       # argparse names the type in its messages
    return parse


#: output tile sizes in pixels (the Python API's bounds)
TILE = int_between(*arguments.TILE)
#: the mosaic's search range S: each search holds (2 S + 1)^2 costs of 8 bytes (S = 100000
#: asked for 299 GiB; 256 asks 2 MiB, and is 100 m at 0.4 m pixels)
MAX_SHIFT = int_between(1, 256)


def finite_float(text: str) -> float:
    """argparse type: a finite number."""
    import math
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not math.isfinite(v):
        raise argparse.ArgumentTypeError(f"must be a finite number, got {text}")
    return v


def positive_float(text: str) -> float:
    """argparse type: a finite number above zero."""
    import math
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not (math.isfinite(v) and v > 0):
        raise argparse.ArgumentTypeError(f"must be a number above 0, got {text}")
    return v
