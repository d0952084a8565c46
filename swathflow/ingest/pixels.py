"""Two checks of a raw image's pixels for ``validate``: where an ENVI file's pixels start
(its header offset) and whether the image holds a valid pixel at all."""
from __future__ import annotations

import numpy as np

from swathflow.errors import SwathflowError


def envi_offset(src) -> int:
    """The ``header offset`` of an open ENVI image (bytes before its pixels; 0 if none)."""
    for f in src.files:
        if f.lower().endswith(".hdr"):
            try:
                with open(f, encoding="latin-1") as h:
                    for line in h:
                        k, _, v = line.partition("=")
                        if k.strip().lower() == "header offset":
                            return max(int(v.strip()), 0)
            except (OSError, ValueError):
                return 0
    return 0


#: lines of a raw image read to tell it holds data (all of it only when none of these has)
SAMPLE_LINES = 32


def has_data(src, path) -> None:
    """Refuse a raw image (``src``: the open dataset of ``path``) without one valid pixel
    (all NaN, or all its nodata value): its products would be empty. A few lines spread
    over the image are read; all of it only when none of those holds a valid pixel."""
    from rasterio.windows import Window
    rows, cols, nodata = src.height, src.width, src.nodata

    def valid(a) -> bool:
        ok = np.isfinite(a) if a.dtype.kind == "f" else np.ones(a.shape, bool)
        if nodata is not None:
            ok &= a != nodata
        return bool(ok.any())
    for r in np.unique(np.linspace(0, rows - 1, min(SAMPLE_LINES, rows)).astype(int)):
        if valid(src.read(window=Window(0, int(r), cols, 1))):
            return
    step = max(1, (64 << 20) // max(cols * src.count * 8, 1))
    for r0 in range(0, rows, step):
        if valid(src.read(window=Window(0, r0, cols, min(step, rows - r0)))):
            return
    what = "NaN" if nodata is None else f"NaN or its nodata value {nodata}"
    raise SwathflowError(f"{path}: no valid pixel (every pixel is {what}): its products "
                         f"would be empty; check the export of the image")
