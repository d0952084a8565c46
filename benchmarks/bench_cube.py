"""Cube benchmark: a uint16 hyperspectral cube (ENVI BSQ, BIL and BIP files of the same
data), bilinear, rectified by swathflow (lattice, window read, resampling of every band:
the whole engine, one thread) side by side with ``rasterio.warp.reproject`` given the
geolocation arrays for free (fewer bands for the peer; figures are per band), on an output
grid at about the raw resolution and on one 5x finer.

    .venv/bin/python benchmarks/bench_cube.py                      # 100 bands, 1200 x 256
    .venv/bin/python benchmarks/bench_cube.py --bands 100 --peer-bands 8 --ratios 1,5

Prints output Mpx x bands per CPU second (``time.process_time``; the fair per-core figure on
a shared machine) and per wall second, for each interleave and the peer, and their ratio.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))
sys.path.insert(0, str(ROOT / "benchmarks"))

LAYOUTS = {"bsq": (0, 1, 2), "bil": (1, 0, 2), "bip": (1, 2, 0)}


def make_cube(bands, lines, elements):
    """Each band its own smooth pattern (uint16)."""
    b, li, ei = np.ogrid[0:bands, 0:lines, 0:elements]
    return (2000 + 7 * b + 300 * np.sin(li / 9.0 + b / 17.0) * np.cos(ei / 7.0)).astype(np.uint16)


def write_envi(path: Path, cube, layout):
    np.ascontiguousarray(cube.transpose(LAYOUTS[layout])).tofile(path)
    nb, nl, ne = cube.shape
    Path(str(path) + ".hdr").write_text(
        f"ENVI\nsamples = {ne}\nlines = {nl}\nbands = {nb}\nheader offset = 0\n"
        f"data type = 12\ninterleave = {layout}\nbyte order = 0\n")


def ours(model, path, grid, terrain, repeat, keep=8):
    """Rectify tile by tile, each tile computed and dropped as the COG writer streams
    them (no whole-image concatenation in the timing); then, untimed, the first ``keep``
    bands for the checks."""
    import dask
    from swathflow.rectification import tiles as T
    from swathflow.rectification.rawimage import open_raw_image
    img = open_raw_image(path)
    best = None
    with dask.config.set(scheduler="sync"):
        for _ in range(repeat):
            c0, t0 = time.process_time(), time.perf_counter()
            arr = T.rectify(model, img, grid, terrain, tile=512)
            for d in arr.to_delayed().ravel():
                d.compute()
            run = (time.perf_counter() - t0, time.process_time() - c0)
            best = run if best is None or run[1] < best[1] else best
        out = arr[:keep].compute()
    return out, best


def ours_cog(model, path, grid, terrain, out):
    """The whole engine and the COG writer (tiles compressed once by GDAL as they stream,
    our overviews, the COG layout copied by tifflayout; deflate), one thread: (wall s,
    CPU s)."""
    import dask
    from swathflow.rectification import tiles as T
    from swathflow.rectification.rawimage import open_raw_image
    from swathflow.rectification.writing import write_cogs
    img = open_raw_image(path)
    with dask.config.set(scheduler="sync"):
        c0, t0 = time.process_time(), time.perf_counter()
        write_cogs([{"path": out, "array": T.rectify(model, img, grid, terrain, tile=512),
                     "grid": grid, "nodata": 0}], blocksize=512, scheduler="sync")
        return time.perf_counter() - t0, time.process_time() - c0


def peer(cube, X, Y, grid, repeat):
    from rasterio.crs import CRS
    from rasterio.warp import Resampling, reproject
    crs = CRS.from_wkt(grid.pyproj_crs.to_wkt())
    best = None
    for _ in range(repeat):
        dst = np.zeros((cube.shape[0],) + grid.shape, np.uint16)
        c0, t0 = time.process_time(), time.perf_counter()
        reproject(cube, dst, src_geoloc_array=np.stack([X, Y]), src_crs=crs,
                  dst_transform=grid.transform, dst_crs=crs, dst_nodata=0,
                  resampling=Resampling.bilinear, num_threads=1)
        run = (time.perf_counter() - t0, time.process_time() - c0)
        best = run if best is None or run[1] < best[1] else best
    return dst, best


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--bands", type=int, default=100)
    ap.add_argument("--peer-bands", type=int, default=8)
    ap.add_argument("--lines", type=int, default=1200)
    ap.add_argument("--elements", type=int, default=256)
    ap.add_argument("--ratios", default="1,5", help="output/raw pixel-count ratios")
    ap.add_argument("--repeat", type=int, default=2, help="runs per figure, best CPU kept")
    ap.add_argument("--cog", action="store_true",
                    help="also time the engine with the COG writer (BSQ file, one run)")
    ap.add_argument("--memory", action="store_true",
                    help="peak RSS of 'swathflow rectify' on a --bands x --memory-lines x "
                         "2048 uint16 ENVI BIL swing (20,000 lines: 8 GB on disk)")
    ap.add_argument("--memory-lines", type=int, default=20000)
    ap.add_argument("--memory-gsd", type=float, default=1.0)
    ap.add_argument("--memory-mission", help="reuse a mission written by an earlier run")
    args = ap.parse_args(argv)
    if args.memory:
        r = memory_run(args.memory_lines, 2048, args.bands, args.memory_gsd,
                       mission=args.memory_mission)
        print(json.dumps(r))
        print(f"{r['raw'][0]} x {r['raw'][1]} x {r['raw'][2]} uint16 BIL swing "
              f"({r['raw_gb']} GB): 'swathflow rectify' peak RSS {r['peak_rss_mb']} MB "
              f"(bound 2048), {r['wall_s']} s wall, {r['cpu_s']} CPU-s, output "
              f"{r['grid'][0]} x {r['grid'][1]} ({r['out_gb']} GB COG); bands "
              f"{r['checked_bands']} at {r['checked_px']} pixels: worst {r['max_err_dn']} DN "
              f"from the pattern")
        print("reproduce: .venv/bin/python benchmarks/bench_cube.py " + " ".join(sys.argv[1:]))
        return 0
    from bench_rectify import geoloc_arrays
    from test_rectify import scene_model

    from swathflow.geometry.grid import footprint_grid
    from swathflow.geometry.terrain import ConstantHeight
    nb, nl, ne = args.bands, args.lines, args.elements
    model = scene_model(n_lines=nl, n_elements=ne, swing=15.0, pixel_pitch=30e-6)
    terrain = ConstantHeight(5.0)
    cube = make_cube(nb, nl, ne)
    g0 = footprint_grid(model, terrain, 1.0)
    rows = []
    with tempfile.TemporaryDirectory() as td:
        paths = {}
        for lay in LAYOUTS:
            paths[lay] = Path(td) / f"cube.{lay}"
            write_envi(paths[lay], cube, lay)
        small = footprint_grid(model, terrain, 8.0)
        for lay in LAYOUTS:                                     # compile / warm caches
            ours(model, paths[lay], small, terrain, 1)
        for ratio in [float(r) for r in args.ratios.split(",") if r.strip()]:
            gsd = math.sqrt(g0.shape[0] * g0.shape[1] / (ratio * nl * ne))
            grid = footprint_grid(model, terrain, gsd)
            mpx = grid.shape[0] * grid.shape[1] / 1e6
            res = {}
            for lay in LAYOUTS:
                out, (wall, cpu) = ours(model, paths[lay], grid, terrain, args.repeat,
                                        args.peer_bands)
                res[lay] = out
                rows.append((ratio, grid.shape, f"swathflow, ENVI {lay.upper()}", nb, wall, cpu,
                             mpx * nb))
            if args.cog:
                wall, cpu = ours_cog(model, paths["bsq"], grid, terrain, Path(td) / "o.tif")
                rows.append((ratio, grid.shape, "swathflow + COG writer, ENVI BSQ", nb, wall,
                             cpu, mpx * nb))
            X, Y = geoloc_arrays(model, terrain, grid.pyproj_crs)
            pb = min(args.peer_bands, nb)
            pd, (wall, cpu) = peer(cube[:pb], X, Y, grid, args.repeat)
            rows.append((ratio, grid.shape, "rasterio.warp.reproject (geoloc)", pb, wall, cpu,
                         mpx * pb))
            both = (res["bsq"][:pb] > 0) & (pd > 0)
            diff = np.abs(res["bsq"][:pb].astype(int) - pd.astype(int))[both]
            same = all((res[k] == res["bsq"]).all() for k in LAYOUTS)
            rows.append((ratio, grid.shape, f"check: BSQ = BIL = BIP {same}; |ours - peer| "
                         f"median {np.median(diff):.1f} DN, p99 {np.percentile(diff, 99):.1f}",
                         0, 0, 0, 0))
    print(f"cube benchmark: {nb} bands uint16, raw {nl} x {ne}, bilinear, one thread")
    print(f"  {'out/raw':>7} {'grid':>11} {'method':<36} {'bands':>5} {'wall s':>7} "
          f"{'CPU s':>6} {'Mpx x bands / CPU-s':>20} {'/ wall-s':>9}")
    peer_rate = {}
    for ratio, shape, name, b, wall, cpu, work in rows:
        if not b:
            print(f"  {'':>7} {'':>11} {name}")
            continue
        rate = work / cpu
        if name.startswith("rasterio"):
            peer_rate[ratio] = rate
        print(f"  {ratio:7g} {shape[0]:5d}x{shape[1]:<5d} {name:<36} {b:5d} {wall:7.3f} "
              f"{cpu:6.3f} {rate:20.1f} {work / wall:9.1f}")
    for ratio, _shape, name, b, _wall, cpu, work in rows:
        if b and not name.startswith("rasterio"):
            print(f"  ratio to the peer at {ratio:g}x, {name}: "
                  f"{work / cpu / peer_rate[ratio]:.1f}x")
    print(json.dumps({"bands": nb, "raw": [nl, ne]}))
    print("reproduce: .venv/bin/python benchmarks/bench_cube.py " + " ".join(sys.argv[1:]))
    return 0



# ----------------------------------------------------------------------------------------
# peak memory of 'swathflow rectify' on a 2,048 x 20,000 x 100-band uint16 ENVI BIL swing
# ----------------------------------------------------------------------------------------
def pattern(b, li, ei):
    """The swing's known pattern: band b is a plane in (line, element), its own per band."""
    return 100.0 * b + 2.0 * ei + li / 8.0


