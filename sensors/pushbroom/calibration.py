"""Push-broom (three-line camera) calibration: papers.md section 2, spec/geometry.md's
push-broom section.

Unknowns: the lever arm ``u_gps``, the boresight ``opk_cam``, the per-segment cubic APs
``ax_<view>_<i>`` / ``bx_<view>_<i>`` of every CCD line, the LIM orientation-fix corrections
``d_ned_<k>`` / ``d_opk_<k>`` (every calibration parameter carries its prior as a
pseudo-observation), and the ground coordinates (ECEF) of every tie point. Observations: the
image coordinates of control points (known ground) and of tie points (ground unknown),
observed minus computed through ``ground_to_image``. The AP continuity (C0) and smoothness
(C1) conditions at every segment boundary are hard equality constraints
(:func:`swathflow.sensors.pushbroom.continuity_matrix`), solved exactly.

The Jacobian is sparse (a tie point's rows touch its own three coordinates and the
parameters of one image, and an image depends only on the fixes around its time), so the
generic engine :func:`swathflow.adjustment.solve` runs on sparse normal equations (SuperLU).
Internally every parameter is scaled by its prior sigma (AP coefficients span 12 orders of
magnitude otherwise).

Two solutions: ``joint`` (everything at once) and the paper's iterative ``two-step``
scheme (exterior: lever arm, boresight and fix corrections with the APs held; then
interior: the APs with the exterior held; repeated, with Anderson acceleration, until the
joint Gauss-Newton step at the current values is below 0.1 joint sigma; tie coordinates
are free in both steps). Its covariance is the joint one at its solution (the per-step
covariances are conditional on the other block, hence too small).
"""
from __future__ import annotations

import math
import os
import time
from dataclasses import dataclass, field
from typing import Mapping, Sequence

import numpy as np
import pandas as pd
import scipy.sparse as sp

from swathflow.adjustment import Problem, RankDeficiencyError, Solution, solve
from swathflow.calibration.result import CalibrationResult, residual_table, summarize
from swathflow.calibration.unknowns import CalibrationError, build_unknowns
from swathflow.errors import FormatError

TIE_COLUMNS = ("tie_id", "image_id", "line", "element")
#: a weak prior (m) on the tie coordinates around their first intersection: it adds no
#: information where two or more rays meet, and keeps a tie determined when blunder
#: detection rejects all but one of its rays (that ray then fits exactly)
TIE_PRIOR_M = 1000.0
METHODS = ("joint", "two-step", "both")


# --- tie points ---------------------------------------------------------------------------
def read_ties(path, images: Sequence[str] | None = None) -> pd.DataFrame:
    """Read a tie-point table (``tie_id,image_id,line,element``; see
    docs/mission-format-pushbroom.md). Raises FormatError naming the file, row and fix."""
    path = os.fspath(path)
    if not os.path.exists(path):
        raise FormatError(f"{path}: tie-point file not found (check [ties].file in "
                          f"mission.toml)")
    try:
        df = pd.read_csv(path, dtype={"tie_id": str, "image_id": str})
    except (pd.errors.ParserError, pd.errors.EmptyDataError, UnicodeDecodeError) as exc:
        raise FormatError(f"{path}: cannot be read as CSV: {exc}") from None
    df.columns = [str(c).strip() for c in df.columns]
    miss = [c for c in TIE_COLUMNS if c not in df.columns]
    if miss:
        raise FormatError(f"{path}: missing column(s) {', '.join(miss)}; the header must "
                          f"contain {','.join(TIE_COLUMNS)}")
    for c in ("line", "element"):
        v = pd.to_numeric(df[c], errors="coerce").to_numpy(float)
        bad = ~np.isfinite(v)
        if bad.any():
            raise FormatError(f"{path}: file row {int(np.flatnonzero(bad)[0]) + 2}, column "
                              f"{c}: not a finite number; delete unmeasured rows")
        df[c] = v
    for c in ("tie_id", "image_id"):
        bad = df[c].isna().to_numpy()
        if bad.any():
            raise FormatError(f"{path}: file row {int(np.flatnonzero(bad)[0]) + 2}: empty "
                              f"{c}")
    df["tie_id"] = df["tie_id"].astype(str)
    df["image_id"] = df["image_id"].astype(str)
    if images is not None:
        bad = ~df["image_id"].isin(list(images)).to_numpy()
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            raise FormatError(f"{path}: file row {i + 2}: unknown image id "
                              f"{df['image_id'][i]!r}; use one of {', '.join(images)}")
    dup = df.duplicated(["tie_id", "image_id"]).to_numpy()
    if dup.any():
        raise FormatError(f"{path}: file row {int(np.flatnonzero(dup)[0]) + 2}: tie point "
                          f"measured twice in one image; keep one row per tie and image")
    return df.reset_index(drop=True)


