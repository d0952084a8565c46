"""The mission flow's stages as Prefect tasks.

Each task takes paths and small values, returns a path or a small dict, reuses a finished
output whose inputs have not changed (:mod:`swathflow.cache`), and never hashes arrays
(``cache_policy=NO_CACHE``: Prefect's own input hashing costs seconds per large input).
"""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np
from prefect import task
from prefect.cache_policies import NO_CACHE

from swathflow.cache import is_fresh, mark_done, stage_key
from swathflow.errors import SwathflowError
from swathflow.tasks import swings


_load = swings.load
_mission_files = swings.mission_files
_image_files = swings.image_files


@task(name="ingest", cache_policy=NO_CACHE)
def ingest(mission_path: str) -> dict:
    """Load and validate the mission (every problem listed at once) and summarise it."""
    m = _load(mission_path)
    return {"name": m.name, "images": list(m.images), "sensor": m.sensor.get("model"),
            "gcps": 0 if m.gcps is None else int(len(m.gcps)), "crs": m.crs, "gsd": m.gsd}


_EO_COLUMNS = ("line", "time", "lat", "lon", "h", "roll", "pitch", "heading")


def _write_eo(path, time_, cols: dict) -> None:
    """``<image>.eo.csv``: the line number, then every value with 10 decimals (empty for
    NaN), as pandas' ``to_csv(float_format="%.10f")`` writes it, at a fraction of its
    cost (pandas formats each value in Python)."""
    table = np.column_stack([time_] + [cols[k] for k in _EO_COLUMNS[2:]])
    row = ",".join(["%d"] + ["%.10f"] * table.shape[1])
    with open(path, "w", encoding="utf-8", newline="") as f:
        f.write(",".join(_EO_COLUMNS) + "\n")
        if np.isfinite(table).all():
            f.write("".join(row % ((i,) + tuple(v)) + "\n" for i, v in enumerate(table.tolist())))
        else:
            for i, v in enumerate(table.tolist()):
                f.write(",".join([str(i)] + ["" if x != x else "%.10f" % x for x in v]) + "\n")


@task(name="interpolate-pos", cache_policy=NO_CACHE)
def interpolate_pos(mission_path: str, out_dir: str) -> list[str]:
    """Exterior orientation of every scan line: the POS interpolated to each line's time,
    written as ``OUT/pos/<image>.eo.csv`` (a product, and a check that the POS covers every
    line before the heavy stages start)."""
    from swathflow.io import atomic_path
    from swathflow.formats.pos import pos_columns
    m = _load(mission_path)
    paths = []
    for iid in m.images:
        out = Path(out_dir) / "pos" / f"{iid}.eo.csv"
        key = stage_key("pos", _mission_files(m) + [m.images[iid].lines_file])
        if not is_fresh(out, key):
            lines = m.lines(iid)
            cols = pos_columns(m.trajectory, lines["time"])   # built once with the mission
            with atomic_path(out) as tmp:
                _write_eo(tmp, np.asarray(lines["time"], float), cols)
            mark_done(out, key)
        paths.append(str(out))
    return paths


@task(name="calibrate", cache_policy=NO_CACHE)
def calibrate(mission_path: str, out_dir: str, calibration: str | None = None) -> str:
    """Per-swing-direction calibration from the mission's control points, or the given
    calibration file (checked), or, without control points, from the mission's
    ``[reference]`` orthophoto (automatic control), or else the mission's priors."""
    from swathflow.formats.calibfile import read_calibration, write_calibration
    m = _load(mission_path)
    out = Path(out_dir) / "calibration" / "calibration.json"
    if calibration:
        doc = read_calibration(calibration)
        if doc.get("sensor") not in (None, m.sensor.get("model")):
            raise SwathflowError(f"{calibration}: calibration is for sensor {doc['sensor']!r}, "
                                 f"the mission uses {m.sensor.get('model')!r}")
        return str(Path(calibration).resolve())
    from swathflow.calibration.autocontrol import reference_paths
    gcp_file = m.config.get("gcp", {}).get("file")
    ties_file = m.config.get("ties", {}).get("file")
    ref = reference_paths(m)
    key = stage_key("calibrate", _mission_files(m) + [m.path / gcp_file if gcp_file else None]
                    + [m.path / ties_file if ties_file else None]
                    + ([Path(p) for p in ref if p] if ref else [])
                    + [f for iid in m.images for f in _image_files(m, iid)[1:]])
    if is_fresh(out, key):
        return str(out)
    if (m.gcps is None or len(m.gcps) == 0) and not ref:
        write_calibration(out, m.sensor.get("model", ""), m.priors.to_dict(),
                          note="no control points: the mission's prior values, uncalibrated")
    else:
        from swathflow.calibration.strategy import calibrate_mission
        calibrate_mission(m).write(out.parent)     # the sensor plugin's strategy
    mark_done(out, key)
    return str(out)


@task(name="rectify", cache_policy=NO_CACHE, retries=1, retry_delay_seconds=2)
def rectify(mission_path: str, image_id: str, calibration: str, out_dir: str) -> str:
    """Orthorectify one swing to ``OUT/rectified/<image>.tif`` (COG) with the calibration:
    ``to_cog(rectify(...))`` of the Python API in the raw image's dtype: every band of the
    raw image, or those of ``[rectify] bands`` in mission.toml
    (:func:`swathflow.tasks.swings.rectify_swing`)."""
    return swings.rectify_swing(_load(mission_path), image_id, calibration, out_dir)


