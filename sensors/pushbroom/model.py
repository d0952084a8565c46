"""The push-broom line camera of the GFXJ paper (papers.md section 2), exactly as
spec/geometry.md's push-broom section.

One CCD line along the sensor y axis, made of segments; every image line is one read-out at
one instant. A three-line camera (forward, nadir, backward) is three such lines sharing the
trajectory, the lever arm, the boresight and the orientation fixes: one model per line image,
the line chosen by the image attribute ``view`` (see docs/mission-format-pushbroom.md).

Viewing angles per element come from the nominal design (``pixel_pitch``, ``focal_length``,
``s_c``, ``psi_x0_deg``) or from a laboratory table (``tan_psi_x``, ``tan_psi_y``, one value per
element, linear between element centres), plus the additional parameters (APs): a cubic in
``ds = s - segments[i]`` per CCD segment for ``tan_psi_x`` (``ax``) and ``tan_psi_y`` (``bx``).
The LIM orientation-fix model corrects position and attitude by ``d_ned`` (m) and ``d_opk``
(deg) interpolated linearly in time between fixes (held constant outside them).
"""
from __future__ import annotations

from typing import Any, Mapping

import numpy as np

from swathflow.errors import FormatError
from swathflow.geometry.rotations import T, apply, apply_t, r_en, r_nb, r_opk

from swathflow.sensors.base import Parameter, ParameterSet, SensorModel

#: nominal along-track angles of the three lines of a three-line camera (deg)
THREE_LINE_VIEWS = {"forward": 25.0, "nadir": 0.0, "backward": -25.0}
#: prior sigmas of the AP coefficients a0..a3 (tan units per element^k)
AP_SIGMA = tuple(1e-3 / 1024.0 ** k for k in range(4))
#: finite-difference steps of the AP coefficients a0..a3 (a change of about 1e-6 rad at
#: ds = 1000 elements); ``fd_step_sizes`` hands them to contract tests
AP_STEP = tuple(1e-6 / 1000.0 ** k for k in range(4))


# --- configuration ----------------------------------------------------------------------------
def views(sensor: Mapping[str, Any]) -> dict[str, dict]:
    """The CCD lines of a ``[sensor]`` table, name -> effective configuration.

    Without a ``views`` table the camera has one line, named ``""``; with one, each entry
    (a number = ``psi_x0_deg``, or a table overriding any sensor key) is one line."""
    base = {k: v for k, v in sensor.items() if k != "views"}
    if "views" not in sensor:
        return {"": base}
    out = {}
    for name, v in dict(sensor["views"]).items():
        extra = {"psi_x0_deg": v} if np.isscalar(v) else dict(v)
        out[str(name)] = {**base, **extra}
    return out


def ap_name(kind: str, view: str, segment: int) -> str:
    """Parameter block name of one segment's APs: ``ax_0`` or ``ax_forward_0``."""
    return f"{kind}_{view}_{segment}" if view else f"{kind}_{segment}"


def fix_times(sensor: Mapping[str, Any]) -> np.ndarray:
    fx = sensor.get("fixes") or {}
    return np.asarray(fx.get("time", []), float).ravel()


def _check_view(name: str, cfg: Mapping[str, Any]) -> list[str]:
    where = f"view {name!r}: " if name else ""
    out = []
    n = cfg.get("n_elements")
    try:
        n = int(n)
        if n < 2:
            out.append(f"{where}n_elements must be at least 2, got {n}")
    except (TypeError, ValueError):
        return [f"{where}n_elements must be an integer, got {n!r}"]
    has_table = "tan_psi_x" in cfg or "tan_psi_y" in cfg
    if has_table:
        for k in ("tan_psi_x", "tan_psi_y"):
            a = np.asarray(cfg.get(k, []), float).ravel()
            if a.size != n or not np.all(np.isfinite(a)):
                out.append(f"{where}{k} needs {n} finite values (one per element), got {a.size}")
    else:
        for k in ("pixel_pitch", "focal_length", "s_c"):
            if k not in cfg:
                out.append(f"{where}missing key {k!r} (or give the laboratory table "
                           f"tan_psi_x/tan_psi_y)")
        for k in ("pixel_pitch", "focal_length"):
            if k in cfg and not float(cfg[k]) > 0:
                out.append(f"{where}{k} must be positive, got {cfg[k]!r}")
    seg = np.asarray(cfg.get("segments", [0]), float).ravel()
    if seg.size == 0 or seg[0] != 0 or np.any(np.diff(seg) <= 0) or seg[-1] >= n:
        out.append(f"{where}segments must start at 0 and increase below n_elements, "
                   f"got {list(seg)}")
    for k in ("ax", "bx"):
        if k in cfg:
            a = np.asarray(cfg[k], float)
            if a.shape != (seg.size, 4):
                out.append(f"{where}{k} needs 4 coefficients per segment "
                           f"({seg.size} segments), got shape {a.shape}")
    return out


