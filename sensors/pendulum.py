"""The pendulum (left/right swinging) infrared scanner of the calibration paper
(papers.md section 1), exactly as spec/geometry.md's pendulum section.

A TDI detector line along the sensor x axis (the flight direction) inside a gimbal that
swings the camera across track; each image is one swing, each line one instant.
"""
from __future__ import annotations

from typing import Any, Mapping

import numpy as np

from swathflow.errors import FormatError
from swathflow.linesolve import bracket_lines, secant_lines
from swathflow.rotations import T, apply, apply_t, r_en, r_nb, r_opk, r_ph

from .base import Parameter, ParameterSet, SensorModel


class PendulumModel(SensorModel):
    """Pendulum whisk-broom scanner: 15 parameters (12 with a shared IMU boresight)."""

    name = "pendulum"
    kind = "whisk-broom"
    required_keys = ("pixel_pitch", "focal_length", "n_elements", "k0")

    @classmethod
    def check_config(cls, sensor: Mapping[str, Any]) -> list[str]:
        problems = super().check_config(sensor)
        for k in ("pixel_pitch", "focal_length"):
            if k in sensor and not float(sensor[k]) > 0:
                problems.append(f"{k} must be positive, got {sensor[k]!r}")
        if "n_elements" in sensor and not int(sensor["n_elements"]) > 0:
            problems.append(f"n_elements must be positive, got {sensor['n_elements']!r}")
        return problems

    @classmethod
    def default_parameters(cls, sensor: Mapping[str, Any]) -> ParameterSet:
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
        # exact state at every integer line: projection centre and scan-plane normal
        c, r = self._state(self._lidx)
        self._c_lines = c
        self._n_lines = r @ np.array([0.0, self._f, self._y0])

    @property
    def direction(self) -> str:
        return self._direction

    # --- exact evaluation at fractional lines -------------------------------------------
    def _state(self, line) -> tuple[np.ndarray, np.ndarray]:
        """Projection centre C (ECEF) and R_ES at fractional lines (spec/geometry.md)."""
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

    def _camera_vectors(self, element) -> np.ndarray:
        k = np.asarray(element, float)
        return np.stack(np.broadcast_arrays((k - self._k0) * self._pp, self._y0,
                                            -self._f), axis=-1)

    # --- interface ------------------------------------------------------------------------
    def ray(self, image):
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
        shape = ground.shape[:-1]
        g = ground.reshape(-1, 3)
        n = g.shape[0]
        out = np.full((n, 2), np.nan)
        if n == 0:
            return out.reshape(shape + (2,))
        cl, nl = self._c_lines, self._n_lines

        def f_int(i, j):
            return np.einsum("ij,ij->i", nl[j], g[i] - cl[j])

        j, fj, fj1, found = bracket_lines(f_int, n, self.n_lines)
        k = np.flatnonzero(found)
        if k.size:
            gk = g[k]
            nvec = np.array([0.0, self._f, self._y0])

            def f_exact(i, line):
                c, r = self._state(line)
                return np.einsum("ij,ij->i", apply(r, nvec), gk[i] - c)

            line = secant_lines(f_exact, j[k], fj[k], fj1[k])
            c, r = self._state(line)
            cam = apply_t(r, gk - c)
            with np.errstate(invalid="ignore", divide="ignore"):
                elem = self._k0 + self._f * cam[:, 0] / (-cam[:, 2]) / self._pp
            front = cam[:, 2] < 0
            elem = np.where(front, elem, np.nan)
            line = np.where(front, line, np.nan)
            if clip:
                off = (elem < -0.5) | (elem > self.n_elements - 0.5)
                elem = np.where(off, np.nan, elem)
                line = np.where(off, np.nan, line)
            out[k, 0] = line
            out[k, 1] = elem
        return out.reshape(shape + (2,))

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
