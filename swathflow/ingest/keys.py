"""The keys and columns of the mission folder's format (docs/mission-format.md) that
swathflow reads: the tables of ``mission.toml`` and their keys, the keys of an
``[[images]]`` entry, and the per-line columns every line table has.
"""
from __future__ import annotations

#: per-line columns every line table needs; plugins may ask for more (``line_columns``)
BASE_LINE_COLUMNS = ("line", "time")
#: the keys of an ``[[images]]`` entry that swathflow reads (others go to the sensor model)
IMAGE_KEYS = ("id", "file", "lines", "direction", "strip")

#: the keys of each mission.toml table that swathflow reads (docs/mission-format.md)
KNOWN_KEYS = {
    "": ("mission", "sensor", "pos", "terrain", "gcp", "images", "calibration", "ties",
         "rectify", "reference"),
    "reference": ("ortho", "dem", "ties"),
    "mission": ("name", "crs", "gsd", "max_pixels", "description", "date"),
    "pos": ("file", "format", "max_gap"),
    "terrain": ("dem", "height", "vertical", "geoid", "undulation"),
    "gcp": ("file", "crs"),
    "rectify": ("bands",),
    "images": IMAGE_KEYS + ("view",),
}
