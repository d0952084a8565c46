"""Simulated pendulum-scanner missions with their truth (``swathflow simulate``).

Writes a complete mission bundle (docs/mission-format.md v1) plus ``OUT/truth/``:
``calibration.json`` (true parameters), ``pos.csv`` (true trajectory before noise),
``ortho.tif`` (truth orthophoto on the mission's output grid, expected DN), ``gcp.csv``
(noise-free image and ground coordinates), ``truth.json`` (everything else a test needs).

Physics (docs/references.md section 1): a TDI detector line along track in a gimbal that swings
across track, alternating left and right swings, pitch compensation that holds each swing
on a fixed ground strip, several parallel strips with side overlap and alternating flight
directions, aircraft motion, POS at 200 Hz with noise. Images are rendered THROUGH the
registered sensor plugin: exact rays on every (sub)line at a coarse set of elements,
intersected with the mission's DEM, then a cubic spline along the detector line (the
interpolation error is tested to be far below 0.01 px), the texture integrated over each
detector pixel with ``supersample`` x ``supersample`` samples, plus sensor noise.
"""
from __future__ import annotations

import json
import math
import os
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np
import pandas as pd

from swathflow.simulation.bundle import (Plan, Rendering, make_trajectory, plain, toml_value,
                                        write_mission_toml, write_noisy_pos, write_swing,
                                        write_truth_ortho)
from swathflow.errors import SwathflowError
from swathflow.geometry.geodesy import ecef_to_geodetic, geodetic_to_ecef, transformer, utm_crs_for
from swathflow.geometry.intersect import intersect
from swathflow.io import write_text
from swathflow.formats.pos import Trajectory
from swathflow.sensors.pendulum.simwrite import texture_with_targets, write_gcps, write_terrain

#: docs/references.md section 1, Table 4 (Hai'an 2018): the true parameters of preset ``paper``
TABLE4 = {
    "u_gps": (-0.078, 0.236, 0.911),
    "u_sen": (-0.066, -0.109, -2.010),
    "opk_sen": (0.028, -0.472, -0.044),
    "opk_pos_L": (2.726, 0.002, -0.110),
    "opk_pos_R": (2.676, -0.005, -0.068),
}
#: the nominal design values written as the mission's [calibration] priors
PRIORS = {
    "u_gps": ([0.0, 0.0, 0.0], [1.0, 1.0, 1.0]),
    "u_sen": ([0.0, 0.0, -2.0], [1.0, 1.0, 1.0]),
    "opk_sen": ([0.0, 0.0, 0.0], [1.0, 1.0, 1.0]),
    "opk_pos_L": ([0.0, 0.0, 0.0], [5.0, 5.0, 5.0]),
    "opk_pos_R": ([0.0, 0.0, 0.0], [5.0, 5.0, 5.0]),
}


