"""Building blocks every sensor plugin's simulator shares: the flight plan and true
trajectory, rendering raw images through the plugin's sensor model, and writing the mission
bundle (raw images, line tables, CSV/TOML files) atomically."""
from __future__ import annotations

import json
import math
import os
import shutil
import tempfile
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from swathflow.errors import SwathflowError
from swathflow.geometry.geodesy import geodetic_to_ecef, transformer
from swathflow.geometry.intersect import intersect
from swathflow.geometry.rotations import r_en
from swathflow.io import atomic_path, write_text


def _sines(rng, t, amp, periods, n=3):
    """A smooth random signal: sum of ``n`` sines with random periods and phases."""
    out = np.zeros_like(t)
    w = rng.uniform(0.5, 1.0, n)
    w /= np.sqrt((w ** 2).sum() / 2)          # rms-ish amplitude ``amp``
    for k in range(n):
        p = rng.uniform(*periods)
        out += amp * w[k] / np.sqrt(n) * np.sin(2 * np.pi * t / p + rng.uniform(0, 2 * np.pi))
    return out



@dataclass(kw_only=True)
class Rendering:
    """The fields of a simulator's configuration that the shared pieces here read
    (:func:`render_image`, :func:`write_swing`, :func:`write_noisy_pos`,
    :func:`write_truth_ortho`); a plugin's configuration dataclass inherits them and may
    change their defaults."""

    # POS noise and format
    gps_noise: float = 0.01         # m, per axis
    att_noise: float = 0.001        # deg
    pos_format: str = "sbet"        # "sbet" or "csv"
    # rendering through the sensor model
    render: bool = True
    supersample: int = 2
    node_step: int = 8
    block_lines: int = 256
    gain: float = 12000.0
    offset: float = 1000.0
    read_noise: float = 15.0        # DN
    shot_noise: float = 1.0         # DN per sqrt(DN)
    image_format: str = "tif"       # "tif" or "envi"
    write_ortho: bool = True
    ortho_supersample: int = 2

@dataclass
class Plan:
    crs: str
    centre: tuple            # E, N of the flight area centre
    swath: float             # cross-track width of one swing on the ground (m)
    spacing: float           # between strip centre lines (m)
    lines_per_swing: int
    line_period: float
    swing_period: float
    strip_duration: float
    strip_length: float
    t0: float = 302400.0     # GPS seconds of week (Wednesday 12:00, on FLIGHT_DATE)


#: the simulated flights' UTC date ([mission] date): a Wednesday, as Plan.t0 is
FLIGHT_DATE = "2024-06-05"


