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

from swathflow.errors import SwathflowError
from swathflow.geometry.geodesy import ecef_to_geodetic, geodetic_to_ecef, transformer, utm_crs_for
from swathflow.io import write_text
from swathflow.formats.pos import Trajectory, write_pos_csv, write_sbet
from swathflow.simulation.bundle import (Plan, make_trajectory, plain, square_grid, toml_value,
                                        write_csv, write_mission_toml, write_swing)

VIEWS = {"forward": 25.0, "nadir": 0.0, "backward": -25.0}
VIEW_LETTER = {"forward": "F", "nadir": "N", "backward": "B"}


@dataclass
class PushbroomConfig:
    """Everything that defines a simulated push-broom mission (a preset plus overrides)."""

    preset: str = "pushbroom"
    # place and flight
    lat0: float = 32.53
    lon0: float = 120.45
    heading: float = 8.0            # azimuth of the first strip (deg)
    n_strips: int = 1
    agl: float = 300.0              # m above the mean terrain
    speed: float = 50.0             # m/s
    common_length: float = 120.0    # along-track ground length seen by all three lines (m)
    side_overlap: float = 0.3
    strip_gap: float = 40.0         # s between strips (turn)
    # camera
    n_elements: int = 96
    n_segments: int = 3
    pixel_pitch: float = 10e-6
    focal_length: float = 0.006
    views: dict = field(default_factory=lambda: dict(VIEWS))
    along_gsd_factor: float = 1.0   # along-track sample distance / cross-track GSD (nadir)
    fix_interval: float = 2.0       # s between orientation fixes (per strip, ends included)
    # output grid
    gsd: float = 0.5
    # terrain
    terrain_base: float = 25.0
    terrain_relief: float = 15.0
    terrain_wavelength: float = 500.0
    dem_cell: float = 2.0
    # aircraft motion (as swathflow.sensors.pendulum.simulate)
    roll_amp: float = 1.0
    pitch_amp: float = 0.4
    pitch_mean: float = 1.5
    heading_amp: float = 0.3
    crab_max: float = 2.0
    alt_amp: float = 2.0
    sway_amp: float = 2.0
    # POS: white noise on top of the (fix-corrected) POS
    pos_rate: float = 200.0
    gps_noise: float = 0.01         # m
    att_noise: float = 0.001        # deg
    pos_format: str = "sbet"
    # truth and priors
    u_gps: tuple = (0.12, -0.21, -1.08)          # m (truth)
    u_gps_prior: tuple = (0.0, 0.0, -1.0)
    u_gps_sigma: float = 0.3
    opk_cam: tuple = (0.21, -0.34, 0.15)         # deg (truth)
    opk_cam_sigma: float = 1.0
    ap_px: float = 2.0              # typical size of the true APs (pixels)
    ap_sigma_px: float = 10.0       # prior sigma of the APs (pixels at the segment's end)
    d_ned_true: float = 0.05        # m, sd of the true fix corrections
    d_ned_sigma: float = 0.1        # prior sigma
    d_opk_true: float = 0.003       # deg
    d_opk_sigma: float = 0.005
    # ground points
    n_control: int = 12
    n_check: int = 6
    n_ties: int = 30
    gcp_noise: float = 0.3          # px
    tie_noise: float = 0.3          # px
    edge_margin: float = 3.0        # px from the image edges
    target_radius_px: float = 1.5
    # rendering (as swathflow.sensors.pendulum.simulate.render_image)
    render: bool = True
    supersample: int = 2
    node_step: int = 8
    block_lines: int = 256
    gain: float = 12000.0
    offset: float = 1000.0
    read_noise: float = 15.0
    shot_noise: float = 1.0
    image_format: str = "tif"
    write_ortho: bool = True
    ortho_supersample: int = 2

    @property
    def ifov(self) -> float:
        return self.pixel_pitch / self.focal_length

    @property
    def segments(self) -> list[int]:
        n, k = self.n_elements, self.n_segments
        return [int(round(i * n / k)) for i in range(k)]