@dataclass
class SimConfig(Rendering):
    """Everything that defines a simulated mission (a preset plus overrides)."""

    preset: str = "tiny"
    # place and flight
    lat0: float = 32.53
    lon0: float = 120.45
    heading: float = 8.0            # azimuth of the first flight line (deg, grid)
    n_strips: int = 1
    swings_per_strip: int = 2       # alternating L, R, L, ...
    agl: float = 500.0              # flying height above the mean terrain (m)
    speed: float = 50.0             # ground speed (m/s)
    along_overlap: float = 0.10     # between consecutive swings (at nadir)
    side_overlap: float = 0.15      # between adjacent strips
    swing_gap: float = 0.05         # gimbal turn-around between swings (s)
    strip_gap: float = 60.0         # time between strips (turn), s
    # sensor
    n_elements: int = 64
    pixel_pitch: float = 15e-6
    focal_length: float = 0.02
    swing_max: float = 10.0         # swing from -S to +S (deg)
    stabilise: bool = True          # gimbal compensates roll and pitch
    # output grid
    gsd: float = 0.4
    # terrain
    terrain_base: float = 25.0      # mean ellipsoidal height (m)
    terrain_relief: float = 20.0    # peak-to-peak (m)
    terrain_wavelength: float = 600.0
    dem_cell: float = 2.0
    # aircraft motion (amplitudes)
    roll_amp: float = 1.2           # deg
    pitch_amp: float = 0.5          # deg
    pitch_mean: float = 1.5         # deg nose up
    heading_amp: float = 0.4        # deg
    crab_max: float = 2.0           # deg
    alt_amp: float = 3.0            # m
    sway_amp: float = 2.0           # m
    # POS
    pos_rate: float = 200.0
    gps_noise: float = 0.02         # m, per axis
    att_noise: float = 0.005        # deg
    # truth parameters
    perturb: float = 0.02           # random change of Table 4 values (m / deg), 0 for paper
    direction_effect: bool = True   # False: opk_pos_L == opk_pos_R (their mean)
    direction_omega: float | None = None  # omega_L - omega_R (deg); None: Table 4's
    # GCPs
    gcp_control: int = 9            # per image
    gcp_check: int = 3
    gcp_plan: dict = field(default_factory=dict)  # image_id -> (control, check)
    gcp_other: tuple = ()           # (lo, hi): check points on images not in gcp_plan
    exclusive_gcps: bool = False    # points seen by one image only (exact counts)
    #: > 0: the first 3 control points of a swing lie where its recorded swing angle is
    #: above this (deg), the next 3 where it is below minus this (calibration needs both)
    gcp_swing_side: float = 0.0
    gcp_noise: float = 1.0          # px, per axis
    gross_fraction: float = 0.0
    gross_range: tuple = (10.0, 40.0)   # px
    ground_noise: float = 0.0       # m
    # rendering
    supersample: int = 3
    ortho_supersample: int = 3
    target_radius_px: float = 2.0   # GCP targets: disk radius in nadir pixels

    @property
    def ifov(self) -> float:
        return self.pixel_pitch / self.focal_length


PRESETS: dict[str, dict] = {
    # seconds: 1 strip, one L and one R swing, small images, a handful of GCPs
    "tiny": dict(preset="tiny", swing_max=15.0, gcp_swing_side=6.0),
    # the README demo: 2 strips x 4 swings
    "demo": dict(preset="demo", n_strips=2, swings_per_strip=4, n_elements=192,
                 focal_length=0.03, swing_max=15.0, agl=600.0, speed=45.0, gsd=0.3,
                 dem_cell=4.0, terrain_relief=30.0, terrain_wavelength=900.0,
                 gcp_control=10, gcp_check=4),
    # the paper's geometry: 15 um, 0.16 m (0.094 mrad), +-50 deg, 3 L/R pairs
    "paper": dict(preset="paper", n_strips=1, swings_per_strip=6, n_elements=1024,
                  focal_length=0.16, swing_max=50.0, agl=2000.0, speed=60.0, gsd=0.5,
                  swing_gap=0.2, dem_cell=20.0, terrain_relief=15.0,
                  terrain_wavelength=3000.0, perturb=0.0, render=False,
                  gcp_plan={"L1": (65, 10), "R1": (65, 10)}, gcp_other=(16, 22),
                  exclusive_gcps=True, block_lines=64, write_ortho=False),
    # many strips for mosaicking benchmarks
    "area": dict(preset="area", n_strips=6, swings_per_strip=10, n_elements=128,
                 focal_length=0.015, swing_max=20.0, agl=500.0, speed=45.0, gsd=0.5,
                 dem_cell=5.0, terrain_relief=40.0, terrain_wavelength=1200.0,
                 gcp_control=6, gcp_check=2),
    # docs/references.md section 3's survey (You & Li): 24 strips of ~6 km, 650 m above ground,
    # 30 deg field of view (+-15 deg swing), 2 m pixels (2 m / 650 m IFOV), ~20 % side
    # overlap (348 m swath), ~40 km2; 10 swings of 320 elements per strip
    "survey": dict(preset="survey", n_strips=24, swings_per_strip=10, n_elements=320,
                   focal_length=0.004875, swing_max=15.0, agl=650.0, speed=55.0, gsd=2.0,
                   side_overlap=0.2, strip_gap=20.0, pos_rate=50.0, dem_cell=10.0,
                   terrain_relief=30.0, terrain_wavelength=2500.0, supersample=2,
                   ortho_supersample=1, gcp_control=3, gcp_check=1, block_lines=512),
}