def make_trajectory(cfg, plan: Plan, terrain_mean: float, rng):
    """True trajectory (xarray Dataset over time, continuous at ``pos_rate`` through the
    turns between strips) and per-strip timing.

    On a strip the aircraft flies the planned line at constant ground speed with sway,
    altitude wander, roll/pitch/heading oscillations and a constant crab angle; between
    strips it follows a smooth turn (cubic Hermite in position, banked by its curvature)."""
    from swathflow.formats.posdata import pos_dataset
    to_ll = transformer(plan.crs, "EPSG:4326")
    az = math.radians(cfg.heading)
    fwd = np.array([math.sin(az), math.cos(az)])         # E, N unit vector along strip 1
    right = np.array([fwd[1], -fwd[0]])
    lead = 3.0
    period = plan.strip_duration + 2 * lead + cfg.strip_gap
    t_first = plan.t0 - lead
    t_last = plan.t0 + (cfg.n_strips - 1) * period + plan.strip_duration + lead
    t = t_first + np.arange(int(round((t_last - t_first) * cfg.pos_rate)) + 1) / cfg.pos_rate
    # smooth disturbances on the whole time axis (continuous across strips and turns)
    sway = _sines(rng, t - plan.t0, cfg.sway_amp, (15, 40))
    dh = _sines(rng, t - plan.t0, cfg.alt_amp, (20, 60))
    roll = _sines(rng, t - plan.t0, cfg.roll_amp, (3, 15))
    pitch = cfg.pitch_mean + _sines(rng, t - plan.t0, cfg.pitch_amp, (4, 20))
    dpsi = _sines(rng, t - plan.t0, cfg.heading_amp, (5, 25))
    crab = np.zeros_like(t)
    en = np.zeros((t.size, 2))
    strips, seg = [], []
    for k in range(cfg.n_strips):
        t_start = plan.t0 + k * period
        sgn = 1.0 if k % 2 == 0 else -1.0                  # alternate flight directions
        off = (k - (cfg.n_strips - 1) / 2) * plan.spacing
        tc = t_start + plan.strip_duration / 2
        # half a POS interval of tolerance: t comes from a rounded sample count, so the
        # last epoch can lie a rounding error past the strip's end (it was left at the
        # origin, lat 0, before)
        tol = 0.5 / cfg.pos_rate
        on = (t >= t_start - lead - tol) & (t <= t_start + plan.strip_duration + lead + tol)
        along = sgn * cfg.speed * (t[on] - tc)
        en[on] = (np.asarray(plan.centre)[None] + along[:, None] * fwd[None]
                  + (off + sway[on])[:, None] * right[None])
        c = float(rng.uniform(-cfg.crab_max, cfg.crab_max))
        crab[on] = c
        seg.append(np.flatnonzero(on))
        strips.append({"strip": k + 1, "t_start": float(t_start), "direction_sign": sgn,
                       "offset_m": float(off), "crab_deg": c})
    for k in range(cfg.n_strips - 1):       # turns: Hermite between the strip ends
        a, b = seg[k], seg[k + 1]
        i0, i1 = a[-1], b[0]
        if i1 - i0 < 2:
            continue
        v0 = (en[i0] - en[i0 - 1]) * cfg.pos_rate
        v1 = (en[i1 + 1] - en[i1]) * cfg.pos_rate
        T = t[i1] - t[i0]
        u = (t[i0 + 1:i1] - t[i0]) / T
        h00, h10 = 2 * u ** 3 - 3 * u ** 2 + 1, u ** 3 - 2 * u ** 2 + u
        h01, h11 = -2 * u ** 3 + 3 * u ** 2, u ** 3 - u ** 2
        en[i0 + 1:i1] = (h00[:, None] * en[i0] + h10[:, None] * T * v0
                         + h01[:, None] * en[i1] + h11[:, None] * T * v1)
        crab[i0 + 1:i1] = crab[i0] + (crab[i1] - crab[i0]) * u
    h = terrain_mean + cfg.agl + dh
    lon, lat = to_ll.transform(en[:, 0], en[:, 1])
    ecef = geodetic_to_ecef(np.stack([lat, lon, h], -1))
    v = np.gradient(ecef, t, axis=0)
    ned = np.einsum("nji,nj->ni", r_en(np.radians(lat), np.radians(lon)), v)
    track = np.unwrap(np.arctan2(ned[:, 1], ned[:, 0]))
    speed = np.hypot(ned[:, 0], ned[:, 1])
    bank = np.degrees(np.arctan(speed * np.gradient(track, t) / 9.80665))
    heading = np.degrees(track) + crab + dpsi
    heading = (heading + 180.0) % 360.0 - 180.0
    ds = pos_dataset(t, lat, lon, h, roll + bank, pitch, heading, source="simulated truth")
    return ds, strips


def footprint_en(model, terrain, to_map, lines, elements) -> np.ndarray:
    """Exact ground (E, N) of image points on the grid ``lines x elements``: ``(L, K, 2)``."""
    pts = np.stack(np.meshgrid(lines, elements, indexing="ij"), -1)
    o, d = model.ray(pts)
    g = intersect(o, d, terrain)
    e, n, _ = to_map.transform(g[..., 0], g[..., 1], g[..., 2])
    return np.stack([e, n], -1)


def spline_en(model, terrain, to_map, lines, elements, node_step: int) -> np.ndarray:
    """Ground (E, N) on ``lines x elements``: exact rays at every line but only at nodes
    every ``node_step`` elements, a cubic spline along the detector in between."""
    from scipy.interpolate import CubicSpline
    elements = np.asarray(elements, float)
    lo, hi = float(elements.min()), float(elements.max())
    m = max(int(math.ceil((hi - lo) / node_step)) + 1, 4)
    nodes = np.linspace(lo, hi, m)
    en = footprint_en(model, terrain, to_map, lines, nodes)
    return CubicSpline(nodes, en, axis=1)(elements)


def render_image(model, terrain, texture, to_map, cfg, rng) -> np.ndarray:
    """Integrate the texture over every detector pixel, add noise; uint16 (lines, elements)."""
    n_lines, n_el = model.shape
    ss = cfg.supersample
    sub = (np.arange(ss) + 0.5) / ss - 0.5
    ef = (np.arange(n_el)[:, None] + sub[None]).ravel()
    out = np.empty((n_lines, n_el), np.uint16)
    for j0 in range(0, n_lines, cfg.block_lines):
        j1 = min(n_lines, j0 + cfg.block_lines)
        lf = (np.arange(j0, j1)[:, None] + sub[None]).ravel()
        en = spline_en(model, terrain, to_map, lf, ef, cfg.node_step)
        v = texture(en[..., 0], en[..., 1])
        v = v.reshape(j1 - j0, ss, n_el, ss).mean(axis=(1, 3))
        dn = cfg.offset + cfg.gain * v
        noise = rng.normal(0.0, 1.0, dn.shape) * np.sqrt(cfg.read_noise ** 2
                                                          + cfg.shot_noise ** 2 * dn)
        out[j0:j1] = np.clip(np.rint(dn + noise), 0, 65535).astype(np.uint16)
    return out


