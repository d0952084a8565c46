"""The pendulum scanner's calibration parameters (docs/references.md section 1: 15, or 12 with a
shared boresight) and the check of its per-line table (the swing column)."""
from __future__ import annotations

from typing import Any, Mapping

import numpy as np

from swathflow.sensormodel.base import Parameter, ParameterSet


def default_parameters(sensor: Mapping[str, Any]) -> ParameterSet:
    """The 15 calibration parameters with their prior values and sigmas."""
    return ParameterSet((
        Parameter("u_gps", "m", (0.0, 0.0, 0.0), (1.0,) * 3,
                  description="GPS antenna to gimbal rotation centre, IMU body frame"),
        Parameter("u_sen", "m", (0.0, 0.0, 0.0), (1.0,) * 3,
                  description="gimbal rotation centre to projection centre, scan-head frame"),
        Parameter("opk_sen", "deg", (0.0, 0.0, 0.0), (1.0,) * 3,
                  description="sensor mounting in the scan head (omega, phi, kappa)"),
        Parameter("opk_pos_L", "deg", (0.0, 0.0, 0.0), (5.0,) * 3,
                  description="IMU boresight for left swings (omega, phi, kappa)"),
        Parameter("opk_pos_R", "deg", (0.0, 0.0, 0.0), (5.0,) * 3,
                  description="IMU boresight for right swings (omega, phi, kappa)"),
    ))

def check_lines(lines: Mapping[str, Any]) -> list:
    """The swing column in degrees, sweeping one way at a steady rate."""
    sw = np.asarray(lines.get("swing", ()), float)
    if sw.size < 3 or not np.isfinite(sw).all():
        return []
    span = float(np.ptp(sw))
    if np.abs(sw).max() < 1.6 and span > 0.02:
        return [(f"column swing: the angles look like radians ({sw.min():.3g} to "
                 f"{sw.max():.3g}; a swing of {np.degrees(span):.1f} deg in degrees)",
                 "write swing (and pitch_comp) in degrees: multiply by 57.2958")]
    d = np.diff(sw)
    step = float(np.median(np.abs(d)))
    back = np.sign(d) != np.sign(sw[-1] - sw[0])
    if step > 0 and (np.abs(d) > 20 * step + 0.05).any():
        i = int(np.argmax(np.abs(d)))
        return [(f"column swing jumps by {d[i]:.3g} deg between lines {i} and {i + 1} "
                 f"(typical step {step:.3g} deg): not one swing of the gimbal",
                 "one image per swing, the swing angle of every line in degrees")]
    if (back & (np.abs(d) > 5 * step + 1e-9)).any():
        return [("column swing reverses direction inside the image: not one swing",
                 "one image per swing (split the file at the turn-around)")]
    return []
