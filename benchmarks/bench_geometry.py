"""Throughput of the pendulum model's ground_to_image and image_to_ground (points per second).

Reproduce:  python benchmarks/bench_geometry.py [--points 1000000] [--threads 1] [--repeat 3]
Prints points/s for ground_to_image (constant height), image_to_ground (constant height)
and image_to_ground (a DEM), on one core unless --threads says otherwise.
"""
from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--points", type=int, default=1_000_000)
    ap.add_argument("--threads", type=int, default=1, help="BLAS/OpenMP threads (default 1)")
    ap.add_argument("--repeat", type=int, default=3,
                    help="runs per figure; the first call pays page faults on fresh memory, "
                         "later ones show the steady state of a long run (default 3)")
    args = ap.parse_args(argv)
    for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ[var] = str(args.threads)

    import numpy as np
    import rasterio
    from rasterio.transform import from_origin

    from swathflow.geometry.geodesy import ecef_to_geodetic, transformer, utm_crs_for
    from swathflow.sensormodel.base import CHUNK
    from swathflow.sensors.pendulum import PendulumModel
    from swathflow.geometry.terrain import DEM

    n = args.points
    m = PendulumModel.example_model(n_lines=8000)
    rng = np.random.default_rng(0)
    img = np.stack([rng.uniform(0, m.n_lines - 1, n), rng.uniform(0, m.n_elements - 1, n)], -1)

    rows = []

    def timed(label, fn):
        fn_small = fn(slice(0, 1000))          # warm-up
        del fn_small
        runs = []
        for _ in range(args.repeat):           # the first call also pays page faults
            t, c = time.perf_counter(), time.process_time()
            out = fn(slice(None))
            runs.append((time.perf_counter() - t, time.process_time() - c))
        (dt, dc), best = runs[0], min(runs)
        rows.append((label, n / dt, dt, n / dc, n / best[1]))
        return out

    ground = timed("image_to_ground, constant height",
                   lambda s: m.image_to_ground(img[s], 10.0))
    back = timed("ground_to_image, constant height", lambda s: m.ground_to_image(ground[s]))
    err = np.nanmax(np.abs(back - img))
    # the same solve through the numpy path (before the compiled kernels; their reference)
    timed("ground_to_image, constant height, numpy path",
          lambda s: np.concatenate([m._ground_to_image_numpy(c, True) for c in
                                    np.array_split(ground[s], max(1, len(ground[s]) // CHUNK))]))

    # a DEM under the swing: hills on a 10 m grid in UTM
    llh = ecef_to_geodetic(ground[:: max(1, n // 1000)])
    crs = utm_crs_for(float(np.mean(llh[:, 0])), float(np.mean(llh[:, 1])))
    e, nn = transformer("EPSG:4326", crs).transform(llh[:, 1], llh[:, 0])
    x0, y1 = e.min() - 500, nn.max() + 500
    w, h = int((e.max() - e.min() + 1000) / 10), int((nn.max() - nn.min() + 1000) / 10)
    yy, xx = np.mgrid[0:h, 0:w]
    dem_data = 20 + 15 * np.sin(xx / 40.0) * np.cos(yy / 55.0)
    with tempfile.TemporaryDirectory() as tmp:
        path = os.path.join(tmp, "dem.tif")
        with rasterio.open(path, "w", driver="GTiff", width=w, height=h, count=1,
                           dtype="float64", crs=crs, transform=from_origin(x0, y1, 10, 10)) as d:
            d.write(dem_data, 1)
        dem = DEM.open(path)
        timed("image_to_ground, DEM (10 m grid, 5-35 m hills)",
              lambda s: m.image_to_ground(img[s], dem))
        _tile_ground_points(rows, dem, crs, x0 + 100, y1 - 100, n, args.repeat)

    print(f"swathflow geometry benchmark: {n:,} points, pendulum model, "
          f"{args.threads} thread(s), {os.cpu_count()} cores on this machine")
    print(f"  {'':<48} {'first call, wall':>18} {'per CPU-second':>22} "
          f"{'best of ' + str(args.repeat) + ', per CPU-s':>24}")
    for label, rate, dt, cpu_rate, best_rate in rows:
        print(f"  {label:<48} {rate / 1e6:9.3f} M points/s {cpu_rate / 1e6:9.3f} M points/CPU-s"
              f" {best_rate / 1e6:9.3f} M points/CPU-s  ({dt:6.2f} s)")
    print(f"  round-trip worst error: {err:.2e} px")
    print(f"reproduce: python benchmarks/bench_geometry.py --points {n} --threads {args.threads}"
          f" --repeat {args.repeat}")
    return 0


def _tile_ground_points(rows, dem, crs, x0, y1, n, repeat) -> None:
    """ECEF of a 257 x 257 window of 2 m pixels on the DEM (a rectify tile's exact
    evaluations): the tile's frame (``tile_frame(...).ecef``, the pixels in row order as a
    tile evaluated at every pixel gives them, and in a random order as the lattice's
    nodes come) and pyproj (``Grid.to_ecef``); rows as ``timed`` adds them."""
    import time
    import warnings

    import numpy as np
    from affine import Affine

    from swathflow.geometry.grid import Grid, tile_frame
    grid = Grid(str(crs), Affine(2.0, 0, x0, 0, -2.0, y1), (256, 256))
    rr, cc = np.indices((257, 257))
    rr, cc = rr.ravel(), cc.ravel()
    perm = np.random.default_rng(1).permutation(rr.size)
    frame = tile_frame(grid, dem, 257, 257)
    calls = max(1, n // rr.size)

    def pyproj_ecef(r, c):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            return grid.to_ecef(*grid.xy(r, c), dem)
    for label, fn, r, c in (
            ("tile ground points, frame, row order", frame.ecef, rr, cc),
            ("tile ground points, frame, random order", frame.ecef, rr[perm], cc[perm]),
            ("tile ground points, pyproj (Grid.to_ecef)", pyproj_ecef, rr, cc)):
        fn(r[:100], c[:100])                                    # warm-up
        runs = []
        for _ in range(repeat):
            t, cpu = time.perf_counter(), time.process_time()
            for _ in range(calls):
                fn(r, c)
            runs.append((time.perf_counter() - t, time.process_time() - cpu))
        (dt, dc), best = runs[0], min(runs)
        k = calls * rr.size
        rows.append((label, k / dt, dt, k / dc, k / best[1]))


if __name__ == "__main__":
    sys.exit(main())
