"""Compiled refinement of the pendulum's ground_to_image (numba): the same steps as
``PendulumModel._refine`` and ``_camera_of`` one point at a time (POS interpolation,
closed-form rotation chain, inverse quadratic root and Lagrange camera vector), so the
lattice's exact projections cost well under a microsecond a point.
"""
from __future__ import annotations

import math

import numpy as np

from swathflow.geometry.navkernel import body_to_ecef, line_at, pos_epoch
from swathflow.geometry.planesolve import bracket_one
from numba import njit

DEG = math.pi / 180.0


def trig_tables(geo) -> tuple:
    """The sines and cosines the kernels' :func:`_camera_of` starts from: of the POS
    table's latitude, longitude, roll, pitch and heading at the epochs ``k0 ..`` the
    image's lines span ``(n, 10)``, of the swing and pitch compensation at every line
    ``(lines, 4)``; every line's POS epoch (the search's start); and ``k0``."""
    cols, time, table = geo[0], geo[1], geo[2]
    epoch = np.searchsorted(time, cols[:, 0], side="right") - 1
    k0 = max(int(epoch.min()), 0)
    a = np.radians(table[k0:max(int(epoch.max()), k0) + 2, 3:8])
    pos_trig = np.ascontiguousarray(np.stack([np.sin(a), np.cos(a)], axis=-1).reshape(-1, 10))
    line_trig = np.ascontiguousarray(np.stack([np.sin(cols[:, 1:3]), np.cos(cols[:, 1:3])],
                                              axis=-1).reshape(-1, 4))
    return pos_trig, line_trig, epoch, k0


@njit(cache=True, nogil=True, error_model="numpy")
def _sin_cos(a, d, sa, ca):
    """sin and cos of ``a + d`` (radians) from ``sin a``, ``cos a``: the angle sum with
    the Taylor series of a small ``d`` (|d| < 0.02: the terms left out are below 1e-25),
    else ``math.sin``, ``math.cos``."""
    if abs(d) < 0.02:
        d2 = d * d
        sd = d * (1 - d2 / 6 * (1 - d2 / 20 * (1 - d2 / 42 * (1 - d2 / 72))))
        cd = 1 - d2 / 2 * (1 - d2 / 12 * (1 - d2 / 30 * (1 - d2 / 56 * (1 - d2 / 90))))
        return sa * cd + ca * sd, ca * cd - sa * sd
    return math.sin(a + d), math.cos(a + d)


