"""The regional case: a simulated mosaic of about ``gpx`` gigapixels mosaicked end to end
(match + network + feather + COG) in one fresh process (its wall time and peak RSS), then
the same area cut into four quarter runs (each with the swings that reach its quarter, the
whole run's offsets) compared with the whole, pixel for pixel, tile by tile.

    python benchmarks/bench_mosaic.py --regional 1.0

Swings: 2000 px wide strips (20 % side overlap) cut into 2048-row swings, uint16, a cheap
two-octave procedural texture (tests/mosaic_synth.value_noise), strips displaced by 1-5 px.
"""
from __future__ import annotations

import json
import math
import os
import shutil
import subprocess
import sys
import time

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "tests"))

from mosaic_synth import random_shifts, value_noise  # noqa: E402

SWATH = 2000
ROWS = 2048


def cheap_texture(r, c, seed: int = 0):
    """The regional truth: two octaves of value noise (tests/mosaic_synth.value_noise),
    compiled (numba) when available: a gigapixel costs seconds, not minutes."""
    try:
        return _fast_texture(np.ascontiguousarray(r, float), np.ascontiguousarray(c, float),
                             seed)
    except ImportError:
        return (400.0 + 300.0 * value_noise(r, c, 11, seed)
                + 150.0 * value_noise(r, c, 4, seed + 1))


_KERNEL = []


def _fast_texture(r, c, seed):
    if not _KERNEL:
        _KERNEL.append(_compile())
    out = np.empty(r.shape)
    _KERNEL[0][0](r.ravel(), c.ravel(), seed, out.ravel())
    return out


def _compile():
    """tests/mosaic_synth.value_noise (hash and quintic fade) as one compiled loop."""
    from numba import njit, prange

    @njit(inline="always")
    def hsh(ix, iy, seed):
        m = np.uint64(0xFFFFFFFF)
        h = (np.uint64(ix) * np.uint64(0x9E3779B1) + np.uint64(iy) * np.uint64(0x85EBCA77)
             + np.uint64((seed * 0xC2B2AE3D + 12345) & 0xFFFFFFFF)) & m
        h ^= h >> np.uint64(15)
        h = (h * np.uint64(0x2C1B3C6D)) & m
        h ^= h >> np.uint64(12)
        h = (h * np.uint64(0x297A2D39)) & m
        h ^= h >> np.uint64(15)
        return np.float64(h) / 4294967296.0

    @njit(inline="always")
    def noise(r, c, scale, seed):
        u, v = r / scale, c / scale
        i, j = np.floor(u), np.floor(v)
        a, b = u - i, v - j
        a = a * a * a * (a * (a * 6 - 15) + 10)
        b = b * b * b * (b * (b * 6 - 15) + 10)
        ii, jj = np.int64(i) + 1_000_000, np.int64(j) + 1_000_000
        return (hsh(ii, jj, seed) * (1 - a) * (1 - b) + hsh(ii + 1, jj, seed) * a * (1 - b)
                + hsh(ii, jj + 1, seed) * (1 - a) * b + hsh(ii + 1, jj + 1, seed) * a * b)

    @njit(parallel=True)
    def kern(r, c, seed, out):
        for k in prange(r.size):
            out[k] = (400.0 + 300.0 * noise(r[k], c[k], 11.0, seed)
                      + 150.0 * noise(r[k], c[k], 4.0, seed + 1))

    @njit(parallel=True)
    def tex(r, c, seed, out):
        for k in prange(r.size):
            v = 100.0
            for q, (sc, amp) in enumerate(((96.0, 40.0), (48.0, 30.0), (24.0, 20.0),
                                           (12.0, 14.0), (6.0, 10.0), (4.0, 5.0))):
                v += amp * noise(r[k], c[k], sc, seed + q)
            out[k] = v + 30 * np.tanh((noise(r[k], c[k], 40.0, seed + 99) - 0.5) * 25)

    @njit(parallel=True)
    def swing(r0, r1, c0, c1, k, step, swath, t0, t1, b, sigma, seed, out):
        """One uint16 swing of tests/mosaic_synth.make_swings (its footprint, shift,
        radiometric offset and noise; no drift) with the texture above."""
        for i in prange(r1 - r0):
            rr = float(r0 + i)
            np.random.seed(seed * 100003 + i)
            left = k * step + 4 + 3.0 * np.sin(2 * np.pi * rr / 170 + k)
            right = k * step + swath + 3.0 * np.sin(2 * np.pi * rr / 130 + 2 * k)
            for j in range(c1 - c0):
                cc = float(c0 + j)
                if cc < left or cc >= right:
                    out[i, j] = 0
                    continue
                v = (400.0 + 300.0 * noise(rr - t0, cc - t1, 11.0, 0)
                     + 150.0 * noise(rr - t0, cc - t1, 4.0, 1) + b
                     + sigma * np.random.standard_normal())
                out[i, j] = min(max(np.round(v), 1.0), 65535.0)
    return kern, swing, tex


