"""What the command line shows while it works, through rich.

One progress bar per stage when stderr is a terminal; nothing when it is not (a log file, a
pipe, a scheduler) unless ``--verbose`` asks for plain lines; nothing at all with
``--quiet``. The level is set once by the command line (:func:`set_verbosity`).
"""
from __future__ import annotations

import sys
import time

QUIET, NORMAL, VERBOSE = -1, 0, 1
_LEVEL = {"level": NORMAL}


def set_verbosity(level: int) -> None:
    """-1 quiet, 0 normal (bars on a terminal), 1 verbose (also plain lines elsewhere)."""
    _LEVEL["level"] = int(level)


def verbosity() -> int:
    return _LEVEL["level"]


class Progress:
    """Stage progress: ``start(stage, total)``, ``update(stage, done, total)``,
    ``finish(stage, total)``; ``timings`` holds each finished stage's seconds. Use as a
    context manager so the bars are closed when the work ends or fails."""

    def __init__(self, stream=None, level: int | None = None):
        from rich.console import Console
        from rich.progress import (BarColumn, MofNCompleteColumn, TextColumn,
                                   TimeElapsedColumn)
        from rich.progress import Progress as Bars
        self.level = verbosity() if level is None else int(level)
        self.console = Console(file=stream or sys.stderr)
        self.bars = self.level > QUIET and self.console.is_terminal
        self.lines = not self.bars and self.level >= VERBOSE
        self._bars = Bars(TextColumn("{task.description:<16}"), BarColumn(),
                          MofNCompleteColumn(), TimeElapsedColumn(), console=self.console,
                          disable=not self.bars)
        self.timings: dict[str, float] = {}
        #: each stage's (start, end) in wall-clock seconds (``time.time()``)
        self.spans: dict[str, list[float]] = {}
        self._t0: dict[str, float] = {}
        self._ids: dict[str, int] = {}

    def __enter__(self) -> Progress:
        self._bars.start()
        return self

    def __exit__(self, *exc) -> None:
        self._bars.stop()

    def start(self, stage: str, total: int = 1) -> None:
        self._t0[stage] = time.perf_counter()
        self.spans[stage] = [time.time(), float("nan")]
        self._ids[stage] = self._bars.add_task(stage, total=max(int(total), 1))
        if self.lines:
            self.console.print(f"{stage}: started ({total})", highlight=False)

    def update(self, stage: str, done: int, total: int) -> None:
        if stage in self._ids:
            self._bars.update(self._ids[stage], completed=done, total=max(int(total), 1))

    def finish(self, stage: str, total: int = 1) -> None:
        self.timings[stage] = time.perf_counter() - self._t0.get(stage, time.perf_counter())
        self.spans.setdefault(stage, [time.time(), 0.0])[1] = time.time()
        self.update(stage, total, total)
        if self.lines:
            self.console.print(f"{stage}: done in {self.timings[stage]:.1f} s", highlight=False)
