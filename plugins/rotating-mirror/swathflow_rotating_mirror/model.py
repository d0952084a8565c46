"""A rotating-mirror whisk-broom scanner (docs/references.md section 3, the instrument class of the
fast-rectification paper).

One detector looks at a mirror that turns about the aircraft's forward axis. Each image row
is one sweep of the mirror across track; the pixel index gives the scan angle and the time:

    theta(line, element) = scan_start[line] + element * ifov + scan_offset   (positive: left)
    t(line, element) = time[line] + element * dwell

``time[line]`` is the time of the row's first pixel (per-line table column ``time``) and
``scan_start[line]`` the mirror angle of that pixel read from the shaft encoder (the
plugin's own per-line column ``scan_start``, degrees from nadir; the sampling clock starts a
row at an index pulse, so the start angle wanders a little as the mirror's speed is
regulated); both
are interpolated linearly in the line. ``dwell`` is the time per pixel. Without a
``scan_start`` column (a model built in code) every row starts at the nominal
``-center * ifov``. Frames follow
docs/geometry.md: B is the IMU body frame (x forward, y right, z down), M the scanner's own
frame (nominally B; the mounting boresight ``opk_mount`` rotates B into M). At scan angle
theta the line of sight in M is ``d = (0, -sin theta, cos theta)`` and the ray is

    X(lam) = X_ant(t) + R_EN R_NB ( u_gps + lam R_BM d ),   R_BM = R_opk(opk_mount).

Ground to image: a ground point G is seen when it lies in the scan plane (the plane through
the mirror centre normal to M's x axis), at the time t* when ``w_x(t*) = 0`` with
``w(t) = R_BM^T (R_NB^T R_EN^T (G - X_ant(t)) - u_gps)``. That time fixes both image
coordinates at once: the scan angle ``atan2(-w_y, w_z)`` at t*, then line and element from
``time[line] + element * dwell = t*`` and ``scan_start[line] + element * ifov + scan_offset =
theta`` (a fixed-point iteration: the start angle changes little between rows). Solving for
t* is one scalar crossing problem, so the shared line solver (bracket over row start times,
secant refinement) does it.
The POS must cover the last pixel of the last row.
"""
from __future__ import annotations

from typing import Any, Mapping

import numpy as np

from swathflow.errors import FormatError
from swathflow.geometry.linesolve import bracket_lines, secant_lines
from swathflow.geometry.rotations import apply, apply_t, r_en, r_nb, r_opk
from swathflow.sensormodel.base import Parameter, ParameterSet, SensorModel


