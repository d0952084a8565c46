"""Plausibility checks of a mission: values that parse but cannot be right.

Angles written in radians where degrees are expected, a platform that jumps or turns
faster than an aircraft can, a DEM above the aircraft, lat/lon swapped, an output grid far
too large or too small for the footprint. Each check adds problems to a
:class:`~swathflow.validate.Collector` naming the column or key and the fix; numpy warnings
are silenced (the problem is reported once, in words).
"""
from __future__ import annotations

import numpy as np

#: an aircraft: ground speeds, accelerations and angular rates it cannot exceed
MAX_SPEED = 400.0          # m/s
MAX_ACCEL = 40.0           # m/s^2 over >= 0.5 s
MAX_RATE = 200.0           # deg/s (roll, pitch, heading) ...
MAX_STEP = 10.0            # ... in a step of more than this between two epochs (deg)
EARTH_R = 6371000.0


def _wrap(a):
    return (np.asarray(a, float) + 180.0) % 360.0 - 180.0


# ------------------------------------------------------------------------------------------
# POS

def check_pos_plausible(ds, pp, fmt: str, c) -> bool:
    """Angle ranges, motion, angle units of a POS; False when it is unusable."""
    with np.errstate(all="ignore"):
        if not _pos_ranges(ds, pp, fmt, c):
            return False
        if not _pos_time_unit(ds, pp, c):
            return False
        ok = _pos_motion(ds, pp, c)
        return _pos_units(ds, pp, fmt, c) and ok


#: units a POS time column is mistaken for, and their length in seconds
TIME_UNITS = (("milliseconds", 1e-3), ("minutes", 60.0), ("hours", 3600.0))
#: a typical survey ground speed (m/s), to tell which unit the times seem to be in
TYPICAL_SPEED = 60.0


def _pos_time_unit(ds, pp, c) -> bool:
    """Times in another unit than seconds show as a platform moving uniformly too fast (or
    too slow), not as one jump: told as such, with the unit that fits."""
    from swathflow.geometry.geodesy import geodetic_to_ecef
    t = np.asarray(ds["time"].values, float)
    if t.size < 3:
        return True
    xyz = geodetic_to_ecef(np.stack([ds[k].values for k in ("lat", "lon", "h")], -1))
    step = np.linalg.norm(np.diff(xyz, axis=0), axis=-1)
    v = step / np.diff(t)
    med = float(np.median(v))
    if not np.isfinite(med) or (0.5 <= med <= MAX_SPEED) or step.sum() < 100.0:
        return True
    unit = min(TIME_UNITS, key=lambda u: abs(np.log(med / u[1] / TYPICAL_SPEED)))
    msg = (f"with its times read as seconds the platform moves at {med:.3g} m/s all along "
           f"the flight (an aircraft flies at 20-{MAX_SPEED:g} m/s): the times look like "
           f"{unit[0]} ({med / unit[1]:.3g} m/s then)")
    fix = f"write the time column in seconds (multiply by {unit[1]:g})"
    if med > MAX_SPEED:
        c.add(pp, "column time", msg, fix)
        return False
    c.warn(pp, "column time", msg, fix)
    return True


def _pos_ranges(ds, pp, fmt, c) -> bool:
    sbet = fmt in ("sbet", "out")
    for k, lim in (("lat", 90.0), ("lon", 360.0), ("roll", 90.0), ("pitch", 90.0)):
        v = ds[k].values
        bad = np.abs(v) > lim
        if not bad.any():
            continue
        i = int(np.flatnonzero(bad)[0])
        head = (f"{k} {v[i]:.6g} deg at t={float(ds.time[i]):.3f} s (epoch {i}, "
                f"{int(bad.sum())} epochs in all) is outside -{lim:g}..{lim:g}")
        if sbet:
            fix = ("an SBET stores radians: this file seems to hold degrees, or is not an "
                   "SBET; re-export it, or use a CSV POS in degrees")
        elif k == "lat" and (np.abs(ds["lon"].values) <= 90).all():
            fix = "lat and lon look swapped: swap the lat and lon columns"
        else:
            fix = f"check the {k} column (degrees) of the POS"
        c.add(pp, f"column {k}", head, fix)
        return False
    return True


