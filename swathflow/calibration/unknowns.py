"""The adjustment's unknowns and their mapping onto each image's model parameters:
per-direction blocks (``NAME_L``/``NAME_R``), a shared boresight, time-linear drift."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from swathflow.errors import SwathflowError

DIRECTION_SUFFIXES = ("_L", "_R")


class CalibrationError(SwathflowError):
    """The control points cannot determine the requested parameters."""


@dataclass
class Unknowns:
    names: list[str]
    units: list[str]
    value: np.ndarray
    sigma: np.ndarray
    fixed: np.ndarray
    blocks: dict[str, list[int]]            # unknown block -> its unknown indices
    block_units: dict[str, str]
    model_map: dict[str, tuple[str, str | None]] = field(default_factory=dict)


def _flat(name, size, i):
    return name if size == 1 else f"{name}[{i}]"


def _pairs(blocks) -> dict[str, str]:
    """``NAME_L``/``NAME_R`` block names -> ``NAME`` for every complete pair."""
    bnames = {b.name for b in blocks}
    paired = {}
    for b in blocks:
        for suf in DIRECTION_SUFFIXES:
            base = b.name[:-len(suf)]
            if b.name.endswith(suf) and all(base + s in bnames for s in DIRECTION_SUFFIXES):
                paired[b.name] = base
    if not paired:
        raise CalibrationError("shared boresight (12-parameter model) needs parameter "
                               "blocks named NAME_L and NAME_R; this sensor has "
                               + ", ".join(b.name for b in blocks))
    return paired


class _Builder:
    """Unknown blocks appended one after another."""

    def __init__(self):
        self.names, self.units, self.value, self.sigma, self.fix = [], [], [], [], []
        self.blocks: dict[str, list[int]] = {}
        self.block_units: dict[str, str] = {}

    def add(self, uname, size, unit, vals, sigs, fixed=()):
        start = len(self.names)
        self.names += [_flat(uname, size, i) for i in range(size)]
        self.units += [unit] * size
        self.value += list(vals[:size])
        self.sigma += list(sigs[:size])
        self.fix += [bool(f) for f in (tuple(fixed) or (False,) * size)]
        self.blocks[uname] = list(range(start, start + size))
        self.block_units[uname] = unit


def _drift_blocks(drift, blocks) -> list[str]:
    if drift is not True:
        return list(drift)
    out = [b.name for b in blocks if b.name.endswith(DIRECTION_SUFFIXES)]
    if not out:
        raise CalibrationError("drift=True drifts the per-direction blocks (NAME_L, "
                               "NAME_R), and this sensor has none: name the blocks")
    return out


def _fixed_mask(fixed, u: _Builder, model_map) -> np.ndarray:
    out = np.array(u.fix, bool)
    for f in fixed:
        if f in u.blocks:
            out[u.blocks[f]] = True
        elif f in u.names:
            out[u.names.index(f)] = True
        elif f in model_map:
            out[u.blocks[model_map[f][0]]] = True
        else:
            raise CalibrationError(f"--fix {f}: no such parameter; known: "
                                   + ", ".join(list(u.blocks) + u.names))
    return out


def build_unknowns(priors, shared_boresight: bool = False, fixed: Sequence[str] = (),
                   drift: bool | Sequence[str] = False, drift_sigma: float = 1.0) -> Unknowns:
    """The adjustment's unknowns from the prior :class:`ParameterSet`.

    shared_boresight: each pair ``NAME_L`` / ``NAME_R`` becomes one unknown ``NAME``.
    fixed: block names (``opk_sen``) or flat names (``opk_sen[1]``) held at their priors.
    drift: True (every per-direction block) or block names: adds ``NAME_rate`` unknowns in
        units per hour with prior 0 +- ``drift_sigma``.
    """
    blocks = list(priors.blocks)
    paired = _pairs(blocks) if shared_boresight else {}
    u = _Builder()
    model_map: dict[str, tuple[str, str | None]] = {}
    for b in blocks:
        uname = paired.get(b.name, b.name)
        if uname not in u.blocks:
            if uname != b.name:      # merged pair: average the priors
                pair = [priors.block(uname + s) for s in DIRECTION_SUFFIXES]
                vals = np.mean([p.value for p in pair], axis=0)
                sigs = np.min([p.sigma for p in pair], axis=0)
            else:
                vals, sigs = b.value, b.sigma
            u.add(uname, b.size, b.units, vals, sigs, b.fixed)
        model_map[b.name] = (uname, None)
    for name in (_drift_blocks(drift, blocks) if drift else ()):
        if name not in model_map:
            raise CalibrationError(f"drift: no parameter block {name!r}; known: "
                                   + ", ".join(model_map))
        uname = model_map[name][0]
        rname = uname + "_rate"
        if rname not in u.blocks:
            size = len(u.blocks[uname])
            u.add(rname, size, u.block_units[uname] + "/h", [0.0] * size,
                  [drift_sigma] * size)
        model_map[name] = (uname, rname)
    return Unknowns(u.names, u.units, np.array(u.value, float), np.array(u.sigma, float),
                    _fixed_mask(fixed, u, model_map), u.blocks, u.block_units, model_map)


def model_matrix(model, unknowns: Unknowns, dt_hours: float = 0.0) -> np.ndarray:
    """M with ``model_vector = M @ x`` for one image (dt_hours: image time - t_ref)."""
    ps = model.parameters
    rows = []
    for b in ps.blocks:
        if b.name not in unknowns.model_map:
            raise CalibrationError(f"model parameter {b.name!r} has no unknown")
        uname, rname = unknowns.model_map[b.name]
        for i in range(b.size):
            row = np.zeros(len(unknowns.names))
            row[unknowns.blocks[uname][i]] = 1.0
            if rname is not None:
                row[unknowns.blocks[rname][i]] = dt_hours
            rows.append(row)
    return np.array(rows)


def _swap_direction(vec: np.ndarray, params) -> np.ndarray:
    """A model vector with every NAME_L / NAME_R pair exchanged (cross-application)."""
    out = vec.copy()
    names = params.names
    pos, i = {}, 0
    for b in params.blocks:
        pos[b.name] = (i, b.size)
        i += b.size
    for n in names:
        if n.endswith("_L") and n[:-2] + "_R" in pos:
            (a, s), (c, _) = pos[n], pos[n[:-2] + "_R"]
            out[a:a + s], out[c:c + s] = vec[c:c + s], vec[a:a + s]
    return out