def preset_config(name: str, **overrides) -> SimConfig:
    if name not in PRESETS:
        raise SwathflowError(f"unknown preset {name!r}; choose one of {', '.join(PRESETS)}")
    cfg = SimConfig(**PRESETS[name])
    unknown = set(overrides) - set(SimConfig.__dataclass_fields__)
    if unknown:
        raise SwathflowError(f"unknown simulation option(s) {', '.join(sorted(unknown))}")
    cfg = replace(cfg, **overrides)
    if not 0.0 <= cfg.gross_fraction <= 1.0:
        raise SwathflowError(f"--gross-errors {cfg.gross_fraction}: a fraction of the GCP "
                             f"measurements, between 0 and 1 (e.g. 0.05)")
    if not (math.isfinite(cfg.gcp_noise) and cfg.gcp_noise >= 0):
        raise SwathflowError(f"--gcp-noise {cfg.gcp_noise}: a noise in pixels, 0 or more")
    return cfg


# ------------------------------------------------------------------------------------------
# flight plan, trajectory, line tables

def make_plan(cfg: SimConfig) -> Plan:
    crs = utm_crs_for(cfg.lat0, cfg.lon0).to_string()
    e0, n0 = transformer("EPSG:4326", crs).transform(cfg.lon0, cfg.lat0)
    n_lines = int(round(math.radians(2 * cfg.swing_max) / cfg.ifov)) + 1
    footprint = cfg.n_elements * cfg.ifov * cfg.agl          # along track, at nadir
    swing_period = (1 - cfg.along_overlap) * footprint / cfg.speed
    line_period = (swing_period - cfg.swing_gap) / n_lines
    if line_period <= 0:
        raise SwathflowError("swing_gap leaves no time for the swing; lower it")
    swath = 2 * cfg.agl * math.tan(math.radians(cfg.swing_max))
    spacing = (1 - cfg.side_overlap) * swath
    dur = cfg.swings_per_strip * swing_period
    return Plan(crs, (float(e0), float(n0)), swath, spacing, n_lines, line_period,
                swing_period, dur, dur * cfg.speed)


def make_lines(cfg: SimConfig, plan: Plan, strips, traj: Trajectory, params: dict):
    """Line tables of every swing: (image_id, direction, strip, dict).

    The gimbal centres each swing on the true nadir (the swing range is offset by the
    boresight's omega), and, with ``stabilise``, takes out the aircraft's roll and pitch."""
    out = []
    counter = {"L": 0, "R": 0}
    n = plan.lines_per_swing
    s_cmd = np.linspace(-cfg.swing_max, cfg.swing_max, n)
    for st in strips:
        for j in range(cfg.swings_per_strip):
            d = "L" if j % 2 == 0 else "R"
            counter[d] += 1
            iid = f"{d}{counter[d]}"
            t = st["t_start"] + j * plan.swing_period + np.arange(n) * plan.line_period
            s = (s_cmd if d == "L" else s_cmd[::-1]) - params[f"opk_pos_{d}"][0]
            t_mid = 0.5 * (t[0] + t[-1])
            q = np.degrees(np.arctan(cfg.speed * (t_mid - t) * np.cos(np.radians(s))
                                     / cfg.agl))
            if cfg.stabilise:
                att = traj.interpolate(t)
                s = s - att["roll"]
                q = q - att["pitch"]
            out.append((iid, d, st["strip"], {"time": t, "swing": s, "pitch_comp": q}))
    return out


def true_parameters(cfg: SimConfig, rng) -> dict:
    p = {k: np.array(v, float) for k, v in TABLE4.items()}
    if cfg.perturb:
        for k in p:
            p[k] = p[k] + rng.normal(0, cfg.perturb, 3)
    if not cfg.direction_effect:
        m = 0.5 * (p["opk_pos_L"] + p["opk_pos_R"])
        p["opk_pos_L"], p["opk_pos_R"] = m.copy(), m.copy()
    elif cfg.direction_omega is not None:
        m = 0.5 * (p["opk_pos_L"] + p["opk_pos_R"])
        p["opk_pos_L"], p["opk_pos_R"] = m.copy(), m.copy()
        p["opk_pos_L"][0] += cfg.direction_omega / 2
        p["opk_pos_R"][0] -= cfg.direction_omega / 2
    return {k: [float(x) for x in np.round(v, 6)] for k, v in p.items()}