# --- the model ----------------------------------------------------------------------------------
def _compose(x, ren, rnb, do, u_gps, R_bs):
    """Projection centre and R_ES from the antenna position ``x``, R_EN, R_NB, the fix
    attitude correction ``do`` (rad, or None), the lever arm and R_BS."""
    if do is not None:
        rnb = rnb @ r_opk(do[..., 0], do[..., 1], do[..., 2])
    reb = ren @ rnb
    return x + apply(reb, u_gps), reb @ R_bs


class PushbroomModel(SensorModel):
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
    def simulator(cls):
        from swathflow.sensors.pushbroom import simulate
        return simulate
    #: exact correction steps follow the interpolated solve when linear interpolation of
    #: the state between lines is estimated to be off by more than this (pixels)
    exact_threshold_px: float = 1e-4

    @classmethod
    def check_config(cls, sensor: Mapping[str, Any]) -> list[str]:
        problems = super().check_config(sensor)
        if problems:
            return problems
        if "views" in sensor and (not isinstance(sensor["views"], Mapping)
                                  or not sensor["views"]):
            return ["views must be a table of line name -> psi_x0_deg (or a table of keys)"]
        for name, cfg in views(sensor).items():
            problems += _check_view(name, cfg)
        fx = sensor.get("fixes")
        if fx is not None:
            t = fix_times(sensor)
            if t.size == 0 or np.any(np.diff(t) <= 0):
                problems.append("fixes.time must be a non-empty increasing list of times (s)")
            for k in ("d_ned", "d_opk"):
                if k in fx and np.asarray(fx[k], float).shape != (t.size, 3):
                    problems.append(f"fixes.{k} needs 3 values per fix ({t.size} fixes)")
        return problems

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
        self._coef_t = np.ascontiguousarray(self._tangent_table().T)   # (8, n_elements)
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

    def _tangent_table(self) -> np.ndarray:
        """Per element interval ``[i, i + 1)`` (i = 0 .. n-1, the last one extrapolating) the
        cubic coefficients in ``u = s - i`` of tan_psi_x (columns 0-3) and tan_psi_y (4-7):
        exact, since within an interval the APs are one cubic and the rest is linear."""
        n = self._nel
        i = np.arange(n, dtype=float)
        seg = np.clip(np.searchsorted(self._seg, i, side="right") - 1, 0, self._seg.size - 1)
        d = i - self._seg[seg]
        out = np.zeros((n, 8))
        for col, a in ((0, self._ax[seg]), (4, self._bx[seg])):
            out[:, col] = a[:, 0] + d * (a[:, 1] + d * (a[:, 2] + d * a[:, 3]))
            out[:, col + 1] = a[:, 1] + d * (2 * a[:, 2] + 3 * d * a[:, 3])
            out[:, col + 2] = a[:, 2] + 3 * d * a[:, 3]
            out[:, col + 3] = a[:, 3]
        if self._tab is None:
            out[:, 0] += self._tpx0
            out[:, 4] += (i - self._sc) * self._k
            out[:, 5] += self._k
        else:
            for col, y in ((0, self._tab[0]), (4, self._tab[1])):
                slope = np.diff(y)
                out[:, col] += y
                out[:, col + 1] += np.append(slope, slope[-1])
        return out

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
        return _compose(*self._frames(t), self._u_gps, self._R_bs)

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

    # --- the solve ------------------------------------------------------------------------
    #: points per block in the solve (temporaries stay in cache: about 2.5x faster)
    chunk: int = 32768

    def _solve(self, g: np.ndarray):
        """Lines and elements of ECEF points ``g`` (n, 3) and the 2x2 Jacobian of the
        conditions (r - tan_psi_x, q - tan_psi_y) in (line, element) at the solution."""
        n = g.shape[0]
        line = np.full(n, np.nan)
        elem = np.full(n, np.nan)
        jac = np.full((n, 2, 2), np.nan)
        if self.n_lines < 2:
            return line, elem, jac
        for i0 in range(0, n, self.chunk):
            sl = slice(i0, i0 + self.chunk)
            line[sl], elem[sl], jac[sl] = self._solve_block(g[sl])
        return line, elem, jac

    def _solve_block(self, g: np.ndarray, tol: float = 1e-7, max_iter: int = 10):
        """Bracket the knot interval with the viewing plane of the middle element, then
        Newton jointly in (line, element) with position and rotation linear between the two
        knots (the camera vector is then quadratic in the fraction), moving to the
        neighbouring interval while the solution lies outside; then exact correction steps
        when that interpolation is not negligible. Points the plane does not bracket but
        that lie within a few lines of an end start from that end."""
        n = g.shape[0]
        line = np.full(n, np.nan)
        elem = np.full(n, np.nan)
        jac = np.full((n, 2, 2), np.nan)
        K = self._kline.size
        L = self.n_lines
        nv, dv = self._nvec, self._dvec

        def f_at(i, j):
            if i is None:                  # all points, one line: no gathers
                return g @ nv[j] - dv[j]
            gi = g[i]
            nj = nv[j]
            return nj[:, 0] * gi[:, 0] + nj[:, 1] * gi[:, 1] + nj[:, 2] * gi[:, 2] - dv[j]

        j, fj, fj1, found = _bracket(f_at, n, L)     # over lines (uniform steps)
        with np.errstate(invalid="ignore", divide="ignore"):
            w = fj / (fj - fj1)
        # near misses at the ends (the middle element's plane is not the point's plane)
        near = ~found & np.isfinite(fj) & np.isfinite(fj1)
        if near.any():
            i = np.flatnonzero(near)
            f0, fK = fj[i], fj1[i]
            first = np.abs(f0) < np.abs(fK)
            jj = np.where(first, 0, L - 2)
            slope = np.abs(f_at(i, jj + 1) - f_at(i, jj))
            close = np.where(first, np.abs(f0), np.abs(fK)) < 20 * slope
            i, jj, first = i[close], jj[close], first[close]
            found[i] = True
            j[i] = jj
            w[i] = np.where(first, 0.0, 1.0)
        k = np.flatnonzero(found)
        if k.size == 0:
            return line, elem, jac
        # camera vector at the bracket's first line: element guess, then the line estimate
        # corrected from the middle element's plane to the guessed element's
        gk = g[k]
        jl, w = j[k], np.where(np.isfinite(w[k]), w[k], 0.5)
        kj = self._line_knot[jl]
        g0 = _matvec(self._Mt[kj], gk) - self._p[kj]
        with np.errstate(invalid="ignore", divide="ignore"):
            s = self._element_guess(g0[:, 1] / -g0[:, 2])
            dw = (self.view_tangents(s)[0] - self._tpx_mid) * g0[:, 2] / (fj[k] - fj1[k])
        l0 = jl + w + np.where(np.isfinite(dw), dw, 0.0)
        kl, dl = self._kline, self._dline
        j = np.clip(np.searchsorted(kl, l0, side="right") - 1, 0, K - 2)
        w = (l0 - kl[j]) / dl[j]
        a, b, c = self._quadratic(gk, j)
        w, s, J, gz = self._newton(a, b, c, w, s, tol, max_iter)
        for _ in range(4):  # solutions outside [j, j + 1]: move there and solve again
            out = np.flatnonzero((w < -1e-9) | (w > 1 + 1e-9))
            lo_ = kl[j[out]] + w[out] * dl[j[out]]
            jn = np.clip(np.searchsorted(kl, lo_, side="right") - 1, 0, K - 2)
            keep = jn != j[out]
            mv, jn, lo_ = out[keep], jn[keep], lo_[keep]
            if mv.size == 0:
                break
            j[mv] = jn
            wm = (lo_ - kl[jn]) / dl[jn]
            am, bm, cm = self._quadratic(gk[mv], j[mv])
            w[mv], s[mv], J[mv], gz[mv] = self._newton(am, bm, cm, wm, s[mv], tol, max_iter)
        lk = kl[j] + w * dl[j]
        J[:, :, 0] /= dl[j][:, None]          # d/dw -> d/dline
        if self._interp_px > self.exact_threshold_px:
            for _ in range(3):
                F = self._conditions_exact(gk, lk, s)
                d_l, d_e = _solve2(J, F)
                lk, s = lk - d_l, s - d_e
                if np.nanmax(np.abs(d_l) + np.abs(d_e), initial=0.0) < 1e-8:
                    break
        ok = np.isfinite(lk) & (gz < 0) & (lk >= -1e-6) & (lk <= self.n_lines - 1 + 1e-6)
        line[k] = np.where(ok, lk, np.nan)
        elem[k] = np.where(ok, s, np.nan)
        jac[k] = J
        return line, elem, jac

    def _quadratic(self, g, j):
        """g_S(w) = a + w b + w^2 c: the camera-frame vector of ``g`` at the fraction ``w``
        of knot interval ``j``, with position and rotation linear between the knots."""
        a = _matvec(self._Mt[j], g) - self._p[j]
        e = _matvec(self._Mt[j + 1], g) - self._p[j + 1]
        c = self._cq[j]
        return a, e - a - c, c

    def _newton(self, a, b, c, w, s, tol, max_iter):
        for _ in range(max_iter):
            gw = a + w[:, None] * (b + w[:, None] * c)
            dg = b + 2 * w[:, None] * c
            F, J = self._cond_jac(gw, dg, s)
            dw, ds = _solve2(J, F)
            w = w - dw
            s = s - ds
            if np.nanmax(np.abs(dw) + np.abs(ds) * 1e-3, initial=0.0) < tol:
                break   # converged: J (one step old) is as good as new
        return w, s, J, gw[:, 2]

    def _cond_jac(self, gw, dg, s):
        """Conditions F = (g_x/-g_z - tan_psi_x(s), g_y/-g_z - tan_psi_y(s)) and their
        Jacobian in (w, element), given g and dg/dw."""
        with np.errstate(invalid="ignore", divide="ignore"):
            iz = -1.0 / gw[:, 2]
            r = gw[:, 0] * iz
            q = gw[:, 1] * iz
            dr = (dg[:, 0] + r * dg[:, 2]) * iz
            dq = (dg[:, 1] + q * dg[:, 2]) * iz
        tx, ty, dtx, dty = self.view_tangents(s)
        F = np.stack([r - tx, q - ty], axis=-1)
        J = np.empty(gw.shape[:1] + (2, 2))
        J[:, 0, 0], J[:, 0, 1], J[:, 1, 0], J[:, 1, 1] = dr, -dtx, dq, -dty
        return F, J

    def _camera_vector(self, g, line) -> np.ndarray:
        c, r = self._state_t(self._line_time(line))
        return apply_t(r, g - c)

    def _conditions_exact(self, g, line, s) -> np.ndarray:
        ok = np.isfinite(line) & np.isfinite(s)
        F = np.full(line.shape + (2,), np.nan)
        if ok.any():
            gv = self._camera_vector(g[ok], np.clip(line[ok], 0, self.n_lines - 1))
            tx, ty, _, _ = self.view_tangents(s[ok])
            with np.errstate(invalid="ignore", divide="ignore"):
                F[ok, 0] = gv[:, 0] / -gv[:, 2] - tx
                F[ok, 1] = gv[:, 1] / -gv[:, 2] - ty
        return F

    # --- partial derivatives ----------------------------------------------------------------
    def fd_step_sizes(self) -> np.ndarray:
        """A sensible finite-difference step per flat parameter (for contract tests):
        1e-4 m, 1e-4 deg, and for AP coefficient k ``1e-6 / 1000**k``."""
        out = []
        for b in self._params.blocks:
            if b.units == "":
                out += list(AP_STEP[:b.size])
            else:
                out += [self.fd_steps.get(b.units, 1e-6)] * b.size
        return np.array(out)

    def parameter_partials(self, ground, names: list[str] | None = None) -> np.ndarray:
        """d(line, element)/d(parameter), ``(..., 2, P)``, by the implicit-function theorem
        at the solution: AP columns in closed form, geometric columns from central
        differences of the conditions at the fixed (line, element) (no re-solve).
        Parameters this image does not depend on get zero columns."""
        ground = np.asarray(ground, float)
        shape = ground.shape[:-1]
        g = ground.reshape(-1, 3)
        flat = self._params.flat_names()
        sel = list(range(len(flat))) if names is None else [flat.index(n) for n in names]
        line, s, J = self._solve(g)
        out = np.zeros((g.shape[0], 2, len(sel)))
        out[~np.isfinite(line)] = np.nan
        ok = np.flatnonzero(np.isfinite(line))
        if ok.size == 0 or not sel:
            return out.reshape(shape + (2, len(sel)))
        gk, lk, sk = g[ok], line[ok], s[ok]
        segk = np.clip(np.searchsorted(self._seg, sk, side="right") - 1, 0, self._seg.size - 1)
        dsk = sk - self._seg[segk]
        dF = np.zeros((ok.size, 2, len(sel)))
        blocks = [(b.name, i) for b in self._params.blocks for i in range(b.size)]
        geo = []
        for col, p in enumerate(sel):
            if not self._relevant[p]:
                continue
            bname, comp = blocks[p]
            if bname.startswith(("ax_", "bx_")):
                seg = int(bname.rsplit("_", 1)[1])
                row = 0 if bname.startswith("ax_") else 1
                dF[:, row, col] = np.where(segk == seg, -dsk ** comp, 0.0)
            else:
                geo.append((col, p, bname, comp))
        if geo:
            self._geometric_partials(gk, lk, sk, geo, dF)
        Jinv = np.linalg.inv(J[ok])
        out[ok] = -Jinv @ dF
        return out.reshape(shape + (2, len(sel)))

    def _geometric_partials(self, g, line, s, cols, dF) -> None:
        """Central differences of the conditions at fixed (line, element) for the lever
        arm, boresight and fix-correction columns ``cols`` = [(column, flat index, block,
        component)], written into ``dF``. The trajectory is interpolated once; a fix
        correction is differenced only where its interpolation weight is non-zero."""
        t = self._line_time(np.clip(line, 0, self.n_lines - 1))
        x, ren, rnb, do = self._frames(t)
        do = np.zeros(t.shape + (3,)) if do is None else do
        tx, ty, _, _ = self.view_tangents(s)
        opk = np.radians(np.asarray(self._params["opk_cam"], float))
        steps = self.fd_step_sizes()

        def cond(i, x_, do_, u, R_bs):
            # the centre relative to the ground point: differences of small numbers (ECEF
            # coordinates would cost the central differences 1e-9 m of rounding)
            c, r = _compose(x_ - g[i], ren[i], rnb[i], do_, u, R_bs)
            gv = apply_t(r, -c)
            with np.errstate(invalid="ignore", divide="ignore"):
                return np.stack([gv[:, 0] / -gv[:, 2] - tx[i],
                                 gv[:, 1] / -gv[:, 2] - ty[i]], axis=-1)

        every = np.arange(t.size)
        for col, p, bname, k in cols:
            h = steps[p]
            e = np.zeros(3)
            e[k] = h
            i, xs, dos, us, rs = every, (x, x), (do, do), (self._u_gps,) * 2, (self._R_bs,) * 2
            if bname == "u_gps":
                us = (self._u_gps + e, self._u_gps - e)
            elif bname == "opk_cam":
                rs = tuple(r_opk(*(opk + sgn * np.radians(e))) @ T for sgn in (1, -1))
            else:                                  # d_ned_<j> / d_opk_<j>
                j = int(bname.rsplit("_", 1)[1])
                w = np.interp(t, self._ft, np.eye(self._ft.size)[j])
                i = np.flatnonzero(w != 0)
                if not i.size:
                    continue
                if bname.startswith("d_ned_"):
                    d = apply(ren[i], w[i, None] * e)
                    xs = (x[i] + d, x[i] - d)
                else:
                    d = w[i, None] * np.radians(e)
                    dos = (do[i] + d, do[i] - d)
            xs = tuple(a if a.shape[0] == i.size else a[i] for a in xs)
            dos = tuple(a if a.shape[0] == i.size else a[i] for a in dos)
            fp = cond(i, xs[0], dos[0], us[0], rs[0])
            fm = cond(i, xs[1], dos[1], us[1], rs[1])
            dF[i, :, col] = (fp - fm) / (2 * h)

    def ground_partials(self, ground, step: float = 0.01) -> np.ndarray:
        """d(line, element)/d(X, Y, Z) in ECEF, ``(..., 2, 3)``, in closed form by the
        implicit-function theorem at the solution (``step`` is not used)."""
        ground = np.asarray(ground, float)
        shape = ground.shape[:-1]
        g = ground.reshape(-1, 3)
        line, s, J = self._solve(g)
        out = np.full((g.shape[0], 2, 3), np.nan)
        ok = np.flatnonzero(np.isfinite(line))
        if ok.size:
            c, r = self._state_t(self._line_time(line[ok]))
            gv = apply_t(r, g[ok] - c)
            iz = -1.0 / gv[:, 2]
            d = np.zeros((ok.size, 2, 3))          # d(r, q)/d(g_S)
            d[:, 0, 0] = iz
            d[:, 0, 2] = gv[:, 0] * iz * iz
            d[:, 1, 1] = iz
            d[:, 1, 2] = gv[:, 1] * iz * iz
            dF = d @ np.swapaxes(r, -1, -2)         # g_S = R^T (G - C)
            out[ok] = -np.linalg.inv(J[ok]) @ dF
        return out.reshape(shape + (2, 3))

    # --- AP constraints (calibration) -------------------------------------------------------
    def continuity_residuals(self, params: ParameterSet | None = None) -> np.ndarray:
        """C0/C1 residuals of this camera's AP polynomials (see :func:`continuity_residuals`)."""
        return continuity_residuals(self._sensor, params or self._params)

    @classmethod
    def example_model(cls, view: str = "nadir", n_lines: int = 600) -> "PushbroomModel":
        """A realistic three-line camera image (for contract tests and examples): 3072
        elements in three segments, 10 um pixels, f = 0.1 m, 2000 m above ground at 60 m/s
        with a gently wobbling attitude, small APs, three orientation fixes."""
        return _example(cls, view, n_lines)


