"""A minimal third-party sensor: a frame-less nadir push-broom line with no parameters
but a lever arm, enough to exercise the registry and the contract suite."""
import numpy as np

from swathflow.geometry.rotations import apply, apply_t, r_en, r_nb
from swathflow.sensormodel.base import Parameter, ParameterSet, SensorModel


class SampleNadirModel(SensorModel):
    """Ideal nadir push-broom line (test plugin)."""

    name = "sample-nadir"
    kind = "push-broom"
    required_keys = ("n_elements", "ifov")

    @classmethod
    def default_parameters(cls, sensor):
        return ParameterSet((Parameter("u_gps", "m", (0.0, 0.0, 0.0), (1.0,) * 3),))

    def _setup(self):
        self._idx = np.arange(self.n_lines, dtype=float)
        c, r = self._state(self._idx)
        self._c, self._n = c, r[..., :, 0]

    def _state(self, line):
        t = np.interp(line, np.arange(self.n_lines, dtype=float), self._lines["time"])
        p = self._trajectory.interpolate(t)
        r = r_en(np.radians(p["lat"]), np.radians(p["lon"])) @ r_nb(
            np.radians(p["roll"]), np.radians(p["pitch"]), np.radians(p["heading"]))
        return p["ecef"] + apply(r, self._params["u_gps"]), r

    def ray(self, image):
        image = np.asarray(image, float)
        c, r = self._state(image[..., 0])
        a = (image[..., 1] - (self.n_elements - 1) / 2) * float(self._sensor["ifov"])
        d = np.stack(np.broadcast_arrays(0.0, -np.tan(a), 1.0), axis=-1)
        d = apply(r, d)
        return c, d / np.linalg.norm(d, axis=-1, keepdims=True)

    def image_time(self, image):
        return np.interp(np.asarray(image, float)[..., 0], self._idx, self._lines["time"])

    def ground_to_image(self, ground, clip=True):
        from swathflow.geometry.linesolve import bracket_lines, secant_lines
        g = np.asarray(ground, float).reshape(-1, 3)
        out = np.full((g.shape[0], 2), np.nan)
        j, fj, fj1, found = bracket_lines(
            lambda i, j: np.einsum("ij,ij->i", self._n[j], g[i] - self._c[j]), g.shape[0],
            self.n_lines)
        k = np.flatnonzero(found)
        if k.size:
            def fx(i, line):
                c, r = self._state(line)
                return np.einsum("ij,ij->i", r[..., :, 0], g[k][i] - c)
            line = secant_lines(fx, j[k], fj[k], fj1[k])
            c, r = self._state(line)
            v = apply_t(r, g[k] - c)
            elem = np.arctan2(-v[:, 1], v[:, 2]) / float(self._sensor["ifov"]) + (
                self.n_elements - 1) / 2
            ok = v[:, 2] > 0
            if clip:
                ok &= (elem >= -0.5) & (elem <= self.n_elements - 0.5)
            out[k, 0] = np.where(ok, line, np.nan)
            out[k, 1] = np.where(ok, elem, np.nan)
        return out.reshape(np.shape(ground)[:-1] + (2,))

    @classmethod
    def example_model(cls):
        from swathflow.testing import straight_trajectory
        traj, lines = straight_trajectory(n_lines=400, line_rate=100.0)
        return cls.build({"n_elements": 256, "ifov": 1e-3}, lines, traj,
                         {"u_gps": [0.1, -0.2, 0.5]})


not_a_model = object()
