"""The push-broom simulator's configuration (:class:`PushbroomConfig`, the presets) and
the simulated camera: flight plan, ``[sensor]`` table, true parameters and priors."""
from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

from swathflow.errors import SwathflowError
from swathflow.geometry.geodesy import transformer, utm_crs_for
from swathflow.simulation.bundle import Plan, Rendering, square_grid

VIEWS = {"forward": 25.0, "nadir": 0.0, "backward": -25.0}
VIEW_LETTER = {"forward": "F", "nadir": "N", "backward": "B"}


@dataclass
class PushbroomConfig(Rendering):
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


def dem_grid(plan: Plan, cfg: PushbroomConfig):
    half_w = (cfg.n_strips - 1) / 2 * plan.spacing + plan.swath + 0.2 * cfg.agl + 50
    half_l = plan.strip_length / 2 + 0.6 * cfg.agl + 50
    return square_grid(plan.centre, math.hypot(half_w, half_l), cfg.dem_cell)
