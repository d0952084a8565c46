"""The report style around a whole report's drawing (:func:`styled`), without importing
matplotlib until a report is drawn."""
from __future__ import annotations

import functools


def styled(fn):
    """``fn`` run inside :func:`swathflow.drawing.report_style`: every figure it builds
    (axes, tick labels, texts made before it is saved) takes the report settings, and one
    report is drawn at a time in the process, so that the same inputs give the same bytes
    whatever else draws on other threads."""
    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        from swathflow.drawing import report_style
        with report_style():
            return fn(*args, **kwargs)
    return wrapper