def _matvec(m, v) -> np.ndarray:
    """``m @ v`` for stacks ``(n, 3, 3)`` and ``(n, 3)`` (faster than einsum here)."""
    return (m[:, :, 0] * v[:, 0:1] + m[:, :, 1] * v[:, 1:2] + m[:, :, 2] * v[:, 2:3])


def _bracket(f_at, n: int, K: int):
    """Like :func:`swathflow.geometry.linesolve.bracket_lines` (same returns; ``f_at(None, j)``
    evaluates all points at one line ``j``), but faster for the
    near-linear push-broom condition: each step evaluates ``m`` and ``m + 1`` at a guess
    (first the bracket's chord, then a Newton step with the local slope ``f(m+1) - f(m)``)
    and usually settles in two or three steps; from the fourth step on, a step that does not
    halve the bracket makes the next one a bisection, so the worst case stays logarithmic."""
    lo = np.zeros(n, dtype=np.intp)
    hi = np.full(n, K - 1, dtype=np.intp)
    flo = f_at(None, 0)
    fhi = f_at(None, K - 1)
    found = (np.sign(flo) != np.sign(fhi)) & np.isfinite(flo) & np.isfinite(fhi)
    x = np.zeros(n)
    with np.errstate(invalid="ignore", divide="ignore"):
        x[:] = flo / (flo - fhi) * (K - 1)          # chord
    bisect = np.zeros(n, bool)
    act = np.flatnonzero(found & (hi - lo > 1))
    step = 0
    while act.size:
        step += 1
        l, h, fl = lo[act], hi[act], flo[act]
        xa = x[act]
        m = np.where(bisect[act] | ~np.isfinite(xa), (l + h) // 2,
                     np.floor(np.nan_to_num(xa)).astype(np.intp))
        m = np.clip(m, l + 1, h - 1)
        m1 = np.minimum(m + 1, h)
        fm = f_at(act, m)
        fm1 = f_at(act, m1)
        same = np.sign(fm) == np.sign(fl)
        same1 = np.sign(fm1) == np.sign(fl)
        # the root lies in (l, m), (m, m1) or (m1, h)
        nl = np.where(same, np.where(same1, m1, m), l)
        nfl = np.where(same, np.where(same1, fm1, fm), fl)
        nh = np.where(same, np.where(same1, h, m1), m)
        nfh = np.where(same, np.where(same1, fhi[act], fm1), fm)
        bisect[act] = (step >= 4) & ((nh - nl) * 2 > (h - l))
        with np.errstate(invalid="ignore", divide="ignore"):
            x[act] = m - fm / (fm1 - fm)           # Newton with the local slope
        lo[act], hi[act], flo[act], fhi[act] = nl, nh, nfl, nfh
        act = act[(nh - nl) > 1]
    return lo, flo, fhi, found


