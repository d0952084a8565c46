"""Calibration strategies: how a sensor plugin's parameters are estimated for a mission.

The framework never branches on a sensor's name: it asks the plugin
(:meth:`SensorModel.calibration_strategy <swathflow.sensormodel.base.SensorModel.calibration_strategy>`)
and falls back to :data:`CONTROL_POINTS`, the generic control-point adjustment of
:mod:`swathflow.calibration.control`. A strategy is any object with
``calibrate(mission, options) -> result``; the result has ``write(out_dir)`` (returning the
written paths) and ``summary_lines()`` (what a person reads on the terminal).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Mapping, Protocol

from swathflow.calibration.control import DROPPED_REASON, calibrate
from swathflow.calibration.unknowns import CalibrationError
from swathflow.errors import SwathflowWarning


class CalibrationWarning(SwathflowWarning):
    """An observation a calibration could not use (dropped, with its id)."""


@dataclass(frozen=True)
class CalibrationOptions:
    """What a user chooses for a calibration; ``extra`` holds strategy-specific options
    (for instance a push-broom camera's ``method`` and ``max_rounds``)."""

    fixed: tuple[str, ...] = ()
    images: tuple[str, ...] | None = None      # control points of these images enter
    robust: bool = True
    vce: bool = True
    vce_priors: bool = False
    sigma_px: float = 1.0
    shared_boresight: bool = False             # one boresight for every swing direction
    drift: bool = False
    reference: str | None = None               # reference orthophoto: automatic control
    reference_dem: str | None = None           # heights of the reference's points
    max_rounds: int = 4                        # match / adjust rounds with a reference
    ties: bool = False                         # with a reference: tie points L <-> R swings
    extra: Mapping[str, Any] = field(default_factory=dict)


class CalibrationStrategy(Protocol):
    def calibrate(self, mission, options: CalibrationOptions) -> Any: ...


class ControlPointCalibration:
    """The default: every parameter of the plugin from control points, per-direction
    blocks (``name_L``/``name_R``) separated, priors as pseudo-observations."""

    def calibrate(self, mission, options: CalibrationOptions):
        if mission.gcps is None or len(mission.gcps) == 0:
            raise CalibrationError(f"{mission.path}: no control points (add [gcp] file = "
                                   f"\"gcp.csv\" to mission.toml)")
        models = {iid: mission.model(iid) for iid in mission.image_ids}
        return calibrate(models, mission.gcps, mission.priors,
                         shared_boresight=options.shared_boresight,
                         fixed=list(options.fixed), drift=options.drift,
                         robust=options.robust, vce=options.vce,
                         vce_priors=options.vce_priors, obs_sigma_px=options.sigma_px,
                         calibration_images=(list(options.images) if options.images
                                             else None))


CONTROL_POINTS = ControlPointCalibration()


def strategy_for(mission) -> CalibrationStrategy:
    """The calibration strategy of a mission's sensor plugin (or the default)."""
    return mission.sensor_class.calibration_strategy() or CONTROL_POINTS


class ReferenceCalibration:
    """Automatic control points from a reference orthophoto and DEM
    (:mod:`swathflow.calibration.autocontrol`), in the generic control-point adjustment;
    for every sensor plugin (it uses only the sensor-model interface)."""

    def __init__(self, ortho: str, dem: str | None = None, ties: bool = False):
        self.ortho, self.dem, self.ties = ortho, dem, bool(ties)

    def calibrate(self, mission, options: CalibrationOptions, progress=None):
        from swathflow.calibration.autocontrol import calibrate_mission_from_reference
        return calibrate_mission_from_reference(
            mission, self.ortho, self.dem, max_rounds=options.max_rounds, progress=progress,
            ties=options.ties or self.ties,
            shared_boresight=options.shared_boresight, fixed=list(options.fixed),
            drift=options.drift, robust=options.robust, vce=options.vce,
            vce_priors=options.vce_priors)


def reference_strategy(mission, options: CalibrationOptions) -> ReferenceCalibration | None:
    """The reference calibration when one is asked for (``options.reference``), or when the
    mission has no control points and a ``[reference]`` table."""
    from swathflow.calibration.autocontrol import reference_paths
    if options.reference:
        return ReferenceCalibration(options.reference, options.reference_dem)
    if mission.gcps is not None and len(mission.gcps):
        return None
    paths = reference_paths(mission)
    if not paths:
        return None
    ties = ((mission.config or {}).get("reference") or {}).get("ties", False)
    if not isinstance(ties, bool):
        raise CalibrationError(f"{mission.path}/mission.toml: [reference] ties must be true "
                               f"or false, got {ties!r}")
    return ReferenceCalibration(*paths, ties=ties)


def calibrate_mission(mission, options: CalibrationOptions | None = None, progress=None):
    """Calibrate a loaded mission: from a reference orthophoto when one is given (or the
    mission has no control points and a ``[reference]``), else with its sensor plugin's
    strategy."""
    options = options or CalibrationOptions()
    ref = reference_strategy(mission, options)
    if ref is not None:
        result = ref.calibrate(mission, options, progress)
    else:
        result = strategy_for(mission).calibrate(mission, options)
    return estimated(result, mission)


def estimated(result, mission=None):
    """``result`` when it estimated something; a warning per observation it dropped (its
    point and image named). A calibration from no usable observation (its sigma0 not a
    number: every point unprojectable, e.g. heights in the wrong unit or 30 km off) is an
    error, never the priors written as a calibration."""
    import math
    import warnings
    dropped = _dropped(result)
    for gcp, image in dropped[:50]:
        warnings.warn(CalibrationWarning(
            f"control point {gcp} in image {image}: not used ({DROPPED_REASON})"),
            stacklevel=3)
    if len(dropped) > 50:
        warnings.warn(CalibrationWarning(f"... and {len(dropped) - 50} more control point "
                                         f"observations not used"), stacklevel=3)
    sigma0 = getattr(result, "sigma0", None)
    try:
        ok = sigma0 is None or math.isfinite(float(sigma0))
    except (TypeError, ValueError):
        ok = True
    if not ok:
        where = f"{mission.path}: " if mission is not None else ""
        raise CalibrationError(
            f"{where}nothing estimated: no observation was usable"
            + (f" ({len(dropped)} control point observations do not project into their "
               f"images)" if dropped else "")
            + "; check the control points' coordinates, their height unit and vertical "
              "datum ([gcp] crs, [terrain] vertical), and the priors")
    return result


def _dropped(result) -> list[tuple[str, str]]:
    """(point id, image id) of the control observations a result could not compute."""
    inner = getattr(result, "result", result)       # a reference calibration wraps one
    res = getattr(inner, "residuals", None)
    if res is None:
        return []
    try:
        after = res[(res["stage"] == "after") & (res["role"] != "check")]
        bad = after[after["x"].isna() | after["y"].isna()]
        return [(str(g), str(i)) for g, i in zip(bad["gcp_id"], bad["image_id"])]
    except (TypeError, KeyError, AttributeError):
        return []