def fast_texture(r, c, seed: int = 0):
    """tests/mosaic_synth.texture compiled (the benchmarks' truth; same values to 1e-12)."""
    if not _KERNEL:
        _KERNEL.append(_compile())
    r = np.ascontiguousarray(np.broadcast_to(r, np.broadcast(r, c).shape), float)
    c = np.ascontiguousarray(np.broadcast_to(c, r.shape), float)
    out = np.empty(r.shape)
    _KERNEL[0][2](r.ravel(), c.ravel(), seed, out.ravel())
    return out


def regional_swings(folder, n_strips, swath, length, overlap, n_swings, swing_overlap,
                    shifts, rads, noise=2.0):
    """tests/mosaic_synth.make_swings (uint16, no drift, uncompressed files) with the
    compiled texture: the same geometry, a gigapixel in minutes."""
    from affine import Affine
    from mosaic_synth import CRS, X0, Y0, grid_shape
    from swathflow.formats.raster import write_geotiff
    if not _KERNEL:
        _KERNEL.append(_compile())
    swing = _KERNEL[0][1]
    os.makedirs(folder, exist_ok=True)
    step = int(round(swath * (1 - overlap)))
    H, W = grid_shape(n_strips, swath, length, overlap)
    seg = (length + (n_swings - 1) * swing_overlap) // n_swings
    paths = []
    for k in range(n_strips):
        for s in range(n_swings):
            r0 = s * (seg - swing_overlap)
            r1 = H if s == n_swings - 1 else min(H, r0 + seg)
            c0, c1 = k * step, min(W, k * step + swath + 8)
            arr = np.empty((r1 - r0, c1 - c0), np.uint16)
            swing(r0, r1, c0, c1, k, step, swath, float(shifts[k][0]), float(shifts[k][1]),
                  float(rads[k]), noise, k * 1000 + s, arr)
            p = os.path.join(folder, f"s{k:03d}_{s:03d}.tif")
            write_geotiff(p, arr, CRS, Affine(2.0, 0, X0 + c0 * 2.0, 0, -2.0, Y0 - r0 * 2.0),
                          nodata=0, compress="none", tags={"image_id": f"S{k}_{s}",
                                                           "strip": k})
            paths.append(p)
    return paths, (H, W)


_RUN = r"""
import json, sys, time
import numpy as np
from swathflow.mosaicking import mosaic as M
a = json.loads(sys.argv[1])
t0 = time.perf_counter()
if a["mode"] == "whole":
    rep = M.mosaic(a["paths"], a["out"], anchors=["0"], workers=a["workers"], png=False)
    lay = M.scan_inputs(a["paths"])
    node = {n["node"]: n for n in rep["nodes"]}
    off = [node[str(s.strip)]["offset"] for s in lay.swings]
    rad = [node[str(s.strip)]["radiometric"] for s in lay.swings]
    extra = {"offsets": off, "rad": rad, "nodes": rep["nodes"],
             "seconds_match": rep["seconds_match"], "seconds_render": rep["seconds_render"]}
else:
    lay = M.scan_inputs(a["paths"])
    M.write_mosaic(lay, a["out"], np.array(a["offsets"]), np.array(a["rad"]),
                   workers=a["workers"], cog=False)
    extra = {}
# VmHWM: this process's own peak (ru_maxrss would keep the parent's across exec)
hwm = [ln for ln in open("/proc/self/status") if ln.startswith("VmHWM")][0].split()[1]
print(json.dumps({"seconds": time.perf_counter() - t0, "rss_mb": int(hwm) / 1024} | extra))
"""


def _run(args: dict) -> dict:
    return _run_many([args])[0]


