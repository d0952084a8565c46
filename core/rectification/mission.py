"""Rectify every (or some) image of a mission with a calibration: one COG per image and a
``rectify.json`` summary."""
from __future__ import annotations

import hashlib
import json
import os
import time
from collections.abc import Callable, Sequence

from swathflow.errors import FormatError
from swathflow.formats.calibfile import calibration_priors, read_calibration
from swathflow.geometry.grid import footprint_grid
from swathflow.ingest.mission import load_mission
from swathflow.io import write_text
from swathflow.rectification.rawimage import open_raw_image
from swathflow.rectification.rectify import TOLERANCE_PX, rectify_image


def mission_bands(mission, image_id: str | None = None):
    """The band selection of ``[rectify] bands`` in the mission's ``mission.toml`` (the
    syntax of ``--bands``: ``"1,4-6"``, ``"550nm"``, or a list of 1-based indices), None
    (every band) when absent. With ``image_id`` the selection is checked against that
    image's bands (a :class:`FormatError` naming mission.toml and the key)."""
    spec = (mission.config.get("rectify") or {}).get("bands")
    if spec in (None, "", []):
        return None
    if not isinstance(spec, (str, list)) or (isinstance(spec, list) and not all(
            isinstance(b, int) and not isinstance(b, bool) for b in spec)):
        raise FormatError(f"{mission.path / 'mission.toml'}: [rectify] bands = {spec!r} is "
                          f"neither a string such as \"1,4-6\" or \"550nm\" nor a list of "
                          f"1-based band numbers")
    if image_id is not None:
        img = open_raw_image(mission.images[image_id].file)
        try:
            img.select(spec)
        except FormatError as exc:
            raise FormatError(f"{mission.path / 'mission.toml'}: [rectify] bands = {spec!r} "
                              f"does not fit image {image_id!r}: "
                              f"{str(exc).split(': ', 1)[-1]}") from None
    return spec


def rectify_mission(mission_path, out_dir, calibration: str | None = None,
                    images: Sequence[str] | None = None, method: str = "exact",
                    kernel: str = "bilinear", tol: float = TOLERANCE_PX, tile: int = 512,
                    products: Sequence[str] = (),
                    progress: Callable[[str], None] | None = None, bands=None,
                    dtype: str | None = None, mask_band: bool = False) -> list[dict]:
    """Rectify the mission's images into ``out_dir/<id>.tif`` with ``calibration`` (a
    calibration.json; default: the mission's priors). Every band of each raw image is
    rectified (``bands``: a subset by 1-based index or wavelength, see
    :func:`~swathflow.rectification.rawimage.parse_bands`; default: ``[rectify] bands``
    of mission.toml, see :func:`mission_bands`), in the raw dtype unless
    ``dtype`` says otherwise (integer nodata, or a mask band with ``mask_band``). Returns
    one summary per image."""
    mission = load_mission(mission_path)
    params, cal_tag = mission.priors, "none: mission priors (mission.toml [calibration])"
    if calibration:
        doc = read_calibration(calibration)
        if doc.get("sensor") and doc["sensor"] != mission.sensor.get("model"):
            raise FormatError(f"{calibration}: calibration is for sensor "
                              f"{doc['sensor']!r}, the mission uses "
                              f"{mission.sensor.get('model')!r}")
        params = mission.priors.updated(calibration_priors(doc))
        with open(calibration, "rb") as f:
            digest = hashlib.sha256(f.read()).hexdigest()[:16]
        cal_tag = f"{os.path.abspath(calibration)} (sha256 {digest})"
    ids = mission.image_ids
    if images:
        missing = [i for i in images if i not in ids]
        if missing:
            raise FormatError(f"{mission_path}: no image(s) {', '.join(missing)}; the mission "
                              f"has {', '.join(ids)}")
        ids = list(images)
    os.makedirs(out_dir, exist_ok=True)
    summaries = []
    for iid in ids:
        sel = bands if bands not in (None, "") else mission_bands(mission, iid)
        model = mission.model(iid, params)
        grid = footprint_grid(model, mission.terrain, mission.gsd, mission.crs)
        out = os.path.join(out_dir, f"{iid}.tif")
        t0 = time.perf_counter()
        s = rectify_image(model, open_raw_image(mission.images[iid].file), mission.terrain,
                          out, grid=grid, method=method, kernel=kernel, tol=tol, tile=tile,
                          products=tuple(products), bands=sel, dtype=dtype,
                          mask_band=mask_band,
                          tags={"image_id": iid, "calibration": cal_tag,
                                "mission": mission.name,
                                "parameters": json.dumps(model.parameters.values_dict())})
        s["image_id"] = iid
        summaries.append(s)
        if progress:
            progress(f"{iid}: {grid.shape[0]} x {grid.shape[1]} px -> {out} "
                     f"({time.perf_counter() - t0:.1f} s)")
    write_text(os.path.join(out_dir, "rectify.json"),
               json.dumps({"images": summaries, "calibration": cal_tag}, indent=2) + "\n")
    return summaries
