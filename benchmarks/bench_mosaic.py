"""Mosaic benchmark: memory versus area, peers side by side, and the paper's job.

    /tmp/venv/bin/python benchmarks/bench_mosaic.py --memory --peers --paper

--memory  mosaics synthetic areas of 1x, 4x and 16x the base area in fresh subprocesses
          and prints each one's peak RSS (the mosaic is streamed tile by tile, so the peak
          should not grow with the area).
--peers   on the 4x area, one run each of: swathflow as the CLI runs it (overlaps matched
          on a local Dask cluster; its RSS is the main process's only), swathflow in one
          process (threads; match + network + feathering + COG), swathflow without
          matching (blending only), gdalbuildvrt + gdal_translate,
          gdalwarp, and rasterio.merge.merge (the last three do no blending); prints time,
          output megapixels per second and the time ratio to swathflow.
--paper   You & Li's job (papers.md section 3): 24 strips of 6 km at 2 m pixels, swath of
          a 30 degree field of view from 650 m (348 m = 174 px), 20 % overlap, about 40 km2,
          strips displaced by 1-5 px; simulated as rectified swings and mosaicked end to end.
          Their figure for rectification plus mosaic on 2000 hardware: about 45 minutes.

Inputs are written by tests/mosaic_synth.py (known truth, one swing at a time). Work files
go to --work (default a temp folder, removed unless --keep).
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(HERE, "..", "tests"))

from mosaic_synth import make_swings, random_shifts  # noqa: E402

SWING_ROWS = 512


def generate(folder, n_strips, length, swath=180, overlap=0.2, seed=1, swing_rows=SWING_ROWS):
    shifts, rads = random_shifts(n_strips, seed=seed)
    n_sw = max(1, int(round(length / swing_rows)))
    t0 = time.perf_counter()
    paths, _, shape = make_swings(folder, n_strips=n_strips, swath=swath, length=length,
                                  overlap=overlap, n_swings=n_sw, swing_overlap=24,
                                  shifts=shifts, rads=rads, drift=3.0, noise=0.5,
                                  footprints=False, seed=seed)
    return dict(paths=paths, shape=shape, shifts=shifts, rads=rads,
                seconds=time.perf_counter() - t0)


_CHILD = r"""
import contextlib, json, sys
from swathflow.cluster import dask_client
from swathflow.mosaicking.mosaic import mosaic
a = json.loads(sys.argv[1])
# as `swathflow mosaic` does: the overlaps are matched on a local Dask cluster
ctx = dask_client() if a.get("cluster") and a.get("match", True) else contextlib.nullcontext()
with ctx:
    rep = mosaic(a["paths"], a["out"], anchors=a.get("anchors", ["0"]),
                 match=a.get("match", True), png=a.get("png", True), workers=a.get("workers"))
print(json.dumps({k: rep[k] for k in ("seconds", "mpx_per_s", "shape")} |
                 {"nodes": rep.get("nodes"), "skipped": len(rep.get("skipped", []))}))
