"""Which library writes swathflow's COGs: GDAL's COG driver (through rasterio), rio-cogeo or
odc-geo's COG writer, on a uint16 cube streamed from a dask array (the shape of a rectified
hyperspectral swing). Each writer runs in its own process under ``/usr/bin/time -v``: wall
time and peak RSS; then the output's pixels are checked against the source and the file
against ``rio cogeo validate``.

    .venv/bin/python benchmarks/bench_codec.py                        # 100 x 1400 x 1354
    .venv/bin/python benchmarks/bench_codec.py --bands 100 --rows 4096 --cols 2048 --runs 3

Writers (all DEFLATE level 1 with the horizontal predictor, 512-px tiles, average
overviews, nodata 0):

- ``gdal-cog``: the blocks stored (``dask.array.store``) into a band-interleaved tiled
  GTiff beside the target, then ``rasterio.shutil.copy(..., driver="COG")``: the COG
  driver builds the overviews;
- ``gdal-cog-pixel``: the same with a pixel-interleaved GTiff;
- ``gdal-ovr``: the band-interleaved GTiff given GDAL's overviews first
  (``build_overviews``), copied by the COG driver with ``OVERVIEWS=FORCE_USE_EXISTING``
  (what :mod:`swathflow.rectification.writing` does);
- ``rio-cogeo``: ``rio_cogeo.cog_translate`` of the band-interleaved GTiff;
- ``odc-geo``: ``odc.geo.cog.save_cog_with_dask`` of the dask array (no GTiff between).
"""
from __future__ import annotations

import argparse
import json
import os
import re
import statistics
import subprocess
import sys
import tempfile
import time

WRITERS = ("gdal-cog", "gdal-cog-pixel", "gdal-ovr", "rio-cogeo", "odc-geo")
BLOCK = 512


