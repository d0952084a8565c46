"""Viewing angles of the push-broom CCD lines: the ``[sensor]`` table's lines (views), the
per-segment cubic additional parameters (APs) and their continuity (C0) and smoothness (C1)
constraints (docs/geometry.md, push-broom section).

Per element the viewing angles come from the nominal design (``pixel_pitch``,
``focal_length``, ``s_c``, ``psi_x0_deg``) or from a laboratory table (``tan_psi_x``,
``tan_psi_y``, one value per element, linear between element centres), plus the APs: a cubic
in ``ds = s - segments[i]`` per CCD segment for ``tan_psi_x`` (``ax``) and ``tan_psi_y``
(``bx``).
"""
from __future__ import annotations

from typing import Any, Mapping

import numpy as np

from swathflow.sensormodel.base import ParameterSet

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


# --- configuration checks -------------------------------------------------------------------
def check_view(name: str, cfg: Mapping[str, Any]) -> list[str]:
    """Problems with one CCD line's effective configuration (``views(sensor)[name]``)."""
    where = f"view {name!r}: " if name else ""
    n = cfg.get("n_elements")
    try:
        n = int(n)
    except (TypeError, ValueError):
        return [f"{where}n_elements must be an integer, got {n!r}"]
    out = [f"{where}n_elements must be at least 2, got {n}"] if n < 2 else []
    return out + _check_angles(where, cfg, n) + _check_segments(where, cfg, n)


def _check_angles(where: str, cfg: Mapping[str, Any], n: int) -> list[str]:
    """The laboratory table (one finite value per element) or the nominal design keys."""
    out = []
    if "tan_psi_x" in cfg or "tan_psi_y" in cfg:
        for k in ("tan_psi_x", "tan_psi_y"):
            a = np.asarray(cfg.get(k, []), float).ravel()
            if a.size != n or not np.all(np.isfinite(a)):
                out.append(f"{where}{k} needs {n} finite values (one per element), got {a.size}")
        return out
    for k in ("pixel_pitch", "focal_length", "s_c"):
        if k not in cfg:
            out.append(f"{where}missing key {k!r} (or give the laboratory table "
                       f"tan_psi_x/tan_psi_y)")
    for k in ("pixel_pitch", "focal_length"):
        if k in cfg and not float(cfg[k]) > 0:
            out.append(f"{where}{k} must be positive, got {cfg[k]!r}")
    return out


def _check_segments(where: str, cfg: Mapping[str, Any], n: int) -> list[str]:
    """Segment starts and the shape of the AP coefficient tables."""
    out = []
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


def check_fixes(sensor: Mapping[str, Any]) -> list[str]:
    """Problems with the ``[sensor.fixes]`` table (LIM orientation fixes)."""
    fx = sensor.get("fixes")
    if fx is None:
        return []
    out = []
    t = fix_times(sensor)
    if t.size == 0 or np.any(np.diff(t) <= 0):
        out.append("fixes.time must be a non-empty increasing list of times (s)")
    for k in ("d_ned", "d_opk"):
        if k in fx and np.asarray(fx[k], float).shape != (t.size, 3):
            out.append(f"fixes.{k} needs 3 values per fix ({t.size} fixes)")
    return out


# --- per-element tangents -------------------------------------------------------------------
def tangent_table(n: int, seg: np.ndarray, ax: np.ndarray, bx: np.ndarray,
                  nominal: tuple[float, float, float] | None = None,
                  table: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
    """Per element interval ``[i, i + 1)`` (i = 0 .. n-1, the last one extrapolating) the
    cubic coefficients in ``u = s - i`` of tan_psi_x (columns 0-3) and tan_psi_y (4-7):
    exact, since within an interval the APs are one cubic and the rest is linear.

    ``seg`` are the segment starts, ``ax``/``bx`` the APs ``(n_segments, 4)``; the rest is
    either ``nominal = (tan psi_x0, pixel_pitch / focal_length, s_c)`` or the laboratory
    ``table = (tan_psi_x, tan_psi_y)``."""
    i = np.arange(n, dtype=float)
    sg = np.clip(np.searchsorted(seg, i, side="right") - 1, 0, seg.size - 1)
    d = i - seg[sg]
    out = np.zeros((n, 8))
    for col, a in ((0, ax[sg]), (4, bx[sg])):
        out[:, col] = a[:, 0] + d * (a[:, 1] + d * (a[:, 2] + d * a[:, 3]))
        out[:, col + 1] = a[:, 1] + d * (2 * a[:, 2] + 3 * d * a[:, 3])
        out[:, col + 2] = a[:, 2] + 3 * d * a[:, 3]
        out[:, col + 3] = a[:, 3]
    if table is None:
        tpx0, k, sc = nominal
        out[:, 0] += tpx0
        out[:, 4] += (i - sc) * k
        out[:, 5] += k
    else:
        for col, y in ((0, table[0]), (4, table[1])):
            slope = np.diff(y)
            out[:, col] += y
            out[:, col + 1] += np.append(slope, slope[-1])
    return out


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