def _pos_motion(ds, pp, c) -> bool:
    """Speed and attitude rates between epochs, acceleration over half-second baselines."""
    from swathflow.geometry.geodesy import geodetic_to_ecef
    t = ds["time"].values
    xyz = geodetic_to_ecef(np.stack([ds[k].values for k in ("lat", "lon", "h")], -1))
    dt = np.diff(t)
    v = np.linalg.norm(np.diff(xyz, axis=0), axis=-1) / dt
    if (v > MAX_SPEED).any():
        i = int(np.argmax(v))
        c.add(pp, f"epochs {i}-{i + 1} (t={t[i]:.3f}-{t[i + 1]:.3f} s)",
              f"the platform moves {v[i] * dt[i]:.6g} m in {dt[i]:.3g} s ({v[i]:.3g} m/s; "
              f"an aircraft flies below {MAX_SPEED:g} m/s)",
              "the POS has a position jump: re-export it, or cut the bad epochs")
        return False
    ok = True
    for k in ("roll", "pitch", "heading"):
        a = np.degrees(np.unwrap(np.radians(ds[k].values)))
        step = np.abs(np.diff(a))
        r = np.where(step > MAX_STEP, step / dt, 0.0)
        if (r > MAX_RATE).any():
            i = int(np.argmax(r))
            c.add(pp, f"column {k}, epochs {i}-{i + 1} (t={t[i]:.3f} s)",
                  f"{k} changes by {abs(a[i + 1] - a[i]):.3g} deg in {dt[i]:.3g} s "
                  f"({r[i]:.3g} deg/s; an aircraft turns below {MAX_RATE:g} deg/s)",
                  "the POS attitude jumps: re-export it, or cut the bad epochs")
            ok = False
    stride = max(1, round(0.5 / max(float(np.median(dt)), 1e-9)))
    ts, xs = t[::stride], xyz[::stride]
    if ts.size >= 3:
        vel = np.diff(xs, axis=0) / np.diff(ts)[:, None]
        acc = np.linalg.norm(np.diff(vel, axis=0), axis=-1) / (0.5 * (ts[2:] - ts[:-2]))
        if (acc > MAX_ACCEL).any():
            i = int(np.argmax(acc)) + 1
            c.add(pp, f"near t={ts[i]:.3f} s",
                  f"the platform accelerates at {acc[i - 1]:.3g} m/s^2 (an aircraft stays "
                  f"below {MAX_ACCEL:g})", "the POS has a position jump: re-export it")
            ok = False
    return ok


def _track(ds):
    """Course over ground (deg) and ground speed (m/s) over ~1 s baselines."""
    t = ds["time"].values
    stride = max(1, round(1.0 / max(float(np.median(np.diff(t))), 1e-9)))
    lat, lon = ds["lat"].values[::stride], ds["lon"].values[::stride]
    ts = t[::stride]
    dn = np.radians(np.diff(lat)) * EARTH_R
    de = np.radians(_wrap(np.diff(lon))) * EARTH_R * np.cos(np.radians(lat[:-1]))
    speed = np.hypot(dn, de) / np.diff(ts)
    return np.degrees(np.arctan2(de, dn)), speed, stride


def _pos_units(ds, pp, fmt, c) -> bool:
    """Heading against the course over ground: degrees where radians were expected (or
    the other way round) show up as a heading that matches the track only once converted."""
    if ds.sizes["time"] < 4:
        return True
    track, speed, stride = _track(ds)
    moving = speed > 10.0
    if moving.sum() < 3:
        return True
    hd = ds["heading"].values[::stride][:-1][moving]
    tr = track[moving]
    as_is = np.median(np.abs(_wrap(hd - tr)))
    if fmt in ("sbet", "out"):
        return True     # radians by format; degrees in an SBET fail the range checks
    alt = np.median(np.abs(_wrap(np.degrees(hd) - tr)))
    if alt < 20.0 and as_is > 2 * alt + 3.0:
        c.add(pp, "columns roll, pitch, heading",
              f"the angles look like radians (heading {np.min(hd):.3g}..{np.max(hd):.3g}; "
              f"in degrees it would match the flight track, now {as_is:.0f} deg off)",
              "write roll, pitch and heading in degrees (multiply by 57.2958)")
        return False
    if as_is < 45.0:
        return True
    c.warn(pp, "column heading", f"the heading differs from the flight track by "
           f"{as_is:.0f} deg (median)", "check that heading is the true heading in degrees")
    return True


# ------------------------------------------------------------------------------------------
# line tables (the sensor plugin knows its columns)