def _solve2(J, F) -> tuple[np.ndarray, np.ndarray]:
    """Solve the 2x2 systems ``J x = F`` (stacked), NaN where singular."""
    det = J[:, 0, 0] * J[:, 1, 1] - J[:, 0, 1] * J[:, 1, 0]
    with np.errstate(invalid="ignore", divide="ignore"):
        x0 = (J[:, 1, 1] * F[:, 0] - J[:, 0, 1] * F[:, 1]) / det
        x1 = (J[:, 0, 0] * F[:, 1] - J[:, 1, 0] * F[:, 0]) / det
    return x0, x1


# --- AP continuity (C0) and smoothness (C1) constraints ------------------------------------------
def continuity_matrix(sensor: Mapping[str, Any], params: ParameterSet
                      ) -> tuple[np.ndarray, list[str]]:
    """The linear C0/C1 constraints of the AP polynomials as ``(A, labels)``: the
    residuals are ``A @ params.vector()`` (zero when the constraints hold). Per view, per
    segment boundary ``b = segments[i + 1]`` and per polynomial (ax, bx): value (C0) and first
    derivative (C1) of segment ``i`` at ``ds = b - segments[i]`` minus segment ``i + 1`` at 0."""
    flat = params.flat_names()
    col = {n: i for i, n in enumerate(flat)}
    rows, labels = [], []
    for view, cfg in views(sensor).items():
        seg = np.asarray(cfg.get("segments", [0]), float)
        for i in range(seg.size - 1):
            d = seg[i + 1] - seg[i]
            for kind in ("ax", "bx"):
                left, right = ap_name(kind, view, i), ap_name(kind, view, i + 1)
                for order, coef in (("C0", [1.0, d, d * d, d ** 3]),
                                    ("C1", [0.0, 1.0, 2 * d, 3 * d * d])):
                    r = np.zeros(len(flat))
                    for m in range(4):
                        r[col[f"{left}[{m}]"]] += coef[m]
                    r[col[f"{right}[0]" if order == "C0" else f"{right}[1]"]] -= 1.0
                    rows.append(r)
                    labels.append(f"{order} {kind} {view + ' ' if view else ''}"
                                  f"segments {i}/{i + 1} at element {int(seg[i + 1])}")
    A = np.array(rows).reshape(-1, len(flat))
    return A, labels


