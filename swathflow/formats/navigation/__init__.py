"""Navigation (POS) formats as plugins: the registry and the built-in readers.

``swathflow.read_pos(path, format=..., **options)`` is the one public entry; this package
holds the registry (entry-point group ``swathflow.pos_formats``) and the readers: ``sbet``
(Applanix), ``csv``, ``lcf`` (Resonon, with its ``.times`` file) and ``ascii`` (NovAtel
Inertial Explorer / Applanix POSPac text exports). Column mappings: docs/navigation-formats.md.
"""
from .registry import (
           GROUP,
           PosFormat,
           PosFormatWarning,
           find_format,
           list_formats,
           read,
           refresh,
)

__all__ = ["GROUP", "PosFormat", "PosFormatWarning", "find_format", "list_formats", "read",
           "refresh"]
