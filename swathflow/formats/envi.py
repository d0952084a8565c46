"""ENVI raw images (BSQ, BIL, BIP with their ``.hdr``): the header parsed, the data file
found beside it and memory-mapped in its own interleave and byte order, viewed as
``(bands, lines, elements)`` without a copy; the bands' names, wavelengths, FWHM and their
units as the header gives them.
"""
from __future__ import annotations

import os
import re
from dataclasses import dataclass

import numpy as np

from swathflow.errors import FormatError

#: ENVI ``data type`` codes -> numpy types (byte order from ``byte order``)
ENVI_DTYPES = {1: "u1", 2: "i2", 3: "i4", 4: "f4", 5: "f8", 12: "u2", 13: "u4", 14: "i8",
               15: "u8"}


@dataclass(frozen=True)
class EnviImage:
    """An ENVI image mapped into memory: ``data`` ``(bands, lines, elements)`` (a view of
    the memmap in the file's interleave), the data file's ``path``, its ``interleave``, the
    ``nodata`` value (``data ignore value``), and per band its ``names`` (as many as the
    header gives), ``wavelengths`` and ``fwhm`` (None each when absent) in ``units``."""

    data: np.ndarray
    path: str
    interleave: str
    nodata: float | None
    names: list
    wavelengths: list
    fwhm: list
    units: str | None


def envi_header_path(path) -> str | None:
    """The ``.hdr`` of an ENVI data file (``x.bil.hdr`` or ``x.hdr``), or None."""
    path = os.fspath(path)
    if path.lower().endswith(".hdr"):
        return path
    for cand in (path + ".hdr", os.path.splitext(path)[0] + ".hdr"):
        if os.path.exists(cand):
            return cand
    return None


def read_envi_header(path) -> dict:
    """Parse an ENVI header into ``{key (lower case): str | list[str]}`` (brace lists
    split on commas). Raises :class:`FormatError` naming the file when it is not one."""
    with open(path, encoding="utf-8", errors="replace") as f:
        text = f.read()
    if not text.lstrip().upper().startswith("ENVI"):
        raise FormatError(f"{path}: not an ENVI header (the first line must be 'ENVI')")
    out: dict = {}
    for m in re.finditer(r"^\s*([^=\n]+?)\s*=\s*(\{[^}]*\}|[^\n]*)", text, re.MULTILINE):
        key, val = m.group(1).strip().lower(), m.group(2).strip()
        if val.startswith("{"):
            inner = val[1:-1].strip()
            out[key] = [v.strip() for v in inner.split(",")] if key != "description" else inner
        else:
            out[key] = val
    return out


def _int(hdr, key, path, default=None):
    """An integer item of a header (``default`` when absent)."""
    try:
        return int(hdr[key]) if key in hdr else default
    except ValueError:
        raise FormatError(f"{path}: '{key} = {hdr[key]}' is not an integer") from None


def _floats(hdr, key, n, path):
    """A per-band list of numbers (``n`` of them; None each when absent)."""
    if key not in hdr:
        return [None] * n
    vals = hdr[key] if isinstance(hdr[key], list) else [hdr[key]]
    try:
        vals = [float(v) for v in vals if v != ""]
    except ValueError:
        raise FormatError(f"{path}: '{key}' holds a value that is not a number") from None
    if len(vals) != n:
        raise FormatError(f"{path}: '{key}' lists {len(vals)} values for {n} bands; give "
                          f"one per band")
    return vals


def map_envi(path) -> EnviImage:
    """An ENVI image (BSQ, BIL or BIP; ``path`` the data file or its ``.hdr``) mapped into
    memory, its header checked against the file's size."""
    path = os.fspath(path)
    hdr_path = envi_header_path(path)
    if hdr_path is None:
        raise FormatError(f"{path}: no ENVI header beside it (expected {path}.hdr)")
    hdr = read_envi_header(hdr_path)
    data = path if not path.lower().endswith(".hdr") else _data_path(hdr_path)
    ns, nl, nb = (_int(hdr, k, hdr_path) for k in ("samples", "lines", "bands"))
    if not (ns and nl and nb):
        raise FormatError(f"{hdr_path}: 'samples', 'lines' and 'bands' are required")
    code = _int(hdr, "data type", hdr_path)
    if code not in ENVI_DTYPES:
        raise FormatError(f"{hdr_path}: 'data type = {hdr.get('data type')}' is not "
                          f"supported; use one of {sorted(ENVI_DTYPES)}")
    order = ">" if _int(hdr, "byte order", hdr_path, 0) == 1 else "<"
    dtype = np.dtype(order + ENVI_DTYPES[code])
    inter = str(hdr.get("interleave", "bsq")).lower()
    shapes = {"bsq": ((nb, nl, ns), (0, 1, 2)), "bil": ((nl, nb, ns), (1, 0, 2)),
              "bip": ((nl, ns, nb), (2, 0, 1))}
    if inter not in shapes:
        raise FormatError(f"{hdr_path}: 'interleave = {inter}' is not bsq, bil or bip")
    offset = _int(hdr, "header offset", hdr_path, 0)
    need = offset + nb * nl * ns * dtype.itemsize
    if not os.path.exists(data) or os.path.getsize(data) < need:
        have = os.path.getsize(data) if os.path.exists(data) else 0
        raise FormatError(f"{data}: {have} bytes but the header {hdr_path} describes "
                          f"{need} ({nb} bands x {nl} lines x {ns} samples of {dtype.name}, "
                          f"offset {offset}); fix the header or the file")
    if os.path.getsize(data) > need:    # a 5-band BIL read as 3 would come out scrambled
        raise FormatError(f"{data}: {os.path.getsize(data)} bytes but the header {hdr_path} "
                          f"describes {need} ({nb} bands x {nl} lines x {ns} samples of "
                          f"{dtype.name}, offset {offset}): the header does not describe "
                          f"the file; fix its bands, lines, samples or data type")
    shape, axes = shapes[inter]
    mm = np.memmap(data, dtype=dtype, mode="r", offset=offset, shape=shape)
    nodata = hdr.get("data ignore value")
    nodata = float(nodata) if isinstance(nodata, str) and nodata else None
    names = hdr.get("band names") or []
    units = hdr.get("wavelength units")
    return EnviImage(mm.transpose(axes), data, inter, nodata,
                     names if isinstance(names, list) else [names],
                     _floats(hdr, "wavelength", nb, hdr_path), _floats(hdr, "fwhm", nb, hdr_path),
                     units if isinstance(units, str) and units.lower() != "unknown" else None)


def _data_path(hdr_path: str) -> str:
    """The data file beside a header (the header's name without ``.hdr``, or with one of
    the usual suffixes)."""
    stem = os.path.splitext(hdr_path)[0]
    for ext in ("", ".bil", ".bip", ".bsq", ".img", ".dat", ".raw"):
        if os.path.exists(stem + ext) and not (stem + ext).lower().endswith(".hdr"):
            return stem + ext
    raise FormatError(f"{hdr_path}: no data file beside the header (tried {stem}.bil/.bip/"
                      f".bsq/.img/.dat)")
