"""The pendulum (left/right swinging) infrared scanner of the calibration paper
(docs/references.md section 1), exactly as docs/geometry.md's pendulum section.

A TDI detector line along the sensor x axis (the flight direction) inside a gimbal that
swings the camera across track; each image is one swing, each line one instant.
"""
from __future__ import annotations

from typing import Any, Mapping

import numpy as np

from swathflow.errors import FormatError
from swathflow.geometry.navkernel import pos_table
from swathflow.geometry.planesolve import coarse_grid
from swathflow.geometry.rotations import T, apply, r_en, r_nb, r_opk, r_ph

from swathflow.sensormodel.base import CHUNK, ParameterSet, SensorModel
from swathflow.sensors.pendulum import kernel, parameters
from swathflow.sensors.pendulum.crossing import ROUGH_LINE, Crossing


class PendulumModel(Crossing, SensorModel):
    """Pendulum whisk-broom scanner: 15 parameters (12 with a shared IMU boresight)."""

    name = "pendulum"
    kind = "whisk-broom"
    required_keys = ("pixel_pitch", "focal_length", "n_elements", "k0")
    optional_keys = ("y0",)
    line_columns = ("time", "swing", "pitch_comp")
    directions = ("L", "R")

    @classmethod
    def simulator(cls):
        from swathflow.sensors.pendulum import simulate
        return simulate

    @classmethod
    def projector(cls, models):
        """Every observation of every swing in one compiled call, analytic partials."""
        from swathflow.sensors.pendulum.projection import PendulumProjector
        return PendulumProjector(models)

    @classmethod
    def default_parameters(cls, sensor: Mapping[str, Any]) -> ParameterSet:
        return parameters.default_parameters(sensor)

    @classmethod
    def check_lines(cls, lines: Mapping[str, Any]) -> list:
        """The swing column in degrees, sweeping one way at a steady rate."""
        return parameters.check_lines(lines)

    @classmethod
    def check_config(cls, sensor: Mapping[str, Any]) -> list[str]:
        problems = super().check_config(sensor)
        for k in ("pixel_pitch", "focal_length"):
            if k in sensor and not float(sensor[k]) > 0:
                problems.append(f"{k} must be positive, got {sensor[k]!r}")
        if "n_elements" in sensor and not int(sensor["n_elements"]) > 0:
            problems.append(f"n_elements must be positive, got {sensor['n_elements']!r}")
        return problems

    def _setup(self) -> None:
        s = self._sensor
        direction = str(self._image.get("direction", "")).upper()
        if direction not in ("L", "R"):
            raise FormatError(f"pendulum image {self._image.get('image_id', '')!r}: direction "
                              f"must be 'L' or 'R', got {direction!r}")
        self._direction = direction
        for k in ("time", "swing", "pitch_comp"):
            if k not in self._lines:
                raise FormatError(f"pendulum line table: missing column {k!r}")
        self._pp = float(s["pixel_pitch"])
        self._f = float(s["focal_length"])
        self._k0 = float(s["k0"])
        self._y0 = float(s.get("y0", 0.0))
        p = self._params
        self._u_gps = p["u_gps"]
        self._u_sen = p["u_sen"]
        self._R_hs = r_opk(*np.radians(p["opk_sen"])) @ T
        self._R_bp = r_opk(*np.radians(p[f"opk_pos_{direction}"]))
        self._lidx = np.arange(self.n_lines, dtype=float)
        # exact state at every integer line: projection centre and scan-plane normal; the
        # parameter-independent part (POS at the line times, gimbal) is computed once and
        # shared with every with_parameters() copy (calibration rebuilds models often)
        c, nrm = self._line_states()
        self._c_lines = c
        self._n_lines = nrm
        self._planes = np.concatenate(
            [self._n_lines, -np.einsum("ij,ij->i", self._n_lines, c)[:, None]], axis=1)
        self._r_bp_t = np.ascontiguousarray(self._R_bp)   # v @ R == R.T @ v for row vectors
        self._r_hs = np.ascontiguousarray(self._R_hs)
        if "line_cols" not in self._shared:
            lt = self._lines
            self._shared["line_cols"] = np.stack(
                [lt["time"], np.radians(lt["swing"]), np.radians(lt["pitch_comp"])], axis=-1)
        self._line_cols = self._shared["line_cols"]

    def _line_states(self) -> tuple[np.ndarray, np.ndarray]:
        """Projection centre and scan-plane normal ``R_ES (0, f, y0)`` (ECEF) at every
        integer line, from the shared parameter-free part (vector rotations only)."""
        sh = self._shared
        if "r_eb" not in sh:
            lt = self._lines
            pos = self._trajectory.interpolate(lt["time"])
            sh["x_ant"] = pos["ecef"]
            sh["r_eb"] = r_en(np.radians(pos["lat"]), np.radians(pos["lon"])) @ r_nb(
                np.radians(pos["roll"]), np.radians(pos["pitch"]), np.radians(pos["heading"]))
            sh["r_ph"] = r_ph(np.radians(lt["swing"]), np.radians(lt["pitch_comp"]))
        r_eb, r_ph_ = sh["r_eb"], sh["r_ph"]
        lever = apply(r_ph_, self._u_sen) @ self._R_bp.T + self._u_gps
        c = sh["x_ant"] + apply(r_eb, lever)
        nvec = self._R_hs @ np.array([0.0, self._f, self._y0])
        nrm = apply(r_eb, apply(r_ph_, np.broadcast_to(nvec, lever.shape)) @ self._R_bp.T)
        return c, nrm

    @property
    def direction(self) -> str:
        return self._direction

    # --- exact evaluation at fractional lines -------------------------------------------
    def _state(self, line) -> tuple[np.ndarray, np.ndarray]:
        """Projection centre C (ECEF) and R_ES at fractional lines (docs/geometry.md)."""
        line = np.asarray(line, float)
        lt = self._lines
        t = np.interp(line, self._lidx if hasattr(self, "_lidx") else
                      np.arange(self.n_lines, dtype=float), lt["time"])
        idx = np.arange(self.n_lines, dtype=float)
        s = np.radians(np.interp(line, idx, lt["swing"]))
        q = np.radians(np.interp(line, idx, lt["pitch_comp"]))
        pos = self._trajectory.interpolate(t)
        r_eb = r_en(np.radians(pos["lat"]), np.radians(pos["lon"])) @ r_nb(
            np.radians(pos["roll"]), np.radians(pos["pitch"]), np.radians(pos["heading"]))
        r_bh = self._R_bp @ r_ph(s, q)
        c = pos["ecef"] + apply(r_eb, self._u_gps + apply(r_bh, self._u_sen))
        return c, r_eb @ r_bh @ self._R_hs

    def _line_values(self, line):
        """time, swing, pitch_comp (rad) at fractional lines (linear between line centres)."""
        n = self.n_lines
        line = np.clip(line, 0.0, n - 1.0)
        i = np.minimum(line.astype(np.intp), n - 2)
        w = (line - i)[:, None]
        v = self._line_cols[i] * (1 - w) + self._line_cols[i + 1] * w
        return v[:, 0], v[:, 1], v[:, 2]

    def _camera_of(self, line, g) -> np.ndarray:
        """The camera-frame vector of ground points ``g`` seen from fractional ``line``:
        ``R_HS^T (R_PH^T R_BP^T (R_NB^T R_EN^T (G - X_ant) - u_gps) - u_sen)``, applied as a
        chain of closed-form rotations of vectors (the hot path of ground_to_image)."""
        t, s, q = self._line_values(line)
        pos = self._trajectory.interpolate(t)
        v = g - pos["ecef"]
        lat, lon = np.radians(pos["lat"]), np.radians(pos["lon"])
        sl, cl, so, co = np.sin(lat), np.cos(lat), np.sin(lon), np.cos(lon)
        x, y, z = v[:, 0], v[:, 1], v[:, 2]
        # R_EN^T
        e_ = -so * x + co * y
        n_ = -sl * co * x - sl * so * y + cl * z
        d_ = -cl * co * x - cl * so * y - sl * z
        x, y, z = n_, e_, d_
        # R_NB^T = Rx(roll)^T Ry(pitch)^T Rz(heading)^T
        h = np.radians(pos["heading"])
        sh, ch = np.sin(h), np.cos(h)
        x, y = ch * x + sh * y, -sh * x + ch * y
        p = np.radians(pos["pitch"])
        sp, cp = np.sin(p), np.cos(p)
        x, z = cp * x - sp * z, sp * x + cp * z
        r = np.radians(pos["roll"])
        sr, cr = np.sin(r), np.cos(r)
        y, z = cr * y + sr * z, -sr * y + cr * z
        v = np.stack([x, y, z], axis=-1) - self._u_gps
        v = v @ self._r_bp_t
        x, y, z = v[:, 0], v[:, 1], v[:, 2]
        # R_PH^T = Ry(q)^T Rx(s)^T
        ss, cs = np.sin(s), np.cos(s)
        y, z = cs * y + ss * z, -ss * y + cs * z
        sq, cq = np.sin(q), np.cos(q)
        x, z = cq * x - sq * z, sq * x + cq * z
        v = np.stack([x, y, z], axis=-1) - self._u_sen
        return v @ self._r_hs

    def _camera_vectors(self, element) -> np.ndarray:
        k = np.asarray(element, float)
        return np.stack(np.broadcast_arrays((k - self._k0) * self._pp, self._y0,
                                            -self._f), axis=-1)

    # --- interface ------------------------------------------------------------------------
    def ray(self, image):
        """Compiled (``kernel.rays``); the numpy path where the kernel declines (a line
        off the POS or not finite: the numpy path reports it)."""
        image = np.asarray(image, float)
        flat = np.ascontiguousarray(image.reshape(-1, 2))
        c, d = np.empty((flat.shape[0], 3)), np.empty((flat.shape[0], 3))
        geo = self._geo()
        if self.n_lines >= 2 and kernel.rays(flat, geo, self._trig(geo), self._k0,
                                             self._pp, self._y0, self._f, c, d):
            shape = image.shape[:-1] + (3,)
            return c.reshape(shape), d.reshape(shape)
        return self._ray_numpy(image)

    def _ray_numpy(self, image):
        """The numpy path of :meth:`ray` (reference for the compiled one)."""
        image = np.asarray(image, float)
        c, r = self._state(image[..., 0])
        d = apply(r, self._camera_vectors(image[..., 1]))
        return c, d / np.linalg.norm(d, axis=-1, keepdims=True)

    def image_time(self, image) -> np.ndarray:
        image = np.asarray(image, float)
        return np.interp(image[..., 0], self._lidx, self._lines["time"])

    def sensor_attitude(self, time) -> np.ndarray:
        return self._state(self._time_to_image(time)[..., 0])[1]

    def ground_to_image(self, ground, clip: bool = True) -> np.ndarray:
        ground = np.asarray(ground, float)
        shape, g = ground.shape[:-1], ground.reshape(-1, 3)
        if 0 < g.shape[0] <= CHUNK:      # one chunk (the lattice's calls): no copy
            return self._ground_to_image(g, clip).reshape(shape + (2,))
        out = np.full((g.shape[0], 2), np.nan)
        for s in range(0, g.shape[0], CHUNK):    # the temporaries stay in the CPU cache
            out[s:s + CHUNK] = self._ground_to_image(g[s:s + CHUNK], clip)
        return out.reshape(shape + (2,))

    def _ground_to_image(self, g, clip: bool) -> np.ndarray:
        """Compiled path (``kernel.ground_to_image``): the numpy path, point by point."""
        out, clip = np.empty((g.shape[0], 2)), bool(clip)
        g = np.ascontiguousarray(g, dtype=float)
        args, pixel = self._kernel_args()
        if self.n_lines >= 2 and kernel.ground_to_image(g, *args, ROUGH_LINE, pixel, clip,
                                                        out):
            return out
        return self._ground_to_image_numpy(g, clip)   # the POS has a gap there: it reports

    def _kernel_args(self) -> tuple:
        """The model's arguments of ``kernel.ground_to_image``, made once (~8 calls a tile)."""
        if getattr(self, "_g2i_args", None) is None:
            coarse = self._shared.setdefault("coarse_grid", coarse_grid(self.n_lines))
            geo, nvec = self._geo(), np.array([0.0, self._f, self._y0])
            trig = self._trig(geo)
            frames = self._line_frames() + kernel.epoch_frames(geo, trig, nvec)
            self._g2i_args = ((self._planes, coarse, nvec, geo, trig, frames),
                              (self._k0, self._f, self._pp, float(self.n_elements)))
        return self._g2i_args

    def _trig(self, geo) -> tuple:
        """The kernels' sine tables (``kernel.trig_tables``), made once per swing."""
        if "trig" not in self._shared:
            self._shared["trig"] = kernel.trig_tables(geo)
        return self._shared["trig"]

    def _geo(self) -> tuple:
        """The kernels' view of the geometry: line columns, POS times and table (ECEF,
        lat, lon, attitude), max gap, R_BP, R_HS, u_gps, u_sen."""
        time, table, max_gap = pos_table(self._trajectory)
        return (self._line_cols, time, table, max_gap, self._r_bp_t, self._r_hs,
                np.asarray(self._u_gps, float), np.asarray(self._u_sen, float))

    @classmethod
    def example_model(cls, direction: str = "L", n_lines: int = 800) -> "PendulumModel":
        """A realistic small swing (contract tests, examples): +-40 deg over 800 lines."""
        from swathflow.testing import straight_trajectory
        traj, lines = straight_trajectory(n_lines=n_lines, line_rate=400.0)
        sweep = np.linspace(-40.0, 40.0, n_lines)
        lines["swing"] = sweep if direction == "L" else sweep[::-1]
        lines["pitch_comp"] = np.linspace(1.5, -1.5, n_lines)
        sensor = {"pixel_pitch": 15e-6, "focal_length": 0.16, "n_elements": 512,
                  "k0": 255.5, "y0": 0.0}
        params = {"u_gps": [-0.08, 0.24, 0.91], "u_sen": [-0.07, -0.11, -2.01],
                  "opk_sen": [0.03, -0.47, -0.04], "opk_pos_L": [2.73, 0.0, -0.11],
                  "opk_pos_R": [2.68, -0.01, -0.07]}
        return cls.build(sensor, lines, traj, params, direction=direction)