#: the last :func:`mosaic_control` of this process: {key: offsets}
_CONTROL: dict = {}


def mosaic_control(mission_path: str, calibration: str) -> dict:
    """Image id -> (absolute offset, sigma) in grid pixels from the mission's control
    points with ``calibration`` (see :mod:`swathflow.mosaicking.control`); memoised on
    the mission's and the calibration file's stamps (the flow computes it while the
    workers rectify: :func:`prepare_mosaic`)."""
    from swathflow.formats.calibfile import calibration_priors, read_calibration
    from swathflow.mosaicking.control import control_offsets
    st = os.stat(calibration)
    key = (swings.mission_stamp(mission_path), os.path.abspath(calibration), st.st_size,
           st.st_mtime_ns)
    if key not in _CONTROL:
        m = _load(mission_path)
        params = m.priors.updated(calibration_priors(read_calibration(calibration)))
        offsets = {k: (o, s) for k, (o, s, _) in control_offsets(m, params).items()}
        _CONTROL.clear()
        _CONTROL[key] = offsets
    return dict(_CONTROL[key])


def _has_control(m) -> bool:
    return m is not None and m.gcps is not None and bool((m.gcps["role"] == "control").any())


def prepare_mosaic(mission_path: str, calibration: str) -> None:
    """What the mosaic stage (``anchor="auto"``) needs that no swing changes: the control
    points' offsets (:func:`mosaic_control`, about 0.4 CPU-s on the survey), computed now
    in this process, e.g. while the workers rectify, instead of at the mosaic's start."""
    if calibration and _has_control(_load(mission_path)):
        mosaic_control(mission_path, calibration)


@task(name="mosaic", cache_policy=NO_CACHE)
def mosaic(rectified: list[str], out_dir: str, mission_path: str | None = None,
           calibration: str | None = None, anchor: str = "auto") -> str:
    """Strip matching and feathered mosaic of the rectified swings: ``OUT/mosaic.tif``.
    ``anchor``: ``"gcp"`` ties the network to the mission's control points, ``"mean"``
    holds the mean offset at zero; ``"auto"``: gcp when the mission has control points."""
    from swathflow.mosaicking.api import write_mosaic   # the files only: no lazy array
    out = Path(out_dir) / "mosaic.tif"
    m = _load(mission_path) if mission_path else None
    has_control = _has_control(m)
    if anchor == "gcp" and not has_control:
        raise SwathflowError(f"{mission_path}: --anchor gcp needs control points (role "
                             f"control in the GCP file); the mission has none")
    use_gcp = anchor == "gcp" or (anchor == "auto" and has_control and calibration)
    deps = list(rectified)
    if use_gcp:
        gcp_file = m.config.get("gcp", {}).get("file", "gcp.csv")
        deps += [str(m.path / gcp_file), calibration]
    key = stage_key("mosaic" + ("-gcp" if use_gcp else ""), deps)
    if is_fresh(out, key):
        return str(out)
    control = mosaic_control(mission_path, calibration) if use_gcp else None
    strips = {iid: e.strip for iid, e in m.images.items()} if m is not None else None
    write_mosaic(list(rectified), out, control=control, strips=strips)
    mark_done(out, key)
    return str(out)


@task(name="catalog", cache_policy=NO_CACHE)
def catalog(mission_path: str, rectified: list[str], mosaic_path: str | None, calibration: str,
            out_dir: str) -> str:
    """The STAC catalogue of the run's products: ``OUT/stac/catalog.json``."""
    from swathflow.formats.stac import write_catalog
    m = _load(mission_path)
    out = Path(out_dir) / "stac" / "catalog.json"
    cal = Path(calibration)
    report = cal.parent / "report.html"
    mos = Path(mosaic_path) if mosaic_path else None
    side = [p for p in ([mos.with_suffix(".json"), mos.with_suffix(".html"),
                         mos.with_suffix(".png")] if mos else []) if p.exists()]
    key = stage_key("catalog", list(rectified) + [mos, cal, report if report.exists() else None]
                    + side + [m.path / "mission.toml"])
    # the manifest sits beside the catalogue's folder (OUT/stac.swathflow.json), not in it
    if is_fresh(out.parent, key) and out.exists():
        return str(out)
    spans = {iid: span for iid in m.image_ids
             if (span := m.acquisition_span(iid)) is not None}
    html = mos.with_suffix(".html") if mos else None
    path = write_catalog(
        rectified, mos, out.parent, calibration=cal, report=report if report.exists() else None,
        mosaic_report=html if html and html.exists() else (mos.with_suffix(".json") if mos else None),
        quicklook=mos.with_suffix(".png") if mos else None, title=f"swathflow run of {m.name}",
        catalog_id=f"swathflow-{m.name}", spans=spans,
        facts={Path(p).stem: f for p in rectified
               if (f := swings.recorded_facts(p)) is not None})
    mark_done(out.parent, key)
    return path