def continuity_residuals(sensor: Mapping[str, Any], params: ParameterSet) -> np.ndarray:
    """C0 and C1 residuals of the AP polynomials at every segment boundary (tan units and
    tan units per element), in the row order of :func:`continuity_matrix`."""
    A, _ = continuity_matrix(sensor, params)
    return A @ params.vector()


# --- example ---------------------------------------------------------------------------------------
def example_sensor() -> dict:
    """The three-line camera of :meth:`PushbroomModel.example_model` as a ``[sensor]`` dict."""
    rng = np.random.default_rng(8)
    seg = [0, 1024, 2048]

    def aps():
        # smooth APs: one cubic over the whole line, re-expanded per segment (C0/C1 hold)
        c = rng.normal(0, 1, 4) * np.array([2e-4, 1e-7, 1e-11, 1e-14])
        out = []
        for s0 in seg:
            # p(s0 + ds) = sum c_m (s0 + ds)^m -> coefficients in ds
            a0 = c[0] + c[1] * s0 + c[2] * s0 ** 2 + c[3] * s0 ** 3
            a1 = c[1] + 2 * c[2] * s0 + 3 * c[3] * s0 ** 2
            a2 = c[2] + 3 * c[3] * s0
            out.append([a0, a1, a2, c[3]])
        return out

    v = {name: {"psi_x0_deg": psi, "ax": aps(), "bx": aps()}
         for name, psi in THREE_LINE_VIEWS.items()}
    return {"model": "pushbroom", "n_elements": 3072, "segments": seg, "pixel_pitch": 1e-5,
            "focal_length": 0.1, "s_c": 1535.5, "views": v,
            "fixes": {"time": [1000.0, 1005.0, 1010.0],
                      "d_ned": [[0.1, -0.2, 0.05], [-0.1, 0.15, 0.0], [0.05, 0.0, -0.1]],
                      "d_opk": [[0.002, -0.001, 0.003], [0.0, 0.002, -0.002],
                                [-0.001, 0.0, 0.001]]}}


