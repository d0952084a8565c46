"""Rectify every (or some) image of a mission with a calibration: one COG per image and a
``rectify.json`` summary. Each image is ``to_cog(rectify(...))`` of the Python API
(:mod:`swathflow.rectification.api`), as the flow's rectify task writes it."""
from __future__ import annotations

import json
import os
import time
from collections.abc import Callable, Sequence

from swathflow.errors import FormatError
from swathflow.ingest.mission import load_mission
from swathflow.io import write_text
from swathflow.rectification.api import geolocation, rectify, to_cog
from swathflow.rectification.lattice import TOLERANCE_PX
from swathflow.rectification.rawimage import open_raw_image


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
    ``dtype`` says otherwise (integer nodata, or a mask band with ``mask_band``);
    ``products`` adds ``<id>.glt.tif`` / ``<id>.igm.tif``. Returns one summary per image."""
    unknown = set(products) - {"glt", "igm"}
    if unknown:
        raise FormatError(f"unknown product(s) {', '.join(sorted(unknown))}; use glt, igm")
    mission = load_mission(mission_path)
    ids = mission.image_ids
    if images:
        missing = [i for i in images if i not in ids]
        if missing:
            raise FormatError(f"{mission_path}: no image(s) {', '.join(missing)}; the mission "
                              f"has {', '.join(ids)}")
        ids = list(images)
    os.makedirs(out_dir, exist_ok=True)
    summaries, cal_tag = [], ""
    for iid in ids:
        out = os.path.join(out_dir, f"{iid}.tif")
        t0 = time.perf_counter()
        sel = bands if bands not in (None, "") else mission_bands(mission, iid)
        arr = rectify(mission, iid, calibration, kernel=kernel, tile=tile, method=method,
                      tol=tol, bands=sel, dtype=dtype, mask_band=mask_band)
        s = to_cog(arr, out, blocksize=tile)
        for p in products:
            to_cog(geolocation(mission, iid, calibration, p, kernel=kernel, tile=tile, tol=tol),
                   os.path.join(out_dir, f"{iid}.{p}.tif"), blocksize=tile)
        s.update(image_id=iid, method=method, kernel=kernel,
                 seconds=round(time.perf_counter() - t0, 3))
        cal_tag = arr.attrs["calibration"]
        summaries.append(s)
        if progress:
            progress(f"{iid}: {arr.rio.height} x {arr.rio.width} px -> {out} "
                     f"({time.perf_counter() - t0:.1f} s)")
    write_text(os.path.join(out_dir, "rectify.json"),
               json.dumps({"images": summaries, "calibration": cal_tag}, indent=2) + "\n")
    return summaries
