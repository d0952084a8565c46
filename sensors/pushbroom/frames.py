"""The camera state from the POS: small helpers shared by the model and its partials."""
from __future__ import annotations

import numpy as np

from swathflow.geometry.rotations import apply, r_opk


def compose(x, ren, rnb, do, u_gps, R_bs):
    """Projection centre and R_ES from the antenna position ``x``, R_EN, R_NB, the fix
    attitude correction ``do`` (rad, or None), the lever arm and R_BS."""
    if do is not None:
        rnb = rnb @ r_opk(do[..., 0], do[..., 1], do[..., 2])
    reb = ren @ rnb
    return x + apply(reb, u_gps), reb @ R_bs


def matvec(m, v) -> np.ndarray:
    """``m @ v`` for stacks ``(n, 3, 3)`` and ``(n, 3)`` (faster than einsum here)."""
    return (m[:, :, 0] * v[:, 0:1] + m[:, :, 1] * v[:, 1:2] + m[:, :, 2] * v[:, 2:3])