PRESETS: dict[str, dict] = {
    # small rendered mission (seconds): validate / rectify / mosaic / run
    "pushbroom": dict(preset="pushbroom"),
    # two strips with side overlap, for mosaicking
    "pushbroom-demo": dict(preset="pushbroom-demo", n_strips=2, common_length=200.0,
                           n_elements=192, focal_length=0.006, agl=300.0, gsd=0.5,
                           n_control=10, n_check=4, n_ties=40),
    # a three-line camera (3 segments of 256 elements, 0.5 mrad) for calibration tests:
    # two opposite strips, 20 orientation fixes, geometry only
    "pushbroom-calib": dict(preset="pushbroom-calib", n_strips=2, n_elements=768,
                            pixel_pitch=10e-6, focal_length=0.02, agl=1000.0, speed=60.0,
                            common_length=500.0, fix_interval=3.0, gsd=0.5, dem_cell=10.0,
                            terrain_relief=40.0, terrain_wavelength=1500.0,
                            side_overlap=0.3, n_control=40, n_check=20, n_ties=120,
                            render=False, write_ortho=False),
    # benchmark: 20 orientation fixes, 500 tie points, 100 control points
    "pushbroom-bench": dict(preset="pushbroom-bench", n_strips=2, n_elements=768,
                            pixel_pitch=10e-6, focal_length=0.02, agl=1000.0, speed=60.0,
                            common_length=800.0, fix_interval=3.4, gsd=0.5, dem_cell=10.0,
                            terrain_relief=40.0, terrain_wavelength=1500.0,
                            side_overlap=0.3, n_control=100, n_check=30, n_ties=500,
                            render=False, write_ortho=False),
}


def preset_config(name: str, **overrides) -> PushbroomConfig:
    if name not in PRESETS:
        raise SwathflowError(f"unknown push-broom preset {name!r}; choose one of "
                             f"{', '.join(PRESETS)}")
    cfg = PushbroomConfig(**PRESETS[name])
    unknown = set(overrides) - set(PushbroomConfig.__dataclass_fields__)
    if unknown:
        raise SwathflowError(f"unknown simulation option(s) {', '.join(sorted(unknown))}")
    return replace(cfg, **overrides)


# ------------------------------------------------------------------------------------------
# plan, sensor, truth

def make_plan(cfg: PushbroomConfig) -> Plan:
    crs = utm_crs_for(cfg.lat0, cfg.lon0).to_string()
    e0, n0 = transformer("EPSG:4326", crs).transform(cfg.lon0, cfg.lat0)
    reach = cfg.agl * max(math.tan(math.radians(abs(v))) for v in cfg.views.values())
    length = cfg.common_length + 2 * reach + 2 * cfg.agl * math.tan(math.radians(
        cfg.pitch_amp * 2 + abs(cfg.pitch_mean))) + 20.0
    duration = length / cfg.speed
    line_period = cfg.along_gsd_factor * cfg.ifov * cfg.agl / cfg.speed
    n_lines = int(length / (cfg.speed * line_period)) + 1
    swath = cfg.n_elements * cfg.ifov * cfg.agl
    spacing = (1 - cfg.side_overlap) * swath
    return Plan(crs, (float(e0), float(n0)), swath, spacing, n_lines, line_period,
                duration, duration, length)


def sensor_table(cfg: PushbroomConfig, fix_times) -> dict:
    """The mission's ``[sensor]`` table (nominal design, views, fix times)."""
    return {"model": "pushbroom", "n_elements": cfg.n_elements, "segments": cfg.segments,
            "pixel_pitch": cfg.pixel_pitch, "focal_length": cfg.focal_length,
            "s_c": (cfg.n_elements - 1) / 2, "views": dict(cfg.views),
            "fixes": {"time": [float(t) for t in fix_times]}}


def smooth_aps(rng, cfg: PushbroomConfig) -> np.ndarray:
    """Per-segment cubic coefficients ``(n_segments, 4)`` of one smooth cubic over the whole
    line (so C0 and C1 hold at every boundary exactly), of about ``ap_px`` pixels."""
    P = np.polynomial.Polynomial
    half = cfg.n_elements / 2
    c = rng.normal(0, 1, 4) * cfg.ap_px * cfg.ifov * np.array([1.0, 0.7, 0.6, 0.4])
    pu = P(c)                                                  # in u = (s - s_c) / half
    ps = pu(P([-((cfg.n_elements - 1) / 2) / half, 1 / half]))  # in s
    out = np.zeros((cfg.n_segments, 4))
    for i, s0 in enumerate(cfg.segments):
        q = ps(P([s0, 1.0])).coef                              # in ds = s - s0
        out[i, :q.size] = q[:4]
    return out