def mission_ties(mission) -> pd.DataFrame | None:
    """The mission's tie points (``[ties] file = "ties.csv"``), or None."""
    tc = mission.config.get("ties")
    if tc is None:
        return None
    if not isinstance(tc, dict) or "file" not in tc:
        raise FormatError(f"{mission.path / 'mission.toml'}: [ties] needs file = "
                          f"\"ties.csv\"")
    p = mission.path / tc["file"]
    return read_ties(p, list(mission.images))


def intersect_rays(models: Mapping, obs: pd.DataFrame, id_col: str = "tie_id"):
    """Least-squares intersection of the rays of every point's image observations:
    ``(ids, ECEF (n, 3), rays per point)``; points with fewer than two rays are left out."""
    o_all, d_all, k_all = [], [], []
    ids, inv = np.unique(obs[id_col].to_numpy(str), return_inverse=True)
    for iid, g in obs.groupby("image_id", sort=False):
        o, d = models[iid].ray(g[["line", "element"]].to_numpy(float))
        o_all.append(o)
        d_all.append(d)
        k_all.append(inv[g.index.to_numpy()])
    o, d, k = np.concatenate(o_all), np.concatenate(d_all), np.concatenate(k_all)
    ok = np.isfinite(o).all(1) & np.isfinite(d).all(1)
    o, d, k = o[ok], d[ok], k[ok]
    M = np.eye(3)[None] - d[:, :, None] * d[:, None, :]
    A = np.zeros((ids.size, 3, 3))
    b = np.zeros((ids.size, 3))
    np.add.at(A, k, M)
    np.add.at(b, k, np.einsum("nij,nj->ni", M, o))
    n = np.bincount(k, minlength=ids.size)
    good = n >= 2
    X = np.full((ids.size, 3), np.nan)
    X[good] = np.linalg.solve(A[good], b[good][..., None])[..., 0]
    return ids, X, n


