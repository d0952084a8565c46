"""The least-squares network of strip (or image) offsets from pairwise overlap offsets,
anchored on given nodes or tied to absolute (control point) offsets, with iterative
rejection of inconsistent overlaps."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["Network", "solve_network"]


@dataclass
class Network:
    nodes: list                          # node keys
    offsets: np.ndarray                  # (n, 2) px
    sigmas: np.ndarray                   # (n, 2) px (NaN when not computed)
    radiometric: np.ndarray              # (n,)
    residuals: np.ndarray                # (m, 2) per observation (NaN if rejected)
    used: np.ndarray                     # (m,) bool
    sigma0: float
    anchored: list
    free_groups: list                    # components without an anchor (mean fixed to 0)


def _components(n, edges, max_dense: int = 1500):
    """``(count, labels)`` of the connected components, numbered in the order of their
    first node (as scipy.sparse.csgraph.connected_components numbers them). Up to
    ``max_dense`` nodes by union-find here (scipy's import is most of a small network's
    cost), above by scipy."""
    if not edges:
        return n, np.arange(n)
    if n > max_dense:
        from scipy.sparse import coo_matrix
        from scipy.sparse.csgraph import connected_components
        e = np.array(edges)
        g = coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(n, n))
        return connected_components(g, directed=False)
    parent = list(range(n))

    def root(k):
        while parent[k] != k:
            parent[k] = parent[parent[k]]
            k = parent[k]
        return k

    for i, j in edges:
        a, b = root(int(i)), root(int(j))
        if a != b:
            parent[max(a, b)] = min(a, b)
    first: dict = {}
    labels = np.array([first.setdefault(root(k), len(first)) for k in range(n)])
    return len(first), labels


def _solve_lsq(n, edges, values, weights, anchored, labels, tied=(), max_dense: int = 1500):
    """Weighted LSQ of ``x_j - x_i = value`` per edge, plus absolute observations
    ``tied``: ``(nodes, values, weights)`` saying ``x_k = value``. Anchored nodes are held
    at 0; every component with neither an anchor nor an absolute observation has its mean
    held at 0. The normal equations are summed from their terms: dense and inverted up to
    ``max_dense`` nodes (no scipy import), sparse and solved above. Returns
    ``(x, sigma_x)``; ``sigma_x`` is NaN above ``max_dense`` nodes."""
    e = np.asarray(edges, int).reshape(-1, 2)
    values = np.asarray(values, float)
    weights = np.asarray(weights, float)
    wmed = float(np.median(weights)) if len(weights) else 1.0
    t_nodes, t_vals, t_w = (np.asarray(v) for v in tied) if len(tied) else ([], [], [])
    fixed = set(int(a) for a in anchored)
    held = {labels[k] for k in fixed} | {labels[int(k)] for k in t_nodes}
    # the normal equations' terms (row, col, value) and right-hand side, summed below:
    # an edge row has +1 at j and -1 at i
    i, j = e[:, 0], e[:, 1]
    nr = [i, j, i, j]
    nc = [i, j, j, i]
    nv = [weights, weights, -weights, -weights]
    b = np.zeros(n)
    np.add.at(b, j, weights * values)
    np.add.at(b, i, -weights * values)
    for comp in np.unique(labels):
        if comp in held:
            continue
        members = np.nonzero(labels == comp)[0]
        c = 1.0 / len(members)
        nr.append(np.repeat(members, len(members)))
        nc.append(np.tile(members, len(members)))
        nv.append(np.full(len(members) ** 2, wmed * c * c))
    extra = [(k, 0.0, 1e12) for k in sorted(fixed)] + list(zip(t_nodes, t_vals, t_w))
    for k, v, wk in extra:
        nr.append([int(k)])
        nc.append([int(k)])
        nv.append([float(wk)])
        b[int(k)] += float(wk) * float(v)
    nr, nc = np.concatenate(nr).astype(int), np.concatenate(nc).astype(int)
    nv = np.concatenate([np.asarray(x, float) for x in nv])
    if n <= max_dense:
        nmat = np.zeros((n, n))
        np.add.at(nmat, (nr, nc), nv)
        cov = np.linalg.inv(nmat)
        return cov @ b, np.sqrt(np.maximum(np.diag(cov), 0.0))
    from scipy import sparse
    from scipy.sparse.linalg import spsolve
    nmat = sparse.coo_matrix((nv, (nr, nc)), shape=(n, n)).tocsc()
    return spsolve(nmat, b), np.full(n, np.nan)


def _offsets(n, obs, idx, anchors, labels, ncomp, absolute):
    """One solution of the offsets from the used observations ``idx``: ``(x, sigma_x,
    residuals v, normalised |v|/s, sigma0)``."""
    edges = [(obs[k][0], obs[k][1]) for k in idx]
    d = np.array([obs[k][2].offset for k in idx]).reshape(-1, 2)
    s = np.array([obs[k][2].sigma for k in idx]).reshape(-1, 2)
    xs, sxs = [], []
    for c in range(2):
        tied = ()
        if absolute:
            tied = ([a[0] for a in absolute], [a[1][c] for a in absolute],
                    [1.0 / a[2][c] ** 2 for a in absolute])
        xc, sc = _solve_lsq(n, edges, d[:, c], 1.0 / s[:, c] ** 2, anchors, labels, tied)
        xs.append(xc)
        sxs.append(sc)
    x = np.column_stack(xs)
    v = d - np.array([x[j] - x[i] for i, j in edges]).reshape(-1, 2)
    norm = np.abs(v) / s
    chi2 = float((norm ** 2).sum())
    n_abs = len(absolute or ())
    if absolute:
        av = np.array([np.asarray(a[1]) - x[a[0]] for a in absolute])
        chi2 += float(((av / np.array([a[2] for a in absolute])) ** 2).sum())
    held = {labels[a] for a in anchors} | {labels[a[0]] for a in absolute or ()}
    unknowns = n - len(anchors) - (ncomp - len(held))
    dof = 2 * (len(idx) + n_abs) - 2 * unknowns
    s0 = float(np.sqrt(chi2 / dof)) if dof > 0 else float("nan")
    sx = np.column_stack(sxs) * (max(s0, 1.0) if np.isfinite(s0) else 1.0)
    return x, sx, v, norm, s0


def _radiometric(n, obs, idx, anchors, labels):
    edges = [(obs[k][0], obs[k][1]) for k in idx]
    rv = np.array([obs[k][2].radiometric for k in idx])
    rs = np.array([obs[k][2].radiometric_sigma for k in idx])
    pos = np.where(np.isfinite(rs) & (rs > 0), rs, np.nan)
    fill = float(np.nanmedian(pos)) if np.isfinite(pos).any() else 1.0
    rs = np.where(np.isfinite(pos), pos, fill)
    rad, _ = _solve_lsq(n, edges, rv, 1.0 / np.maximum(rs, 1e-3) ** 2, anchors, labels)
    return np.asarray(rad, float)


def solve_network(nodes: list, obs: list, anchors=(), reject: float = 4.0,
                  min_reject: float = 0.3, max_rounds: int = 20, absolute=()) -> Network:
    """Least-squares offsets per node from pairwise observations.

    ``obs``: ``(i, j, OverlapMatch)`` with node indices ``i, j`` (ref, mov): each accepted
    match says ``t_j - t_i = offset`` and ``b_j - b_i = radiometric``. ``anchors``: node
    indices held at zero offset (calibrated images). ``absolute``: ``(i, (drow, dcol),
    (sigma_row, sigma_col))`` absolute offsets of nodes (from control points), which tie
    their components to the ground. Components with neither get their mean fixed at zero.
    An observation whose normalised residual exceeds ``reject`` (and ``min_reject`` px) is
    dropped and the network solved again, as long as dropping it does not split the graph.
    """
    n = len(nodes)
    used = np.array([o[2].ok for o in obs], bool)
    anchors = sorted(set(int(a) for a in anchors))
    absolute = [(int(i), tuple(map(float, d)), tuple(map(float, sd))) for i, d, sd in absolute]
    x, sx, s0 = np.zeros((n, 2)), np.full((n, 2), np.nan), float("nan")
    while used.any():
        idx = np.nonzero(used)[0]
        ncomp, labels = _components(n, [(obs[k][0], obs[k][1]) for k in idx])
        x, sx, v, norm, s0 = _offsets(n, obs, idx, anchors, labels, ncomp, absolute)
        worst = int(np.argmax(norm.max(axis=1)))
        if max_rounds > 0 and norm[worst].max() > reject and np.abs(v[worst]).max() > min_reject:
            used[idx[worst]] = False
            n2, _ = _components(n, [(obs[q][0], obs[q][1]) for q in np.nonzero(used)[0]])
            if n2 <= ncomp:
                max_rounds -= 1
                continue
            used[idx[worst]] = True          # the only link: keep it (cannot be checked)
        break
    idx = np.nonzero(used)[0]
    ncomp, labels = _components(n, [(obs[k][0], obs[k][1]) for k in idx])
    if not used.any() and absolute:
        x, sx, _, _, s0 = _offsets(n, obs, idx, anchors, labels, ncomp, absolute)
    rad = _radiometric(n, obs, idx, anchors, labels) if used.any() else np.zeros(n)
    residuals = np.full((len(obs), 2), np.nan)
    for k in idx:
        residuals[k] = np.array(obs[k][2].offset) - (x[obs[k][1]] - x[obs[k][0]])
    return Network(list(nodes), x, sx, rad, residuals, used, s0, [nodes[a] for a in anchors],
                   _free_groups(nodes, labels, set(anchors) | {a[0] for a in absolute}))


def _free_groups(nodes, labels, held):
    """Components with no held node (anchor or absolute observation), as node keys."""
    out = []
    for c in np.unique(labels):
        members = np.nonzero(labels == c)[0].tolist()
        if not held.intersection(members):
            out.append([nodes[q] for q in members])
    return out