def example_trajectory(t0: float = 995.0, t1: float = 1015.0, lat0: float = 34.0,
                       lon0: float = 113.0, h: float = 2080.0, speed: float = 60.0,
                       heading: float = 30.0, rate: float = 200.0):
    """A straight flight line with a gentle attitude wobble, as a Trajectory."""
    import xarray as xr
    from swathflow.formats.pos import Trajectory
    t = np.arange(t0, t1 + 0.5 / rate, 1.0 / rate)
    d = speed * (t - t0)
    R = 6378137.0
    hd = np.radians(heading)
    lat = lat0 + np.degrees(d * np.cos(hd) / R)
    lon = lon0 + np.degrees(d * np.sin(hd) / (R * np.cos(np.radians(lat0))))
    roll = 0.3 * np.sin(2 * np.pi * 0.21 * (t - t0))
    pitch = 1.5 + 0.2 * np.sin(2 * np.pi * 0.13 * (t - t0) + 1.0)
    hdg = heading + 0.4 * np.sin(2 * np.pi * 0.07 * (t - t0))
    ds = xr.Dataset({"lat": ("time", lat), "lon": ("time", lon), "h": ("time", np.full_like(t, h)),
                     "roll": ("time", roll), "pitch": ("time", pitch),
                     "heading": ("time", (hdg + 180) % 360 - 180)}, coords={"time": t})
    return Trajectory.from_dataset(ds)


def _example(cls, view: str, n_lines: int):
    line_period = 0.2 / 60.0   # one ground sample (0.2 m at 2000 m) per line at 60 m/s
    time = 1003.0 + line_period * np.arange(n_lines)
    return cls.build(example_sensor(), {"time": time}, example_trajectory(), None,
                     image_id=f"{view}-1", view=view, strip=1)
