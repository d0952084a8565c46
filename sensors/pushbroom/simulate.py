"""Simulated three-line push-broom missions with their truth (``swathflow simulate --preset
pushbroom...``).

A three-line camera (forward / nadir / backward lines at about +25 / 0 / -25 deg, each CCD
line made of segments) flies parallel strips over the simulator's procedural terrain and
texture (:mod:`swathflow.simulation.texture`). The truth has smooth additional parameters (one cubic
over the whole line per view and polynomial, re-expanded per segment, so C0/C1 hold
exactly), a lever arm, a boresight and LIM orientation-fix corrections. The mission's POS
is the one the camera's geometry is defined on (the fix corrections model its slowly
varying errors) plus white noise; ``truth/pos.csv`` is that POS without the noise, so
``truth/pos.csv`` + ``truth/calibration.json`` reproduce the true geometry exactly.

Writes a mission bundle in the push-broom format (docs/mission-format-pushbroom.md): one
image per CCD line and strip (``view`` = forward/nadir/backward), line tables, ``gcp.csv``
(control and check points, survey targets in the texture), ``ties.csv`` (tie points
measured in the images, ground unknown), ``[sensor.fixes]`` and the priors; plus
``truth/`` (calibration.json, pos.csv, gcp.csv, ties.csv, ortho.tif, truth.json).

Images are rendered through the sensor plugin with :func:`swathflow.simulation.bundle.render_image`
(``render=False``: blank images, for geometry-only calibration tests).

The configuration, presets and the simulated camera are in
:mod:`~swathflow.sensors.pushbroom.simconfig`, the ground points in
:mod:`~swathflow.sensors.pushbroom.simpoints`; this module (the plugin's ``simulator()``)
runs the simulation and writes the bundle.
"""
from __future__ import annotations

import json
import math
import os
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from swathflow.formats.pos import Trajectory
from swathflow.geometry.geodesy import transformer
from swathflow.io import write_text
from swathflow.sensors.pushbroom.simconfig import (PRESETS, VIEW_LETTER, VIEWS, PushbroomConfig,
                                                   dem_grid, make_plan, preset_config,
                                                   prior_table, sensor_table, true_parameters)
from swathflow.sensors.pushbroom.simpoints import sample_points, write_points
from swathflow.simulation.bundle import (make_trajectory, plain, toml_value, write_mission_toml,
                                        write_noisy_pos, write_swing, write_truth_ortho)

__all__ = ["PRESETS", "VIEWS", "PushbroomConfig", "preset_config", "simulate"]


@dataclass
class _Camera:
    """The simulated camera: fix times, ``[sensor]`` table, true parameters, images
    (id, view, strip, line table) and their true models."""

    fix_t: np.ndarray
    sensor: dict
    params: dict
    pset: object
    images: list
    models: dict


@dataclass
class _Points:
    """Control/check points (targets in the texture) and tie points with their image
    observations."""

    g_xyz: np.ndarray
    g_en: np.ndarray
    g_obs: dict
    gcp_ids: list
    roles: np.ndarray
    t_xyz: np.ndarray
    t_obs: dict
    tie_ids: list
    radius: float
    nadir_gsd: float


