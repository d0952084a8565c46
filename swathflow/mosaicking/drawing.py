"""Moved to :mod:`swathflow.drawing` (the one canvas of every report's figures); this name
stays importable for the mosaicking modules that still import it."""
from swathflow.drawing import Axes, Canvas, colour, colour_bar, nice_ticks, png_bytes

__all__ = ["Canvas", "Axes", "colour", "nice_ticks", "colour_bar", "png_bytes"]