@njit(cache=True, nogil=True, error_model="numpy")
def _epoch_sin_cos(table, pos, pos_trig, k, kt, c):
    """sin and cos of the interpolated POS angle ``pos[c]`` (degrees; columns 3-7 of the
    table) from those at epoch ``k`` (row ``kt`` of ``pos_trig``, -1: not there). One
    return: an early one cost reference counting of the arrays at every call."""
    a = table[k, c] * DEG
    p = pos[c] * DEG
    if kt < 0:
        sp, cp = math.sin(p), math.cos(p)
    else:
        sp, cp = _sin_cos(a, p - a, pos_trig[kt, 2 * (c - 3)], pos_trig[kt, 2 * (c - 3) + 1])
    return sp, cp


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _camera_of(line, g, cols, time, table, max_gap, rig, pos_trig, line_trig, line_epoch,
               k0, cam, pos):
    """The camera-frame vector of ground point ``g`` seen from fractional ``line`` (the
    POS interpolated linearly, its angles' sines from the epochs' by :func:`_sin_cos`;
    the arrays of ``geo`` and ``trig`` one by one, ``rig`` from :func:`_rig`: the
    kernels unpack their tuples once per call, not once per point, whose reference
    counting cost more than the rotations). False where the POS cannot be interpolated
    (outside the trajectory, in a gap)."""
    n = cols.shape[0]
    line = min(max(line, 0.0), n - 1.0)
    i = min(int(line), n - 2)
    w = line - i
    t = cols[i, 0] * (1 - w) + cols[i + 1, 0] * w
    k = pos_epoch(time, table, max_gap, t, line_epoch[i], pos)
    if k < 0:
        return False
    x, y, z = g[0] - pos[0], g[1] - pos[1], g[2] - pos[2]
    kt = k - k0                    # in the table (the epochs the lines span), or -1
    if kt < 0 or kt >= pos_trig.shape[0]:
        kt = -1
    sl, cl = _epoch_sin_cos(table, pos, pos_trig, k, kt, 3)
    so, co = _epoch_sin_cos(table, pos, pos_trig, k, kt, 4)
    e_ = -so * x + co * y
    n_ = -sl * co * x - sl * so * y + cl * z
    d_ = -cl * co * x - cl * so * y - sl * z
    x, y, z = n_, e_, d_
    sh, ch = _epoch_sin_cos(table, pos, pos_trig, k, kt, 7)
    x, y = ch * x + sh * y, -sh * x + ch * y
    sp, cp = _epoch_sin_cos(table, pos, pos_trig, k, kt, 6)
    x, z = cp * x - sp * z, sp * x + cp * z
    sr, cr = _epoch_sin_cos(table, pos, pos_trig, k, kt, 5)
    y, z = cr * y + sr * z, -sr * y + cr * z
    x, y, z = x - rig[6, 0], y - rig[6, 1], z - rig[6, 2]
    x, y, z = (x * rig[0, 0] + y * rig[1, 0] + z * rig[2, 0],
               x * rig[0, 1] + y * rig[1, 1] + z * rig[2, 1],
               x * rig[0, 2] + y * rig[1, 2] + z * rig[2, 2])
    s = cols[i, 1] * (1 - w) + cols[i + 1, 1] * w
    q = cols[i, 2] * (1 - w) + cols[i + 1, 2] * w
    ss, cs = _sin_cos(cols[i, 1], s - cols[i, 1], line_trig[i, 0], line_trig[i, 1])
    y, z = cs * y + ss * z, -ss * y + cs * z
    sq, cq = _sin_cos(cols[i, 2], q - cols[i, 2], line_trig[i, 2], line_trig[i, 3])
    x, z = cq * x - sq * z, sq * x + cq * z
    x, y, z = x - rig[7, 0], y - rig[7, 1], z - rig[7, 2]
    for a in range(3):
        cam[a] = x * rig[3, a] + y * rig[4, a] + z * rig[5, a]
    return True


@njit(cache=True, nogil=True, error_model="numpy")
def _rig(r_bp_t, r_hs, u_gps, u_sen):
    """``R_BP^T``, ``R_HS`` (rows 0-2, 3-5), ``u_gps``, ``u_sen`` (rows 6, 7) of ``geo``
    in one ``(8, 3)`` array, as :func:`_camera_of` takes them."""
    rig = np.empty((8, 3))
    for a in range(3):
        for b in range(3):
            rig[a, b], rig[3 + a, b] = r_bp_t[a, b], r_hs[a, b]
        rig[6, a], rig[7, a] = u_gps[a], u_sen[a]
    return rig


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _frame_vector(r_es, c, j, g, out):
    """``R_ES[j]^T (g - C[j])``: the camera vector at integer line ``j``."""
    dx, dy, dz = g[0] - c[j, 0], g[1] - c[j, 1], g[2] - c[j, 2]
    for k in range(3):
        out[k] = r_es[j, 0, k] * dx + r_es[j, 1, k] * dy + r_es[j, 2, k] * dz


@njit(cache=True, nogil=True, error_model="numpy")
def _sgn(v):
    return (v > 0.0) - (v < 0.0)