def simulate(out, preset: str = "pushbroom", seed: int = 0, progress=None,
             texture: str | None = None, **overrides) -> dict:
    """Write a simulated push-broom mission to ``out``; returns the truth summary.
    ``texture``: an image to render (e.g. a real orthophoto; procedural without)."""
    from swathflow.formats.calibfile import write_calibration
    from swathflow.simulation.texture import ImageTexture, ProceduralTexture
    say = progress or (lambda msg: None)
    clock = time.perf_counter()
    cfg = preset_config(preset, **overrides)
    out = _prepare(out)
    rng = np.random.default_rng([int(seed), 81])
    plan = make_plan(cfg)
    to_map = transformer("EPSG:4978", plan.crs)
    terrain, terrain_mean = _write_terrain(out, cfg, plan, seed)
    # trajectory (the POS the geometry is defined on), line tables, fixes
    pos_ds, strips = make_trajectory(cfg, plan, terrain_mean, rng)
    cam = _camera(cfg, plan, strips, Trajectory.from_dataset(pos_ds), rng)
    pts = _ground_points(cfg, plan, strips, cam.models, terrain, rng)
    tex0 = (ImageTexture(texture, plan.centre, rotation_deg=float(
        np.random.default_rng([int(seed), 85]).uniform(0, 360))) if texture
        else ProceduralTexture(seed, pts.nadir_gsd, plan.centre))
    tex = tex0.with_targets(pts.g_en, pts.radius)
    say(f"rendering {len(cam.models)} push-broom images of {plan.lines_per_swing} x "
        f"{cfg.n_elements}" + ("" if cfg.render else " (geometry only: blank images)"))
    entries = []
    for k, (iid, view, s, lt) in enumerate(cam.images):
        paths = write_swing(out, iid, cam.models[iid], terrain, tex, to_map, cfg,
                            np.random.default_rng([int(seed), 82, k]), {"time": lt["time"]})
        entries.append((iid, *paths, view, s))
    ortho = write_truth_ortho(out, cfg, plan.crs, cam.models, terrain, tex, to_map, say)
    gobs, tobs = write_points(out, cfg, seed, pts)
    pos_name = write_noisy_pos(out, pos_ds, cfg, np.random.default_rng([int(seed), 84]))
    # truth calibration, truth.json, mission.toml
    write_calibration(out / "truth" / "calibration.json", "pushbroom",
                      {b.name: {"value": list(b.value), "sigma": [0.0] * b.size,
                                "units": b.units} for b in cam.pset.blocks},
                      note=f"simulation truth: preset {cfg.preset}, seed {seed}")
    priors = prior_table(cfg, cam.fix_t.size)
    truth = _truth(cfg, seed, plan, strips, cam, pts, gobs, tobs, priors, ortho, terrain_mean)
    if texture:
        truth["texture"] = {"source": str(texture), "pixel_size_m": tex0.pixel_size}
    truth["seconds"] = round(time.perf_counter() - clock, 3)
    write_text(out / "truth" / "truth.json", json.dumps(truth, indent=2) + "\n")
    _write_toml(out, cfg, plan, pos_name, entries, cam.sensor, priors)
    return truth


def _prepare(out) -> Path:
    out = Path(out)
    (out / "images").mkdir(parents=True, exist_ok=True)
    (out / "truth").mkdir(parents=True, exist_ok=True)
    if (out / "mission.toml").exists():
        os.remove(out / "mission.toml")
    return out


def _write_terrain(out: Path, cfg: PushbroomConfig, plan, seed: int):
    """The procedural terrain as ``dem.tif`` (the truth terrain); returns it opened and
    its mean height."""
    from swathflow.formats.raster import write_geotiff
    from swathflow.geometry.terrain import DEM
    from swathflow.simulation.texture import ProceduralTerrain
    dem_tr, dem_shape = dem_grid(plan, cfg)
    hfun = ProceduralTerrain(seed, cfg.terrain_base, cfg.terrain_relief,
                             cfg.terrain_wavelength, plan.centre)
    rr, cc = np.indices(dem_shape)
    a, _, c0, _, e, f0 = dem_tr
    hgrid = hfun(c0 + (cc + 0.5) * a, f0 + (rr + 0.5) * e).astype(np.float32)
    write_geotiff(out / "dem.tif", hgrid, plan.crs, dem_tr, nodata=-9999.0,
                  tags={"vertical": "ellipsoidal", "source": "procedural"})
    return DEM.open(out / "dem.tif"), float(np.mean(hgrid))


def _camera(cfg: PushbroomConfig, plan, strips, pos_traj, rng) -> _Camera:
    """Fix times, the ``[sensor]`` table, the true parameters and one true model per CCD
    line and strip."""
    from swathflow.sensormodel import get_sensor
    n_fix_strip = max(2, int(math.ceil(plan.strip_duration / cfg.fix_interval)) + 1)
    fix_t = np.concatenate([np.linspace(s["t_start"], s["t_start"] + plan.strip_duration,
                                        n_fix_strip) for s in strips])
    sensor = sensor_table(cfg, fix_t)
    params = true_parameters(cfg, fix_t.size, rng)
    cls = get_sensor("pushbroom")
    pset = cls.default_parameters(sensor).updated(params)
    images = []
    for st in strips:
        t = st["t_start"] + np.arange(plan.lines_per_swing) * plan.line_period
        for view in cfg.views:
            iid = f"{VIEW_LETTER.get(view, view[:1].upper())}{st['strip']}"
            images.append((iid, view, st["strip"], {"time": t}))
    models = {iid: cls.build(sensor, lt, pos_traj, pset, image_id=iid, view=v, strip=s)
              for iid, v, s, lt in images}
    return _Camera(fix_t, sensor, params, pset, images, models)


