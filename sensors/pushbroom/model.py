"""The push-broom line camera of the GFXJ paper (docs/references.md section 2), exactly as
docs/geometry.md's push-broom section: the geometry (configuration, parameters, the camera
state along the trajectory, rays).

One CCD line along the sensor y axis, made of segments; every image line is one read-out at
one instant. A three-line camera (forward, nadir, backward) is three such lines sharing the
trajectory, the lever arm, the boresight and the orientation fixes: one model per line image,
the line chosen by the image attribute ``view`` (see docs/mission-format-pushbroom.md).

The viewing angles per element and the additional parameters (APs) are in
:mod:`~swathflow.sensors.pushbroom.viewing`, ground to image in
:mod:`~swathflow.sensors.pushbroom.solve`, the partial derivatives in
:mod:`~swathflow.sensors.pushbroom.partials`, the bulk projection of every observation of
every image for the adjustment (:meth:`PushbroomModel.projector`) in
:mod:`~swathflow.sensors.pushbroom.projection` and :mod:`~swathflow.sensors.pushbroom.bulk`.
The LIM orientation-fix model corrects position
and attitude by ``d_ned`` (m) and ``d_opk`` (deg) interpolated linearly in time between
fixes (held constant outside them).
"""
from __future__ import annotations

from typing import Any, Mapping

import numpy as np

from swathflow.errors import FormatError
from swathflow.geometry.rotations import T, apply, r_en, r_nb, r_opk
from swathflow.sensormodel.base import Parameter, ParameterSet, SensorModel
from swathflow.sensors.pushbroom.example import example_image, example_sensor, example_trajectory
from swathflow.sensors.pushbroom.frames import compose
from swathflow.sensors.pushbroom.partials import Partials
from swathflow.sensors.pushbroom.solve import GroundSolver
from swathflow.sensors.pushbroom.viewing import (AP_SIGMA, AP_STEP, THREE_LINE_VIEWS, ap_name,
                                                 check_fixes, check_view, continuity_matrix,
                                                 continuity_residuals, fix_times,
                                                 tangent_table, views)

__all__ = ["PushbroomModel", "continuity_matrix", "continuity_residuals", "example_sensor",
           "example_trajectory", "views", "ap_name", "fix_times", "THREE_LINE_VIEWS",
           "AP_SIGMA", "AP_STEP"]