def ap_prior_sigma(cfg: PushbroomConfig) -> list[float]:
    """Prior sigma of AP coefficient k: ``ap_sigma_px`` pixels at the segment's end."""
    seg = cfg.n_elements / cfg.n_segments
    return [cfg.ap_sigma_px * cfg.ifov / seg ** k for k in range(4)]


def true_parameters(cfg: PushbroomConfig, n_fix: int, rng) -> dict:
    p = {"u_gps": list(cfg.u_gps), "opk_cam": list(cfg.opk_cam)}
    for view in cfg.views:
        for kind in ("ax", "bx"):
            co = smooth_aps(rng, cfg)
            for i in range(cfg.n_segments):
                p[f"{kind}_{view}_{i}"] = [float(v) for v in co[i]]
    for k in range(n_fix):
        p[f"d_ned_{k}"] = [float(v) for v in np.round(rng.normal(0, cfg.d_ned_true, 3), 5)]
        p[f"d_opk_{k}"] = [float(v) for v in np.round(rng.normal(0, cfg.d_opk_true, 3), 6)]
    return p


def prior_table(cfg: PushbroomConfig, n_fix: int) -> dict:
    """The mission's ``[calibration]`` priors: name -> (value, sigma)."""
    out = {"u_gps": (list(cfg.u_gps_prior), [cfg.u_gps_sigma] * 3),
           "opk_cam": ([0.0] * 3, [cfg.opk_cam_sigma] * 3)}
    aps = ap_prior_sigma(cfg)
    for view in cfg.views:
        for kind in ("ax", "bx"):
            for i in range(cfg.n_segments):
                out[f"{kind}_{view}_{i}"] = ([0.0] * 4, aps)
    for k in range(n_fix):
        out[f"d_ned_{k}"] = ([0.0] * 3, [cfg.d_ned_sigma] * 3)
        out[f"d_opk_{k}"] = ([0.0] * 3, [cfg.d_opk_sigma] * 3)
    return out


def _dem_grid(plan: Plan, cfg: PushbroomConfig):
    half_w = (cfg.n_strips - 1) / 2 * plan.spacing + plan.swath + 0.2 * cfg.agl + 50
    half_l = plan.strip_length / 2 + 0.6 * cfg.agl + 50
    return square_grid(plan.centre, math.hypot(half_w, half_l), cfg.dem_cell)


# ------------------------------------------------------------------------------------------
# ground points

def _ground_xyz(en, terrain, crs) -> np.ndarray:
    en = np.asarray(en, float).reshape(-1, 2)
    lon, lat = transformer(crs, "EPSG:4326").transform(en[:, 0], en[:, 1])
    h = terrain.height(np.asarray(lat), np.asarray(lon))
    return geodetic_to_ecef(np.stack([lat, lon, h], -1))


def sample_points(cfg, plan, strips, models, terrain, n, rng, min_views=3,
                  min_sep=0.0, avoid=None, max_tries=30):
    """``n`` ground points (ECEF) under the common coverage of the strips, each seen by at
    least ``min_views`` images well inside their edges; returns (xyz, en, image points
    per image id: (point index, line, element))."""
    az = math.radians(cfg.heading)
    fwd = np.array([math.sin(az), math.cos(az)])
    right = np.array([fwd[1], -fwd[0]])
    got_en, got_xyz = [], []
    taken = np.empty((0, 2)) if avoid is None else np.asarray(avoid, float).reshape(-1, 2)
    for _ in range(max_tries):
        k = max(4 * (n - len(got_en)), 16)
        st = rng.integers(0, len(strips), k)
        off = np.array([s["offset_m"] for s in strips])[st]
        along = rng.uniform(-0.5, 0.5, k) * (cfg.common_length + 60.0)
        across = rng.uniform(-0.5, 0.5, k) * plan.swath * 0.95
        en = (np.asarray(plan.centre)[None] + along[:, None] * fwd[None]
              + (off + across)[:, None] * right[None])
        xyz = _ground_xyz(en, terrain, plan.crs)
        seen = np.zeros(k, int)
        for m in models.values():
            ij = m.ground_to_image(xyz)
            seen += _inside(ij, m, cfg.edge_margin)
        for i in np.flatnonzero(seen >= min_views):
            if min_sep > 0:
                allp = np.concatenate([taken, np.array(got_en).reshape(-1, 2)])
                if len(allp) and np.min(np.hypot(*(allp - en[i]).T)) < min_sep:
                    continue
            got_en.append(en[i])
            got_xyz.append(xyz[i])
            if len(got_en) == n:
                break
        if len(got_en) == n:
            break
    if len(got_en) < n:
        raise SwathflowError(f"could place only {len(got_en)} of {n} ground points seen by "
                             f"{min_views} images; lengthen the strip (common_length)")
    xyz = np.array(got_xyz)
    obs = {}
    for iid, m in models.items():
        ij = m.ground_to_image(xyz)
        ok = _inside(ij, m, cfg.edge_margin)
        obs[iid] = (np.flatnonzero(ok), ij[ok, 0], ij[ok, 1])
    return xyz, np.array(got_en), obs