def _ground_points(cfg: PushbroomConfig, plan, strips, models, terrain, rng) -> _Points:
    """Control + check points (survey targets, kept apart) and tie points."""
    n_gcp = cfg.n_control + cfg.n_check
    nadir_gsd = cfg.ifov * cfg.agl
    radius = cfg.target_radius_px * nadir_gsd
    g_xyz, g_en, g_obs = sample_points(cfg, plan, strips, models, terrain, n_gcp, rng,
                                       min_views=3, min_sep=6 * radius)
    gcp_ids = [f"G{k + 1:04d}" for k in range(n_gcp)]
    roles = np.array(["control"] * cfg.n_control + ["check"] * cfg.n_check)
    t_xyz, _, t_obs = sample_points(cfg, plan, strips, models, terrain, cfg.n_ties, rng,
                                    min_views=2)
    tie_ids = [f"T{k + 1:04d}" for k in range(cfg.n_ties)]
    return _Points(g_xyz, g_en, g_obs, gcp_ids, roles, t_xyz, t_obs, tie_ids, radius,
                   nadir_gsd)


def _truth(cfg: PushbroomConfig, seed, plan, strips, cam: _Camera, pts: _Points, gobs, tobs,
           priors, ortho, terrain_mean) -> dict:
    """The truth summary (``truth/truth.json``, without ``seconds``)."""
    return {
        "format": "swathflow-simulation-truth/1", "sensor": "pushbroom",
        "preset": cfg.preset, "seed": int(seed), "config": plain(asdict(cfg)),
        "crs": plan.crs, "gsd": cfg.gsd, "centre_en": list(plan.centre),
        "plan": plain(asdict(plan)), "strips": strips,
        "images": [{"id": iid, "view": v, "strip": s, "lines": cam.models[iid].n_lines,
                    "elements": cfg.n_elements, "t0": float(lt["time"][0]),
                    "t1": float(lt["time"][-1])} for iid, v, s, lt in cam.images],
        "images_rendered": bool(cfg.render),
        "parameters": cam.params,
        "priors": {k2: {"value": v, "sigma": s} for k2, (v, s) in priors.items()},
        "fix_times": [float(t) for t in cam.fix_t],
        "noise": {"gps_m": cfg.gps_noise, "attitude_deg": cfg.att_noise,
                  "gcp_px": cfg.gcp_noise, "tie_px": cfg.tie_noise,
                  "read_noise_dn": cfg.read_noise, "shot_noise": cfg.shot_noise},
        "gcp_counts": {iid: {r: int(((gobs.image_id == iid) & (gobs.role == r)).sum())
                             for r in ("control", "check")} for iid in cam.models},
        "tie_observations": int(len(tobs)),
        "gcp_target_radius_m": pts.radius,
        "radiometry": {"gain": cfg.gain, "offset": cfg.offset},
        "ortho": ({"file": "truth/ortho.tif", "transform": list(ortho["transform"]),
                   "shape": list(ortho["shape"]), "supersample": cfg.ortho_supersample}
                  if cfg.write_ortho else None),
        "footprint_bounds": ortho["bounds"],
        "texture": {"source": "procedural", "scale_m": pts.nadir_gsd},
        "terrain": {"source": "procedural", "mean_h": terrain_mean, "dem_cell": cfg.dem_cell},
        "nadir_gsd_m": pts.nadir_gsd,
    }


def _write_toml(out, cfg, plan, pos_name, entries, sensor, priors):
    lines = [f"{k} = {toml_value(v)}" for k, v in sensor.items() if k not in ("views", "fixes")]
    lines += ["", "[sensor.views]"] + [f"{k} = {toml_value(float(v))}"
                                       for k, v in sensor["views"].items()]
    lines += ["", "[sensor.fixes]", f"time = {toml_value(sensor['fixes']['time'])}"]
    write_mission_toml(out, cfg.preset, plan.crs, cfg.gsd, pos_name, lines, priors, entries,
                        "view", ties=True)
