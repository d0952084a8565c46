"""Writing the simulated pendulum mission's files: the terrain (``dem.tif``), the texture
with survey targets, the truth ortho over the swings' footprint, the GCP measurements and
the POS with noise (the steps of :func:`swathflow.sensors.pendulum.simulate.simulate`)."""
from __future__ import annotations

import math
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from swathflow.geometry.geodesy import transformer
from swathflow.simulation.bundle import Plan, square_grid, write_csv

if TYPE_CHECKING:
    from swathflow.sensors.pendulum.simulate import SimConfig


def dem_grid(plan: Plan, cfg: SimConfig):
    """A north-up DEM grid (transform, shape) that covers the flight with a wide margin."""
    half_w = (cfg.n_strips - 1) / 2 * plan.spacing + plan.swath * 0.9 + 0.3 * cfg.agl
    half_l = plan.strip_length / 2 + 0.5 * cfg.agl + 50
    return square_grid(plan.centre, math.hypot(half_w, half_l), cfg.dem_cell)


def write_terrain(out: Path, cfg: SimConfig, plan: Plan, seed: int, dem: str | None):
    """``dem.tif`` from a procedural terrain or the shape of a given DEM; returns it
    opened, its mean height and where it came from."""
    from swathflow.formats.raster import write_geotiff
    from swathflow.geometry.terrain import DEM
    from swathflow.simulation.texture import ProceduralTerrain, RasterTerrain
    dem_tr, dem_shape = dem_grid(plan, cfg)
    if dem:
        shape_src = RasterTerrain(dem, plan.centre, cell=1.0, base=cfg.terrain_base,
                                  relief=cfg.terrain_relief)
        rows_src, cols_src = shape_src.data.shape
        shape_src.cell = dem_shape[0] * cfg.dem_cell / min(rows_src, cols_src)
        hfun = shape_src
        dem_info = {"source": str(dem), "source_range": shape_src.source_range,
                    "vscale": shape_src.vscale, "cell_m": shape_src.cell}
    else:
        hfun = ProceduralTerrain(seed, cfg.terrain_base, cfg.terrain_relief,
                                 cfg.terrain_wavelength, plan.centre)
        dem_info = {"source": "procedural"}
    rr, cc = np.indices(dem_shape)
    a, _, c0, _, e, f0 = dem_tr
    hgrid = hfun(c0 + (cc + 0.5) * a, f0 + (rr + 0.5) * e).astype(np.float32)
    write_geotiff(out / "dem.tif", hgrid, plan.crs, dem_tr, nodata=-9999.0,
                  tags={"vertical": "ellipsoidal", "source": dem_info["source"]})
    return DEM.open(out / "dem.tif"), float(np.mean(hgrid)), dem_info


def texture_with_targets(cfg: SimConfig, plan: Plan, seed: int, texture: str | None, rng, pts,
             nadir_gsd: float):
    """The ground texture (an image or procedural) with survey targets at the GCPs."""
    from swathflow.simulation.texture import ImageTexture, ProceduralTexture
    if texture:
        tex0 = ImageTexture(texture, plan.centre,
                            rotation_deg=float(rng.uniform(0, 360)))
        tex_info = {"source": str(texture), "pixel_size_m": tex0.pixel_size}
    else:
        tex0 = ProceduralTexture(seed, nadir_gsd, plan.centre)
        tex_info = {"source": "procedural", "scale_m": nadir_gsd}
    radius = cfg.target_radius_px * nadir_gsd
    return tex0.with_targets(pts[["E", "N"]].to_numpy(), radius), tex_info


def write_gcps(out: Path, cfg: SimConfig, plan: Plan, models, pts, obs, seed: int):
    """GCP observations with noise and gross errors (``gcp.csv``) and their truth
    (``truth/gcp.csv``); returns the measurements and the gross errors."""
    grng = np.random.default_rng([int(seed), 3])
    meas = obs.copy()
    meas["line"] = obs["line"] + grng.normal(0, cfg.gcp_noise, len(obs))
    meas["element"] = obs["element"] + grng.normal(0, cfg.gcp_noise, len(obs))
    gross = []
    if cfg.gross_fraction > 0 and len(obs):
        k = max(1, int(round(cfg.gross_fraction * len(obs))))
        idx = np.sort(grng.choice(len(obs), k, replace=False))
        size = grng.uniform(*cfg.gross_range, k)
        ang = grng.uniform(0, 2 * np.pi, k)
        meas.loc[idx, "line"] += size * np.sin(ang)
        meas.loc[idx, "element"] += size * np.cos(ang)
        gross = [{"gcp_id": obs.gcp_id[i], "image_id": obs.image_id[i], "size_px": float(s)}
                 for i, s in zip(idx, size)]
    for col, n in (("line", "n_lines"), ("element", "n_elements")):
        size = meas.image_id.map({k: getattr(v, n) for k, v in models.items()})
        meas[col] = np.clip(meas[col], -0.49, size - 0.51)
    if cfg.ground_noise > 0:
        de, dn = grng.normal(0, cfg.ground_noise, (2, len(pts)))
        dh = grng.normal(0, cfg.ground_noise, len(pts))
        lon2, lat2 = transformer(plan.crs, "EPSG:4326").transform(pts.E + de, pts.N + dn)
        gmap = dict(zip(pts.gcp_id, zip(lon2, lat2, pts.h + dh)))
        meas["x"] = [gmap[g][0] for g in meas.gcp_id]
        meas["y"] = [gmap[g][1] for g in meas.gcp_id]
        meas["z"] = [gmap[g][2] for g in meas.gcp_id]
    cols = ["gcp_id", "image_id", "line", "element", "x", "y", "z", "role"]
    fmt = {"line": "%.3f", "element": "%.3f", "x": "%.9f", "y": "%.9f", "z": "%.4f"}
    write_csv(out / "gcp.csv", meas[cols], fmt)
    write_csv(out / "truth" / "gcp.csv", obs, {**fmt, "line": "%.6f", "element": "%.6f",
                                                 "E": "%.4f", "N": "%.4f"})
    return meas, gross
