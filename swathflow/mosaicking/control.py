"""Absolute offsets of rectified swings from the mission's control points, for tying the
mosaic network to the ground (``swathflow mosaic --anchor gcp``, the flow's default when
the mission has control points).

A control point measured at raw pixel ``(line, element)`` of an image shows, in that
image's rectified swing, at the ground point the sensor model gives for that pixel
(``image_to_ground`` with the calibration used for rectifying); its surveyed position is
where it belongs. The mean difference over an image's control points, in grid pixels
(row down, column right), is the image's absolute offset ``t`` (``image[x] =
truth[x - t]``, the mosaic's convention); its sigma is the scatter over the points divided
by their square root, never below ``floor`` (and ``single`` for an image with one point).
"""
from __future__ import annotations

import numpy as np

__all__ = ["control_offsets"]


def control_offsets(mission, params, floor: float = 0.1, single: float = 1.0) -> dict:
    """Image id -> ``((drow, dcol), (sigma_row, sigma_col), n_points)`` in grid pixels of
    ``mission.gsd`` from the mission's ``control`` points, with sensor parameters
    ``params``. Images without control points are left out."""
    from swathflow.geometry.geodesy import transformer
    g = mission.gcps
    if g is None or len(g) == 0:
        return {}
    g = g[g["role"] == "control"]
    to_map = transformer("EPSG:4978", mission.crs)
    out = {}
    for iid, grp in g.groupby("image_id"):
        if iid not in mission.images:
            continue
        model = mission.model(iid, params)
        est = model.image_to_ground(grp[["line", "element"]].to_numpy(float), mission.terrain)
        e1, n1, _ = to_map.transform(est[:, 0], est[:, 1], est[:, 2])
        e0, n0, _ = to_map.transform(*(grp[c].to_numpy(float) for c in ("X", "Y", "Z")))
        d = np.column_stack([-(np.asarray(n1) - n0), np.asarray(e1) - e0]) / mission.gsd
        d = d[np.isfinite(d).all(axis=1)]
        if len(d) == 0:
            continue
        if len(d) == 1:
            sig = np.full(2, single)
        else:
            sig = np.maximum(d.std(axis=0, ddof=1) / np.sqrt(len(d)), floor)
        out[str(iid)] = (tuple(float(v) for v in d.mean(axis=0)),
                         tuple(float(v) for v in sig), int(len(d)))
    return out