def cube(bands, rows, cols):
    """A lazy uint16 cube with a smooth pattern per band and a nodata (0) corner."""
    import dask.array as da
    import numpy as np

    def block(block_info=None):
        (b0, b1), (r0, r1), (c0, c1) = block_info[None]["array-location"]
        b, r, c = np.ogrid[b0:b1, r0:r1, c0:c1]
        v = (2000 + 7 * b + 300 * np.sin(r / 9.0 + b / 17.0) * np.cos(c / 7.0)).astype(np.uint16)
        v[:, r[0, :, 0] < rows // 8, :] = 0
        return v
    return da.map_blocks(block, dtype=np.uint16, chunks=((bands,), _chunks(rows),
                                                         _chunks(cols)))


def _chunks(n):
    return tuple(min(BLOCK, n - i) for i in range(0, n, BLOCK))


def _part(arr, path, interleave):
    import dask.array as da
    import rasterio
    from rasterio.transform import from_origin
    nb, h, w = arr.shape
    with rasterio.open(path, "w", driver="GTiff", width=w, height=h, count=nb,
                       dtype="uint16", nodata=0, tiled=True, blockxsize=BLOCK,
                       blockysize=BLOCK, interleave=interleave, crs="EPSG:32633",
                       transform=from_origin(500000, 6000000, 1, 1)) as dst:
        da.store(arr, _Target(dst), lock=True, scheduler="threads")


class _Target:
    def __init__(self, dst):
        self.dst = dst

    def __setitem__(self, key, value):
        from rasterio.windows import Window
        _, rs, cs = key
        self.dst.write(value, window=Window(cs.start, rs.start, cs.stop - cs.start,
                                            rs.stop - rs.start))


COG = dict(driver="COG", COMPRESS="DEFLATE", LEVEL=1, PREDICTOR="YES", BLOCKSIZE=BLOCK,
           OVERVIEW_RESAMPLING="AVERAGE", BIGTIFF="IF_SAFER", NUM_THREADS="ALL_CPUS")


def write(name, bands, rows, cols, out):
    """One writer's COG of the cube at ``out``."""
    import rasterio
    from rasterio.shutil import copy
    arr = cube(bands, rows, cols)
    part = out + ".part.tif"
    with rasterio.Env(GDAL_CACHEMAX=256):
        if name in ("gdal-cog", "gdal-cog-pixel"):
            _part(arr, part, "pixel" if name.endswith("pixel") else "band")
            copy(part, out, **COG)
        elif name == "gdal-ovr":
            from rasterio.enums import Resampling
            _part(arr, part, "band")
            with rasterio.open(part, "r+") as ds:
                f, levels = 1, []
                while max(rows // f, cols // f) > BLOCK:
                    f *= 2
                    levels.append(f)
                ds.build_overviews(levels, Resampling.average)
            copy(part, out, OVERVIEWS="FORCE_USE_EXISTING", **COG)
        elif name == "rio-cogeo":
            from rio_cogeo.cogeo import cog_translate
            from rio_cogeo.profiles import cog_profiles
            _part(arr, part, "band")
            profile = cog_profiles.get("deflate")
            profile.update(blockxsize=BLOCK, blockysize=BLOCK, predictor=2, zlevel=1)
            cog_translate(part, out, profile, overview_resampling="average", quiet=True,
                          in_memory=False, config={"GDAL_NUM_THREADS": "ALL_CPUS"})
        elif name == "odc-geo":
            import xarray as xr
            from odc.geo.cog import save_cog_with_dask
            from odc.geo.xr import xr_coords  # noqa: F401  (registers .odc)
            from odc.geo.geobox import GeoBox
            from affine import Affine
            gbox = GeoBox((rows, cols), Affine(1, 0, 500000, 0, -1, 6000000), "EPSG:32633")
            xx = xr.DataArray(arr, dims=("band", "y", "x"),
                              coords={"band": range(1, bands + 1), **xr_coords(gbox)},
                              attrs={"nodata": 0})
            save_cog_with_dask(xx, out, compression="DEFLATE", level=1, predictor=2,
                               blocksize=BLOCK, overview_resampling="average").compute()
    if os.path.exists(part):
        os.remove(part)


def check(out, bands, rows, cols) -> dict:
    """Pixels of a few bands against the source, and ``rio cogeo validate``."""
    import numpy as np
    import rasterio
    arr = cube(bands, rows, cols)
    with rasterio.open(out) as src:
        pick = sorted({1, bands // 2, bands})
        same = all(np.array_equal(src.read(b), arr[b - 1].compute()) for b in pick)
        ovr = src.overviews(1)
    v = subprocess.run([os.path.join(os.path.dirname(sys.executable), "rio"), "cogeo",
                        "validate", out], capture_output=True, text=True)
    return {"same_pixels": same, "overviews": ovr, "valid_cog": v.returncode == 0
            and "is a valid cloud optimized" in v.stdout,
            "mb": round(os.path.getsize(out) / 1e6, 1)}


def timed(name, args, out) -> dict:
    cmd = ["/usr/bin/time", "-v", sys.executable, __file__, "--one", name,
           "--bands", str(args.bands), "--rows", str(args.rows), "--cols", str(args.cols),
           "--out", out]
    t0 = time.perf_counter()
    p = subprocess.run(cmd, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    if p.returncode:
        return {"error": p.stderr.split("\tCommand being timed")[0][-800:]}
    rss = int(re.search(r"Maximum resident set size \(kbytes\): (\d+)", p.stderr).group(1))
    return {"wall_s": wall, "rss_mb": rss / 1024}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--bands", type=int, default=100)
    ap.add_argument("--rows", type=int, default=1400)
    ap.add_argument("--cols", type=int, default=1354)
    ap.add_argument("--runs", type=int, default=3, help="alternated runs; medians reported")
    ap.add_argument("--writers", default=",".join(WRITERS))
    ap.add_argument("--one", help=argparse.SUPPRESS)
    ap.add_argument("--out", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.one:
        write(args.one, args.bands, args.rows, args.cols, args.out)
        return 0
    names = [w for w in args.writers.split(",") if w]
    runs: dict = {n: [] for n in names}
    facts = {}
    with tempfile.TemporaryDirectory(dir=os.getcwd()) as td:
        for _ in range(args.runs):
            for n in names:                       # alternated: the machine is shared
                out = os.path.join(td, f"{n}.tif")
                runs[n].append(timed(n, args, out))
                if n not in facts and os.path.exists(out):
                    facts[n] = check(out, args.bands, args.rows, args.cols)
                if os.path.exists(out):
                    os.remove(out)
    print(f"COG writers: {args.bands} x {args.rows} x {args.cols} uint16 "
          f"({args.bands * args.rows * args.cols * 2 / 1e9:.2f} GB), median of {args.runs}")
    for n in names:
        ok = [r for r in runs[n] if "error" in r] or None
        if ok:
            print(f"  {n:15s} failed: {ok[0]['error']}")
            continue
        wall = statistics.median(r["wall_s"] for r in runs[n])
        rss = statistics.median(r["rss_mb"] for r in runs[n])
        print(f"  {n:15s} wall {wall:7.2f} s  peak RSS {rss:7.0f} MB  {json.dumps(facts.get(n))}")
    print("reproduce: .venv/bin/python benchmarks/bench_codec.py " + " ".join(sys.argv[1:]))
    return 0


if __name__ == "__main__":
    sys.exit(main())
