"""swathflow: calibrate, orthorectify and mosaic airborne line-scanner imagery.

The pure maths lives here (numpy, scipy, pyproj, rasterio; no Prefect). Sensor models are
in :mod:`swathflow.sensors`, Prefect tasks in :mod:`swathflow.tasks`, flows in
:mod:`swathflow.flows`.
"""
from swathflow.errors import FormatError, OutOfRangeError, SwathflowError
from swathflow.ingest.mission import Mission, load_mission, validate_mission
from swathflow.formats.pos import Trajectory, interpolate_pos, read_pos

from swathflow._version import __version__

__all__ = ["FormatError", "Mission", "OutOfRangeError", "SwathflowError", "Trajectory",
           "interpolate_pos", "load_mission", "read_pos", "validate_mission", "__version__"]