def write_bil_swing(path: Path, lines: int, elements: int, bands: int, block: int = 128):
    """Write the pattern as an ENVI BIL file block by block (never the whole cube in
    memory) with its header."""
    b = np.arange(bands)[None, :, None]
    e = np.arange(elements)[None, None, :]
    with open(path, "wb") as f:
        for l0 in range(0, lines, block):
            li = np.arange(l0, min(l0 + block, lines))[:, None, None]
            f.write(np.round(pattern(b, li, e)).astype("<u2").tobytes())
    Path(str(path) + ".hdr").write_text(
        f"ENVI\nsamples = {elements}\nlines = {lines}\nbands = {bands}\nheader offset = 0\n"
        f"data type = 12\ninterleave = bil\nbyte order = 0\n")


def prepare_swing(td: Path, lines=20000, elements=2048, bands=100, gsd=1.0):
    """Simulate a one-swing geometry (the paper preset's sensor with ``elements`` elements
    and a swing of ``lines`` lines) in ``td/mission`` and write swing L1 as a ``bands``-band
    uint16 ENVI BIL; returns (mission folder, lines, seconds spent writing)."""
    from swathflow.ingest.mission import load_mission
    from swathflow.sensors.pendulum.simulate import preset_config, simulate
    ifov = preset_config("paper").ifov
    swing = math.degrees((lines - 1) * ifov) / 2
    m = Path(td) / "mission"
    simulate(m, preset="paper", seed=0, n_elements=elements, swing_max=swing,
             render=False, write_ortho=False, gsd=gsd, gcp_plan={}, gcp_other=(2, 3))
    mission = load_mission(m)
    nl = mission.model("L1").shape[0]
    t0 = time.perf_counter()
    write_bil_swing(m / "images" / "L1.bil", nl, elements, bands)
    t_write = time.perf_counter() - t0
    old = mission.images["L1"].file.name
    toml = m / "mission.toml"
    toml.write_text(toml.read_text().replace(f'"images/{old}"', '"images/L1.bil"'))
    (m / "images" / old).unlink()
    return m, nl, t_write


