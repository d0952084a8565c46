"""The push-broom (linear CCD, three-line) camera: model, calibration strategy (tie points,
orientation fixes, C0/C1 constraints) and simulator."""
from swathflow.sensors.pushbroom.model import (PushbroomModel, continuity_matrix,
                                               continuity_residuals)

__all__ = ["PushbroomModel", "continuity_matrix", "continuity_residuals"]
