"""The push-broom calibration as one adjustment problem: unknowns (the parameters scaled by
their prior sigmas, then the tie coordinates), image observations of control and tie points,
priors, and the C0/C1 constraints as hard equality constraints."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import pandas as pd
import scipy.sparse as sp

from swathflow.adjustment import Problem
from swathflow.calibration.unknowns import CalibrationError, build_unknowns
from swathflow.errors import FormatError
from swathflow.sensors.pushbroom.calibration.ties import intersect_rays
from swathflow.sensors.pushbroom.viewing import continuity_matrix

#: a weak prior (m) on the tie coordinates around their first intersection: it adds no
#: information where two or more rays meet, and keeps a tie determined when blunder
#: detection rejects all but one of its rays (that ray then fits exactly)
TIE_PRIOR_M = 1000.0


@dataclass
class Setup:
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
    projector: object                # the bulk projection over the images (image_ids)
    obs_image: np.ndarray            # (n_obs,) the image of each observation
    ground: np.ndarray               # (n_obs, 3) control coordinates (NaN for ties)
    obs_tie: np.ndarray              # (n_obs,) the tie of each observation (-1: control)
    cache: dict = field(default_factory=dict)

    @property
    def n(self) -> int:
        return self.n_par + 3 * self.tie_ids.size

    def params(self, z) -> np.ndarray:
        return self.p0 + self.scale * z[:self.n_par]

    def ties(self, z) -> np.ndarray:
        return self.T0 + z[self.n_par:].reshape(-1, 3)

    def fn(self, z, jacobian=True):
        """Observed minus computed image coordinates at the scaled unknowns ``z`` and their
        sparse Jacobian: every observation of every image in one bulk projection
        (:meth:`PushbroomModel.projector`), started at the previous evaluation's answer."""
        key = z.tobytes()
        ent = self.cache.get(key)
        if ent is None or (jacobian and ent[1] is None):
            p = self.params(z)
            ground = self.ground.copy()
            if self.tie_ids.size:
                ground[self.obs_tie >= 0] = self.ties(z)[self.obs_tie[self.obs_tie >= 0]]
            V = np.broadcast_to(p, (len(self.projector.models), p.size))
            out = self.projector.project(self.obs_image, ground, V, partials=jacobian,
                                         start=self.cache.get("start"))
            good = np.isfinite(out.image).all(axis=1)
            start = self.cache.get("start", np.full_like(out.image, np.nan))
            start[good] = out.image[good]
            self.cache.clear()
            self.cache["start"] = start
            J = self._jacobian(out) if jacobian else None
            ent = self.cache[key] = (out.image.ravel(), J)
        comp, J = ent
        return self.l_obs - comp, (J if jacobian else None)

    def _jacobian(self, out):
        """The sparse Jacobian of the computed coordinates (rows interleaved line, element)
        by the scaled unknowns: the parameter columns where non-zero, and each tie
        observation's three ground columns."""
        m = out.image.shape[0]
        D = np.nan_to_num(out.d_parameters * self.scale, nan=0.0).reshape(2 * m, self.n_par)
        rr, cc = np.nonzero(D)
        rows, cols, vals = [rr], [cc], [D[rr, cc]]
        tie = np.flatnonzero(self.obs_tie >= 0)
        if tie.size:
            Dg = np.nan_to_num(out.d_ground[tie], nan=0.0)                # (t, 2, 3)
            rows.append(np.repeat(2 * tie[:, None] + np.arange(2), 3, axis=1).ravel())
            cols.append(np.tile(self.n_par + 3 * self.obs_tie[tie][:, None]
                                + np.arange(3), (1, 2)).ravel())
            vals.append(Dg.ravel())
        rows, cols, vals = (np.concatenate(a) for a in (rows, cols, vals))
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
        if self.tie_ids.size:           # the tie coordinates: eliminated 3 x 3 per point
            P.eliminate(np.arange(self.n_par, self.n).reshape(-1, 3))
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


def _initial_ties(models, ties, p0, cal, info):
    """The tie observations on the calibration images and their first ground coordinates
    (ray intersection with the prior parameters); ties with fewer than two usable rays are
    dropped (recorded in ``info``)."""
    if ties is None or not len(ties):
        return np.zeros(0, str), np.zeros((0, 3)), None
    tobs = ties[ties["image_id"].isin(cal)].reset_index(drop=True)
    start = {iid: m.with_vector(p0) for iid, m in models.items()}
    ids, X, nray = intersect_rays(start, tobs)
    good = np.isfinite(X).all(1)
    info["dropped_ties"] = [str(i) for i in ids[~good]]
    tie_ids, T0 = ids[good], X[good]
    tobs = tobs[tobs["tie_id"].isin(set(tie_ids))].reset_index(drop=True)
    return tie_ids, T0, tobs


def _observations(calibration_images, ctrl, tobs, tie_ids):
    """Spans (image, rows, ground or tie index), observed (line, element) interleaved,
    component labels and point names, image by image (control points, then ties)."""
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
    return spans, np.concatenate(l_obs), comp, names


def build_setup(models, gcps, ties, priors, fixed, calibration_images) -> tuple[Setup, dict]:
    """The calibration problem of ``models`` (image id -> model) from control points
    ``gcps`` (checked, ECEF) and tie observations ``ties``; returns it and
    ``{"dropped_ties": [...]}``."""
    first = next(iter(models.values()))
    unk = build_unknowns(priors, fixed=fixed)
    if unk.names != priors.flat_names():
        raise CalibrationError("push-broom calibration: unexpected parameter layout")
    p0 = priors.vector()
    scale = _scale(priors, first)
    info = {"dropped_ties": []}
    cal = set(calibration_images)
    ctrl = gcps[(gcps["role"] == "control") & gcps["image_id"].isin(cal)] \
        if gcps is not None else pd.DataFrame(columns=["gcp_id", "image_id"])
    tie_ids, T0, tobs = _initial_ties(models, ties, p0, cal, info)
    spans, l_obs, comp, names = _observations(calibration_images, ctrl, tobs, tie_ids)
    A, labels = continuity_matrix(first.sensor, priors)
    ap = np.array([n.startswith(("ax_", "bx_")) for n in unk.names])
    image_ids = list(dict.fromkeys(iid for iid, *_ in spans))
    pos = {iid: k for k, iid in enumerate(image_ids)}
    n_obs = l_obs.size // 2
    obs_image = np.zeros(n_obs, np.intp)
    ground = np.full((n_obs, 3), np.nan)
    obs_tie = -np.ones(n_obs, np.intp)
    for iid, sl, G, ti in spans:
        rows = slice(sl.start // 2, sl.stop // 2)
        obs_image[rows] = pos[iid]
        if ti is None:
            ground[rows] = G
        else:
            obs_tie[rows] = ti
    projector = type(first).projector([models[i] for i in image_ids])
    st = Setup(dict(models), unk, p0, scale, p0.size, tie_ids, T0, spans, l_obs,
               np.array(comp, dtype=object), np.array(names, dtype=object), A, labels, ap,
               projector, obs_image, ground, obs_tie)
    return st, info


def check_gcps(gcps: pd.DataFrame, models) -> pd.DataFrame:
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
