"""Simulated rotating-mirror missions with their truth (``swathflow simulate OUT --preset
rotating-mirror``): the plugin's simulator, found by swathflow through
``RotatingMirrorModel.simulator()``, which returns a :class:`Simulator` holding the model
class (this module does not import the model).

A rotating-mirror scanner flies parallel strips over swathflow's procedural terrain and
texture. One mirror turn per row (one facet): the row period is one along-track ground
sample, each pixel dwells ``row_period * ifov / 360``, and the encoder's scan-start angle of
every row (the per-line column ``scan_start``) is the nominal ``-center * ifov`` plus a bias
and a slow wander. The truth has a lever arm, a mounting boresight and a scan-angle encoder
offset.

Built on :mod:`swathflow.simulation.bundle` (the flight plan and true trajectory, rendering
through the sensor model, atomic writers of the mission bundle) and
:mod:`swathflow.simulation.texture`. Writes ``mission.toml``, the POS (the true one plus
white noise), ``dem.tif``, one raw image with its line table per strip, ``gcp.csv``
(survey targets in the texture) and ``truth/`` (calibration.json, pos.csv, gcp.csv,
ortho.tif, truth.json).
"""
from __future__ import annotations

import json
import math
import os
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import ClassVar

import numpy as np
import pandas as pd

from swathflow.errors import SwathflowError
from swathflow.formats.pos import Trajectory
from swathflow.geometry.geodesy import ecef_to_geodetic, transformer, utm_crs_for
from swathflow.io import write_text
from swathflow.simulation.bundle import (Plan, Rendering, make_trajectory, plain, square_grid, toml_value,
                                        write_csv, write_mission_toml, write_noisy_pos,
                                        write_swing, write_truth_ortho)


@dataclass
class MirrorConfig(Rendering):
    """Everything that defines a simulated rotating-mirror mission (a preset plus overrides;
    the field names :mod:`swathflow.simulation.bundle` reads are shared with the built-in
    simulators)."""

    preset: str = "rotating-mirror"
    # place and flight
    lat0: float = 44.05
    lon0: float = -123.07
    heading: float = 12.0           # azimuth of the first strip (deg)
    n_strips: int = 1
    agl: float = 300.0              # m above the mean terrain
    speed: float = 50.0             # m/s
    strip_length: float = 160.0     # m of ground along track
    side_overlap: float = 0.3
    strip_gap: float = 40.0         # s between strips (turn)
    # scanner: one detector, a one-facet mirror (one turn per row)
    n_elements: int = 160
    ifov_deg: float = 0.1
    along_gsd_factor: float = 1.0   # along-track sample distance / nadir pixel
    scan_start_bias_deg: float = 0.06      # encoder start angle minus nominal (truth)
    scan_start_wander_deg: float = 0.03    # amplitude of its slow wander
    scan_start_period_s: float = 2.5
    # output grid and terrain
    gsd: float = 0.5
    terrain_base: float = 120.0
    terrain_relief: float = 15.0
    terrain_wavelength: float = 400.0
    dem_cell: float = 2.0
    # aircraft motion (swathflow.simulation.bundle.make_trajectory)
    roll_amp: float = 1.0
    pitch_amp: float = 0.4
    pitch_mean: float = 1.5
    heading_amp: float = 0.3
    crab_max: float = 2.0
    alt_amp: float = 2.0
    sway_amp: float = 2.0
    # POS: white noise on top of the true trajectory
    pos_rate: float = 200.0
    # truth and priors
    u_gps: tuple = (0.25, -0.15, -0.9)       # m
    opk_mount: tuple = (0.3, -0.2, 0.25)     # deg
    scan_offset: float = 0.05                # deg
    u_gps_sigma: float = 1.0
    opk_mount_sigma: float = 1.0
    scan_offset_sigma: float = 0.2
    # control points (survey targets in the texture)
    n_control: int = 8
    n_check: int = 4
    gcp_noise: float = 0.3          # px
    edge_margin: float = 4.0        # px from the image edges
    target_radius_px: float = 1.5
    # rendering (swathflow.simulation.bundle.render_image)

    @property
    def ifov(self) -> float:
        return math.radians(self.ifov_deg)

    @property
    def center(self) -> float:
        return (self.n_elements - 1) / 2.0


