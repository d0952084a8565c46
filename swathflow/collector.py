"""The garbage collector paused while a process makes objects that live to its end."""
from __future__ import annotations

import contextlib
import gc

__all__ = ["uncollected"]


@contextlib.contextmanager
def uncollected(freeze: bool = True):
    """No collector passes inside the block (an engine's imports and numba's start make
    some 100 000 objects that all live to the end: the passes over them while they are
    made cost 0.1-0.2 CPU-s), and with ``freeze`` the objects then alive moved out of the
    collector's reach after it (``gc.freeze``: later full collections and the
    interpreter's last ones at exit no longer walk them; they are still freed by reference
    counting). Freeze once a process: a reference cycle alive at that moment is kept. The
    collector's state is restored after. Only the standard library's ``gc`` API."""
    on = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if freeze:
            gc.freeze()
        if on:
            gc.enable()