# --- the adjustment -----------------------------------------------------------------------
@dataclass
class _Setup:
    models: dict
    unk: object
    p0: np.ndarray
    scale: np.ndarray
    n_par: int
    tie_ids: np.ndarray
    T0: np.ndarray
    spans: list                      # (iid, rows slice, ground (n, 3) or None, tie index)
    l_obs: np.ndarray                # (2 n_obs,) line, element interleaved
    comp: np.ndarray                 # component label per observation
    point_names: np.ndarray
    cons_A: np.ndarray               # C0/C1 rows over the model vector
    cons_labels: list
    ap_mask: np.ndarray              # over the parameters
    cache: dict = field(default_factory=dict)

    @property
    def n(self) -> int:
        return self.n_par + 3 * self.tie_ids.size

    def params(self, z) -> np.ndarray:
        return self.p0 + self.scale * z[:self.n_par]

    def ties(self, z) -> np.ndarray:
        return self.T0 + z[self.n_par:].reshape(-1, 3)

    def fn(self, z, jacobian=True):
        key = z.tobytes()
        ent = self.cache.get(key)
        if ent is None:
            self.cache.clear()
            p = self.params(z)
            T = self.ties(z)
            comp = np.empty_like(self.l_obs)
            mods, grounds = {}, []
            for iid, sl, G, ti in self.spans:
                m = mods.get(iid)
                if m is None:           # one model per image (its control and tie spans)
                    m = mods[iid] = self.models[iid].with_vector(p)
                g = G if ti is None else T[ti]
                grounds.append(g)
                comp[sl] = m.ground_to_image(g, clip=False).ravel()
            ent = self.cache[key] = [comp, mods, grounds, None]
        comp, mods, grounds, J = ent
        r = self.l_obs - comp
        if jacobian and J is None:
            J = self._jacobian(mods, grounds)
            ent[3] = J
        return r, (J if jacobian else None)

    def _jacobian(self, mods, grounds):
        rows, cols, vals = [], [], []
        for (iid, sl, G, ti), g in zip(self.spans, grounds):
            m = mods[iid]
            r0 = sl.start
            nobs = g.shape[0]
            D = m.parameter_partials(g) * self.scale          # (n, 2, P)
            D = D.reshape(2 * nobs, self.n_par)
            rr, cc = np.nonzero(np.nan_to_num(D))
            rows.append(rr + r0)
            cols.append(cc)
            vals.append(D[rr, cc])
            if ti is not None:
                Dg = m.ground_partials(g).reshape(2 * nobs, 3)   # (2n, 3)
                rr = np.repeat(np.arange(2 * nobs), 3)
                cc = self.n_par + 3 * np.repeat(ti, 2 * 3) + np.tile(np.arange(3), 2 * nobs)
                rows.append(rr + r0)
                cols.append(cc)
                vals.append(Dg.ravel())
        rows, cols, vals = (np.concatenate(a) for a in (rows, cols, vals))
        vals = np.where(np.isfinite(vals), vals, 0.0)
        return sp.csr_matrix((vals, (rows, cols)), shape=(self.l_obs.size, self.n))

    def problem(self, z0, free_params: np.ndarray, obs_sigma: float, tie_sigma: float):
        """A Problem starting at ``z0`` with only ``free_params`` (and the ties) free."""
        P = Problem(self._names(), z0, self._units())
        fixed = np.zeros(self.n, bool)
        fixed[:self.n_par] = ~free_params
        P.fix(fixed)
        is_tie = np.char.startswith(self.comp.astype(str), "tie")
        sig = np.where(is_tie, tie_sigma, obs_sigma)
        # blunder tests on every image point, control and tie alike
        P.add_observations("image", self.fn, sig, component=self.comp,
                           point=np.repeat(np.arange(self.l_obs.size // 2), 2),
                           point_names=self.point_names, robust=True)
        prior_sig = np.full(self.n, np.inf)
        prior_sig[:self.n_par] = np.where(self.unk.fixed, np.inf, 1.0)
        P.add_priors(np.zeros(self.n), prior_sig, name="priors")
        tie_sig = np.full(self.n, np.inf)
        tie_sig[self.n_par:] = TIE_PRIOR_M
        P.add_priors(np.zeros(self.n), tie_sig, name="tie priors", counted=False)
        # C0/C1: hard constraints on the free APs, in the scaled unknowns
        if self.cons_A.size:
            A = self.cons_A * self.scale[None]
            keep = np.any(A[:, free_params] != 0, axis=1)
            if keep.any():
                A = A[keep]
                d = -(self.cons_A[keep] @ self.p0)
                nrm = np.abs(A).max(axis=1)
                Af = np.zeros((A.shape[0], self.n))
                Af[:, :self.n_par] = A / nrm[:, None]
                P.add_constraint(sp.csr_matrix(Af), d / nrm)
        return P

    def _names(self):
        return list(self.unk.names) + [f"{t}.{c}" for t in self.tie_ids for c in "XYZ"]

    def _units(self):
        return list(self.unk.units) + ["m"] * (3 * self.tie_ids.size)


def _scale(priors, model) -> np.ndarray:
    s = priors.sigmas().astype(float)
    fallback = model.fd_step_sizes() * 1e3
    return np.where(np.isfinite(s) & (s > 0), s, fallback)


def _setup(models, gcps, ties, priors, fixed, calibration_images) -> tuple[_Setup, dict]:
    first = next(iter(models.values()))
    unk = build_unknowns(priors, fixed=fixed)
    if unk.names != priors.flat_names():
        raise CalibrationError("push-broom calibration: unexpected parameter layout")
    p0 = priors.vector()
    scale = _scale(priors, first)
    n_par = p0.size
    info = {"dropped_ties": []}
    cal = set(calibration_images)
    ctrl = gcps[(gcps["role"] == "control") & gcps["image_id"].isin(cal)] \
        if gcps is not None else pd.DataFrame(columns=["gcp_id", "image_id"])
    # tie points: initial ground by ray intersection with the prior parameters
    tie_ids = np.zeros(0, str)
    T0 = np.zeros((0, 3))
    tobs = None
    if ties is not None and len(ties):
        tobs = ties[ties["image_id"].isin(cal)].reset_index(drop=True)
        start = {iid: m.with_vector(p0) for iid, m in models.items()}
        ids, X, nray = intersect_rays(start, tobs)
        good = np.isfinite(X).all(1)
        info["dropped_ties"] = [str(i) for i in ids[~good]]
        tie_ids, T0 = ids[good], X[good]
        tobs = tobs[tobs["tie_id"].isin(set(tie_ids))].reset_index(drop=True)
    tpos = {t: k for k, t in enumerate(tie_ids)}
    spans, l_obs, comp, names = [], [], [], []
    k = 0
    for iid in calibration_images:
        for kind, df in (("control", ctrl), ("tie", tobs)):
            if df is None:
                continue
            g = df[df["image_id"] == iid]
            if not len(g):
                continue
            sl = slice(2 * k, 2 * (k + len(g)))
            if kind == "control":
                spans.append((iid, sl, g[["X", "Y", "Z"]].to_numpy(float), None))
                names += [f"{p}@{iid}" for p in g["gcp_id"]]
                comp += ["y", "x"] * len(g)
            else:
                spans.append((iid, sl, None, np.array([tpos[t] for t in g["tie_id"]])))
                names += [f"tie {p}@{iid}" for p in g["tie_id"]]
                comp += ["tie y", "tie x"] * len(g)
            l_obs.append(g[["line", "element"]].to_numpy(float).ravel())
            k += len(g)
    if k == 0:
        raise CalibrationError("no control or tie points on the calibration images: add "
                               "control points to gcp.csv (role control) or tie points "
                               "([ties] file)")
    from swathflow.sensors.pushbroom import continuity_matrix
    A, labels = continuity_matrix(first.sensor, priors)
    ap = np.array([n.startswith(("ax_", "bx_")) for n in unk.names])
    st = _Setup(dict(models), unk, p0, scale, n_par, tie_ids, T0, spans,
                np.concatenate(l_obs), np.array(comp, dtype=object),
                np.array(names, dtype=object), A, labels, ap)
    return st, info


def _check_gcps(gcps: pd.DataFrame, models) -> pd.DataFrame:
    need = ("gcp_id", "image_id", "line", "element", "X", "Y", "Z", "role")
    miss = [c for c in need if c not in gcps.columns]
    if miss:
        raise FormatError(f"control-point table: missing column(s) {', '.join(miss)}")
    g = gcps.reset_index(drop=True).copy()
    g["image_id"] = g["image_id"].astype(str)
    g["gcp_id"] = g["gcp_id"].astype(str)
    g["role"] = g["role"].astype(str).str.strip().str.lower()
    bad = ~g["role"].isin(["control", "check"]) | ~g["image_id"].isin(list(models))
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise FormatError(f"control-point table row {i}: role must be control or check and "
                          f"image_id one of {', '.join(models)}")
    return g


def _vce(vce):
    return ["x", "y", "tie x", "tie y"] if vce else False


def _run(P, vce, robust, alpha, tol=None, max_iter=50, damping=True, covariance=True):
    # convergence: the step's length in sigma units (sqrt(dx' N dx)) below 1 % of a sigma
    # per unknown; the model's piecewise-linear POS interpolation puts a floor under it
    tol = 1e-2 * math.sqrt(max(int((~P.fixed).sum()), 1)) if tol is None else tol
    try:
        # no covariance: the engine forms none above max_dense_cov unknowns
        extra = {} if covariance else {"max_dense_cov": 0}
        return solve(P, vce=_vce(vce), robust=robust, alpha=alpha, sparse=True, tol=tol,
                     max_iter=max_iter, damping=damping, **extra)
    except RankDeficiencyError as exc:
        raise CalibrationError(
            f"the observations cannot determine the parameters: {exc}. Add control or tie "
            f"points (spread across the CCD lines and along the strips), give finite prior "
            f"sigmas, or fix parameters (--fix NAME)") from None


def solve_joint(st: _Setup, z0, free, *, vce, robust, alpha, obs_sigma, tie_sigma):
    P = st.problem(z0, free, obs_sigma, tie_sigma)
    return _run(P, vce, robust, alpha), P


def solve_two_step(st: _Setup, z0, free, *, vce, alpha, obs_sigma, tie_sigma,
                   max_rounds: int = 50, gap_sigma: float = 0.1, step_iter: int = 2,
                   accelerate: int = 10):
    """The paper's iterative scheme; returns (Solution at the two-step solution with the
    joint covariance, rounds history, converged).

    A round is the exterior step (lever arm, boresight, fix corrections and tie points with
    the APs held) then the interior step (APs and tie points with the exterior held), each
    ``step_iter`` Gauss-Newton iterations with the a-priori weights (damped in the first
    round only, so that a round is a smooth map).

    Stopping: after every round the joint normal equations are formed at the current
    values and their Gauss-Newton step is computed but not taken; the rounds stop when no
    parameter of that step exceeds ``gap_sigma`` of its joint sigma (the two-step solution
    is then that close to the joint optimum, to first order). A test on the change per
    round does not work here: the blocks are so correlated (boresight and AP offsets,
    conditional sigmas 1/200 of the joint ones) that the plain alternation moves by
    0.004 conditional sigma per round while still 1.3 joint sigma away.

    ``accelerate`` > 0 extrapolates over the last that many rounds (Anderson acceleration
    of the round as a fixed-point map; each round is still the paper's two steps);
    0 gives the plain alternation (on the two-strip test mission still 1 joint sigma away
    after 45 rounds).
    Variance components, when asked for, are estimated once at the end."""
    z = z0.copy()
    ext = free & ~st.ap_mask
    inn = free & st.ap_mask
    idx = np.flatnonzero(free)
    rounds = []
    Xh, Fh = [], []                   # Anderson history: round inputs and changes (free)
    wts = None
    prev_norm = np.inf
    converged = False
    final = joint_sig = None
    best = None                       # (gap, solution) of the round closest to the optimum
    for r in range(max_rounds):
        zin = z.copy()
        sig = np.ones(st.n_par)
        for blk in (ext, inn):
            if not blk.any():
                continue
            # a tiny tolerance: a sub-step is always taken (a larger one stalls the rounds)
            # (conditional sigmas, for the extrapolation's scaling, in the first round only)
            sol = _run(st.problem(z, blk, obs_sigma, tie_sigma), False, False, alpha,
                       tol=1e-9, max_iter=step_iter, damping=r == 0, covariance=r == 0)
            z = sol.x.copy()
            sig[blk] = sol.sigma[:st.n_par][blk]
        if wts is None:
            wts = 1.0 / np.maximum(sig[idx], 1e-12)
        f = (z[idx] - zin[idx]) * wts          # the round's change, in conditional sigmas
        gap, final, joint_sig = _gap(st, z, free, obs_sigma, tie_sigma, alpha, joint_sig)
        rounds.append({"round": r + 1, "gap_sigma": gap,
                       "max_change_sigma": float(np.max(np.abs(f))) if idx.size else 0.0,
                       "sigma0": final.sigma0})
        if best is None or gap < best[0]:
            best = (gap, final)
        if gap < gap_sigma:
            converged = True
            break
        if not accelerate:
            continue
        norm = float(np.linalg.norm(f))
        if norm > 10 * prev_norm:              # extrapolation overshot: restart
            Xh, Fh = [], []
        prev_norm = norm
        Xh.append(zin[idx] * wts)
        Fh.append(f)
        Xh, Fh = Xh[-(accelerate + 1):], Fh[-(accelerate + 1):]
        if len(Fh) < 2:
            continue
        dF = np.diff(np.array(Fh), axis=0).T
        dX = np.diff(np.array(Xh), axis=0).T
        gamma = np.linalg.lstsq(dF, f, rcond=1e-10)[0]
        z[idx] = (Xh[-1] + f - (dX + dF) @ gamma) / wts
        # the extrapolated values are the next round's start; z (the tie points too) is
        # re-solved by its first step
    if not converged and best is not None and best[0] < gap:
        final = best[1]
    z = final.x.copy()          # the values measured closest to the joint optimum
    if vce or not final.cov.any():  # statistics at the two-step solution (no step taken)
        final = _run(st.problem(z, free, obs_sigma, tie_sigma), vce, False, alpha,
                     tol=np.inf)
        final.x[:] = z
    return final, rounds, converged


def _gap(st: _Setup, z, free, obs_sigma, tie_sigma, alpha, sig=None):
    """The first-order distance from ``z`` to the joint optimum: the largest |joint
    Gauss-Newton step| over the free parameters, in joint sigmas; with the joint
    solution's statistics at ``z`` (no step taken) and the sigmas used. Given ``sig``
    (the joint sigmas change little from round to round) the covariance is not formed."""
    P = st.problem(z, free, obs_sigma, tie_sigma)
    sol = _run(P, False, False, alpha, tol=np.inf, covariance=sig is None)
    sol.x[:] = z
    if sig is None:
        sig = sol.sigma[:st.n_par][free]
    rem = np.abs(sol.remaining[:st.n_par][free]) if sol.remaining is not None else np.inf
    gap = float(np.max(rem / np.maximum(sig, 1e-300))) if free.any() else 0.0
    return gap, sol, sig


# --- results -----------------------------------------------------------------------------
@dataclass
class PushbroomCalibrationResult(CalibrationResult):
    """A :class:`~swathflow.calibration.result.CalibrationResult` (same report and file) plus the
    push-broom extras: tie points, C0/C1 residuals, the method and the other solution."""

    method: str = "joint"
    ties: pd.DataFrame | None = None             # tie ground coordinates and sigmas
    tie_residuals: pd.DataFrame | None = None
    continuity: pd.DataFrame | None = None       # label, residual (model units)
    rounds: list = field(default_factory=list)   # two-step history
    alternative: "PushbroomCalibrationResult | None" = None
    timings: dict = field(default_factory=dict)
    dropped_ties: list = field(default_factory=list)

    @property
    def max_continuity_residual(self) -> float:
        c = self.continuity
        return float(np.abs(c["residual"]).max()) if c is not None and len(c) else 0.0

    def summary_lines(self) -> list[str]:
        """What a person reads on the terminal after a calibration."""
        cx, cy = self.check_rms()
        out = [f"calibrated {self.options['model']} push-broom parameters ({self.method}) and "
               f"{self.options['tie_points']} tie points from "
               f"{self.options['observations'] // 2} image points in "
               f"{self.timings.get('total', float('nan')):.1f} s (sigma0 {self.sigma0:.3f}, "
               f"{len(self.rejected)} rejected, C0/C1 max residual "
               f"{self.max_continuity_residual:.1e})",
               f"  check points: RMS x {cx:.3f} y {cy:.3f} px"]
        if self.tie_residuals is not None:
            tr = self.tie_residuals[self.tie_residuals["used"]]
            out.append(f"  tie points:   RMS x {_rms(tr['x']):.3f} y {_rms(tr['y']):.3f} px "
                       f"({len(self.tie_residuals) - len(tr)} tie observations rejected)")
        if self.alternative is not None:
            a = self.alternative
            with np.errstate(invalid="ignore", divide="ignore"):
                d = np.abs(self.values - a.values) / np.where(self.sigmas > 0, self.sigmas,
                                                              np.nan)
            state = "converged" if a.solution.converged else "NOT converged (--max-rounds)"
            out.append(f"  two-step: {len(a.rounds)} rounds, {state}; largest difference "
                       f"from the joint solution {np.nanmax(d):.3f} sigma")
        return out

    def check_rms(self) -> tuple[float, float]:
        """RMS of the check-point residuals after calibration, (x, y) pixels."""
        r = self.residuals
        q = r[(r["stage"] == "after") & (r["role"] == "check")]
        return (float(np.sqrt(np.nanmean(q["x"] ** 2))),
                float(np.sqrt(np.nanmean(q["y"] ** 2))))

    def calibration_document(self) -> dict:
        doc = super().calibration_document()
        doc["method"] = self.method
        doc["continuity"] = {"max_abs": self.max_continuity_residual,
                             "residuals": dict(zip(self.continuity["label"],
                                                   self.continuity["residual"]))}
        if self.ties is not None:
            tr = self.tie_residuals[self.tie_residuals["used"]]
            doc["tie_points"] = {"n": int(len(self.ties)),
                                 "observations": int(len(self.tie_residuals)),
                                 "rejected_observations": int(len(self.tie_residuals)
                                                              - len(tr)),
                                 "single_ray": [str(t) for t in self.ties["tie_id"][
                                     self.ties["rays"] < 2]],
                                 "rms_x": _rms(tr["x"]), "rms_y": _rms(tr["y"]),
                                 "dropped": self.dropped_ties}
        if self.rounds:
            doc["two_step_rounds"] = self.rounds
            doc["two_step_converged"] = bool(self.solution.converged)
        if self.alternative is not None:
            a = self.alternative
            doc["alternative"] = {"method": a.method, "values": a.values, "sigmas": a.sigmas,
                                  "sigma0": a.sigma0, "rounds": a.rounds}
        doc["timings_s"] = self.timings
        return doc

    def extra_html(self) -> str:
        from swathflow.calibration.report import _table
        out = ["<h2>Push-broom calibration</h2>",
               f"<p>Method <b>{self.method}</b>. Residuals: x = element (across track along "
               f"the CCD line), y = line (along track). C0/C1 constraints (hard): largest "
               f"residual {self.max_continuity_residual:.3e}.</p>"]
        if self.ties is not None:
            tr = self.tie_residuals[self.tie_residuals["used"]]
            single = int((self.ties["rays"] < 2).sum())
            out.append(f"<p>{len(self.ties)} tie points ({len(self.tie_residuals)} image "
                       f"observations, {len(self.tie_residuals) - len(tr)} rejected as "
                       f"blunders): RMS x {_rms(tr['x']):.3f}, y {_rms(tr['y']):.3f} px; "
                       f"{len(self.dropped_ties)} dropped before the adjustment and "
                       f"{single} left with one ray after rejection (fewer than two "
                       f"rays: no tie).</p>")
        if self.continuity is not None and len(self.continuity):
            out.append(_table(self.continuity, 3, left=("label",)))
        if self.rounds:
            out.append("<h3>Two-step rounds</h3>")
            out.append(_table(pd.DataFrame(self.rounds), 4))
        if self.alternative is not None:
            a = self.alternative
            with np.errstate(invalid="ignore", divide="ignore"):
                d = (self.values - a.values) / np.where(self.sigmas > 0, self.sigmas, np.nan)
            tab = pd.DataFrame({"name": self.names, self.method: self.values,
                                "sigma": self.sigmas, a.method: a.values,
                                f"{a.method} sigma": a.sigmas, "difference / sigma": d})
            out.append(f"<h3>{_e(self.method)} vs {_e(a.method)}</h3>")
            out.append(_table(tab, 6, left=("name",)))
        if self.timings:
            out.append("<p class='note'>Timings (s): " + ", ".join(
                f"{k} {v:.2f}" for k, v in self.timings.items()) + "</p>")
        return "\n".join(out)

    def write(self, out_dir) -> dict[str, str]:
        from swathflow.formats.calibfile import write_calibration
        from swathflow.io import write_text
        from swathflow.calibration.report import render_report
        os.makedirs(out_dir, exist_ok=True)
        doc = self.calibration_document()
        cal = os.path.join(out_dir, "calibration.json")
        write_calibration(cal, doc.pop("sensor"), doc.pop("parameters"), **doc)
        html = render_report(self).replace("</body>", self.extra_html() + "</body>", 1)
        rep = os.path.join(out_dir, "report.html")
        write_text(rep, html)
        if self.ties is not None:
            from swathflow.io import atomic_path
            with atomic_path(os.path.join(out_dir, "ties.csv")) as tmp:
                self.ties.to_csv(tmp, index=False)
        return {"calibration": cal, "report": rep}


def _e(x) -> str:
    import html
    return html.escape(str(x))


def _rms(v) -> float:
    v = np.asarray(v, float)
    v = v[np.isfinite(v)]
    return float(np.sqrt(np.mean(v ** 2))) if v.size else float("nan")


def _result(st: _Setup, sol: Solution, models, gcps, priors, method, options,
            calibration_images, rounds=(), timings=None, dropped=()):
    n = st.n_par
    S = st.scale
    x = st.params(sol.x)
    cov = sol.cov[:n, :n] * np.outer(S, S)
    fixedp = st.unk.fixed | ~options["free"]
    psol = Solution(list(st.unk.names), list(st.unk.units), x, st.p0.copy(), fixedp, cov,
                    sol.sigma0, sol.redundancy, sol.components, sol.residuals,
                    sol.normalized, sol.used, sol.rejected, sol.iterations, sol.evaluations,
                    sol.converged, sol.history,
                    None if sol.remaining is None else sol.remaining[:n] * S)
    sig = psol.sigma
    params = priors.with_vector(x)
    upd, i = {}, 0
    for b in params.blocks:
        upd[b.name] = {"sigma": list(sig[i:i + b.size])}
        i += b.size
    params = params.updated(upd)
    vec_after = {iid: x for iid in models}
    vec_before = {iid: st.p0 for iid in models}
    if gcps is not None and len(gcps):
        res = pd.concat([residual_table(models, vec_before, gcps, "before"),
                         residual_table(models, vec_after, gcps, "after")], ignore_index=True)
    else:
        res = residual_table(models, vec_after, gcps.iloc[:0] if gcps is not None else
                             pd.DataFrame(columns=["image_id"]), "after")
    res["calibration_image"] = res["image_id"].isin(set(calibration_images))
    # rejected points (robust phase / snooping), GCPs and ties alike
    rej_rows = []
    after = res[res["stage"] == "after"]
    for r in sol.rejected:
        name = str(r["name"])
        pid, _, iid = name.rpartition("@")
        is_tie = pid.startswith("tie ")
        pid = pid[4:] if is_tie else pid
        q = after[(after["gcp_id"] == pid) & (after["image_id"] == iid)]
        rej_rows.append({"name": name, "statistic": r["statistic"], "critical": r["critical"],
                         "phase": r["phase"], "gcp_id": pid, "image_id": iid,
                         "x": float(q["x"].iloc[0]) if len(q) else np.nan,
                         "y": float(q["y"].iloc[0]) if len(q) else np.nan})
    rej = pd.DataFrame(rej_rows, columns=["name", "statistic", "critical", "phase", "gcp_id",
                                          "image_id", "x", "y"])
    bad = set(zip(rej["gcp_id"], rej["image_id"]))
    res["rejected"] = [(g, i) in bad and s == "after" and ro == "control" for g, i, s, ro in
                       zip(res["gcp_id"], res["image_id"], res["stage"], res["role"])]
    res["role"] = np.where(res["rejected"], "rejected", res["role"])
    summary = summarize(res)
    # tie points: ground coordinates, sigmas, residuals
    ties = tie_res = None
    if st.tie_ids.size:
        T = st.ties(sol.x)
        tc = np.diag(sol.cov)[n:].reshape(-1, 3)
        from swathflow.geometry.geodesy import ecef_to_geodetic
        llh = ecef_to_geodetic(T)
        ties = pd.DataFrame({"tie_id": st.tie_ids, "X": T[:, 0], "Y": T[:, 1], "Z": T[:, 2],
                             "lat": llh[:, 0], "lon": llh[:, 1], "h": llh[:, 2],
                             "sigma_X": np.sqrt(np.clip(tc[:, 0], 0, None)),
                             "sigma_Y": np.sqrt(np.clip(tc[:, 1], 0, None)),
                             "sigma_Z": np.sqrt(np.clip(tc[:, 2], 0, None))})
        r = sol.residuals["image"]
        used = sol.used["image"]
        rows = []
        for iid, sl, G, ti in st.spans:
            if ti is None:
                continue
            rr = r[sl].reshape(-1, 2)
            rows.append(pd.DataFrame({"tie_id": st.tie_ids[ti], "image_id": iid,
                                      "x": rr[:, 1], "y": rr[:, 0],
                                      "used": used[sl].reshape(-1, 2).all(1)}))
        tie_res = pd.concat(rows, ignore_index=True)
        # rays left after blunder rejection: a tie seen by fewer than two is not a tie
        rays = tie_res.groupby("tie_id")["used"].sum()
        ties["rays"] = rays.reindex(ties["tie_id"]).fillna(0).astype(int).to_numpy()
    from swathflow.sensors.pushbroom import continuity_matrix
    A, labels = continuity_matrix(next(iter(models.values())).sensor, params)
    cont = pd.DataFrame({"label": labels, "residual": A @ x})
    opts = {k: v for k, v in options.items() if k != "free"}
    return PushbroomCalibrationResult(
        "pushbroom", st.unk, psol, params, cov, res, summary, rej, vec_after,
        list(calibration_images), opts, None, method=method, ties=ties,
        tie_residuals=tie_res, continuity=cont, rounds=list(rounds),
        timings=dict(timings or {}), dropped_ties=list(dropped))


def calibrate_pushbroom(models: Mapping[str, object], gcps: pd.DataFrame | None,
                        ties: pd.DataFrame | None = None, priors=None, *,
                        method: str = "joint", fixed: Sequence[str] = (),
                        robust: bool = True, vce: bool = True, obs_sigma_px: float = 1.0,
                        tie_sigma_px: float | None = None, alpha: float = 0.001,
                        calibration_images: Sequence[str] | None = None,
                        max_rounds: int = 50) -> PushbroomCalibrationResult:
    """Calibrate a push-broom camera from control points and tie points.

    models: image id -> PushbroomModel (every view and strip). gcps: rows gcp_id, image_id,
    line, element, X, Y, Z (ECEF), role (control/check; check points are only evaluated).
    ties: rows tie_id, image_id, line, element (ground unknown; two or more images each).
    priors: ParameterSet of prior values and sigmas (default: the first model's).
    method: "joint", "two-step" (the paper's iterative scheme), or "both" (joint, with the
    two-step solution as ``result.alternative``).
    """
    if method not in METHODS:
        raise CalibrationError(f"method must be one of {', '.join(METHODS)}, got {method!r}")
    if not models:
        raise CalibrationError("no images")
    models = {str(k): v for k, v in models.items()}
    first = next(iter(models.values()))
    if getattr(first, "name", "") != "pushbroom":
        raise CalibrationError("calibrate_pushbroom needs push-broom sensor models")
    priors = priors if priors is not None else first.parameters
    if gcps is not None:
        gcps = _check_gcps(gcps, models)
    if calibration_images is None:
        calibration_images = list(models)
    calibration_images = [str(c) for c in calibration_images]
    for c in calibration_images:
        if c not in models:
            raise CalibrationError(f"calibration image {c!r} is not in the mission")
    t0 = time.perf_counter()
    st, info = _setup(models, gcps, ties, priors, fixed, calibration_images)
    free = ~st.unk.fixed
    n_ctrl = int(np.sum(st.comp == "x"))
    if n_ctrl == 0:
        raise CalibrationError("no control points (role 'control') on the calibration "
                               "images: tie points alone do not fix the datum; add control "
                               "points to gcp.csv")
    tie_sigma = float(tie_sigma_px if tie_sigma_px is not None else obs_sigma_px)
    kw = dict(vce=vce, alpha=alpha, obs_sigma=float(obs_sigma_px), tie_sigma=tie_sigma)
    timings = {"setup": time.perf_counter() - t0}
    z0 = np.zeros(st.n)
    options = {"model": str(st.n_par), "fixed": list(fixed), "robust": robust, "vce": vce,
               "obs_sigma_px": obs_sigma_px, "tie_sigma_px": tie_sigma, "alpha": alpha,
               "unknowns_total": st.n, "tie_points": int(st.tie_ids.size),
               "observations": int(st.l_obs.size), "free": free}
    results = {}
    if method in ("joint", "both"):
        t1 = time.perf_counter()
        sol, _ = solve_joint(st, z0, free, robust=robust, **kw)
        timings["joint"] = time.perf_counter() - t1
        results["joint"] = (sol, [])
    if method in ("two-step", "both"):
        t1 = time.perf_counter()
        sol, rounds, conv = solve_two_step(st, z0, free, max_rounds=max_rounds, **kw)
        sol.converged = conv
        timings["two-step"] = time.perf_counter() - t1
        results["two-step"] = (sol, rounds)
    out = {}
    for name, (sol, rounds) in results.items():
        out[name] = _result(st, sol, models, gcps, priors, name,
                            {**options, "method": name}, calibration_images, rounds, timings,
                            info["dropped_ties"])
    main = out["joint" if method in ("joint", "both") else "two-step"]
    if method == "both":
        main.alternative = out["two-step"]
    main.timings["total"] = time.perf_counter() - t0
    return main


# --- the plugin's calibration strategy ---------------------------------------------------
class PushbroomCalibration:
    """Control and tie points, orientation fixes, C0/C1 constraints (--method, --max-rounds).

    ``options.extra``: ``method`` (joint, two-step, both) and ``max_rounds``."""

    def calibrate(self, mission, options):
        if mission.gcps is None or not len(mission.gcps):
            raise CalibrationError(f"{mission.path}: no control points (add [gcp] file = "
                                   f"\"gcp.csv\" to mission.toml)")
        models = {iid: mission.model(iid) for iid in mission.image_ids}
        extra = dict(options.extra)
        return calibrate_pushbroom(models, mission.gcps, mission_ties(mission), mission.priors,
                                   method=str(extra.get("method") or "joint"),
                                   fixed=list(options.fixed), robust=options.robust,
                                   vce=options.vce, obs_sigma_px=options.sigma_px,
                                   calibration_images=(list(options.images)
                                                       if options.images else None),
                                   max_rounds=int(extra.get("max_rounds") or 50))


STRATEGY = PushbroomCalibration()