PRESETS: dict[str, dict] = {
    # one rendered strip in seconds: validate / rectify / calibrate
    "rotating-mirror": dict(preset="rotating-mirror"),
    # two strips with side overlap, for mosaicking
    "rotating-mirror-demo": dict(preset="rotating-mirror-demo", n_strips=2,
                                 strip_length=240.0, n_control=12, n_check=6),
}


def preset_config(name: str, **overrides) -> MirrorConfig:
    if name not in PRESETS:
        raise SwathflowError(f"unknown rotating-mirror preset {name!r}; choose one of "
                             f"{', '.join(PRESETS)}")
    unknown = set(overrides) - set(MirrorConfig.__dataclass_fields__)
    if unknown:
        raise SwathflowError(f"unknown simulation option(s) {', '.join(sorted(unknown))}")
    return replace(MirrorConfig(**PRESETS[name]), **overrides)


def make_plan(cfg: MirrorConfig) -> Plan:
    """The flight plan: row period one nadir pixel of flight, strips long enough for the
    pitch and the swath's ends."""
    crs = utm_crs_for(cfg.lat0, cfg.lon0).to_string()
    e0, n0 = transformer("EPSG:4326", crs).transform(cfg.lon0, cfg.lat0)
    row_period = cfg.along_gsd_factor * cfg.ifov * cfg.agl / cfg.speed
    length = cfg.strip_length + 2 * cfg.agl * math.tan(math.radians(
        cfg.pitch_amp * 2 + abs(cfg.pitch_mean))) + 20.0
    duration = length / cfg.speed
    n_rows = int(duration / row_period) + 1
    swath = 2 * cfg.agl * math.tan(cfg.n_elements * cfg.ifov / 2)
    return Plan(crs, (float(e0), float(n0)), swath, (1 - cfg.side_overlap) * swath, n_rows,
                row_period, duration, duration, length)


def sensor_table(cfg: MirrorConfig, plan: Plan) -> dict:
    """The mission's ``[sensor]`` table: one mirror turn per row, so a pixel dwells
    ``row_period * ifov / 360``."""
    return {"model": "rotating-mirror", "n_elements": cfg.n_elements,
            "ifov_deg": cfg.ifov_deg, "dwell": plan.line_period * cfg.ifov_deg / 360.0}


def line_table(cfg: MirrorConfig, plan: Plan, strip: dict, rng) -> dict:
    """Row start times and encoder scan-start angles (deg) of one strip's image."""
    t = strip["t_start"] + np.arange(plan.lines_per_swing) * plan.line_period
    phase = rng.uniform(0, 2 * np.pi)
    start = (-cfg.center * cfg.ifov_deg + cfg.scan_start_bias_deg + cfg.scan_start_wander_deg
             * np.sin(2 * np.pi * (t - t[0]) / cfg.scan_start_period_s + phase))
    return {"time": t, "scan_start": start}


def true_parameters(cfg: MirrorConfig) -> dict:
    return {"u_gps": list(cfg.u_gps), "opk_mount": list(cfg.opk_mount),
            "scan_offset": [cfg.scan_offset]}


def prior_table(cfg: MirrorConfig) -> dict:
    """The mission's ``[calibration]`` priors: name -> (value, sigma)."""
    return {"u_gps": ([0.0, 0.0, -1.0], [cfg.u_gps_sigma] * 3),
            "opk_mount": ([0.0] * 3, [cfg.opk_mount_sigma] * 3),
            "scan_offset": ([0.0], [cfg.scan_offset_sigma])}


# --- the simulation --------------------------------------------------------------------------
@dataclass(frozen=True)
class Simulator:
    """The plugin's simulator as swathflow asks for it (``RotatingMirrorModel.simulator()``
    returns one): the :data:`PRESETS` and :meth:`simulate`. ``model`` is the scanner's model
    class, handed over by that hook, which builds the true images."""

    model: type
    PRESETS: ClassVar[dict[str, dict]] = PRESETS

    def simulate(self, out, preset: str = "rotating-mirror", seed: int = 0, progress=None,
                 **options) -> dict:
        """Write a simulated rotating-mirror mission to ``out``; returns the truth summary
        (what ``truth/truth.json`` holds; ``swathflow simulate`` prints its ``images``,
        ``gcp_counts`` and ``images_rendered``)."""
        return simulate_mission(self.model, out, preset, seed, progress, **options)


