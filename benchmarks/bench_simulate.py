"""Simulation time of every preset, and the rendering rate (for the paper preset, whose
full rendering is too slow for routine use: the rate on a block of lines is measured and
extrapolated).

    /tmp/venv/bin/python benchmarks/bench_simulate.py                 # tiny demo paper area
    /tmp/venv/bin/python benchmarks/bench_simulate.py --presets demo  # just one

Prints wall and CPU time per preset (the machine is shared: the load average is printed
too; CPU time counts both texture threads) with the simulator's own breakdown
(truth.json timings_s, wall seconds).
"""
from __future__ import annotations

import argparse
import os
import tempfile
import time
import warnings


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--presets", nargs="+", default=["tiny", "demo", "paper", "area"])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--paper-lines", type=int, default=192,
                    help="lines of a paper swing rendered to measure the rate")
    args = ap.parse_args()
    warnings.simplefilter("ignore")
    from swathflow.sensors.pendulum.simulate import simulate
    print(f"cpus: {os.cpu_count()}, load average: {os.getloadavg()[0]:.1f}")
    with tempfile.TemporaryDirectory() as tmp:
        for p in args.presets:
            t0, c0 = time.perf_counter(), time.process_time()
            truth = simulate(os.path.join(tmp, p), p, seed=args.seed)
            wall, cpu = time.perf_counter() - t0, time.process_time() - c0
            n_img = len(truth["images"])
            shape = f"{truth['images'][0]['lines']} x {truth['images'][0]['elements']}"
            print(f"{p:6s} {wall:7.1f} s wall, {cpu:7.1f} s CPU  {n_img:3d} images of {shape}, "
                  f"rendered={truth['images_rendered']}  breakdown {truth['timings_s']}")
        if "paper" in args.presets:
            _paper_rate(os.path.join(tmp, "paper"), args.paper_lines)


def _paper_rate(out: str, n: int) -> None:
    """Render ``n`` lines of the paper's L1 through the same code path and extrapolate."""
    import numpy as np
    from swathflow import load_mission
    from swathflow.geometry.geodesy import transformer
    from swathflow.sensors.pendulum.simulate import preset_config
    from swathflow.simulation.bundle import render_image
    from swathflow.simulation.texture import ProceduralTexture
    m = load_mission(out)
    full = m.model("L1")
    lt = {k: v[:n] for k, v in m.lines("L1").items() if k != "line"}
    part = type(full).build(m.sensor, lt, full.trajectory, full.parameters, direction="L")
    cfg = preset_config("paper")
    tex = ProceduralTexture(0, cfg.ifov * cfg.agl, (0.0, 0.0))
    t0 = time.perf_counter()
    render_image(part, m.terrain, tex, transformer("EPSG:4978", m.crs), cfg,
                 np.random.default_rng(0))
    dt = time.perf_counter() - t0
    per_line = dt / n
    total = per_line * full.n_lines * len(m.images)
    print(f"paper render rate: {n} lines x {full.n_elements} elements in {dt:.1f} s "
          f"({per_line * 1e3:.1f} ms/line); a full --render of 6 x {full.n_lines} lines "
          f"would take about {total / 60:.0f} min")


if __name__ == "__main__":
    main()
