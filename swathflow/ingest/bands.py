"""An ENVI image's header as rectify reads it, checked by ``validate``: its size against
the data file, its band lists (wavelength, FWHM: one value per band). ``c`` is the
validation's problem collector (``add(file, where, message, fix)``). The ``[rectify] bands``
selection is checked against each image by the ``validate`` command
(:func:`swathflow.flows.guard.band_problems`: the selection's syntax is the rectification's)."""
from __future__ import annotations


def check_envi(entry, c) -> None:
    from swathflow.errors import FormatError
    from swathflow.formats.envi import envi_header_path, map_envi
    if not envi_header_path(entry.file):
        return
    try:
        map_envi(entry.file)
    except (FormatError, OSError, ValueError) as exc:
        c.add(entry.file, f"[[images]] id={entry.id!r}",
              str(exc).replace(str(entry.file) + ": ", ""),
              "correct the image's header (its size, one wavelength and FWHM per band)")