def write_swing(out: Path, iid: str, model, terrain, texture, to_map, cfg, rng,
                columns: dict) -> tuple[str, str]:
    """Render one image (or a blank one for geometry-only runs) and write it with its line
    table (``line`` plus ``columns``); returns both paths relative to ``out``."""
    ext = ".tif" if cfg.image_format == "tif" else ".img"
    if cfg.render:
        arr = render_image(model, terrain, texture, to_map, cfg, rng)
    else:
        arr = np.full(model.shape, int(cfg.offset), np.uint16)
    write_raw_image(out / "images" / f"{iid}{ext}", arr, cfg.image_format)
    df = pd.DataFrame({"line": np.arange(model.n_lines), **columns})
    with atomic_path(out / "images" / f"{iid}.lines.csv") as tmp:
        df.to_csv(tmp, index=False, float_format="%.9f")
    return f"images/{iid}{ext}", f"images/{iid}.lines.csv"


def write_raw_image(path: Path, array: np.ndarray, fmt: str = "tif") -> None:
    """A raw image (no georeferencing): GeoTIFF, or ENVI (``.img`` + ``.hdr``), atomically."""
    import rasterio
    from rasterio.errors import NotGeoreferencedWarning
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    prof = dict(width=array.shape[1], height=array.shape[0], count=1, dtype=array.dtype.name)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", NotGeoreferencedWarning)
        if fmt == "tif":
            with atomic_path(path, suffix=".tif") as tmp:
                with rasterio.open(tmp, "w", driver="GTiff", compress="deflate", predictor=2,
                                   tiled=True, blockxsize=256, blockysize=256, **prof) as d:
                    d.write(array, 1)
            return
        if fmt != "envi":
            raise SwathflowError(f"image format must be 'tif' or 'envi', not {fmt!r}")
        tmpdir = tempfile.mkdtemp(prefix=".envi.", dir=path.parent)
        try:
            tmp = os.path.join(tmpdir, path.name)
            with rasterio.open(tmp, "w", driver="ENVI", **prof) as d:
                d.write(array, 1)
            for name in os.listdir(tmpdir):
                if name.endswith(".aux.xml"):
                    continue
                os.replace(os.path.join(tmpdir, name), path.parent / name)
        finally:
            shutil.rmtree(tmpdir, ignore_errors=True)


def square_grid(centre, radius: float, cell: float):
    """A north-up square grid (transform, shape) of ``cell`` size, snapped to the cell,
    covering a circle of ``radius`` (plus 5 % and 5 cells) around ``centre`` (E, N)."""
    r = radius * 1.05 + 5 * cell
    c = cell
    e0 = math.floor((centre[0] - r) / c) * c
    n1 = math.ceil((centre[1] + r) / c) * c
    size = int(math.ceil(2 * r / c)) + 1
    return (c, 0.0, e0, 0.0, -c, n1), (size, size)


def toml_value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, (list, tuple, np.ndarray)):
        return "[" + ", ".join(toml_value(x) for x in v) + "]"
    if isinstance(v, (float, np.floating)):
        return repr(float(v))
    return str(v)


