"""swathflow: calibrate, orthorectify and mosaic airborne line-scanner imagery.

The pure maths lives here (numpy, scipy, pyproj, rasterio; no Prefect). Sensor models are
in :mod:`swathflow.sensors`, Prefect tasks in :mod:`swathflow.tasks`, flows in
:mod:`swathflow.flows`.
"""
from swathflow.errors import FormatError, OutOfRangeError, SwathflowError

from swathflow._version import __version__

__all__ = ["FormatError", "Mission", "OutOfRangeError", "PosFormat", "SwathflowError",
           "Trajectory", "geolocation", "interpolate_pos", "load_mission", "mosaic",
           "open_mission", "read_pos", "rectify", "to_cog", "validate_mission", "write_mosaic",
           "__version__"]

# imported on first use: xarray, pandas, rioxarray and the engines stay out of
# ``import swathflow`` (a subpackage such as swathflow.mosaicking starts in 0.1 s, not 1 s)
_LAZY = {"open_mission": "swathflow.ingest.api", "rectify": "swathflow.rectification.api",
         "to_cog": "swathflow.rectification.api", "geolocation": "swathflow.rectification.api",
         "mosaic": "swathflow.mosaicking.api", "write_mosaic": "swathflow.mosaicking.api",
         "Mission": "swathflow.ingest.mission",
         "load_mission": "swathflow.ingest.mission",
         "validate_mission": "swathflow.ingest.mission",
         "PosFormat": "swathflow.formats.navigation", "Trajectory": "swathflow.formats.pos",
         "interpolate_pos": "swathflow.formats.pos", "read_pos": "swathflow.formats.pos"}


def __getattr__(name):
    if name in _LAZY:
        from importlib import import_module
        return getattr(import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'swathflow' has no attribute {name!r}")
