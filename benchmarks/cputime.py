"""The CPU time of a benchmark's child processes, one helper for every benchmark."""
from __future__ import annotations

import resource


def children_cpu() -> float:
    """User + system CPU seconds of every child process waited for so far (a command's
    CPU is the difference across it)."""
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime
