"""image_to_ground on a DEM (IGM products, footprints, validation): points per CPU second on
one thread, before and after, for every sensor model.

Reproduce:
    .venv/bin/python benchmarks/bench_igm.py                        # this build
    .venv/bin/python benchmarks/bench_igm.py --before OLD/bin/python   # OLD: another build's venv
    .venv/bin/python benchmarks/bench_igm.py --sizes 10000,100000,1000000 --repeat 3

The scene is the hills DEM of the tests (tests/test_rectify.py ``hills_dem``: 4 m cells,
5-155 m of relief, a hill and ridges) under each model's footprint: the pendulum scanner of
the rectification tests (``scene_model(600, 192)``), the push-broom example camera and the
rotating-mirror plugin's example scanner. Image points are uniform random over the image.
``--before PYTHON`` runs this same script under another interpreter (main's build) in turn
with this one, size by size, so both see the same load; without it the "before" column is
this build's own numpy path (the numpy ray and ``intersect(compiled=False)``, pendulum only).
Figures are CPU seconds (user + sys of this process): the machine is shared.
"""
from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
    os.environ[_v] = "1"

import argparse  # noqa: E402
import json  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
import warnings  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
MODELS = ("pendulum", "pushbroom", "rotating-mirror")


def _model(name):
    if name == "pendulum":
        from test_rectify import scene_model
        return scene_model(n_lines=600, n_elements=192)
    if name == "pushbroom":
        from swathflow.sensors.pushbroom import PushbroomModel
        return PushbroomModel.example_model("nadir", n_lines=600)
    import swathflow        # the plugin of the build being measured (main's for --before)
    repo = Path(swathflow.__file__).resolve().parents[1]
    sys.path.insert(0, str(repo / "plugins" / "rotating-mirror"))
    from swathflow_rotating_mirror.model import RotatingMirrorModel
    return RotatingMirrorModel.example_model()


def _cpu(fn, repeat):
    best = None
    for _ in range(repeat):
        c0, w0 = time.process_time(), time.perf_counter()
        fn()
        run = (time.process_time() - c0, time.perf_counter() - w0)
        best = run if best is None or run[0] < best[0] else best
    return best


def measure(name: str, sizes, repeat: int, numpy_path: bool) -> list[dict]:
    """CPU and wall seconds (best of ``repeat``) of image_to_ground at each size."""
    sys.path.insert(0, str(ROOT / "tests"))
    from test_rectify import hills_dem

    from swathflow.geometry.grid import footprint_grid
    from swathflow.geometry.terrain import ConstantHeight
    model = _model(name)
    out = []
    with tempfile.TemporaryDirectory() as td, warnings.catch_warnings():
        warnings.simplefilter("ignore")
        grid = footprint_grid(model, ConstantHeight(5.0), 2.0)
        dem = hills_dem(Path(td) / "hills.tif", grid)
        rng = np.random.default_rng(0)
        nl, ne = model.shape
        model.image_to_ground(np.array([[nl / 2, ne / 2]]), dem)      # compile, fit once
        for n in sizes:
            img = np.stack([rng.uniform(0, nl - 1, n), rng.uniform(0, ne - 1, n)], axis=-1)
            cpu, wall = _cpu(lambda img=img: model.image_to_ground(img, dem), repeat)
            row = {"model": name, "points": n, "cpu_s": cpu, "wall_s": wall}
            if numpy_path and hasattr(model, "_ray_numpy"):
                from swathflow.geometry.intersect import intersect

                def before(img=img):
                    o, d = model._ray_numpy(img)
                    intersect(o, d, dem, compiled=False)
                row["numpy_cpu_s"], _ = _cpu(before, 1)
            out.append(row)
    return out


def _run_other(python: str, name: str, n: int, repeat: int) -> dict:
    cmd = [python, __file__, "--json", "--models", name, "--sizes", str(n),
           "--repeat", str(repeat)]
    res = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT,
                         env=dict(os.environ, PYTHONWARNINGS="ignore"))
    if res.returncode != 0:
        raise SystemExit(f"{python}: {res.stderr.strip().splitlines()[-1]}")
    return json.loads(res.stdout.strip().splitlines()[-1])[0]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", default="10000,100000,1000000")
    ap.add_argument("--models", default=",".join(MODELS))
    ap.add_argument("--repeat", type=int, default=3, help="best of N runs (default 3)")
    ap.add_argument("--before", metavar="PYTHON",
                    help="the interpreter of the build to compare with (e.g. main's venv)")
    ap.add_argument("--json", action="store_true", help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    sizes = [int(s) for s in a.sizes.split(",")]
    models = [m.strip() for m in a.models.split(",")]
    if a.json:
        rows = [r for m in models for r in measure(m, sizes, a.repeat, False)]
        print(json.dumps(rows))
        return 0
    load = os.getloadavg()[0]
    print(f"image_to_ground on the hills DEM (4 m cells), one thread; load average {load:.1f}")
    head = "before (main)" if a.before else "before (numpy path)"
    print(f"  {'model':<16} {'points':>9} {'after CPU-s':>12} {'after wall-s':>13} "
          f"{'M pts/CPU-s':>12} {head + ' M pts/CPU-s':>30} {'ratio':>6}")
    for m in models:
        for n in sizes:
            row = measure(m, [n], a.repeat, not a.before)[0]
            before = None
            if a.before:
                other = _run_other(a.before, m, n, a.repeat)
                before = n / other["cpu_s"]
            elif "numpy_cpu_s" in row:
                before = n / row["numpy_cpu_s"]
            rate = n / row["cpu_s"]
            b = f"{before / 1e6:30.3f} {rate / before:5.1f}x" if before else f"{'-':>30} {'':>6}"
            print(f"  {m:<16} {n:9d} {row['cpu_s']:12.3f} {row['wall_s']:13.3f} "
                  f"{rate / 1e6:12.3f} {b}")
    cmd = f"python benchmarks/bench_igm.py --sizes {a.sizes} --models {a.models} --repeat {a.repeat}"
    print(f"reproduce: {cmd}" + (f" --before {a.before}" if a.before else ""))
    return 0


if __name__ == "__main__":
    sys.exit(main())