def _inside(ij, m, margin) -> np.ndarray:
    with np.errstate(invalid="ignore"):
        return (np.isfinite(ij).all(-1) & (ij[:, 0] >= margin)
                & (ij[:, 0] <= m.n_lines - 1 - margin) & (ij[:, 1] >= margin)
                & (ij[:, 1] <= m.n_elements - 1 - margin))


def _obs_frame(obs, ids, id_col) -> pd.DataFrame:
    rows = []
    for iid, (idx, li, el) in obs.items():
        rows.append(pd.DataFrame({id_col: np.asarray(ids)[idx], "image_id": iid,
                                  "line": li, "element": el, "_k": idx}))
    df = pd.concat(rows, ignore_index=True)
    return df.sort_values(["_k", "image_id"], kind="stable").reset_index(drop=True)


# ------------------------------------------------------------------------------------------
# the simulation

def simulate(out, preset: str = "pushbroom", seed: int = 0, progress=None,
                       **overrides) -> dict:
    """Write a simulated push-broom mission to ``out``; returns the truth summary."""
    from swathflow.sensors import get_sensor
    from swathflow.formats.calibfile import write_calibration
    from swathflow.formats.raster import write_geotiff
    from swathflow.geometry.terrain import DEM
    from swathflow.simulation.texture import ProceduralTerrain, ProceduralTexture, area_average
    say = progress or (lambda msg: None)
    clock = time.perf_counter()
    cfg = preset_config(preset, **overrides)
    out = Path(out)
    (out / "images").mkdir(parents=True, exist_ok=True)
    (out / "truth").mkdir(parents=True, exist_ok=True)
    if (out / "mission.toml").exists():
        os.remove(out / "mission.toml")
    rng = np.random.default_rng([int(seed), 81])
    plan = make_plan(cfg)
    to_map = transformer("EPSG:4978", plan.crs)

    # terrain -> dem.tif (the truth terrain)
    dem_tr, dem_shape = _dem_grid(plan, cfg)
    hfun = ProceduralTerrain(seed, cfg.terrain_base, cfg.terrain_relief,
                             cfg.terrain_wavelength, plan.centre)
    rr, cc = np.indices(dem_shape)
    a, _, c0, _, e, f0 = dem_tr
    hgrid = hfun(c0 + (cc + 0.5) * a, f0 + (rr + 0.5) * e).astype(np.float32)
    write_geotiff(out / "dem.tif", hgrid, plan.crs, dem_tr, nodata=-9999.0,
                  tags={"vertical": "ellipsoidal", "source": "procedural"})
    terrain = DEM.open(out / "dem.tif")
    terrain_mean = float(np.mean(hgrid))

    # trajectory (the POS the geometry is defined on), line tables, fixes
    pos_ds, strips = make_trajectory(cfg, plan, terrain_mean, rng)
    pos_traj = Trajectory.from_dataset(pos_ds)
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

    # ground points: control + check (targets), ties
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

    # images
    tex = ProceduralTexture(seed, nadir_gsd, plan.centre).with_targets(g_en, radius)
    say(f"rendering {len(models)} push-broom images of {plan.lines_per_swing} x "
        f"{cfg.n_elements}" + ("" if cfg.render else " (geometry only: blank images)"))
    entries = []
    for k, (iid, view, s, lt) in enumerate(images):
        paths = write_swing(out, iid, models[iid], terrain, tex, to_map, cfg,
                            np.random.default_rng([int(seed), 82, k]), {"time": lt["time"]})
        entries.append((iid, *paths, view, s))

    # footprint -> truth ortho
    from swathflow.geometry.intersect import intersect
    from swathflow.ingest.mission import image_border
    border = []
    for m in models.values():
        o, d = m.ray(image_border(m.shape, 40))
        g = intersect(o, d, terrain)
        ee, nn, _ = to_map.transform(g[:, 0], g[:, 1], g[:, 2])
        border.append(np.stack([ee, nn], -1))
    border = np.concatenate(border)
    gsd = cfg.gsd
    xmin = math.floor(np.nanmin(border[:, 0]) / gsd) * gsd
    xmax = math.ceil(np.nanmax(border[:, 0]) / gsd) * gsd
    ymin = math.floor(np.nanmin(border[:, 1]) / gsd) * gsd
    ymax = math.ceil(np.nanmax(border[:, 1]) / gsd) * gsd
    ortho_tr = (gsd, 0.0, xmin, 0.0, -gsd, ymax)
    ortho_shape = (int(round((ymax - ymin) / gsd)), int(round((xmax - xmin) / gsd)))
    if cfg.write_ortho:
        say(f"truth ortho {ortho_shape[1]} x {ortho_shape[0]} at {gsd} m")
        o = area_average(tex, ortho_tr, ortho_shape, cfg.ortho_supersample)
        write_geotiff(out / "truth" / "ortho.tif",
                      (cfg.offset + cfg.gain * o).astype(np.float32), plan.crs, ortho_tr,
                      tags={"units": "expected DN (offset + gain * T)", "gain": cfg.gain,
                            "offset": cfg.offset})

    # GCP and tie observations (with measurement noise)
    grng = np.random.default_rng([int(seed), 83])
    llh = ecef_to_geodetic(g_xyz)
    gobs = _obs_frame(g_obs, gcp_ids, "gcp_id")
    k = gobs.pop("_k").to_numpy()
    gobs["x"], gobs["y"], gobs["z"] = llh[k, 1], llh[k, 0], llh[k, 2]
    gobs["role"] = roles[k]
    truth_g = gobs.copy()
    truth_g["X"], truth_g["Y"], truth_g["Z"] = g_xyz[k, 0], g_xyz[k, 1], g_xyz[k, 2]
    gobs["line"] += grng.normal(0, cfg.gcp_noise, len(gobs))
    gobs["element"] += grng.normal(0, cfg.gcp_noise, len(gobs))
    fmt = {"line": "%.4f", "element": "%.4f", "x": "%.10f", "y": "%.10f", "z": "%.4f"}
    write_csv(out / "gcp.csv", gobs[["gcp_id", "image_id", "line", "element", "x", "y", "z",
                                      "role"]], fmt)
    write_csv(out / "truth" / "gcp.csv", truth_g, {**fmt, "line": "%.6f", "element": "%.6f",
                                                     "X": "%.4f", "Y": "%.4f", "Z": "%.4f"})
    tobs = _obs_frame(t_obs, tie_ids, "tie_id")
    k = tobs.pop("_k").to_numpy()
    truth_t = tobs.copy()
    tllh = ecef_to_geodetic(t_xyz)
    truth_t["lon"], truth_t["lat"], truth_t["h"] = tllh[k, 1], tllh[k, 0], tllh[k, 2]
    truth_t["X"], truth_t["Y"], truth_t["Z"] = t_xyz[k, 0], t_xyz[k, 1], t_xyz[k, 2]
    tobs["line"] += grng.normal(0, cfg.tie_noise, len(tobs))
    tobs["element"] += grng.normal(0, cfg.tie_noise, len(tobs))
    write_csv(out / "ties.csv", tobs, {"line": "%.4f", "element": "%.4f"})
    write_csv(out / "truth" / "ties.csv", truth_t,
               {"line": "%.6f", "element": "%.6f", "lon": "%.10f", "lat": "%.10f",
                "h": "%.4f", "X": "%.4f", "Y": "%.4f", "Z": "%.4f"})

    # POS: the geometry's POS plus white noise
    prng = np.random.default_rng([int(seed), 84])
    nt = pos_ds.sizes["time"]
    lat = pos_ds["lat"].values
    noisy = pos_ds.copy(deep=True)
    noisy["lat"] = ("time", lat + prng.normal(0, cfg.gps_noise, nt) / 111_132.0)
    noisy["lon"] = ("time", pos_ds["lon"].values + prng.normal(0, cfg.gps_noise, nt)
                    / (111_320.0 * np.cos(np.radians(lat))))
    noisy["h"] = ("time", pos_ds["h"].values + prng.normal(0, cfg.gps_noise, nt))
    for kk in ("roll", "pitch", "heading"):
        noisy[kk] = ("time", pos_ds[kk].values + prng.normal(0, cfg.att_noise, nt))
    noisy["heading"] = (noisy["heading"] + 180.0) % 360.0 - 180.0
    pos_name = "pos.sbet" if cfg.pos_format == "sbet" else "pos.csv"
    (write_sbet if cfg.pos_format == "sbet" else write_pos_csv)(noisy, out / pos_name)
    write_pos_csv(pos_ds, out / "truth" / "pos.csv")

    # truth calibration, truth.json, mission.toml
    write_calibration(out / "truth" / "calibration.json", "pushbroom",
                      {b.name: {"value": list(b.value), "sigma": [0.0] * b.size,
                                "units": b.units} for b in pset.blocks},
                      note=f"simulation truth: preset {cfg.preset}, seed {seed}")
    priors = prior_table(cfg, fix_t.size)
    truth = {
        "format": "swathflow-simulation-truth/1", "sensor": "pushbroom",
        "preset": cfg.preset, "seed": int(seed), "config": plain(asdict(cfg)),
        "crs": plan.crs, "gsd": gsd, "centre_en": list(plan.centre),
        "plan": plain(asdict(plan)), "strips": strips,
        "images": [{"id": iid, "view": v, "strip": s, "lines": models[iid].n_lines,
                    "elements": cfg.n_elements, "t0": float(lt["time"][0]),
                    "t1": float(lt["time"][-1])} for iid, v, s, lt in images],
        "images_rendered": bool(cfg.render),
        "parameters": params,
        "priors": {k2: {"value": v, "sigma": s} for k2, (v, s) in priors.items()},
        "fix_times": [float(t) for t in fix_t],
        "noise": {"gps_m": cfg.gps_noise, "attitude_deg": cfg.att_noise,
                  "gcp_px": cfg.gcp_noise, "tie_px": cfg.tie_noise,
                  "read_noise_dn": cfg.read_noise, "shot_noise": cfg.shot_noise},
        "gcp_counts": {iid: {r: int(((gobs.image_id == iid) & (gobs.role == r)).sum())
                             for r in ("control", "check")} for iid in models},
        "tie_observations": int(len(tobs)),
        "gcp_target_radius_m": radius,
        "radiometry": {"gain": cfg.gain, "offset": cfg.offset},
        "ortho": ({"file": "truth/ortho.tif", "transform": list(ortho_tr),
                   "shape": list(ortho_shape), "supersample": cfg.ortho_supersample}
                  if cfg.write_ortho else None),
        "footprint_bounds": [xmin, ymin, xmax, ymax],
        "texture": {"source": "procedural", "scale_m": nadir_gsd},
        "terrain": {"source": "procedural", "mean_h": terrain_mean, "dem_cell": cfg.dem_cell},
        "nadir_gsd_m": nadir_gsd,
        "seconds": round(time.perf_counter() - clock, 3),
    }
    write_text(out / "truth" / "truth.json", json.dumps(truth, indent=2) + "\n")
    _write_toml(out, cfg, plan, pos_name, entries, sensor, priors)
    return truth


def _write_toml(out, cfg, plan, pos_name, entries, sensor, priors):
    lines = [f"{k} = {toml_value(v)}" for k, v in sensor.items() if k not in ("views", "fixes")]
    lines += ["", "[sensor.views]"] + [f"{k} = {toml_value(float(v))}"
                                       for k, v in sensor["views"].items()]
    lines += ["", "[sensor.fixes]", f"time = {toml_value(sensor['fixes']['time'])}"]
    write_mission_toml(out, cfg.preset, plan.crs, cfg.gsd, pos_name, lines, priors, entries,
                        "view", ties=True)
