"""An image's bands as rectify reads them, checked by ``validate``: the ENVI header's band
lists and the ``[rectify] bands`` selection of mission.toml. ``c`` is the validation's
problem collector (``add(file, where, message, fix)``)."""
from __future__ import annotations


def check_bands(entry, cfg: dict, toml, c) -> None:
    """What rectify reads of an image's bands: its ENVI header's band lists (wavelength,
    FWHM: one value per band) and the ``[rectify] bands`` selection, which must fit it."""
    from swathflow.errors import FormatError
    from swathflow.rectification.rawimage import open_raw_image
    where = f"[[images]] id={entry.id!r}"
    try:
        img = open_raw_image(entry.file)
    except (FormatError, OSError, ValueError) as exc:
        c.add(entry.file, where, str(exc).replace(str(entry.file) + ": ", ""),
              "correct the image's header (one wavelength and FWHM per band)")
        return
    spec = (cfg.get("rectify") or {}).get("bands") if isinstance(cfg.get("rectify"),
                                                                  dict) else None
    if spec in (None, "", []):
        return
    if not isinstance(spec, (str, list)) or (isinstance(spec, list) and not all(
            isinstance(b, int) and not isinstance(b, bool) for b in spec)):
        c.add(toml, "[rectify].bands", f"{spec!r} is neither a string such as \"1,4-6\" or "
              f"\"550nm\" nor a list of 1-based band numbers", 'bands = "1,4-6"')
        return
    try:
        img.select(spec)
    except (FormatError, ValueError) as exc:
        c.add(toml, "[rectify].bands", f"{spec!r} does not fit image {entry.id!r}: "
              f"{str(exc).split(': ', 1)[-1]}", "select bands the image has")
