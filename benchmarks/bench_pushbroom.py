"""Push-broom ground_to_image throughput (issue 8; target >= 1e6 points/s/core).

Run:  /tmp/venv/bin/python benchmarks/bench_pushbroom.py [--points 1000000] [--profile]

Builds PushbroomModel.example_model() (3072 elements, three segments with cubic APs, three
orientation fixes, a wobbling trajectory), projects random image points to the ground, then
times ground_to_image on them single-threaded (OMP/BLAS threads pinned to 1) and reports
points per second (wall and CPU time), the round-trip error and where the time goes
(--profile).
"""
from __future__ import annotations

import argparse
import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import time  # noqa: E402

import numpy as np  # noqa: E402

from swathflow.sensors.pushbroom import PushbroomModel  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--points", type=int, default=1_000_000)
    ap.add_argument("--lines", type=int, default=3000)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--exact", action="store_true",
                    help="force the exact correction steps (exact_threshold_px = 0)")
    ap.add_argument("--profile", action="store_true")
    a = ap.parse_args()
    if a.exact:
        PushbroomModel.exact_threshold_px = 0.0
    m = PushbroomModel.example_model("forward", n_lines=a.lines)
    rng = np.random.default_rng(0)
    img = np.stack([rng.uniform(0, m.n_lines - 1, a.points),
                    rng.uniform(0, m.n_elements - 1, a.points)], axis=-1)
    t0 = time.perf_counter()
    ground = m.image_to_ground(img, 80.0)
    t_i2g = time.perf_counter() - t0
    best = best_cpu = np.inf
    for _ in range(a.repeat):
        t0, c0 = time.perf_counter(), time.process_time()
        back = m.ground_to_image(ground)
        best = min(best, time.perf_counter() - t0)
        best_cpu = min(best_cpu, time.process_time() - c0)
    err = np.abs(back - img)
    print(f"model: {m!r}, interpolation estimate {m._interp_px:.2e} px, "
          f"exact steps {'on' if m._interp_px > m.exact_threshold_px else 'off'}")
    print(f"image_to_ground: {a.points} points in {t_i2g:.2f} s "
          f"({a.points / t_i2g:,.0f} points/s)")
    print(f"ground_to_image: {a.points} points in {best:.3f} s wall (best of {a.repeat}) = "
          f"{a.points / best:,.0f} points/s/core; CPU time {best_cpu:.3f} s = "
          f"{a.points / best_cpu:,.0f} points per CPU-second")
    print(f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores (wall time "
          f"suffers when other processes share the cores; CPU time much less)")
    print(f"round trip: max |d line| {np.nanmax(err[:, 0]):.2e} px, max |d element| "
          f"{np.nanmax(err[:, 1]):.2e} px, NaN {np.isnan(back).any(axis=-1).sum()}")
    if a.profile:
        import cProfile
        import pstats
        pr = cProfile.Profile()
        pr.enable()
        m.ground_to_image(ground)
        pr.disable()
        pstats.Stats(pr).sort_stats("tottime").print_stats(12)


if __name__ == "__main__":
    main()