@njit(cache=True, nogil=True, error_model="numpy")
def _quadratic_root(x0, x2, fj, fj1, l1, f1, rough_line):
    """Inverse quadratic root through (x0, l1, x2), the secant against the far bracket end
    where it leaves the bracket; and whether the two disagree (solve exactly)."""
    same = _sgn(f1) == _sgn(fj)
    ja = x2 if same else x0
    fa = fj1 if same else fj
    w = f1 / (f1 - fa) if f1 - fa != 0.0 else math.nan
    line = l1 + (w if math.isfinite(w) else 0.0) * (ja - l1)
    x1 = l1
    q = (x0 * f1 * fj1 / ((fj - f1) * (fj - fj1)) + x1 * fj * fj1 / ((f1 - fj) * (f1 - fj1))
         + x2 * fj * f1 / ((fj1 - fj) * (fj1 - f1)))
    use = math.isfinite(q) and q >= x0 and q <= x2
    rough = (not use) or abs(q - line) > rough_line
    return (q if use else line), rough


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _lagrange(line, x0, l1, x2, cam0, cam1, cam2, out):
    """The camera vector at ``line``: quadratic through the lines x0, l1, x2 (linear
    where the chord point sits on an end)."""
    x1 = l1
    d01, d02, d12 = (x0 - x1) * (x0 - x2), (x1 - x0) * (x1 - x2), (x2 - x0) * (x2 - x1)
    if d01 != 0.0 and d02 != 0.0 and d12 != 0.0:
        a0 = (line - x1) * (line - x2) / d01
        a1 = (line - x0) * (line - x2) / d02
        a2 = (line - x0) * (line - x1) / d12
        if math.isfinite(a0) and math.isfinite(a1) and math.isfinite(a2):
            for k in range(3):
                out[k] = a0 * cam0[k] + a1 * cam1[k] + a2 * cam2[k]
            return
    t = (line - x0) / (x2 - x0)
    for k in range(3):
        out[k] = cam0[k] + t * (cam2[k] - cam0[k])


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _chord_solve(g, x0, f0, cam0, x2, f2, cam2, nvec, cols, time, table, max_gap, rig,
                 pos_trig, line_trig, line_epoch, k0, rough_line, cam1, pos, out):
    """The root inside ``[x0, x2]``, where the condition is smooth, from one exact
    evaluation at the chord point (the inverse quadratic, the camera vector by Lagrange
    through x0, the chord point, x2) into ``out``; NaN where that is rough or the POS
    cannot be interpolated (the caller solves exactly)."""
    d = f0 - f2
    l1 = x0 + f0 / d * (x2 - x0) if d != 0.0 else math.nan
    if not math.isfinite(l1):
        l1 = (x0 + x2) / 2
    if not _camera_of(l1, g, cols, time, table, max_gap, rig, pos_trig, line_trig,
                      line_epoch, k0, cam1, pos):
        return math.nan
    f1 = cam1[0] * nvec[0] + cam1[1] * nvec[1] + cam1[2] * nvec[2]
    line, rough = _quadratic_root(x0, x2, f0, f2, l1, f1, rough_line)
    if rough:
        return math.nan
    _lagrange(line, x0, l1, x2, cam0, cam1, cam2, out)
    return line


@njit(cache=True, nogil=True, error_model="numpy")
def _secant(g, j, fj, fj1, nvec, cols, time, table, max_gap, rig, pos_trig, line_trig,
            line_epoch, k0, tol, max_iter, cam, pos):
    """Secant iterations on the exact condition inside ``[j, j+1]`` (as
    ``linesolve.secant_lines``); the line, with the exact camera vector left in ``cam``."""
    l0, f0 = float(j), fj
    d = fj - fj1
    l1 = j + fj / d if d != 0.0 else math.nan
    if not math.isfinite(l1):
        l1 = j + 0.5
    for _ in range(max_iter):
        if not _camera_of(l1, g, cols, time, table, max_gap, rig, pos_trig, line_trig,
                          line_epoch, k0, cam, pos):
            return math.nan
        f1 = cam[0] * nvec[0] + cam[1] * nvec[1] + cam[2] * nvec[2]
        step = f1 * (l1 - l0) / (f1 - f0)
        if not math.isfinite(step):
            step = 0.0
        l0, f0, l1 = l1, f1, l1 - step
        if not abs(step) > tol:
            break
    if not _camera_of(l1, g, cols, time, table, max_gap, rig, pos_trig, line_trig,
                      line_epoch, k0, cam, pos):
        return math.nan
    return l1


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _dot(cam, nvec):
    return cam[0] * nvec[0] + cam[1] * nvec[1] + cam[2] * nvec[2]