# ------------------------------------------------------------------------------------------
# rendering

# ------------------------------------------------------------------------------------------
# GCPs

def _candidates(m, rng, k: int, band, margin: float, terrain, to_map) -> np.ndarray:
    """``k`` random ground points (E, N) seen by model ``m`` away from its edges, on the
    lines of ``band`` when given."""
    lo_l = max(0.06 * (m.n_lines - 1), margin + 1)
    lo_e = max(0.12 * (m.n_elements - 1), margin + 1)
    li = rng.uniform(*(band or (lo_l, m.n_lines - 1 - lo_l)), k)
    el = rng.uniform(lo_e, m.n_elements - 1 - lo_e, k)
    o, d = m.ray(np.stack([li, el], -1))
    g = intersect(o, d, terrain)
    e, n, _ = to_map.transform(g[:, 0], g[:, 1], g[:, 2])
    cand = np.round(np.stack([e, n], -1), 3)
    return cand[np.isfinite(cand).all(-1)]


def _seen_elsewhere(c, iid, ids, models, terrain, to_map) -> bool:
    xyz = _ground_xyz(c[None], terrain, to_map)
    return any(np.isfinite(models[o].ground_to_image(xyz)).all() for o in ids if o != iid)


def _side_bands(cfg, m, nc: int, margin: float) -> list:
    """Line ranges for the first control points: 3 where the swing angle is above
    ``cfg.gcp_swing_side``, 3 where it is below minus it (empty when not asked for)."""
    sw = m.lines.get("swing")
    if cfg.gcp_swing_side <= 0 or sw is None or nc < 6:
        return []
    idx = np.arange(sw.size)
    ok = (idx > margin + 1) & (idx < sw.size - 2 - margin)
    bands = []
    for sel in (ok & (sw > cfg.gcp_swing_side), ok & (sw < -cfg.gcp_swing_side)):
        if sel.sum() < 2:
            return []
        bands += [(float(idx[sel].min()), float(idx[sel].max()))] * 3
    return bands


def _gcp_counts(cfg, iid: str, rng) -> tuple[int, int]:
    """(control, check) points to place on image ``iid``."""
    if iid in cfg.gcp_plan:
        return tuple(cfg.gcp_plan[iid])
    if cfg.gcp_other:
        return (0, int(rng.integers(cfg.gcp_other[0], cfg.gcp_other[1] + 1)))
    return (cfg.gcp_control, cfg.gcp_check)


def choose_gcps(cfg, models, terrain, to_map, rng):
    """Ground points and their true image coordinates in every image that sees them."""
    ids = list(models)
    plan = {iid: _gcp_counts(cfg, iid, rng) for iid in ids}
    nadir_gsd = cfg.ifov * cfg.agl
    min_sep = 6 * cfg.target_radius_px * nadir_gsd
    # a target cut by the image edge cannot be measured: keep a margin (disk + ring + noise)
    margin = 2 * cfg.target_radius_px + 3 * cfg.gcp_noise + 1
    points = []   # (gcp_id, E, N, role, home image)
    taken = np.empty((0, 2))
    for iid in ids:
        nc, nk = plan[iid]
        need = nc + nk
        if need == 0:
            continue
        m = models[iid]
        got = []
        side = _side_bands(cfg, m, nc, margin)
        for _ in range(20):
            band = side[len(got)] if len(got) < len(side) else None
            cand = _candidates(m, rng, 4 * need, band, margin, terrain, to_map)
            for c in cand:
                if len(got) < len(side) and side[len(got)] != band:
                    break                  # side-banded slots: one band per draw
                allp = np.concatenate([taken, np.array(got).reshape(-1, 2)])
                if len(allp) and np.min(np.hypot(*(allp - c).T)) < min_sep:
                    continue
                if cfg.exclusive_gcps and _seen_elsewhere(c, iid, ids, models, terrain,
                                                          to_map):
                    continue
                got.append(c)
                if len(got) == need:
                    break
            if len(got) == need:
                break
        if len(got) < need:
            raise SwathflowError(f"could not place {need} GCPs on image {iid}")
        for r, c in enumerate(got):
            points.append((f"G{len(points) + 1:04d}", c[0], c[1],
                           "control" if r < nc else "check", iid))
        taken = np.concatenate([taken, np.array(got)])
    pts = pd.DataFrame(points, columns=["gcp_id", "E", "N", "role", "home"])
    xyz = _ground_xyz(pts[["E", "N"]].to_numpy(), terrain, to_map)
    llh = ecef_to_geodetic(xyz)
    pts["lat"], pts["lon"], pts["h"] = llh[:, 0], llh[:, 1], llh[:, 2]
    rows = []
    for iid in ids:
        ij = models[iid].ground_to_image(xyz)
        with np.errstate(invalid="ignore"):
            ok = (np.isfinite(ij).all(-1) & (ij[:, 0] >= margin)
                  & (ij[:, 0] <= models[iid].n_lines - 1 - margin)
                  & (ij[:, 1] >= margin) & (ij[:, 1] <= models[iid].n_elements - 1 - margin))
        for k in np.flatnonzero(ok):
            rows.append((pts.gcp_id[k], iid, ij[k, 0], ij[k, 1], pts.lon[k], pts.lat[k],
                         pts.h[k], pts.role[k], pts.E[k], pts.N[k]))
    obs = pd.DataFrame(rows, columns=["gcp_id", "image_id", "line", "element", "x", "y", "z",
                                      "role", "E", "N"])
    return pts, obs