def simulate_mission(model, out, preset: str = "rotating-mirror", seed: int = 0, progress=None,
                     **options) -> dict:
    """:meth:`Simulator.simulate` with the model class ``model`` (``RotatingMirrorModel``)."""
    from swathflow.formats.calibfile import write_calibration
    from swathflow.simulation.texture import ProceduralTexture
    say = progress or (lambda msg: None)
    clock = time.perf_counter()
    cfg = preset_config(preset, **options)
    out = Path(out)
    for sub in ("images", "truth"):
        (out / sub).mkdir(parents=True, exist_ok=True)
    if (out / "mission.toml").exists():
        os.remove(out / "mission.toml")
    rng = np.random.default_rng([int(seed), 91])
    plan = make_plan(cfg)
    to_map = transformer("EPSG:4978", plan.crs)
    terrain, terrain_mean = _write_terrain(out, cfg, plan, seed)
    pos_ds, strips = make_trajectory(cfg, plan, terrain_mean, rng)
    traj = Trajectory.from_dataset(pos_ds)
    sensor = sensor_table(cfg, plan)
    params = true_parameters(cfg)
    pset = model.default_parameters(sensor).updated(params)
    lines = {f"M{s['strip']}": (s["strip"], line_table(cfg, plan, s, rng)) for s in strips}
    models = {iid: model.build(sensor, lt, traj, pset, image_id=iid, strip=k)
              for iid, (k, lt) in lines.items()}
    gcps = _control_points(cfg, plan, models, terrain, rng)
    nadir_gsd = cfg.ifov * cfg.agl
    radius = cfg.target_radius_px * nadir_gsd
    tex = ProceduralTexture(seed, nadir_gsd, plan.centre).with_targets(
        gcps[["E", "N"]].drop_duplicates().to_numpy(), radius)
    say(f"rendering {len(models)} rotating-mirror images of {plan.lines_per_swing} x "
        f"{cfg.n_elements}")
    entries = []
    for k, (iid, (strip, lt)) in enumerate(lines.items()):
        paths = write_swing(out, iid, models[iid], terrain, tex, to_map, cfg,
                            np.random.default_rng([int(seed), 92, k]), lt)
        entries.append((iid, *paths, "", strip))
    ortho = write_truth_ortho(out, cfg, plan.crs, models, terrain, tex, to_map, say)
    _write_gcps(out, cfg, gcps, seed)
    pos_name = write_noisy_pos(out, pos_ds, cfg, np.random.default_rng([int(seed), 94]))
    write_calibration(out / "truth" / "calibration.json", "rotating-mirror",
                      {b.name: {"value": list(b.value), "sigma": [0.0] * b.size,
                                "units": b.units} for b in pset.blocks},
                      note=f"simulation truth: preset {cfg.preset}, seed {seed}")
    priors = prior_table(cfg)
    truth = {
        "format": "swathflow-simulation-truth/1", "sensor": "rotating-mirror",
        "preset": cfg.preset, "seed": int(seed), "config": plain(asdict(cfg)),
        "crs": plan.crs, "gsd": cfg.gsd, "centre_en": list(plan.centre),
        "plan": plain(asdict(plan)), "strips": strips,
        "images": [{"id": iid, "strip": k, "lines": models[iid].n_lines,
                    "elements": cfg.n_elements, "t0": float(lt["time"][0]),
                    "t1": float(lt["time"][-1])} for iid, (k, lt) in lines.items()],
        "images_rendered": bool(cfg.render),
        "gcp_counts": {iid: {r: int(((gcps.image_id == iid) & (gcps.role == r)).sum())
                             for r in ("control", "check")} for iid in models},
        "parameters": params, "sensor_table": sensor,
        "priors": {k: {"value": v, "sigma": s} for k, (v, s) in priors.items()},
        "noise": {"gps_m": cfg.gps_noise, "attitude_deg": cfg.att_noise,
                  "gcp_px": cfg.gcp_noise, "read_noise_dn": cfg.read_noise},
        "gcp_target_radius_m": radius, "nadir_gsd_m": nadir_gsd,
        "radiometry": {"gain": cfg.gain, "offset": cfg.offset},
        "ortho": ({"file": "truth/ortho.tif", "transform": list(ortho["transform"]),
                   "shape": list(ortho["shape"]), "supersample": cfg.ortho_supersample}
                  if ortho["written"] else None),
        "terrain": {"source": "procedural", "mean_h": terrain_mean},
        "seconds": round(time.perf_counter() - clock, 3),
    }
    write_text(out / "truth" / "truth.json", json.dumps(truth, indent=2) + "\n")
    sensor_lines = [f"{k} = {toml_value(v)}" for k, v in sensor.items()]
    write_mission_toml(out, cfg.preset, plan.crs, cfg.gsd, pos_name, sensor_lines, priors,
                       entries, "direction")
    return truth


