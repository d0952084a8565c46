"""The COG tile codec: ISA-L (swathflow.rectification.tilecodec) against GDAL's DEFLATE
(libdeflate), on the demo mission's swings rectified at a fine GSD.

1. Each swing rectified and written as a COG in this process (dask's synchronous
   scheduler, as in the rectify command's workers), alternately with the codec and
   without it (GDAL compressing), best of ``--repeat`` CPU seconds; the pixels compared.
2. One swing's tiles compressed alone: GDAL's GTiff driver (level 1, the predictor) against
   :func:`tilecodec.encode`.
3. The codec on one thread and on two (ISA-L releases the GIL).

    .venv/bin/python benchmarks/bench_codec.py                    # simulates the demo
    .venv/bin/python benchmarks/bench_codec.py --mission /tmp/demo3 --gsd 0.05 --repeat 3
"""
from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
import warnings
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from rectify_extra import _at_gsd  # noqa: E402


def _write_all(mission, cal, out: Path) -> float:
    """CPU seconds of every swing's rectify + COG in this process."""
    import dask

    import swathflow
    from swathflow.rectification.api import to_cog
    t = time.process_time()
    with dask.config.set(scheduler="sync"):
        for iid in mission.image_ids:
            to_cog(swathflow.rectify(mission, iid, cal, dtype=None),    # the raw type,
                   out / f"{iid}.tif")                                 # as the command
    return time.process_time() - t


def _gdal_compress(tiles, dtype, predictor) -> None:
    from rasterio.io import MemoryFile
    for t in tiles:
        with MemoryFile() as mem, mem.open(driver="GTiff", width=t.shape[1], height=t.shape[0],
                                           count=1, dtype=dtype, tiled=True, blockxsize=512,
                                           blockysize=512, compress="deflate", zlevel=1,
                                           predictor=predictor) as dst:
            dst.write(t[None])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--mission", help="a demo mission (default: simulated, seed 3)")
    ap.add_argument("--gsd", type=float, default=0.05)
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args(argv)
    import rasterio

    from swathflow.ingest.mission import load_mission
    from swathflow.rectification import tilecodec
    warnings.simplefilter("ignore")
    work = Path(tempfile.mkdtemp(prefix="bench-codec-"))
    src = Path(args.mission) if args.mission else work / "demo"
    if not args.mission:
        from swathflow.simulation import simulate
        simulate(src, preset="demo", seed=3)
    mdir = _at_gsd(src, args.gsd)
    mission = load_mission(mdir)
    cal = str(src / "truth" / "calibration.json")
    isal = tilecodec.isal_zlib
    outs = {"isal": work / "isal", "gdal": work / "gdal"}
    for d in outs.values():
        d.mkdir()
    _write_all(mission, cal, outs["isal"])                 # kernels loaded, caches warm
    cpu = {"isal": [], "gdal": []}
    for _ in range(args.repeat):
        for name, mod in (("isal", isal), ("gdal", None)):
            tilecodec.isal_zlib = mod
            cpu[name].append(_write_all(mission, cal, outs[name]))
    tilecodec.isal_zlib = isal
    same, size = True, {"isal": 0, "gdal": 0}
    for iid in mission.image_ids:
        with rasterio.open(outs["isal"] / f"{iid}.tif") as a, \
                rasterio.open(outs["gdal"] / f"{iid}.tif") as b:
            same &= bool(np.array_equal(a.read(), b.read(), equal_nan=True))
        for name in size:
            size[name] += os.path.getsize(outs[name] / f"{iid}.tif")
    n = len(mission.image_ids)
    print(f"== {n} swings at {args.gsd} m, rectify + COG in one process, CPU s (best of "
          f"{args.repeat}, alternated)")
    print(f"   ISA-L {min(cpu['isal']):.3f}  GDAL {min(cpu['gdal']):.3f}  "
          f"({min(cpu['gdal']) / min(cpu['isal']):.2f}x); runs {cpu}")
    print(f"   same pixels: {same}; files {size['isal'] / 1e6:.1f} MB against "
          f"{size['gdal'] / 1e6:.1f} ({size['isal'] / size['gdal'] - 1:+.1%})")

    with rasterio.open(outs["isal"] / f"{mission.image_ids[0]}.tif") as f:
        data = f.read(1)
    tiles = [data[r:r + 512, c:c + 512] for r in range(0, data.shape[0], 512)
             for c in range(0, data.shape[1], 512)]
    pred = 3 if data.dtype.kind == "f" else 2
    best = {}
    for name, fn in (("gdal", lambda: _gdal_compress(tiles, data.dtype.name, pred)),
                     ("isal", lambda: [tilecodec.encode(t, 512, pred) for t in tiles])):
        best[name] = min(_timed(fn) for _ in range(5))
    print(f"== one swing's {len(tiles)} tiles ({data.size / 1e6:.1f} Mpx {data.dtype}) "
          f"compressed alone, best of 5: GDAL {best['gdal'] * 1e3:.1f} ms, ISA-L "
          f"{best['isal'] * 1e3:.1f} ms ({best['gdal'] / best['isal']:.2f}x)")
    one = min(_timed(lambda: [tilecodec.encode(t, 512, pred) for t in tiles * 2])
              for _ in range(3))
    with ThreadPoolExecutor(2) as ex:
        two = min(_timed(lambda: list(ex.map(lambda t: tilecodec.encode(t, 512, pred),
                                                  tiles * 2)))
                  for _ in range(3))
    print(f"== the codec on twice those tiles: one thread {one * 1e3:.1f} ms, two threads "
          f"{two * 1e3:.1f} ms ({one / two:.2f}x)")
    print("reproduce: .venv/bin/python benchmarks/bench_codec.py"
          + (f" --mission {args.mission}" if args.mission else "")
          + f" --gsd {args.gsd:g} --repeat {args.repeat}")
    return 0


def _timed(fn) -> float:
    t = time.perf_counter()
    fn()
    return time.perf_counter() - t


if __name__ == "__main__":
    sys.exit(main())