@njit(cache=True, nogil=True, error_model="numpy")
def epoch_frames(geo, trig, nvec):
    """The camera frames at the POS epochs ``k0 ..`` of :func:`trig_tables` that fall
    inside a line (between two line times): their fractional lines, ``R`` ``(n, 3, 3)``
    and ``C`` ``(n, 3)`` with ``R^T (g - C)`` the camera vector of ``g`` there (as
    :func:`_camera_of` gives it: the chain is affine in ``g``; its columns from
    :func:`_camera_of` at points 1024 m apart along the axes, exact differences), and the
    viewing plane (as the lines' planes); NaN for the other epochs."""
    cols, time, table, max_gap = geo[0], geo[1], geo[2], geo[3]
    pos_trig, line_trig, line_epoch, k0 = trig
    n = pos_trig.shape[0]
    rig = _rig(geo[4], geo[5], geo[6], geo[7])
    lines = np.full(n, np.nan)
    r = np.full((n, 3, 3), np.nan)
    c = np.full((n, 3), np.nan)
    planes = np.full((n, 4), np.nan)
    cam0, cam, pos, x = np.empty(3), np.empty(3), np.empty(8), np.empty(3)
    for kt in range(n):
        k = k0 + kt
        a = np.searchsorted(cols[:, 0], time[k], side="right") - 1
        if not (a >= 0 and a + 1 < cols.shape[0] and time[k] > cols[a, 0]
                and time[k] < cols[a + 1, 0]):
            continue
        le = a + (time[k] - cols[a, 0]) / (cols[a + 1, 0] - cols[a, 0])
        for j in range(3):         # element by element: an array assigned to a slice
            x[j] = geo[2][k, j]    # compiles numba's shape-mismatch message (~5 s)
        if not _camera_of(le, x, cols, time, table, max_gap, rig, pos_trig, line_trig,
                          line_epoch, k0, cam0, pos):
            continue
        for j in range(3):
            x[j] += 1024.0
            _camera_of(le, x, cols, time, table, max_gap, rig, pos_trig, line_trig,
                       line_epoch, k0, cam, pos)
            x[j] -= 1024.0
            for q in range(3):
                r[kt, j, q] = (cam[q] - cam0[q]) / 1024.0
        for j in range(3):
            c[kt, j] = x[j] - (r[kt, j, 0] * cam0[0] + r[kt, j, 1] * cam0[1]
                               + r[kt, j, 2] * cam0[2])
        for j in range(3):
            planes[kt, j] = r[kt, j, 0] * nvec[0] + r[kt, j, 1] * nvec[1] + r[kt, j, 2] * nvec[2]
        planes[kt, 3] = -(planes[kt, 0] * c[kt, 0] + planes[kt, 1] * c[kt, 1]
                          + planes[kt, 2] * c[kt, 2])
        lines[kt] = le
    return lines, r, c, planes


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _end(e, a, kt0, r_es, c, ep_line, ep_r, ep_c, g, cam):
    """End ``e`` of the pieces of line ``[a, a+1]`` (-1: line a, -2: line a + 1, else
    row ``kt0 + e`` of the epoch frames): its fractional line, the camera vector of ``g``
    into ``cam``."""
    if e < 0:
        j = a if e == -1 else a + 1
        _frame_vector(r_es, c, j, g, cam)
        return float(j)
    _frame_vector(ep_r, ep_c, kt0 + e, g, cam)
    return ep_line[kt0 + e]


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _epoch_piece(ep_planes, time, k1, kt0, t1, gx, gy, gz, fa, fb):
    """The piece of a line (its ends at conditions ``fa``, ``fb``; the POS epochs ``k1 ..``
    before ``t1`` inside it, rows ``kt0 ..`` of the epoch frames) on which the condition
    of ground point ``(gx, gy, gz)`` changes sign: ``(left, right, f_left, f_right,
    ok)``, the ends as :func:`_end` takes them; ok False where an epoch has no frame (one
    return: an early one in the loop cost reference counting at every point)."""
    left, right, fl, fr = -1, -2, fa, fb
    ok = k1 >= 1 and kt0 >= 0
    e = 0
    while ok and kt0 + e < ep_planes.shape[0] and k1 + e + 1 < time.shape[0] and (
            time[k1 + e] < t1):
        f = (ep_planes[kt0 + e, 0] * gx + ep_planes[kt0 + e, 1] * gy
             + ep_planes[kt0 + e, 2] * gz + ep_planes[kt0 + e, 3])
        ok = math.isfinite(f)
        if ok and (f == 0.0 or _sgn(f) != _sgn(fl)):
            right, fr = e, f
            break
        left, fl = e, f
        e += 1
    return left, right, fl, fr, ok


