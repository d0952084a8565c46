"""Calibration solve time for the 15-parameter pendulum model (issue 4 benchmark).

Reproduce: /tmp/venv/bin/python benchmarks/bench_calibration.py
Geometry: tests/test_calibration.py (paper scanner, 18,617 x 1024 swings, L1 + R1).
Prints, for 100 / 1,000 / 10,000 control observations (image points; each gives an x and
a y residual): the full calibrate() time (robust + VCE + residual tables), the plain
solve (no robust, no VCE), and one Jacobian by the implicit ray partials vs the sensor's
default parameter_partials (finite differences of ground_to_image).
"""
import importlib.util
import os
import time


HERE = os.path.dirname(os.path.abspath(__file__))
spec = importlib.util.spec_from_file_location(
    "tc", os.path.join(HERE, "..", "tests", "test_calibration.py"))
tc = importlib.util.module_from_spec(spec)
spec.loader.exec_module(tc)
from swathflow.calibration.control import calibrate  # noqa: E402
from swathflow.calibration.partials import image_partials  # noqa: E402


def main():
    models = tc.flight(n_swings=2)
    pri = models["L1"].parameters.updated(u_sen=[0.0, 0.0, -2.0])
    print(f"{'points':>7} {'full calibrate s':>17} {'plain solve s':>14} "
          f"{'implicit J s':>13} {'FD J s':>8} {'iters':>6}")
    for n in (100, 1000, 10000):
        obs = tc.noisy(tc.ground_points(models, tc.TRUTH, n_ctrl=n // 2, n_chk=0, seed=n))
        t = time.perf_counter()
        res = calibrate(models, obs, pri)
        full = time.perf_counter() - t
        t = time.perf_counter()
        calibrate(models, obs, pri, robust=False, vce=False)
        plain = time.perf_counter() - t
        m = models["L1"].with_parameters(tc.TRUTH)
        g = obs[obs["image_id"] == "L1"][["X", "Y", "Z"]].to_numpy()
        img = m.ground_to_image(g, clip=False)
        t = time.perf_counter()
        image_partials(m, g, img)
        ti = time.perf_counter() - t
        t = time.perf_counter()
        m.parameter_partials(g)
        tf = time.perf_counter() - t
        print(f"{n:7d} {full:17.2f} {plain:14.2f} {ti:13.3f} {tf:8.3f} "
              f"{res.iterations:6d}")


if __name__ == "__main__":
    main()