def check_lines_plausible(cls, entry, cols: dict, c) -> None:
    check = getattr(cls, "check_lines", None)
    if check is None:
        return
    try:
        msgs = check({k: v for k, v in cols.items() if k != "line"})
    except (TypeError, ValueError, KeyError) as exc:
        msgs = [(f"the {cls.name} plugin cannot check it: {exc}", "")]
    for m in msgs or ():
        msg, fix = m if isinstance(m, tuple) else (m, "")
        c.add(entry.lines_file, f"[[images]] id={entry.id!r}", msg, fix)


# ------------------------------------------------------------------------------------------
# sensor models against the terrain and the output grid

def check_models(parts: dict, toml, c) -> None:
    """Build every image's model; DEM under the aircraft and around the footprint; the
    output grid's size."""
    from swathflow.errors import SwathflowError
    from swathflow.geometry.terrain import DEM
    cls, traj, terrain = parts["cls"], parts["trajectory"], parts["terrain"]
    with np.errstate(all="ignore"):
        if isinstance(terrain, DEM) and not _pos_over_dem(traj, terrain, parts, c):
            return
        foot = []
        # the terrain's height range and the map transformer once, not per image (each
        # is a scan of the DEM / a CRS parse: 0.6 CPU-s over the survey's 240 images)
        span = (terrain.h_min, terrain.h_max) if terrain is not None else None
        to_map = None
        if terrain is not None and parts.get("crs_ok"):
            from swathflow.geometry.geodesy import transformer
            to_map = transformer("EPSG:4978", parts["crs"])
        for iid, lt in parts["lines"].items():
            if iid not in parts["shapes"]:
                continue
            e = parts["images"][iid]
            try:
                model = cls.build(parts["sensor"], lt, traj, parts["priors"], image_id=iid,
                                  direction=e.direction, strip=e.strip, **e.attrs)
            except (SwathflowError, TypeError, ValueError, KeyError) as exc:
                c.add(toml, f"[[images]] id={iid!r}", f"the sensor model cannot be built: "
                      f"{exc}", "fix the image's entry, its line table or the [sensor] values")
                continue
            if isinstance(terrain, DEM):
                if not _dem_below(model, terrain, traj, lt, iid, c):
                    continue
                _dem_cover(model, terrain, iid, c, span)
            if to_map is not None:
                # the shape, not the model: 240 models kept alive each hold their own
                # copy of the POS table (2.7 GB and 5 s of page faults on the survey)
                foot.append((model.shape, _footprint(model, 0.5 * (span[0] + span[1]),
                                                     to_map)))
        if foot and parts.get("gsd"):
            _output_size(foot, parts, toml, c)


def _pos_over_dem(traj, dem, parts, c) -> bool:
    """The trajectory should lie over the DEM; when only swapped lat/lon would, say so."""
    idx = np.linspace(0, traj.lat.size - 1, 25).astype(int)
    lat, lon = traj.lat[idx], _wrap(traj.lon[idx])
    if np.isfinite(dem.height(lat, lon)).any():
        return True
    pos = parts.get("pos")
    src = pos.attrs.get("source", "POS") if pos is not None else "POS"
    for alt, fix in (((lon, lat), "lat and lon look swapped: swap the lat and lon columns"),
                     ((np.degrees(lat), np.degrees(lon)),
                      "lat and lon look like radians: write them in degrees")):
        if np.all(np.abs(alt[0]) <= 90) and np.isfinite(dem.height(*alt)).any():
            c.add(src, "columns lat, lon", f"the flight (lat {lat[0]:.5f}, lon {lon[0]:.5f}) "
                  f"is nowhere over the DEM {dem.path}", fix)
            return False
    return True


def _dem_below(model, dem, traj, lt, iid, c) -> bool:
    """The DEM under the aircraft must be below it."""
    t = np.asarray(lt["time"], float)
    r = traj.interpolate(np.linspace(t[0], t[-1], 16))
    from swathflow.geometry.geodesy import ecef_to_geodetic
    llh = ecef_to_geodetic(r["ecef"])
    under = dem.height(llh[:, 0], llh[:, 1])
    ref = under if np.isfinite(under).any() else np.full(llh.shape[0], dem.h_min)
    bad = ref >= llh[:, 2] - 1.0
    if not bad.any():
        return True
    k = int(np.flatnonzero(bad)[0])
    c.add(dem.path, f"image {iid!r}",
          f"the DEM ({ref[k]:.1f} m) is above the aircraft ({llh[k, 2]:.1f} m ellipsoidal) "
          f"during this image", "check the DEM's heights, units and vertical datum "
          "([terrain].vertical, geoid, undulation), and the POS heights")
    return False