@njit(cache=True, nogil=True, error_model="numpy")
def ground_to_image(points, planes, grid, nvec, geo, trig, frames, rough_line, pixel, clip,
                    out):
    """``PendulumModel.ground_to_image`` of points ``(n, 3)`` into ``out`` ``(n, 2)``:
    the brackets between the lines' viewing planes (``planesolve.bracket_one`` over the
    coarse ``grid``), the refinement (``geo``: line columns, POS times and table,
    max gap, R_BP^T, R_HS, u_gps, u_sen; ``trig``: :func:`trig_tables`; ``frames``: the
    lines' R_ES and projection centres, then :func:`epoch_frames`), then the element
    (``pixel``: k0, focal length, pixel pitch, elements); NaN behind the camera, where no
    line sees the point and, with ``clip``, off the detector. False where the POS could
    not be interpolated (the caller then takes the numpy path, which reports it)."""
    return _g2i(points, planes, grid, nvec, geo, trig, frames, rough_line, pixel, clip, out,
                np.empty((6, 8)))


@njit(cache=True, nogil=True, error_model="numpy", _nrt=False)
def _g2i(points, planes, grid, nvec, geo, trig, frames, rough_line, pixel, clip, out,
         scratch):
    """:func:`ground_to_image`'s loop, compiled without reference counting (``scratch``:
    its work vectors): with it, the arrays handed to the inlined helpers were counted in
    and out at every point (atomic operations, 2/3 of the kernel's time)."""
    cam0, cam1, cam2 = scratch[0, :3], scratch[1, :3], scratch[2, :3]
    pos, gi, cam = scratch[3], scratch[4, :3], scratch[5, :3]
    k0, focal, pitch, n_elements = pixel
    # the tuples unpacked once, and the refinement written out in the loop: helpers
    # taking the arrays (or the tuples) paid reference counting on every argument at
    # every point, more than the arithmetic (a point seen on a survey tile: 0.68 us with
    # the tuples unpacked per point, 0.25 us now, the same bits)
    cols, time, table, max_gap = geo[0], geo[1], geo[2], geo[3]
    rig = _rig(geo[4], geo[5], geo[6], geo[7])
    pos_trig, line_trig, line_epoch, e0 = trig
    r_es, c, ep_line, ep_r, ep_c, ep_planes = frames
    for i in range(points.shape[0]):
        gi[0], gi[1], gi[2] = points[i, 0], points[i, 1], points[i, 2]
        out[i, 0] = out[i, 1] = math.nan
        a, fa, fb, found = bracket_one(planes, grid, gi[0], gi[1], gi[2])
        if not found:
            continue
        # the refinement, written out here rather than in helpers taking the arrays (the
        # reference counting of their arguments cost more than the arithmetic)
        line = math.nan
        t1 = cols[a + 1, 0]
        k1 = line_epoch[a] + 1           # the first epoch after line a's time
        if k1 + 1 < time.shape[0] and time[k1] < t1:
            # POS epochs inside the line put a kink in the condition at each: the line's
            # ends and the epochs' fractional lines cut it into pieces on which it is
            # smooth; the epochs' viewing planes (:func:`epoch_frames`) find the piece with
            # the sign change, :func:`_chord_solve` solves there (one exact evaluation, as
            # a line without an epoch; the secant needed five or more where a line holds
            # several, as on the survey: a 50 Hz POS, 16 lines a second). Where an epoch
            # has no frame or that solve is rough, the secant below solves exactly.
            kt0 = k1 - e0
            left, right, fl, fr, ok = _epoch_piece(ep_planes, time, k1, kt0, t1, gi[0], gi[1],
                                                   gi[2], fa, fb)
            if ok:
                xl = _end(left, a, kt0, r_es, c, ep_line, ep_r, ep_c, gi, cam0)
                xr = _end(right, a, kt0, r_es, c, ep_line, ep_r, ep_c, gi, cam2)
                if fr == 0.0:
                    for q in range(3):
                        cam[q] = cam2[q]
                    line = xr
                elif xr > xl and _sgn(fl) != _sgn(fr):
                    line = _chord_solve(gi, xl, fl, cam0, xr, fr, cam2, nvec, cols, time,
                                        table, max_gap, rig, pos_trig, line_trig,
                                        line_epoch, e0, rough_line, cam1, pos, cam)
        else:
            # no epoch inside the line: one exact evaluation at the chord point, the
            # inverse quadratic root (rough: the secant below)
            d = fa - fb
            l1 = a + fa / d if d != 0.0 else math.nan
            if not math.isfinite(l1):
                l1 = a + 0.5
            if not _camera_of(l1, gi, cols, time, table, max_gap, rig, pos_trig, line_trig,
                              line_epoch, e0, cam1, pos):
                return False
            f1 = cam1[0] * nvec[0] + cam1[1] * nvec[1] + cam1[2] * nvec[2]
            line, rough = _quadratic_root(float(a), a + 1.0, fa, fb, l1, f1, rough_line)
            if rough:
                line = math.nan
            else:
                _frame_vector(r_es, c, a, gi, cam0)
                _frame_vector(r_es, c, a + 1, gi, cam2)
                _lagrange(line, float(a), l1, a + 1.0, cam0, cam1, cam2, cam)
        if math.isnan(line):     # rough (or the split's solve was): solve exactly
            line = _secant(gi, a, fa, fb, nvec, cols, time, table, max_gap, rig, pos_trig,
                           line_trig, line_epoch, e0, 1e-9, 30, cam, pos)
        if math.isnan(line):
            return False
        if not cam[2] < 0:                       # behind the camera
            continue
        elem = k0 + focal * cam[0] / (-cam[2]) / pitch
        if clip and not (elem >= -0.5 and elem <= n_elements - 0.5):
            continue
        out[i, 0], out[i, 1] = line, elem
    return True