def measure_swing(m: Path, out: Path, check_bands=(0, 49, 99)) -> dict:
    """``swathflow rectify`` of swing L1 under ``/usr/bin/time -v``: peak RSS, times, and
    some bands' pixels against the pattern at the true model's raw coordinates."""
    import re
    import subprocess

    import rasterio
    from swathflow.geometry.grid import Grid
    from swathflow.ingest.mission import load_mission
    cmd = ["/usr/bin/time", "-v", str(Path(sys.executable).parent / "swathflow"),
           "rectify", "-q", str(m), "--out", str(out), "--images", "L1"]
    t0 = time.perf_counter()
    p = subprocess.run(cmd, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    if p.returncode:
        raise RuntimeError(p.stderr[-3000:])
    rss = int(re.search(r"Maximum resident set size \(kbytes\): (\d+)", p.stderr).group(1))
    cpu = sum(float(re.search(rf"{k} time \(seconds\): ([\d.]+)", p.stderr).group(1))
              for k in ("User", "System"))
    mission = load_mission(m)
    model = mission.model("L1")
    nl, ne = model.shape
    rng = np.random.default_rng(0)
    with rasterio.open(out / "L1.tif") as src:
        bands = src.count
        assert src.dtypes[0] == "uint16"
        grid = Grid(mission.crs, src.transform, (src.height, src.width))
        rows = rng.integers(0, src.height, 4000)
        cols = rng.integers(0, src.width, 4000)
        vals = np.stack([src.read(b + 1)[rows, cols] for b in check_bands]).astype(float)
        shape, size = (src.height, src.width), os.path.getsize(out / "L1.tif")
    x, y = grid.xy(rows, cols)
    ij = model.ground_to_image(grid.to_ecef(x, y, mission.terrain))
    inside = (np.isfinite(ij).all(-1) & (ij[:, 0] >= 0) & (ij[:, 0] <= nl - 1)
              & (ij[:, 1] >= 0) & (ij[:, 1] <= ne - 1))
    want = np.stack([pattern(b, ij[inside, 0], ij[inside, 1]) for b in check_bands])
    err = np.abs(vals[:, inside] - want)
    return {"raw": [bands, nl, ne], "raw_gb": round(bands * nl * ne * 2 / 1e9, 2),
            "grid": list(shape), "out_gb": round(size / 1e9, 2), "wall_s": round(wall, 1),
            "cpu_s": round(cpu, 1), "peak_rss_mb": round(rss / 1024),
            "checked_px": int(inside.sum()), "checked_bands": [b + 1 for b in check_bands],
            "max_err_dn": round(float(err.max()), 3),
            "median_err_dn": round(float(np.median(err)), 3)}


def memory_run(lines=20000, elements=2048, bands=100, gsd=1.0, workdir=None,
               mission=None) -> dict:
    """:func:`prepare_swing` (or an existing ``mission`` folder) then :func:`measure_swing`;
    everything written is deleted afterwards."""
    with tempfile.TemporaryDirectory(dir=workdir) as td:
        t_write = None
        if mission is None:
            mission, _, t_write = prepare_swing(Path(td), lines, elements, bands, gsd)
        r = measure_swing(Path(mission), Path(td) / "out")
    r.update(write_s=round(t_write, 1) if t_write else None, gsd=gsd)
    return r


if __name__ == "__main__":
    sys.exit(main())