def _run_many(many: list) -> list:
    """Separate processes, all at once; each reports its wall time and peak RSS."""
    procs = [subprocess.Popen([sys.executable, "-c", _RUN, json.dumps(a)],
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
             for a in many]
    out = []
    for p in procs:
        so, se = p.communicate()
        if p.returncode != 0:
            raise RuntimeError(se[-3000:])
        out.append(json.loads(so.strip().splitlines()[-1]))
    return out


def _same_pixels(whole, part, r0, c0, r1, c1, tile: int = 4096) -> bool:
    import rasterio
    from rasterio.windows import Window
    with rasterio.open(whole) as a, rasterio.open(part) as b:
        ta, tb = a.transform, b.transform
        dr = int(round((ta.f - tb.f) / tb.e))
        dc = int(round((ta.c - tb.c) / tb.a))
        for r in range(r0, r1, tile):
            for c in range(c0, c1, tile):
                h, w = min(tile, r1 - r), min(tile, c1 - c)
                x = a.read(1, window=Window(c, r, w, h))
                y = b.read(1, window=Window(c + dc, r + dr, w, h))
                if not np.array_equal(x, y):
                    return False
    return True


def bench_regional(work, gpx: float = 1.0, workers: int = 2, at_once: int = 1):
    """``at_once``: quarter runs started together (separate processes, ``workers //
    at_once`` threads each)."""
    side = math.sqrt(gpx * 1e9)
    n_strips = max(2, int(round(side / (SWATH * 0.8))))
    length = int(math.ceil(side / ROWS)) * ROWS
    print(f"\n== regional case: about {gpx:g} Gpx ({n_strips} strips of {SWATH} px x "
          f"{length} rows) ==")
    d = os.path.join(work, "regional")
    shifts, rads = random_shifts(n_strips, seed=3)
    t0 = time.perf_counter()
    done = os.path.join(d, "swings.json")
    if os.path.exists(done):        # a kept work folder (--work): the swings are there
        with open(done) as f:
            paths, (H, W) = (lambda j: (j["paths"], j["shape"]))(json.load(f))
    else:
        paths, (H, W) = regional_swings(d, n_strips, SWATH, length, 0.2, length // ROWS, 32,
                                        shifts, rads)
        with open(done, "w") as f:
            json.dump({"paths": paths, "shape": [H, W]}, f)
    print(f"simulated {len(paths)} swings, grid {H} x {W} = {H * W / 1e9:.3f} Gpx in "
          f"{time.perf_counter() - t0:.0f} s", flush=True)
    whole = os.path.join(work, "regional.tif")
    kept = os.path.join(work, "regional.result.json")
    if os.path.exists(kept) and os.path.exists(whole):     # --work: the whole run is done
        with open(kept) as f:
            r = json.load(f)
        print("(whole run reused from the work folder)")
    else:
        r = _run({"mode": "whole", "paths": paths, "out": whole, "workers": workers})
        with open(kept, "w") as f:
            json.dump(r, f)
    off = np.array(r["offsets"])
    err = np.array([np.hypot(*(np.array(n["offset"]) - shifts[int(n["node"])]))
                    for n in r["nodes"]])
    print(f"whole run (match + network + feather + COG, {workers} threads): "
          f"{r['seconds']:.0f} s (match {r['seconds_match']:.0f} s, render "
          f"{r['seconds_render']:.0f} s), {H * W / 1e6 / r['seconds']:.1f} Mpx/s, peak RSS "
          f"{r['rss_mb']:.0f} MB; strip offsets to {err.max():.3f} px (max)", flush=True)
    from swathflow.mosaicking.inputs import scan_inputs
    lay = scan_inputs(paths)
    same, worst_rss = True, 0.0
    jobs, boxes = [], []
    for q, (r0, c0) in enumerate([(0, 0), (0, W // 2), (H // 2, 0), (H // 2, W // 2)]):
        r1, c1 = min(H, r0 + H // 2 + H % 2), min(W, c0 + W // 2 + W % 2)
        sel = [k for k, s in enumerate(lay.swings) if s.row - 16 < r1 and s.row + s.height
               + 16 > r0 and s.col - 16 < c1 and s.col + s.width + 16 > c0]
        part = os.path.join(work, f"regional-q{q}.tif")
        jobs.append({"mode": "part", "paths": [paths[k] for k in sel], "out": part,
                     "workers": max(1, workers // at_once), "offsets": off[sel].tolist(),
                     "rad": np.array(r["rad"])[sel].tolist()})
        boxes.append((part, r0, c0, r1, c1, len(sel)))
    results = []
    for k in range(0, 4, at_once):          # ``at_once`` separate processes at a time
        results += _run_many(jobs[k:k + at_once])
    for q, (rq, (part, r0, c0, r1, c1, n)) in enumerate(zip(results, boxes)):
        worst_rss = max(worst_rss, rq["rss_mb"])
        ok = _same_pixels(whole, part, r0, c0, r1, c1)
        same &= ok
        print(f"  quarter {q}: {n} swings, {rq['seconds']:.0f} s, peak RSS "
              f"{rq['rss_mb']:.0f} MB, same pixels as the whole: {ok}", flush=True)
        os.remove(part)
    print(f"four quarter runs give the same pixels as the whole: {same}; peak RSS per "
          f"process {max(worst_rss, r['rss_mb']):.0f} MB")
    shutil.rmtree(d, ignore_errors=True)
    return r, same


if __name__ == "__main__":
    sys.exit("bench_regional.py is the regional case of bench_mosaic.py; run it as\n"
             "    python benchmarks/bench_mosaic.py --regional 1.0 [--work DIR] "
             "[--quarters-at-once N]")