@njit(cache=True, nogil=True, error_model="numpy")
def rays(image, geo, trig_t, k0, pixel_pitch, y0, focal, c_out, d_out):
    """Projection centres and unit directions (ECEF) of image points ``(n, 2)``: the
    numpy ``PendulumModel.ray`` one point at a time (``geo`` as for
    :func:`ground_to_image`, ``trig_t`` :func:`trig_tables`: the sines start from the
    epochs' and the lines', as in :func:`_camera_of`). Returns False where a line is not
    finite or the POS cannot be interpolated at its time (the caller then takes the numpy
    path, which reports it)."""
    return _rays(image, geo, trig_t, k0, pixel_pitch, y0, focal, c_out, d_out, np.empty(8))


@njit(cache=True, nogil=True, error_model="numpy", _nrt=False)
def _rays(image, geo, trig_t, k0, pixel_pitch, y0, focal, c_out, d_out, pos):
    """:func:`rays`' loop, compiled without reference counting (as :func:`_g2i`)."""
    cols, time, table, max_gap, r_bp, r_hs, u_gps, u_sen = geo
    pos_trig, line_trig, line_epoch, e0 = trig_t
    n = cols.shape[0]
    for i in range(image.shape[0]):
        line = image[i, 0]
        if not math.isfinite(line):
            return False
        j, w = line_at(line, n)
        t = cols[j, 0] * (1 - w) + cols[j + 1, 0] * w
        s = cols[j, 1] * (1 - w) + cols[j + 1, 1] * w
        q = cols[j, 2] * (1 - w) + cols[j + 1, 2] * w
        k = pos_epoch(time, table, max_gap, t, line_epoch[j], pos)
        if k < 0:
            return False
        kt = k - e0
        if kt < 0 or kt >= pos_trig.shape[0]:
            kt = -1
        sl, cl = _epoch_sin_cos(table, pos, pos_trig, k, kt, 3)
        so, co = _epoch_sin_cos(table, pos, pos_trig, k, kt, 4)
        sr, cr = _epoch_sin_cos(table, pos, pos_trig, k, kt, 5)
        sp, cp = _epoch_sin_cos(table, pos, pos_trig, k, kt, 6)
        sh, ch = _epoch_sin_cos(table, pos, pos_trig, k, kt, 7)
        trig = (sr, cr, sp, cp, sh, ch, sl, cl, so, co)
        ss, cs = _sin_cos(cols[j, 1], s - cols[j, 1], line_trig[j, 0], line_trig[j, 1])
        sq, cq = _sin_cos(cols[j, 2], q - cols[j, 2], line_trig[j, 2], line_trig[j, 3])
        # the camera vector in the scan head (R_HS), and the scan head's lever u_sen
        cx, cy, cz = (image[i, 1] - k0) * pixel_pitch, y0, -focal
        hx = r_hs[0, 0] * cx + r_hs[0, 1] * cy + r_hs[0, 2] * cz
        hy = r_hs[1, 0] * cx + r_hs[1, 1] * cy + r_hs[1, 2] * cz
        hz = r_hs[2, 0] * cx + r_hs[2, 1] * cy + r_hs[2, 2] * cz
        for v in range(2):
            if v == 0:
                x, y, z = hx, hy, hz
            else:
                x, y, z = u_sen[0], u_sen[1], u_sen[2]
            # R_PH = Rx(swing) Ry(pitch_comp), then R_BP
            x, z = cq * x + sq * z, -sq * x + cq * z
            y, z = cs * y - ss * z, ss * y + cs * z
            x, y, z = (r_bp[0, 0] * x + r_bp[0, 1] * y + r_bp[0, 2] * z,
                       r_bp[1, 0] * x + r_bp[1, 1] * y + r_bp[1, 2] * z,
                       r_bp[2, 0] * x + r_bp[2, 1] * y + r_bp[2, 2] * z)
            if v == 1:
                x, y, z = x + u_gps[0], y + u_gps[1], z + u_gps[2]
            ex, ey, ez = body_to_ecef(x, y, z, trig)
            if v == 0:
                norm = math.sqrt(ex * ex + ey * ey + ez * ez)
                d_out[i, 0], d_out[i, 1], d_out[i, 2] = ex / norm, ey / norm, ez / norm
            else:
                c_out[i, 0], c_out[i, 1], c_out[i, 2] = pos[0] + ex, pos[1] + ey, pos[2] + ez
    return True