def image_border(shape, n: int = 24) -> np.ndarray:
    """Image coordinates ``(m, 2)`` around an image's outer edge (pixel-centre units)."""
    rows, cols = shape
    li = np.linspace(-0.5, rows - 0.5, n)
    el = np.linspace(-0.5, cols - 0.5, max(n // 4, 3))
    pts = [np.stack([li, np.full_like(li, -0.5)], -1),
           np.stack([li, np.full_like(li, cols - 0.5)], -1),
           np.stack([np.full_like(el, -0.5), el], -1),
           np.stack([np.full_like(el, rows - 0.5), el], -1)]
    return np.concatenate(pts)


def _dem_cover(model, dem, iid: str, c, span=None) -> None:
    """The ground seen by the image's border, at the DEM's lowest and highest heights
    (``span``: ``(dem.h_min, dem.h_max)`` when known), must lie on valid DEM cells."""
    from swathflow.geometry.geodesy import ecef_to_geodetic
    from swathflow.geometry.intersect import intersect
    from swathflow.geometry.terrain import ConstantHeight
    origin, direction = model.ray(image_border(model.shape))
    miss = []
    for h in span or (dem.h_min, dem.h_max):
        llh = ecef_to_geodetic(intersect(origin, direction, ConstantHeight(h)))
        ok = np.isfinite(llh).all(-1)
        hh = np.full(ok.shape, np.nan)
        hh[ok] = dem.height(llh[ok, 0], llh[ok, 1])
        if (~np.isfinite(hh)).any():
            miss.append(llh[~np.isfinite(hh)])
    if miss:
        m = np.concatenate(miss)
        m = m[np.isfinite(m).all(-1)]
        eg = f" e.g. lat {m[0, 0]:.6f}, lon {m[0, 1]:.6f}" if len(m) else ""
        c.add(dem.path, f"image {iid!r}",
              f"the DEM does not cover the ground this image sees ({len(m)} sampled border "
              f"points off the DEM or on nodata{eg})",
              "use a DEM that covers the whole flight area (with a margin), or a constant "
              "[terrain].height")


def _footprint(model, h: float, to_map) -> np.ndarray:
    """Map coordinates (E, N) of the image border on the height ``h`` (the terrain's
    middle height); ``to_map``: the transformer from ECEF to the map CRS."""
    from swathflow.geometry.intersect import intersect
    from swathflow.geometry.terrain import ConstantHeight
    o, d = model.ray(image_border(model.shape, 12))
    g = intersect(o, d, ConstantHeight(h))
    e, n, _ = to_map.transform(g[:, 0], g[:, 1], g[:, 2])
    en = np.stack([e, n], -1)
    return en[np.isfinite(en).all(-1)]


def _output_size(foot, parts, toml, c) -> None:
    """The mosaic grid at ``gsd``: refuse one far beyond memory or one of a few pixels."""
    en = np.concatenate([f for _, f in foot])
    if en.shape[0] < 3:
        return
    w, h = np.ptp(en[:, 0]), np.ptp(en[:, 1])
    gsd = float(parts["gsd"])
    raw = sum(shape[0] * shape[1] for shape, _ in foot)
    area = sum(np.ptp(f[:, 0]) * np.ptp(f[:, 1]) for _, f in foot if len(f) >= 3)
    raw_gsd = float(np.sqrt(area / max(raw, 1)))
    cols, rows = w / gsd, h / gsd
    limit = parts.get("max_pixels", 2e9)
    if cols * rows > limit:
        c.add(toml, "[mission].gsd", f"gsd {gsd:g} m makes the output grid {cols:,.0f} x "
              f"{rows:,.0f} px ({cols * rows:.3g} px, {cols * rows * 4 / 1e9:,.1f} GB as "
              f"float32), above the limit of {limit:.3g} px",
              f"use a gsd near the raw pixels' ground size (about {raw_gsd:.2g} m), or raise "
              f"[mission].max_pixels")
    elif min(cols, rows) < 4:
        c.add(toml, "[mission].gsd", f"gsd {gsd:g} m makes the output grid {max(cols, 1):.0f}"
              f" x {max(rows, 1):.0f} px for a {w:.0f} x {h:.0f} m footprint",
              f"use a gsd near the raw pixels' ground size (about {raw_gsd:.2g} m)")