def _write_terrain(out: Path, cfg: MirrorConfig, plan: Plan, seed: int):
    """The procedural terrain as ``dem.tif``; returns it opened and its mean height."""
    from swathflow.formats.raster import write_geotiff
    from swathflow.geometry.terrain import DEM
    from swathflow.simulation.texture import ProceduralTerrain
    half_w = (cfg.n_strips - 1) / 2 * plan.spacing + plan.swath + 0.2 * cfg.agl + 50
    half_l = plan.strip_length / 2 + 0.6 * cfg.agl + 50
    tr, shape = square_grid(plan.centre, math.hypot(half_w, half_l), cfg.dem_cell)
    hfun = ProceduralTerrain(seed, cfg.terrain_base, cfg.terrain_relief,
                             cfg.terrain_wavelength, plan.centre)
    rr, cc = np.indices(shape)
    h = hfun(tr[2] + (cc + 0.5) * tr[0], tr[5] + (rr + 0.5) * tr[4]).astype(np.float32)
    write_geotiff(out / "dem.tif", h, plan.crs, tr, nodata=-9999.0,
                  tags={"vertical": "ellipsoidal", "source": "procedural"})
    return DEM.open(out / "dem.tif"), float(np.mean(h))


def _control_points(cfg: MirrorConfig, plan: Plan, models, terrain, rng) -> pd.DataFrame:
    """Control and check points: ground under random interior pixels of the images, with
    their exact image coordinates in every image that sees them well inside its edges."""
    from swathflow.geometry.intersect import intersect
    n = cfg.n_control + cfg.n_check
    ids = list(models)
    m0 = cfg.edge_margin + 2
    picks = []
    for k in range(n):
        m = models[ids[k % len(ids)]]
        picks.append((m, [rng.uniform(m0, m.n_lines - 1 - m0),
                          rng.uniform(m0, m.n_elements - 1 - m0)]))
    xyz = np.array([intersect(*m.ray(np.array([ij])), terrain)[0] for m, ij in picks])
    e, nn, _ = transformer("EPSG:4978", plan.crs).transform(*xyz.T)
    llh = ecef_to_geodetic(xyz)
    rows = []
    for iid, m in models.items():
        ij = m.ground_to_image(xyz)
        with np.errstate(invalid="ignore"):
            ok = (np.isfinite(ij).all(-1) & (ij[:, 0] >= cfg.edge_margin)
                  & (ij[:, 0] <= m.n_lines - 1 - cfg.edge_margin)
                  & (ij[:, 1] >= cfg.edge_margin)
                  & (ij[:, 1] <= m.n_elements - 1 - cfg.edge_margin))
        for i in np.flatnonzero(ok):
            rows.append({"gcp_id": f"G{i + 1:03d}", "image_id": iid, "line": ij[i, 0],
                         "element": ij[i, 1], "x": llh[i, 1], "y": llh[i, 0], "z": llh[i, 2],
                         "role": "control" if i < cfg.n_control else "check",
                         "E": e[i], "N": nn[i], "X": xyz[i, 0], "Y": xyz[i, 1],
                         "Z": xyz[i, 2]})
    return pd.DataFrame(rows)


def _write_gcps(out: Path, cfg: MirrorConfig, gcps: pd.DataFrame, seed: int) -> None:
    """``gcp.csv`` (image coordinates with measurement noise) and ``truth/gcp.csv``."""
    grng = np.random.default_rng([int(seed), 93])
    meas = gcps.copy()
    meas["line"] += grng.normal(0, cfg.gcp_noise, len(meas))
    meas["element"] += grng.normal(0, cfg.gcp_noise, len(meas))
    cols = ["gcp_id", "image_id", "line", "element", "x", "y", "z", "role"]
    fmt = {"line": "%.4f", "element": "%.4f", "x": "%.10f", "y": "%.10f", "z": "%.4f"}
    write_csv(out / "gcp.csv", meas[cols], fmt)
    write_csv(out / "truth" / "gcp.csv", gcps, {**fmt, "line": "%.6f", "element": "%.6f",
                                                  "E": "%.4f", "N": "%.4f", "X": "%.4f",
                                                  "Y": "%.4f", "Z": "%.4f"})
