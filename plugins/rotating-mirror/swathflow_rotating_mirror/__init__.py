"""swathflow sensor plugin: a rotating-mirror whisk-broom scanner.

The entry point ``rotating-mirror = "swathflow_rotating_mirror:RotatingMirrorModel"`` in the
group ``swathflow.sensors`` registers :class:`RotatingMirrorModel` with swathflow.
"""
from .model import RotatingMirrorModel

__all__ = ["RotatingMirrorModel"]
__version__ = "0.1.0"