"""


def mosaic_subprocess(paths, out, **opts):
    """swathflow mosaic in a fresh interpreter, measuring its own peak RSS."""
    code = ("import os, resource, runpy, sys\n" + _CHILD +
            "\nprint('RSS', resource.getrusage(resource.RUSAGE_SELF).ru_maxrss)\n")
    arg = json.dumps(dict(paths=paths, out=out, **opts))
    t0 = time.perf_counter()
    p = subprocess.run([sys.executable, "-c", code, arg], capture_output=True, text=True)
    sec = time.perf_counter() - t0
    if p.returncode != 0:
        raise RuntimeError(p.stderr[-3000:])
    lines = p.stdout.strip().splitlines()
    rss = float(lines[-1].split()[1]) / 1024.0
    rep = json.loads(lines[-2])
    return sec, rss, rep


def offset_errors(rep, shifts):
    nodes = {n["node"]: np.array(n["offset"]) for n in rep["nodes"]}
    return np.array([np.hypot(*(nodes[str(k)] - shifts[k])) for k in range(len(shifts))])


def bench_memory(work, base_strips=6, base_rows=1024):
    print("\n== peak memory versus area (fresh subprocess per run) ==")
    print(f"{'area':>5} {'grid (rows x cols)':>20} {'Mpx':>7} {'float32 array MB':>17} "
          f"{'peak RSS MB':>12} {'seconds':>8} {'Mpx/s':>6} {'max offset err px':>18}")
    rows = []
    for f, (ks, kr) in ((1, (1, 1)), (4, (2, 2)), (16, (4, 4))):
        d = os.path.join(work, f"mem{f}")
        g = generate(d, base_strips * ks, base_rows * kr)
        H, W = g["shape"]
        sec, rss, rep = mosaic_subprocess(g["paths"], os.path.join(work, f"mem{f}.tif"))
        err = offset_errors(rep, g["shifts"]).max()
        rows.append((f, H, W, rss, sec))
        print(f"{f:>4}x {H:>9} x {W:<9} {H * W / 1e6:>7.2f} {H * W * 4 / 2**20:>17.1f} "
              f"{rss:>12.1f} {sec:>8.1f} {H * W / 1e6 / sec:>6.2f} {err:>18.3f}", flush=True)
        shutil.rmtree(d, ignore_errors=True)
    return rows


def bench_peers(work, n_strips=12, length=2048):
    print("\n== side by side, same inputs (4x area), one run each ==")
    d = os.path.join(work, "peers")
    g = generate(d, n_strips, length)
    H, W = g["shape"]
    mpx = H * W / 1e6
    paths = g["paths"]
    results = []
    sec, rss, rep = mosaic_subprocess(paths, os.path.join(work, "sf.tif"), cluster=True)
    results.append(("swathflow CLI (local cluster: match+network+feather, COG+PNG)", sec, rss))
    sec1, rss1, _ = mosaic_subprocess(paths, os.path.join(work, "sf1.tif"))
    results.append(("swathflow, one process (threads)", sec1, rss1))
    sec2, rss2, _ = mosaic_subprocess(paths, os.path.join(work, "sf_blend.tif"), match=False,
                                      png=False)
    results.append(("swathflow blend only (feather, COG)", sec2, rss2))
    env = dict(os.environ, GDAL_NUM_THREADS="2")
    if shutil.which("gdalbuildvrt") and shutil.which("gdal_translate"):
        vrt = os.path.join(work, "m.vrt")
        t0 = time.perf_counter()
        subprocess.run(["gdalbuildvrt", "-q", "-srcnodata", "-9999", "-vrtnodata", "-9999",
                        vrt, *paths], check=True, env=env)
        subprocess.run(["gdal_translate", "-q", "-of", "COG", "-co", "COMPRESS=DEFLATE",
                        "-co", "NUM_THREADS=2", vrt, os.path.join(work, "vrt.tif")],
                       check=True, env=env)
        results.append(("gdalbuildvrt + gdal_translate -of COG", time.perf_counter() - t0, None))
    else:
        print("  gdalbuildvrt not found (apt-get install gdal-bin): skipped")
    if shutil.which("gdalwarp"):
        t0 = time.perf_counter()
        subprocess.run(["gdalwarp", "-q", "-overwrite", "-srcnodata", "-9999", "-dstnodata",
                        "-9999", "-multi", "-wo", "NUM_THREADS=2", "-of", "COG", "-co",
                        "COMPRESS=DEFLATE", *paths, os.path.join(work, "warp.tif")],
                       check=True, env=env)
        results.append(("gdalwarp -of COG", time.perf_counter() - t0, None))
    else:
        print("  gdalwarp not found (apt-get install gdal-bin): skipped")
    code = (
        "import sys, json, time, rasterio\nfrom rasterio.merge import merge\n"
        "p = json.loads(sys.argv[1]); t0 = time.perf_counter()\n"
        "arr, tr = merge(p['paths'])\n"
        "with rasterio.open(p['paths'][0]) as s: prof = s.profile\n"
        "prof.update(height=arr.shape[1], width=arr.shape[2], transform=tr, tiled=True, "
        "blockxsize=512, blockysize=512, compress='deflate')\n"
        "with rasterio.open(p['out'], 'w', **prof) as d: d.write(arr)\n"
        "import resource; print(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss)\n")
    t0 = time.perf_counter()
    pr = subprocess.run([sys.executable, "-c", code,
                         json.dumps(dict(paths=paths, out=os.path.join(work, "merge.tif")))],
                        capture_output=True, text=True, check=True)
    results.append(("rasterio.merge.merge (GTiff, in memory)", time.perf_counter() - t0,
                    float(pr.stdout.split()[-1]) / 1024))
    print(f"grid {H} x {W} = {mpx:.2f} Mpx, {len(paths)} swings")
    print(f"{'tool':<62} {'seconds':>8} {'Mpx/s':>7} {'time / swathflow':>17} {'peak RSS MB':>12}")
    for name, s, r in results:
        print(f"{name:<62} {s:>8.2f} {mpx / s:>7.2f} {s / sec:>17.2f} "
              f"{'' if r is None else f'{r:.0f}':>12}")
    shutil.rmtree(d, ignore_errors=True)
    return results


def bench_paper(work):
    print("\n== the paper's job: 24 strips x 6 km, 2 m pixels, 30 deg FOV from 650 m ==")
    swath_m = 2 * 650 * np.tan(np.radians(15))
    swath = int(round(swath_m / 2.0))
    n, length = 24, 3000
    d = os.path.join(work, "paper")
    g = generate(d, n, length, swath=swath, overlap=0.2, swing_rows=500)
    H, W = g["shape"]
    km2 = H * W * 4 / 1e6
    print(f"swath {swath_m:.0f} m = {swath} px, grid {H} x {W} px = {km2:.1f} km2, "
          f"{len(g['paths'])} swings (simulation {g['seconds']:.0f} s)")
    sec, rss, rep = mosaic_subprocess(g["paths"], os.path.join(work, "paper.tif"))
    err = offset_errors(rep, g["shifts"])
    print(f"mosaic end to end (match {len(g['paths'])} swings, network, feather, COG, PNG): "
          f"{sec:.1f} s ({sec / 60:.2f} min) vs about 45 min in 2000; peak RSS {rss:.0f} MB; "
          f"strip offsets recovered to {err.max():.3f} px (max), {np.median(err):.3f} px "
          f"(median); {rep['skipped']} overlaps skipped")
    shutil.rmtree(d, ignore_errors=True)
    return sec


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--memory", action="store_true")
    ap.add_argument("--peers", action="store_true")
    ap.add_argument("--paper", action="store_true")
    ap.add_argument("--work", help="work folder (default: a temp folder)")
    ap.add_argument("--keep", action="store_true", help="keep the work folder")
    a = ap.parse_args(argv)
    if not (a.memory or a.peers or a.paper):
        a.memory = a.peers = a.paper = True
    work = a.work or tempfile.mkdtemp(prefix="swathflow-bench-mosaic-")
    os.makedirs(work, exist_ok=True)
    print(f"swathflow mosaic benchmark, {os.cpu_count()} cores, work folder {work}")
    print("reproduce: /tmp/venv/bin/python benchmarks/bench_mosaic.py "
          + " ".join(f"--{k}" for k in ("memory", "peers", "paper") if getattr(a, k)))
    try:
        if a.memory:
            bench_memory(work)
        if a.peers:
            bench_peers(work)
        if a.paper:
            bench_paper(work)
    finally:
        if not a.keep and not a.work:
            shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
