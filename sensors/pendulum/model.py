"""The pendulum (left/right swinging) infrared scanner of the calibration paper
(papers.md section 1), exactly as spec/geometry.md's pendulum section.

A TDI detector line along the sensor x axis (the flight direction) inside a gimbal that
swings the camera across track; each image is one swing, each line one instant.
"""
from __future__ import annotations

from typing import Any, Mapping

import numpy as np

from swathflow.errors import FormatError
from swathflow.geometry.linesolve import bracket_lines, plane_brackets, secant_lines
from swathflow.geometry.navkernel import pos_table
from swathflow.geometry.planesolve import coarse_grid
from swathflow.geometry.rotations import T, apply, apply_t, r_en, r_nb, r_opk, r_ph

from swathflow.sensormodel.base import CHUNK, Parameter, ParameterSet, SensorModel
from swathflow.sensors.pendulum import kernel

#: root estimates (secant, inverse quadratic) further apart than this (lines) mark a
#: condition that is not smooth inside the line: those points are solved exactly
ROUGH_LINE = 1e-6


def _quadratic_root(x0, x2, f0, f2, l1, f1):
    """The root inside brackets ``[x0, x2]`` (condition ``f0``, ``f2`` at the ends, ``f1``
    at the chord point ``l1``): the inverse quadratic through the three, the secant
    against the bracket end on the other side of the chord point where the quadratic
    leaves the bracket; and where the two differ by more than ``ROUGH_LINE`` (rough:
    solve exactly)."""
    same = np.sign(f1) == np.sign(f0)
    ja = np.where(same, x2, x0)
    fa = np.where(same, f2, f0)
    with np.errstate(invalid="ignore", divide="ignore"):
        w = f1 / (f1 - fa)
    line = l1 + np.where(np.isfinite(w), w, 0.0) * (ja - l1)
    with np.errstate(invalid="ignore", divide="ignore"):
        q = (x0 * f1 * f2 / ((f0 - f1) * (f0 - f2))
             + l1 * f0 * f2 / ((f1 - f0) * (f1 - f2))
             + x2 * f0 * f1 / ((f2 - f0) * (f2 - f1)))
    use = np.isfinite(q) & (q >= x0) & (q <= x2)
    return np.where(use, q, line), ~use | (np.abs(q - line) > ROUGH_LINE)


def _lagrange(line, x0, x1, x2, cam0, cam1, cam2):
    """Camera vectors at ``line``: the quadratic through those at x0, x1, x2 (linear
    between the ends where the chord point sits on one)."""
    with np.errstate(invalid="ignore", divide="ignore"):
        L0 = (line - x1) * (line - x2) / ((x0 - x1) * (x0 - x2))
        L1 = (line - x0) * (line - x2) / ((x1 - x0) * (x1 - x2))
        L2 = (line - x0) * (line - x1) / ((x2 - x0) * (x2 - x1))
    ok = np.isfinite(L0) & np.isfinite(L1) & np.isfinite(L2)
    t = (line - x0) / (x2 - x0)
    lin = cam0 + t[:, None] * (cam2 - cam0)
    with np.errstate(invalid="ignore"):       # the non-finite weights are not selected
        return np.where(ok[:, None], L0[:, None] * cam0 + L1[:, None] * cam1
                        + L2[:, None] * cam2, lin)