def _ground_xyz(en, terrain, to_map):
    en = np.asarray(en, float).reshape(-1, 2)
    to_ll = transformer(to_map.target_crs, "EPSG:4326")
    lon, lat = to_ll.transform(en[:, 0], en[:, 1])
    h = terrain.height(lat, lon)
    return geodetic_to_ecef(np.stack([lat, lon, h], -1))


# ------------------------------------------------------------------------------------------
# the simulation

def simulate(out, preset: str = "tiny", seed: int = 0, texture: str | None = None,
             dem: str | None = None, progress=None, **overrides) -> dict:
    """Write a simulated mission to ``out``; returns the truth summary (truth.json)."""
    from swathflow.sensormodel import get_sensor
    from swathflow.formats.calibfile import write_calibration
    say = progress or (lambda msg: None)
    clock = time.perf_counter()
    timings = {}
    cfg = preset_config(preset, **overrides)
    out = Path(out)
    (out / "images").mkdir(parents=True, exist_ok=True)
    (out / "truth").mkdir(parents=True, exist_ok=True)
    if (out / "mission.toml").exists():
        os.remove(out / "mission.toml")   # an interrupted rewrite leaves no valid mission
    rng = np.random.default_rng([int(seed), 1])
    plan = make_plan(cfg)
    to_map = transformer("EPSG:4978", plan.crs)

    # terrain -> dem.tif (the very DEM the mission uses is the truth terrain)
    terrain, terrain_mean, dem_info = write_terrain(out, cfg, plan, seed, dem)
    timings["terrain"] = time.perf_counter() - clock

    # trajectory, line tables, models
    truth_ds, strips = make_trajectory(cfg, plan, terrain_mean, rng)
    true_traj = Trajectory.from_dataset(truth_ds)
    params = true_parameters(cfg, rng)
    swings = make_lines(cfg, plan, strips, true_traj, params)
    sensor = {"model": "pendulum", "pixel_pitch": cfg.pixel_pitch,
              "focal_length": cfg.focal_length, "n_elements": cfg.n_elements,
              "k0": (cfg.n_elements - 1) / 2, "y0": 0.0}
    cls = get_sensor("pendulum")
    pset = cls.default_parameters(sensor).updated(params)
    models = {iid: cls.build(sensor, lt, true_traj, pset, image_id=iid, direction=d, strip=s)
              for iid, d, s, lt in swings}
    timings["geometry"] = time.perf_counter() - clock - sum(timings.values())

    # GCPs and the texture (with survey targets at the GCPs)
    pts, obs = choose_gcps(cfg, models, terrain, to_map, rng)
    nadir_gsd = cfg.ifov * cfg.agl
    tex, tex_info = texture_with_targets(cfg, plan, seed, texture, rng, pts, nadir_gsd)
    radius = cfg.target_radius_px * nadir_gsd
    timings["gcps"] = time.perf_counter() - clock - sum(timings.values())

    # images
    say(f"rendering {len(models)} images of {plan.lines_per_swing} x {cfg.n_elements}"
        + ("" if cfg.render else " (geometry only: blank images)"))
    image_entries = []
    for k, (iid, d, s, lt) in enumerate(swings):
        paths = write_swing(out, iid, models[iid], terrain, tex, to_map, cfg,
                            np.random.default_rng([int(seed), 2, k]),
                            {"time": lt["time"], "swing": lt["swing"],
                             "pitch_comp": lt["pitch_comp"]})
        image_entries.append((iid, *paths, d, s))
    timings["images"] = time.perf_counter() - clock - sum(timings.values())

    # footprint -> output grid, truth ortho
    ortho = write_truth_ortho(out, cfg, plan.crs, models, terrain, tex, to_map, say)
    timings["ortho"] = time.perf_counter() - clock - sum(timings.values())

    meas, gross = write_gcps(out, cfg, plan, models, pts, obs, seed)
    pos_name = write_noisy_pos(out, truth_ds, cfg, np.random.default_rng([int(seed), 4]))

    # truth calibration and truth.json
    write_calibration(out / "truth" / "calibration.json", "pendulum",
                      {k: {"value": v, "sigma": [0.0] * 3, "units": pset.block(k).units}
                       for k, v in params.items()},
                      note=f"simulation truth: preset {cfg.preset}, seed {seed}")
    counts = {}
    for iid in models:
        sel = meas[meas.image_id == iid]
        counts[iid] = {"control": int((sel.role == "control").sum()),
                       "check": int((sel.role == "check").sum())}
    timings["total"] = time.perf_counter() - clock
    truth = {
        "format": "swathflow-simulation-truth/1",
        "preset": cfg.preset, "seed": int(seed),
        "config": plain(asdict(cfg)),
        "crs": plan.crs, "gsd": cfg.gsd, "centre_en": list(plan.centre),
        "plan": plain(asdict(plan)),
        "strips": strips,
        "images": [{"id": iid, "direction": d, "strip": s, "lines": models[iid].n_lines,
                    "elements": cfg.n_elements, "t0": float(lt["time"][0]),
                    "t1": float(lt["time"][-1])} for iid, d, s, lt in swings],
        "images_rendered": bool(cfg.render),
        "parameters": params,
        "direction_effect": {"enabled": bool(cfg.direction_effect),
                             "opk_pos_L_minus_R": list(np.round(
                                 np.subtract(params["opk_pos_L"], params["opk_pos_R"]), 6))},
        "noise": {"gps_m": cfg.gps_noise, "attitude_deg": cfg.att_noise,
                  "gcp_px": cfg.gcp_noise, "gcp_ground_m": cfg.ground_noise,
                  "read_noise_dn": cfg.read_noise, "shot_noise": cfg.shot_noise},
        "gross_errors": gross,
        "gcp_counts": counts,
        "gcp_target_radius_m": radius,
        "radiometry": {"gain": cfg.gain, "offset": cfg.offset,
                       "dn": "offset + gain * T(E, N) averaged over the pixel, + noise"},
        "ortho": ({"file": "truth/ortho.tif", "transform": list(ortho["transform"]),
                   "shape": list(ortho["shape"]), "supersample": cfg.ortho_supersample}
                  if ortho["written"] else None),
        "footprint_bounds": ortho["bounds"],
        "texture": tex_info, "terrain": {**dem_info, "mean_h": terrain_mean,
                                         "dem_cell": cfg.dem_cell},
        "nadir_gsd_m": nadir_gsd,
        "timings_s": {k: round(v, 3) for k, v in timings.items()},
    }
    write_text(out / "truth" / "truth.json", json.dumps(truth, indent=2) + "\n")
    _write_toml(out, cfg, plan, cfg.gsd, pos_name, image_entries, sensor)
    return truth


def _write_toml(out, cfg, plan, gsd, pos_name, image_entries, sensor):
    write_mission_toml(out, cfg.preset, plan.crs, gsd, pos_name,
                        [f"{k} = {toml_value(v)}" for k, v in sensor.items()], PRIORS,
                        image_entries, "direction")