def plain(x):
    if isinstance(x, dict):
        return {str(k): plain(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [plain(v) for v in x]
    if isinstance(x, (np.floating, np.integer)):
        return x.item()
    return x


def write_csv(path, df, fmt):
    df = df.copy()
    for c, f in fmt.items():
        if c in df:
            df[c] = df[c].map(lambda v, f=f: f % v)
    with atomic_path(path) as tmp:
        df.to_csv(tmp, index=False)


def write_mission_toml(out, preset, crs, gsd, pos_name, sensor_lines, priors, images,
                        image_key, ties=False):
    """mission.toml of a simulated bundle (pendulum and push-broom): ``sensor_lines`` are
    the [sensor] section's lines, ``images`` (id, file, lines file, ``image_key`` value,
    strip) tuples."""
    L = [f"# simulated by swathflow simulate (preset {preset}); the truth is in truth/", "",
         "[mission]", f'name = "sim-{preset}"', f'crs = "{crs}"', f"gsd = {gsd!r}",
         f"date = {FLIGHT_DATE}", "",
         "[sensor]", *sensor_lines]
    L += ["", "[pos]", f'file = "{pos_name}"',
          f'format = "{"sbet" if pos_name.endswith(".sbet") else "csv"}"', "",
          "[terrain]", 'dem = "dem.tif"', 'vertical = "ellipsoidal"', "",
          "[gcp]", 'file = "gcp.csv"', 'crs = "EPSG:4979"', ""]
    if ties:
        L += ["[ties]", 'file = "ties.csv"', ""]
    L.append("[calibration]")
    for k, (v, s) in priors.items():
        L.append(f"{k} = {{ value = {toml_value(v)}, sigma = {toml_value(s)} }}")
    for iid, f, lf, d, s in images:
        L += ["", "[[images]]", f'id = "{iid}"', f'file = "{f}"', f'lines = "{lf}"',
              f'{image_key} = "{d}"', f"strip = {s}"]
    write_text(out / "mission.toml", "\n".join(L) + "\n")



def write_noisy_pos(out: Path, truth_ds, cfg, rng) -> str:
    """The mission's POS file (the true trajectory plus white GPS and attitude noise:
    ``cfg.gps_noise`` m, ``cfg.att_noise`` deg, drawn from ``rng``) in ``cfg.pos_format``
    (sbet or csv), and the truth as ``truth/pos.csv``; returns the POS file's name."""
    from swathflow.formats.pos import write_pos_csv, write_sbet
    nt = truth_ds.sizes["time"]
    lat = truth_ds["lat"].values
    noisy = truth_ds.copy(deep=True)
    noisy["lat"] = ("time", lat + rng.normal(0, cfg.gps_noise, nt) / 111_132.0)
    noisy["lon"] = ("time", truth_ds["lon"].values + rng.normal(0, cfg.gps_noise, nt)
                    / (111_320.0 * np.cos(np.radians(lat))))
    noisy["h"] = ("time", truth_ds["h"].values + rng.normal(0, cfg.gps_noise, nt))
    for k in ("roll", "pitch", "heading"):
        noisy[k] = ("time", truth_ds[k].values + rng.normal(0, cfg.att_noise, nt))
    noisy["heading"] = (noisy["heading"] + 180.0) % 360.0 - 180.0
    name = "pos.sbet" if cfg.pos_format == "sbet" else "pos.csv"
    (write_sbet if cfg.pos_format == "sbet" else write_pos_csv)(noisy, out / name)
    write_pos_csv(truth_ds, out / "truth" / "pos.csv")
    return name


def write_truth_ortho(out: Path, cfg, crs, models, terrain, texture, to_map, say) -> dict:
    """The images' footprint on the ``cfg.gsd`` grid and, with ``cfg.write_ortho``, the truth
    ortho (``truth/ortho.tif``: the texture averaged over each output pixel, in expected DN
    ``cfg.offset + cfg.gain * T``)."""
    from swathflow.formats.raster import write_geotiff
    from swathflow.ingest.plausible import image_border
    from swathflow.simulation.texture import area_average
    gsd = cfg.gsd
    parts = []
    for m in models.values():
        o, d = m.ray(image_border(m.shape, 40))
        g = intersect(o, d, terrain)
        ee, nn, _ = to_map.transform(g[:, 0], g[:, 1], g[:, 2])
        parts.append(np.stack([ee, nn], -1))
    border = np.concatenate(parts)
    xmin = math.floor(np.nanmin(border[:, 0]) / gsd) * gsd
    xmax = math.ceil(np.nanmax(border[:, 0]) / gsd) * gsd
    ymin = math.floor(np.nanmin(border[:, 1]) / gsd) * gsd
    ymax = math.ceil(np.nanmax(border[:, 1]) / gsd) * gsd
    transform = (gsd, 0.0, xmin, 0.0, -gsd, ymax)
    shape = (int(round((ymax - ymin) / gsd)), int(round((xmax - xmin) / gsd)))
    if cfg.write_ortho:
        say(f"truth ortho {shape[1]} x {shape[0]} at {gsd} m")
        t = area_average(texture, transform, shape, cfg.ortho_supersample)
        write_geotiff(out / "truth" / "ortho.tif", (cfg.offset + cfg.gain * t).astype(np.float32),
                      crs, transform, tags={"units": "expected DN (offset + gain * T)",
                                            "gain": cfg.gain, "offset": cfg.offset})
    return {"transform": transform, "shape": shape, "written": bool(cfg.write_ortho),
            "bounds": [xmin, ymin, xmax, ymax]}