class PushbroomModel(GroundSolver, Partials, SensorModel):
    """Push-broom line camera (GFXJ three-line camera): APs per CCD segment, LIM fixes."""

    name = "pushbroom"
    kind = "push-broom"
    required_keys = ("n_elements",)
    #: columns the per-line table (images/<id>.lines.csv) must have besides ``line``
    line_columns = ("time",)

    @classmethod
    def calibration_strategy(cls):
        from swathflow.sensors.pushbroom.calibration import STRATEGY
        return STRATEGY

    @classmethod
    def projector(cls, models):
        """Bulk projection for the adjustment: one compiled call over every observation of
        every image, analytic partials (:mod:`~swathflow.sensors.pushbroom.projection`)."""
        from swathflow.sensors.pushbroom.projection import PushbroomProjector
        return PushbroomProjector(models)

    @classmethod
    def simulator(cls):
        from swathflow.sensors.pushbroom import simulate
        return simulate

    @classmethod
    def check_config(cls, sensor: Mapping[str, Any]) -> list[str]:
        problems = super().check_config(sensor)
        if problems:
            return problems
        if "views" in sensor and (not isinstance(sensor["views"], Mapping)
                                  or not sensor["views"]):
            return ["views must be a table of line name -> psi_x0_deg (or a table of keys)"]
        for name, cfg in views(sensor).items():
            problems += check_view(name, cfg)
        return problems + check_fixes(sensor)

    @classmethod
    def default_parameters(cls, sensor: Mapping[str, Any]) -> ParameterSet:
        blocks = [
            Parameter("u_gps", "m", (0.0, 0.0, 0.0), (1.0,) * 3,
                      description="GPS antenna to projection centre, IMU body frame"),
            Parameter("opk_cam", "deg", (0.0, 0.0, 0.0), (5.0,) * 3,
                      description="camera boresight (omega, phi, kappa), body to camera"),
        ]
        for view, cfg in views(sensor).items():
            nseg = len(cfg.get("segments", [0]))
            for kind, what in (("ax", "tan_psi_x (along track)"),
                               ("bx", "tan_psi_y (across track)")):
                coef = np.asarray(cfg.get(kind, np.zeros((nseg, 4))), float)
                for i in range(nseg):
                    blocks.append(Parameter(
                        ap_name(kind, view, i), "", tuple(coef[i]), AP_SIGMA,
                        description=f"cubic AP of {what}, segment {i}"
                                    + (f" of the {view} line" if view else "")))
        fx = sensor.get("fixes") or {}
        t = fix_times(sensor)
        d_ned = np.asarray(fx.get("d_ned", np.zeros((t.size, 3))), float).reshape(-1, 3)
        d_opk = np.asarray(fx.get("d_opk", np.zeros((t.size, 3))), float).reshape(-1, 3)
        for k in range(t.size):
            blocks.append(Parameter(f"d_ned_{k}", "m", tuple(d_ned[k]), (0.5,) * 3,
                                    description=f"position correction (N, E, D) at fix {k}"))
            blocks.append(Parameter(f"d_opk_{k}", "deg", tuple(d_opk[k]), (0.02,) * 3,
                                    description=f"attitude correction (omega, phi, kappa) "
                                                f"at fix {k}"))
        return ParameterSet(tuple(blocks))

    # --- set-up ---------------------------------------------------------------------------
    def _setup(self) -> None:
        s, img = self._sensor, self._image
        allviews = views(s)
        view = img.get("view")
        if view is None:
            if list(allviews) != [""]:
                raise FormatError(f"pushbroom image {img.get('image_id', '')!r}: the camera "
                                  f"has lines {', '.join(allviews)}; set view = one of them")
            view = ""
        view = str(view)
        if view not in allviews:
            raise FormatError(f"pushbroom image {img.get('image_id', '')!r}: unknown view "
                              f"{view!r}; the [sensor] views are {', '.join(allviews)}")
        cfg = dict(allviews[view])
        if "psi_x0_deg" in img:
            cfg["psi_x0_deg"] = float(img["psi_x0_deg"])
        self._view = view
        if "time" not in self._lines:
            raise FormatError("pushbroom line table: missing column 'time'")
        self._nel = int(cfg["n_elements"])
        self._seg = np.asarray(cfg.get("segments", [0]), float)
        p = self._params
        self._ax = np.array([p[ap_name("ax", view, i)] for i in range(self._seg.size)])
        self._bx = np.array([p[ap_name("bx", view, i)] for i in range(self._seg.size)])
        if "tan_psi_x" in cfg:
            self._tab = (np.asarray(cfg["tan_psi_x"], float), np.asarray(cfg["tan_psi_y"], float))
        else:
            self._tab = None
            self._tpx0 = float(np.tan(np.radians(float(cfg.get("psi_x0_deg", 0.0)))))
            self._k = float(cfg["pixel_pitch"]) / float(cfg["focal_length"])
            self._sc = float(cfg["s_c"])
        self._u_gps = p["u_gps"]
        self._R_bs = r_opk(*np.radians(p["opk_cam"])) @ T
        self._ft = fix_times(s)
        if self._ft.size:
            self._d_ned = np.array([p[f"d_ned_{k}"] for k in range(self._ft.size)])
            self._d_opk = np.array([p[f"d_opk_{k}"] for k in range(self._ft.size)])
        self._ltime = self._lines["time"]
        self._lidx = np.arange(self.n_lines, dtype=float)
        if self.n_lines > 1 and not np.all(np.diff(self._ltime) > 0):
            raise FormatError(f"pushbroom image {img.get('image_id', '')!r}: line times must "
                              f"increase strictly with the line index")
        self._coef_t = self.tangent_coefficients(self._ax, self._bx)   # (8, n_elements)
        self._setup_knots()
        # which parameters this image depends on (others have zero partials)
        self._relevant = self._relevant_mask()

    def _setup_knots(self) -> None:
        """Exact states at knots: every line time plus every POS epoch and fix time inside
        the image. Between knots position and angles are linear in time, so linear
        interpolation of the state is off only by the rotation's curvature (estimated here
        in pixels at the knot mid-points; the solve adds exact steps when it matters)."""
        t = self._ltime
        if t.size < 2:
            self._interp_px = np.inf
            return
        tr = self._trajectory.time
        extra = [tr[(tr > t[0]) & (tr < t[-1])], self._ft[(self._ft > t[0]) & (self._ft < t[-1])]]
        extra = np.concatenate(extra)
        xl = np.interp(extra, t, self._lidx)
        extra = extra[np.abs(xl - np.round(xl)) > 1e-3]   # not (almost) on a line time
        kt = np.unique(np.concatenate([t, extra]))
        self._kline = np.interp(kt, t, self._lidx)
        self._dline = np.diff(self._kline)
        C, R = self._state_t(kt)
        self._Mt = np.ascontiguousarray(np.swapaxes(R, -1, -2))       # R_ES^T per knot
        self._p = np.einsum("kij,kj->ki", self._Mt, C)                 # R^T C
        dR, dC = np.diff(R, axis=0), np.diff(C, axis=0)
        self._cq = -np.einsum("kji,kj->ki", dR, dC)                    # w^2 term
        at_line = np.searchsorted(kt, t)                                # knots of the lines
        self._line_knot = at_line
        self._tpx_mid = self._mid_tpx()
        self._nvec = R[at_line] @ np.array([1.0, 0.0, self._tpx_mid])   # bracket planes
        self._dvec = np.einsum("ij,ij->i", self._nvec, C[at_line])
        cm, rm = self._state_t(0.5 * (kt[1:] + kt[:-1]))
        ang = np.abs(rm - 0.5 * (R[1:] + R[:-1])).max()
        pos = np.abs(cm - 0.5 * (C[1:] + C[:-1])).max() / 100.0   # at >= 100 m range
        self._interp_px = float(max(ang, pos) / self._pixel_angle())

    def tangent_coefficients(self, ax, bx) -> np.ndarray:
        """The viewing tangents' cubic coefficients ``(8, n_elements)`` of this image's CCD
        line with the APs ``ax``, ``bx`` ``(segments, 4)`` (see
        :func:`~swathflow.sensors.pushbroom.viewing.tangent_table`)."""
        ax = np.asarray(ax, float).reshape(self._seg.size, 4)
        bx = np.asarray(bx, float).reshape(self._seg.size, 4)
        if self._tab is None:
            out = tangent_table(self._nel, self._seg, ax, bx,
                                nominal=(self._tpx0, self._k, self._sc))
        else:
            out = tangent_table(self._nel, self._seg, ax, bx, table=self._tab)
        return np.ascontiguousarray(out.T)

    def _pixel_angle(self) -> float:
        if self._tab is None:
            return self._k
        return float(np.median(np.abs(np.diff(self._tab[1]))))

    def _relevant_mask(self) -> np.ndarray:
        mask = []
        t = self._ltime
        for b in self._params.blocks:
            n = b.name
            if n.startswith(("ax_", "bx_")):
                ok = n.rsplit("_", 1)[0] == ap_name(n[:2], self._view, 0).rsplit("_", 1)[0]
            elif n.startswith(("d_ned_", "d_opk_")):
                k = int(n.rsplit("_", 1)[1])
                hat = np.interp(t, self._ft, np.eye(self._ft.size)[k])
                ok = bool(np.any(hat > 0))
            else:
                ok = True
            mask += [ok] * b.size
        return np.array(mask, bool)

    @property
    def segments(self) -> np.ndarray:
        """The first element of each CCD segment of this image's line."""
        return self._seg.copy()

    @property
    def fix_times(self) -> np.ndarray:
        """The times of the orientation fixes (s, POS time scale)."""
        return self._ft.copy()

    @property
    def view(self) -> str:
        """The CCD line this image belongs to (``""`` for a one-line camera)."""
        return self._view

    # --- exact evaluation ----------------------------------------------------------------
    def _corrections(self, t) -> tuple[np.ndarray, np.ndarray]:
        """LIM fix corrections (d_ned m, d_opk rad) interpolated to times ``t``."""
        dn = np.stack([np.interp(t, self._ft, self._d_ned[:, i]) for i in range(3)], axis=-1)
        do = np.stack([np.interp(t, self._ft, self._d_opk[:, i]) for i in range(3)], axis=-1)
        return dn, np.radians(do)

    def _state_t(self, t) -> tuple[np.ndarray, np.ndarray]:
        """Projection centre C (ECEF) and R_ES (camera S to ECEF) at times ``t``."""
        return compose(*self._frames(t), self._u_gps, self._R_bs)

    def _frames(self, t):
        """The parameter-free part of the state at times ``t`` plus the fix corrections:
        fix-corrected antenna position (ECEF), R_EN, R_NB and the fix attitude correction
        (rad; None without fixes)."""
        pos = self._trajectory.interpolate(t)
        ren = r_en(np.radians(pos["lat"]), np.radians(pos["lon"]))
        rnb = r_nb(np.radians(pos["roll"]), np.radians(pos["pitch"]),
                   np.radians(pos["heading"]))
        x, do = pos["ecef"], None
        if self._ft.size:
            dn, do = self._corrections(t)
            x = x + apply(ren, dn)
        return x, ren, rnb, do

    def _line_time(self, line) -> np.ndarray:
        return np.interp(line, self._lidx, self._ltime)

    def view_tangents(self, element):
        """``tan_psi_x``, ``tan_psi_y`` of (continuous) elements and their derivatives
        along the element axis: four arrays."""
        s = np.asarray(element, float)
        i = np.clip(np.floor(np.nan_to_num(s)), 0, self._nel - 1).astype(np.intp)
        u = s - i
        c0, c1, c2, c3, c4, c5, c6, c7 = np.take(self._coef_t, i, axis=1)
        tx = c0 + u * (c1 + u * (c2 + u * c3))
        ty = c4 + u * (c5 + u * (c6 + u * c7))
        dtx = c1 + u * (2 * c2 + 3 * u * c3)
        dty = c5 + u * (2 * c6 + 3 * u * c7)
        return tx, ty, dtx, dty

    def _element_guess(self, q) -> np.ndarray:
        """First guess of the element whose tan_psi_y is ``q`` (inverse of the ideal part)."""
        if self._tab is None:
            return self._sc + q / self._k
        ty = self._tab[1]
        slope = (ty[-1] - ty[0]) / (ty.size - 1)
        return (q - ty[0]) / slope

    def _mid_tpx(self) -> float:
        return float(self.view_tangents(0.5 * (self._nel - 1))[0])

    # --- interface ------------------------------------------------------------------------
    def ray(self, image):
        """Compiled (:func:`~swathflow.sensors.pushbroom.rays.rays`); the numpy path where
        the kernel declines (a line off the POS or not finite: the numpy path reports it)."""
        from swathflow.geometry.navkernel import epochs, pos_table
        from swathflow.sensors.pushbroom.rays import rays
        image = np.asarray(image, float)
        if self.n_lines < 2:
            return self._ray_numpy(image)
        flat = np.ascontiguousarray(image.reshape(-1, 2))
        sh = self._shared
        if "nav" not in sh:
            sh["nav"] = pos_table(self._trajectory)
            lt = np.ascontiguousarray(self._ltime, dtype=float)
            sh["line_epochs"] = (lt, epochs(sh["nav"][0], lt))
        nf = self._ft.size
        fixes = (np.asarray(self._ft, float),
                 np.asarray(self._d_ned if nf else np.zeros((0, 3)), float).reshape(-1, 3),
                 np.radians(np.asarray(self._d_opk if nf else np.zeros((0, 3)),
                                       float)).reshape(-1, 3))
        cam = (np.ascontiguousarray(self._R_bs), np.asarray(self._u_gps, float), self._coef_t)
        c, d = np.empty((flat.shape[0], 3)), np.empty((flat.shape[0], 3))
        if rays(flat, sh["line_epochs"], sh["nav"], fixes, cam, c, d):
            shape = image.shape[:-1] + (3,)
            return c.reshape(shape), d.reshape(shape)
        return self._ray_numpy(image)

    def _ray_numpy(self, image):
        """The numpy path of :meth:`ray` (reference for the compiled one)."""
        image = np.asarray(image, float)
        c, r = self._state_t(self._line_time(image[..., 0]))
        tx, ty, _, _ = self.view_tangents(image[..., 1])
        d = apply(r, np.stack([tx, ty, -np.ones_like(tx)], axis=-1))
        return c, d / np.linalg.norm(d, axis=-1, keepdims=True)

    def image_time(self, image) -> np.ndarray:
        return self._line_time(np.asarray(image, float)[..., 0])

    @property
    def n_elements(self) -> int:
        return self._nel

    def sensor_position(self, time) -> np.ndarray:
        return self._state_t(np.asarray(time, float))[0]

    def sensor_attitude(self, time) -> np.ndarray:
        return self._state_t(np.asarray(time, float))[1]

    def ground_to_image(self, ground, clip: bool = True) -> np.ndarray:
        ground = np.asarray(ground, float)
        shape = ground.shape[:-1]
        line, elem, _ = self._solve(ground.reshape(-1, 3))
        if clip:
            off = (elem < -0.5) | (elem > self._nel - 0.5)
            line = np.where(off, np.nan, line)
            elem = np.where(off, np.nan, elem)
        return np.stack([line, elem], axis=-1).reshape(shape + (2,))

    # --- AP constraints (calibration) -------------------------------------------------------
    def continuity_residuals(self, params: ParameterSet | None = None) -> np.ndarray:
        """C0/C1 residuals of this camera's AP polynomials (see :func:`continuity_residuals`)."""
        return continuity_residuals(self._sensor, params or self._params)

    @classmethod
    def example_model(cls, view: str = "nadir", n_lines: int = 600) -> "PushbroomModel":
        """A realistic three-line camera image (for contract tests and examples): 3072
        elements in three segments, 10 um pixels, f = 0.1 m, 2000 m above ground at 60 m/s
        with a gently wobbling attitude, small APs, three orientation fixes."""
        return example_image(cls, view, n_lines)