class PendulumModel(SensorModel):
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
    def check_config(cls, sensor: Mapping[str, Any]) -> list[str]:
        problems = super().check_config(sensor)
        for k in ("pixel_pitch", "focal_length"):
            if k in sensor and not float(sensor[k]) > 0:
                problems.append(f"{k} must be positive, got {sensor[k]!r}")
        if "n_elements" in sensor and not int(sensor["n_elements"]) > 0:
            problems.append(f"n_elements must be positive, got {sensor['n_elements']!r}")
        return problems

    @classmethod
    def check_lines(cls, lines: Mapping[str, Any]) -> list:
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

    def _refine(self, g, j, fj, fj1):
        """Fractional line and camera vector of points ``g`` crossing between ``j, j+1``.

        One exact evaluation at the chord of the bracket; the root is then the inverse
        quadratic interpolation through the condition at ``j``, the chord point and
        ``j + 1``, and the camera vector there is the quadratic through the camera vectors
        at the same three lines (exact at the integer lines from their frames). Where that
        root leaves the bracket or differs from the secant step against the far bracket end
        by more than ``ROUGH_LINE``, the point is solved exactly (secant iterations). A line
        whose times hold one POS epoch (a kink in the condition: 30 % of the lattice's
        points on the demo mission) is split at the epoch first, and the same solve made on
        the side with the sign change (:meth:`_split_at_epoch`; where that is rough, as
        above). This agrees with a fully
        converged solve to far below 0.001 px (checked in the tests; a linear
        interpolation alone left 1.2e-3 px on a wobbling swing).
        """
        nvec = np.array([0.0, self._f, self._y0])
        with np.errstate(invalid="ignore", divide="ignore"):
            l1 = j + fj / (fj - fj1)
        l1 = np.where(np.isfinite(l1), l1, j + 0.5)
        cam1 = self._camera_of(l1, g)
        x0, x2 = j.astype(float), j + 1.0
        line, rough = _quadratic_root(x0, x2, fj, fj1, l1, cam1 @ nvec)
        # where the secant and the quadratic disagree the condition is not smooth inside the
        # line (a POS sample between the two line times puts a kink in it): solve each side
        rough = np.flatnonzero(rough)
        # the camera vector at ``line``: Lagrange quadratic through the three lines
        r_es, c = self._line_frames()
        cam0 = np.einsum("nji,nj->ni", r_es[j], g - c[j])
        cam2 = np.einsum("nji,nj->ni", r_es[j + 1], g - c[j + 1])
        cam = _lagrange(line, x0, l1, x2, cam0, cam1, cam2)
        # a POS epoch inside the line puts a kink in the condition: solve each side
        lr, cr = self._split_at_epoch(g, j, fj, fj1)
        split = np.isfinite(lr)
        line, cam = np.where(split, lr, line), np.where(split[:, None], cr, cam)
        # a line holding an epoch and not split (several epochs, or the split declined):
        # one quadratic across the kinks is not trusted, its roughness test can miss them
        kinked = np.zeros(j.shape, bool)
        kinked[rough] = True
        kinked |= self._holds_epoch(j)
        rough = np.flatnonzero(kinked & ~split)
        if rough.size:      # rough, or kinked and not split: solve exactly
            line[rough], cam[rough] = self._solve_exact(g[rough], j[rough], fj[rough],
                                                        fj1[rough], tol=1e-9)
        return line, cam

    def _holds_epoch(self, j):
        """True where the times of lines ``j`` and ``j + 1`` hold a POS epoch between them
        (strictly inside: a kink of the condition)."""
        time = np.asarray(self._trajectory.time, float)
        t0, t1 = self._line_cols[j, 0], self._line_cols[j + 1, 0]
        k = np.searchsorted(time, t0, side="right")
        return (k < time.size) & (time[np.minimum(k, time.size - 1)] < t1)

    def _split_at_epoch(self, g, j, fj, fj1):
        """The root inside lines ``[j, j+1]`` whose times hold one POS epoch (a kink of
        the condition): one exact evaluation at the epoch's fractional line picks the
        smooth side with the sign change, where the root is the inverse quadratic through
        its ends and one exact evaluation at its chord point (as in :meth:`_refine`). NaN
        lines where a line holds no single epoch or that solve is rough (the caller solves
        exactly)."""
        nvec = np.array([0.0, self._f, self._y0])
        time = np.asarray(self._trajectory.time, float)
        n = time.size
        t0, t1 = self._line_cols[j, 0], self._line_cols[j + 1, 0]
        k = np.searchsorted(time, t0, side="right")
        te, tn = time[np.minimum(k, n - 1)], time[np.minimum(k + 1, n - 1)]
        le = j + (te - t0) / (t1 - t0)
        one = ((k + 1 < n) & (te > t0) & (te < t1) & ~((k + 2 < n) & (tn < t1))
               & (le > j) & (le < j + 1))
        line, cam = np.full(j.shape, np.nan), np.full(g.shape, np.nan)
        i = np.flatnonzero(one)
        if not i.size:
            return line, cam
        g, j, fj, fj1, le = g[i], j[i], fj[i], fj1[i], le[i]
        r_es, c = self._line_frames()
        cam_e = self._camera_of(le, g)
        fe = cam_e @ nvec
        after = np.sign(fe) == np.sign(fj)          # the root is after the epoch
        jj = np.where(after, j + 1, j)
        cam_j = np.einsum("nji,nj->ni", r_es[jj], g - c[jj])
        x0, f0 = np.where(after, le, j), np.where(after, fe, fj)
        x2, f2 = np.where(after, j + 1.0, le), np.where(after, fj1, fe)
        c0 = np.where(after[:, None], cam_e, cam_j)
        c2 = np.where(after[:, None], cam_j, cam_e)
        with np.errstate(invalid="ignore", divide="ignore"):
            l1 = x0 + f0 / (f0 - f2) * (x2 - x0)
        l1 = np.where(np.isfinite(l1), l1, (x0 + x2) / 2)
        cam1 = self._camera_of(l1, g)
        ln, rough = _quadratic_root(x0, x2, f0, f2, l1, cam1 @ nvec)
        cm = _lagrange(ln, x0, l1, x2, c0, cam1, c2)
        zero = fe == 0
        ln, cm = np.where(zero, le, ln), np.where(zero[:, None], cam_e, cm)
        ln[rough & ~zero] = np.nan
        line[i], cam[i] = ln, cm
        return line, cam

    def _solve_exact(self, g, j, fj, fj1, tol: float):
        """Secant iterations on the exact condition inside brackets ``[j, j+1]``; the
        fractional lines and the exact camera vectors there."""
        nvec = np.array([0.0, self._f, self._y0])

        def f_exact(i, line):
            c, r = self._state(line)
            return apply_t(r, g[i] - c) @ nvec

        line = secant_lines(f_exact, j, fj, fj1, tol=tol, max_iter=30)
        c, r = self._state(line)
        return line, apply_t(r, g - c)

    def _line_frames(self) -> tuple[np.ndarray, np.ndarray]:
        """R_ES and the projection centre at every integer line (computed on first use)."""
        if getattr(self, "_r_es_lines", None) is None:
            sh = self._shared
            r_bs = np.einsum("ij,njk->nik", self._R_bp, sh["r_ph"]) @ self._R_hs
            self._r_es_lines = np.einsum("nij,njk->nik", sh["r_eb"], r_bs)
        return self._r_es_lines, self._c_lines

    def _ground_to_image_converged(self, ground) -> np.ndarray:
        """Reference solve: secant iterations to 1e-12 line (tests compare the fast path)."""
        g = np.asarray(ground, float).reshape(-1, 3)
        cl, nl = self._c_lines, self._n_lines
        j, fj, fj1, found = bracket_lines(
            lambda i, jj: np.einsum("ij,ij->i", nl[jj], g[i] - cl[jj]), g.shape[0], self.n_lines)
        k = np.flatnonzero(found)
        line, cam = self._solve_exact(g[k], j[k], fj[k], fj1[k], tol=1e-12)
        out = np.full((g.shape[0], 2), np.nan)
        out[k, 0] = line
        out[k, 1] = self._k0 + self._f * cam[:, 0] / (-cam[:, 2]) / self._pp
        return out

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

    def _pixels(self, line, cam, clip: bool) -> np.ndarray:
        """(line, element) from fractional lines and camera vectors; NaN behind the camera
        and, with ``clip``, off the detector."""
        with np.errstate(invalid="ignore", divide="ignore"):
            elem = self._k0 + self._f * cam[:, 0] / (-cam[:, 2]) / self._pp
        front = cam[:, 2] < 0
        elem = np.where(front, elem, np.nan)
        line = np.where(front, line, np.nan)
        if clip:
            off = (elem < -0.5) | (elem > self.n_elements - 0.5)
            elem = np.where(off, np.nan, elem)
            line = np.where(off, np.nan, line)
        return np.stack([line, elem], axis=-1)

    def _ground_to_image_numpy(self, g, clip: bool) -> np.ndarray:
        """The numpy path (reference for the compiled one, and its fallback)."""
        n = g.shape[0]
        out = np.full((n, 2), np.nan)
        planes = self._planes

        def f_int(i, j):
            pl = planes[j]
            gi = g[i]
            return (pl[:, 0] * gi[:, 0] + pl[:, 1] * gi[:, 1] + pl[:, 2] * gi[:, 2]
                    + pl[:, 3])

        lo, hi, flo, fhi = plane_brackets(g, planes)
        j, fj, fj1, found = bracket_lines(f_int, n, self.n_lines, lo, hi, flo, fhi)
        k = np.flatnonzero(found)
        if k.size:
            out[k] = self._pixels(*self._refine(g[k], j[k], fj[k], fj1[k]), clip)
        return out

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