class RotatingMirrorModel(SensorModel):
    """Rotating-mirror whisk-broom scanner: per-pixel time, 7 parameters (example plugin)."""

    name = "rotating-mirror"
    kind = "whisk-broom"
    required_keys = ("n_elements", "ifov_deg", "dwell")
    #: columns the per-line table (images/<id>.lines.csv) must have besides ``line``:
    #: the row's first-pixel time and its own column, the encoder's scan-start angle (deg)
    line_columns = ("time", "scan_start")
    #: the largest believable |scan_start| (deg from nadir): beyond it the row would start
    #: looking at the horizon
    max_scan_start_deg: float = 80.0

    # --- plugin hooks ---------------------------------------------------------------------
    @classmethod
    def check_lines(cls, lines: Mapping[str, np.ndarray]) -> list[str]:
        """The scan-start angles must be physical: within +-80 degrees of nadir (a row that
        starts beyond that looks at the horizon; degrees, not radians or encoder counts)."""
        a = np.asarray(lines.get("scan_start", []), float)
        bad = np.flatnonzero(np.abs(a) > cls.max_scan_start_deg)
        if not bad.size:
            return []
        rows = ", ".join(str(int(i) + 2) for i in bad[:5]) + (", ..." if bad.size > 5 else "")
        return [f"column scan_start, file row(s) {rows}: {bad.size} scan-start angle(s) "
                f"beyond +-{cls.max_scan_start_deg:g} deg from nadir (e.g. {a[bad[0]]:g}); "
                f"give the mirror angle of each row's first pixel in degrees"]

    @classmethod
    def simulator(cls):
        """The plugin's mission simulator (presets ``rotating-mirror``,
        ``rotating-mirror-demo``), building its true images with this class."""
        # imported here: pandas and the simulation's writers stay out of loading the plugin
        from swathflow_rotating_mirror.simulate import Simulator
        return Simulator(cls)

    # --- configuration and parameters -----------------------------------------------------
    @classmethod
    def check_config(cls, sensor: Mapping[str, Any]) -> list[str]:
        problems = super().check_config(sensor)
        for k in ("ifov_deg", "n_elements"):
            if k in sensor and not float(sensor[k]) > 0:
                problems.append(f"{k} must be positive, got {sensor[k]!r}")
        if "dwell" in sensor and not float(sensor["dwell"]) >= 0:
            problems.append(f"dwell (s per pixel) must be >= 0, got {sensor['dwell']!r}")
        return problems

    @classmethod
    def default_parameters(cls, sensor: Mapping[str, Any]) -> ParameterSet:
        return ParameterSet((
            Parameter("u_gps", "m", (0.0, 0.0, 0.0), (1.0,) * 3,
                      description="GPS antenna to the mirror centre, IMU body frame"),
            Parameter("opk_mount", "deg", (0.0, 0.0, 0.0), (2.0,) * 3,
                      description="scanner mounting boresight (omega, phi, kappa)"),
            Parameter("scan_offset", "deg", (0.0,), (0.5,),
                      description="scan-angle encoder offset"),
        ))

    def _setup(self) -> None:
        if "time" not in self._lines:
            raise FormatError("rotating-mirror line table: missing column 'time'")
        t = self._lines["time"]
        if t.size < 2 or not np.all(np.diff(t) > 0):
            raise FormatError("rotating-mirror line table: 'time' must increase strictly "
                              "(at least two rows)")
        s, p = self._sensor, self._params
        self._ifov = np.radians(float(s["ifov_deg"]))
        self._dwell = float(s["dwell"])
        self._center = float(s.get("center", (self.n_elements - 1) / 2.0))
        self._offset = np.radians(float(p["scan_offset"][0]))
        if "scan_start" in self._lines:
            self._start = np.radians(np.asarray(self._lines["scan_start"], float))
        else:
            self._start = np.full(self.n_lines, -self._center * self._ifov)
        self._u_gps = p["u_gps"]
        self._R_bm = r_opk(*np.radians(p["opk_mount"]))
        self._rows = np.arange(self.n_lines, dtype=float)
        # bracketing knots: every row start, then more at the last row spacing until the
        # last pixel of the last row (its sweep ends after the last row starts)
        step = t[-1] - t[-2]
        sweep = (self.n_elements - 1) * self._dwell
        extra = t[-1] + np.append(step * np.arange(1, int(np.ceil(sweep / step))), sweep)
        self._knots = np.concatenate([t, extra[extra > t[-1]]])
        self._kidx = np.arange(self._knots.size, dtype=float)
        # mirror centre and scan-plane normal at every knot
        c, r = self._state(self._knots)
        self._c_knots, self._n_knots = c, r[..., :, 0]

    # --- geometry at a time ---------------------------------------------------------------------
    def _state(self, t) -> tuple[np.ndarray, np.ndarray]:
        """Mirror centre (ECEF) and R_EM (scanner frame M to ECEF) at times ``t``."""
        pos = self._trajectory.interpolate(t)
        reb = r_en(np.radians(pos["lat"]), np.radians(pos["lon"])) @ r_nb(
            np.radians(pos["roll"]), np.radians(pos["pitch"]), np.radians(pos["heading"]))
        return pos["ecef"] + apply(reb, self._u_gps), reb @ self._R_bm

    def _row_time(self, line) -> np.ndarray:
        return np.interp(line, self._rows, self._lines["time"])

    def _row_start(self, line) -> np.ndarray:
        return np.interp(line, self._rows, self._start)

    def scan_angle(self, image) -> np.ndarray:
        """Scan angle (radians, positive to the left) of (continuous) image points."""
        image = np.asarray(image, float)
        return self._row_start(image[..., 0]) + image[..., 1] * self._ifov + self._offset

    # --- the SensorModel interface ---------------------------------------------------------------
    def image_time(self, image) -> np.ndarray:
        image = np.asarray(image, float)
        return self._row_time(image[..., 0]) + image[..., 1] * self._dwell

    def ray(self, image):
        """Compiled (``kernel.rays``); the numpy path where the kernel declines (a line off
        the POS or not finite: the numpy path reports it)."""
        from swathflow.geometry.navkernel import epochs, pos_table
        from swathflow_rotating_mirror import kernel
        image = np.asarray(image, float)
        flat = np.ascontiguousarray(image.reshape(-1, 2))
        sh = self._shared
        if "nav" not in sh:
            sh["nav"] = pos_table(self._trajectory)
            rtime = np.ascontiguousarray(self._lines["time"], dtype=float)
            sh["rows"] = (rtime, np.ascontiguousarray(self._start, dtype=float),
                          epochs(sh["nav"][0], rtime))
        scan = (float(self._ifov), float(self._dwell), float(self._offset),
                np.ascontiguousarray(self._R_bm), np.asarray(self._u_gps, float))
        c, d = np.empty((flat.shape[0], 3)), np.empty((flat.shape[0], 3))
        if kernel.rays(flat, sh["rows"], sh["nav"], scan, c, d):
            shape = image.shape[:-1] + (3,)
            return c.reshape(shape), d.reshape(shape)
        return self._ray_numpy(image)

    def _ray_numpy(self, image):
        """The numpy path of :meth:`ray` (reference for the compiled one)."""
        image = np.asarray(image, float)
        c, r = self._state(self.image_time(image))
        th = self.scan_angle(image)
        d = np.stack([np.zeros_like(th), -np.sin(th), np.cos(th)], axis=-1)
        return c, apply(r, d)

    def sensor_position(self, time) -> np.ndarray:
        return self._state(np.asarray(time, float))[0]

    def sensor_attitude(self, time) -> np.ndarray:
        return self._state(np.asarray(time, float))[1]

    def ground_to_image(self, ground, clip: bool = True) -> np.ndarray:
        ground = np.asarray(ground, float)
        shape = ground.shape[:-1]
        g = ground.reshape(-1, 3)
        out = np.full((g.shape[0], 2), np.nan)
        if g.shape[0] == 0:
            return out.reshape(shape + (2,))
        ck, nk = self._c_knots, self._n_knots

        # 1. the scan-plane crossing time, in the continuous knot coordinate u
        def f_knots(i, j):
            return np.einsum("ij,ij->i", nk[j], g[i] - ck[j])

        j, fj, fj1, found = bracket_lines(f_knots, g.shape[0], self._knots.size)
        k = np.flatnonzero(found)
        if k.size == 0:
            return out.reshape(shape + (2,))
        gk = g[k]

        def knot_time(u):
            return np.interp(u, self._kidx, self._knots)

        def f_exact(i, u):
            c, r = self._state(knot_time(u))
            return np.einsum("ij,ij->i", r[..., :, 0], gk[i] - c)

        u = secant_lines(f_exact, j[k], fj[k], fj1[k], tol=1e-10)
        t_star = knot_time(u)
        # 2. the scan angle at that time, 3. line and element from the pixel time and angle
        c, r = self._state(t_star)
        w = apply_t(r, gk - c)
        line, elem = self._line_element(t_star, np.arctan2(-w[:, 1], w[:, 2]))
        ok = (w[:, 2] > 0) & np.isfinite(line)
        if clip:
            ok &= (elem >= -0.5) & (elem <= self.n_elements - 0.5)
        out[k, 0] = np.where(ok, line, np.nan)
        out[k, 1] = np.where(ok, elem, np.nan)
        return out.reshape(shape + (2,))

    def _line_element(self, t_star, theta, max_iter: int = 20):
        """Line and element with ``time[line] + element * dwell = t_star`` and
        ``scan_start[line] + element * ifov + scan_offset = theta``, by fixed-point iteration
        from the row seen at ``t_star`` (exact in one step with a constant start angle or
        zero dwell; each step shrinks the error by dwell * d(start)/d(line) / (ifov *
        d(time)/d(line)), about 1e-6 for a real scanner). NaN outside the image."""
        lt = self._lines["time"]
        line = np.interp(t_star, lt, self._rows, left=np.nan, right=np.nan)
        line = np.where(np.isfinite(line), line, np.clip(
            np.interp(t_star, lt, self._rows), 0, self.n_lines - 1))
        for _ in range(max_iter):
            elem = (theta - self._offset - self._row_start(line)) / self._ifov
            new = np.interp(t_star - elem * self._dwell, lt, self._rows, left=np.nan,
                            right=np.nan)
            done = np.nanmax(np.abs(new - line), initial=0.0) < 1e-10
            line = new
            if done:
                break
        elem = (theta - self._offset - self._row_start(np.nan_to_num(line))) / self._ifov
        return line, np.where(np.isfinite(line), elem, np.nan)

    # --- an instance for the contract suite and the docs ---------------------------------------
    @classmethod
    def example_model(cls) -> "RotatingMirrorModel":
        """The scanner of the fast-rectification paper, roughly: 30 degree field of view in
        600 pixels of 0.05 degree, 650 m above the ground at 60 m/s, one mirror turn per row
        (the sweep uses 30 of 360 degrees, so each pixel dwells 1/12 of a row's time / 600),
        with wandering encoder start angles."""
        from swathflow.testing import straight_trajectory
        rows_per_s = 105.0
        traj, lines = straight_trajectory(n_lines=400, line_rate=rows_per_s, height=700.0)
        sensor = {"n_elements": 600, "ifov_deg": 0.05,
                  "dwell": (1.0 / rows_per_s) * (0.05 / 360.0)}
        # encoder start angles: nominal plus a slow wander of 0.04 deg (0.8 pixel)
        rows = np.arange(400)
        lines = {**lines, "scan_start": -299.5 * 0.05 + 0.04 * np.sin(rows / 37.0)}
        return cls.build(sensor, lines, traj,
                         {"u_gps": [0.3, -0.1, 0.8], "opk_mount": [0.2, -0.4, 0.3],
                          "scan_offset": [0.05]}, image_id="example", strip=1)
