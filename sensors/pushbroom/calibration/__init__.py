"""Push-broom (three-line camera) calibration: docs/references.md section 2, docs/geometry.md's
push-broom section.

Unknowns: the lever arm ``u_gps``, the boresight ``opk_cam``, the per-segment cubic APs
``ax_<view>_<i>`` / ``bx_<view>_<i>`` of every CCD line, the LIM orientation-fix corrections
``d_ned_<k>`` / ``d_opk_<k>`` (every calibration parameter carries its prior as a
pseudo-observation), and the ground coordinates (ECEF) of every tie point. Observations: the
image coordinates of control points (known ground) and of tie points (ground unknown),
observed minus computed, every observation of every image in one bulk projection
(:meth:`PushbroomModel.projector <swathflow.sensors.pushbroom.PushbroomModel.projector>`:
compiled, parameters as a vector, analytic partials). The AP continuity (C0) and smoothness
(C1) conditions at every segment boundary are hard equality constraints
(:func:`swathflow.sensors.pushbroom.continuity_matrix`), solved exactly.

The Jacobian is sparse (a tie point's rows touch its own three coordinates and the
parameters of one image, and an image depends only on the fixes around its time), so the
generic engine :func:`swathflow.adjustment.solve` eliminates the tie coordinates point by
point (Schur complement) and solves the reduced system over the parameters.
Internally every parameter is scaled by its prior sigma (AP coefficients span 12 orders of
magnitude otherwise).

Two solutions: ``joint`` (everything at once) and the paper's iterative ``two-step``
scheme (exterior: lever arm, boresight and fix corrections with the APs held; then
interior: the APs with the exterior held; repeated, with Anderson acceleration, until the
joint Gauss-Newton step at the current values is below 0.1 joint sigma; tie coordinates
are free in both steps). Its covariance is the joint one at its solution (the per-step
covariances are conditional on the other block, hence too small).

Modules: :mod:`.ties` (tie-point table, ray intersection), :mod:`.problem` (unknowns,
observations and C0/C1 constraints as one adjustment problem), :mod:`.solve` (joint and
two-step), :mod:`.result` (the result, its file and report), :mod:`.run`
(:func:`calibrate_pushbroom` and the plugin's calibration strategy).
"""
from swathflow.sensors.pushbroom.calibration.problem import TIE_PRIOR_M
from swathflow.sensors.pushbroom.calibration.result import PushbroomCalibrationResult
from swathflow.sensors.pushbroom.calibration.run import (METHODS, STRATEGY, PushbroomCalibration,
                                                         calibrate_pushbroom)
from swathflow.sensors.pushbroom.calibration.solve import solve_joint, solve_two_step
from swathflow.sensors.pushbroom.calibration.ties import (TIE_COLUMNS, intersect_rays,
                                                          mission_ties, read_ties)

__all__ = ["METHODS", "STRATEGY", "TIE_COLUMNS", "TIE_PRIOR_M", "PushbroomCalibration",
           "PushbroomCalibrationResult", "calibrate_pushbroom", "intersect_rays",
           "mission_ties", "read_ties", "solve_joint", "solve_two_step"]
