"""Cloud-Optimized GeoTIFF checks on real files: rio-cogeo's validator (``rio cogeo
validate``), which also runs GDAL's own checks of the layout (IFDs before the data,
overviews from the smallest up, tiles in order, the ghost area's leaders and trailers)."""
from __future__ import annotations

import os


def cog_problems(path) -> list[str]:
    """The errors ``rio cogeo validate`` finds in ``path`` (warnings too, as errors: a COG
    without overviews that needs them, a mask without overviews...); [] for a valid COG."""
    from rio_cogeo.cogeo import cog_validate
    valid, errors, warnings = cog_validate(os.fspath(path), strict=True)
    return [] if valid else list(errors) + list(warnings)


def cogs_under(folder) -> list:
    """Every GeoTIFF under ``folder`` (``*.tif``; the ``.part`` and scratch names are
    hidden, dot-prefixed files, and must not be there)."""
    from pathlib import Path
    return sorted(p for p in Path(folder).rglob("*.tif"))
