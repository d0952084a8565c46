"""What the run's readable products cost: the calibration report (figures drawn on
swathflow.drawing, inlined as SVG) on the simulated paper mission, and the STAC catalogue
of the tiny mission's rectified swings and mosaic (footprints traced from the nodata mask).

    .venv/bin/python benchmarks/bench_products.py
    .venv/bin/python benchmarks/bench_products.py --mosaic-report [--repeat 3]

Prints the report's size and render time and the catalogue's write time (the machine is
shared: the load average is printed too). ``--mosaic-report``: only the mosaic report
(report picture PNG + HTML page with three SVG figures, matplotlib) of bench_mosaic's
48-swing mosaic, in CPU seconds of this process (robust on a shared machine): the first
report in a fresh process (imports included) and drawn again in this one (best of
``--repeat``).
"""
from __future__ import annotations

import os
import tempfile
import time
import warnings
from pathlib import Path


def mosaic_report(repeat: int = 3) -> None:
    """CPU seconds of the mosaic report of bench_mosaic's 48-swing mosaic."""
    import sys
    sys.path.insert(0, str(Path(__file__).parent))
    from bench_mosaic import generate
    from swathflow.mosaicking.api import write_mosaic
    with tempfile.TemporaryDirectory() as tmp:
        g = generate(os.path.join(tmp, "swings"), 12, 2048)
        out = os.path.join(tmp, "mosaic.tif")
        rep = write_mosaic(g["paths"], out, anchors=["0"])     # its mosaic.json too
        # a fresh process: matplotlib's import included, as the mosaic command pays it
        import json
        import subprocess
        from cputime import children_cpu
        code = ("import json, sys; from swathflow.mosaicking.report_html import write_report; "
                "write_report(sys.argv[1], json.loads(sys.argv[2]))")
        c = children_cpu()
        subprocess.run([sys.executable, "-c", code, out, json.dumps(g["paths"])], check=True)
        first = children_cpu() - c
        from swathflow.mosaicking.report_html import write_report
        write_report(out, g["paths"])
        best = float("inf")
        for _ in range(repeat):
            c = time.process_time()
            write_report(out, g["paths"])
            best = min(best, time.process_time() - c)
    print(f"mosaic report, 48 swings ({len(rep['overlaps'])} overlaps; load average "
          f"{os.getloadavg()[0]:.1f}): {first:.2f} CPU-s in a fresh process (interpreter, "
          f"imports and matplotlib's included), {best:.2f} CPU-s drawn again in this one "
          f"(best of {repeat})")
    print(f"reproduce: .venv/bin/python benchmarks/bench_products.py --mosaic-report "
          f"--repeat {repeat}")


def main() -> None:
    warnings.simplefilter("ignore")
    import swathflow
    from swathflow.calibration.control import calibrate
    from swathflow.calibration.report import render_report
    from swathflow.formats.stac import write_catalog
    from swathflow.ingest.mission import load_mission
    from swathflow.simulation import simulate
    print(f"cpus: {os.cpu_count()}, load average: {os.getloadavg()[0]:.1f}")
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        simulate(root / "paper", preset="paper", seed=3)
        m = load_mission(root / "paper")
        res = calibrate({i: m.model(i) for i in m.images}, m.gcps, m.priors)
        t = time.perf_counter()
        html = render_report(res)
        print(f"calibration report, paper mission ({len(res.residuals)} residual rows, "
              f"{res.residuals['image_id'].nunique()} images): {len(html) / 1e3:.0f} kB, "
              f"rendered in {time.perf_counter() - t:.2f} s")
        simulate(root / "tiny", preset="tiny", seed=1)
        cal = root / "tiny" / "truth" / "calibration.json"
        swings = []
        for iid in ("L1", "R1"):
            path = root / "rect" / f"{iid}.tif"
            path.parent.mkdir(exist_ok=True)
            swathflow.rectify(root / "tiny", iid, cal).rio.to_raster(path)
            swings.append(path)
        swathflow.mosaic(swings, root / "mosaic.tif")
        t = time.perf_counter()
        write_catalog(swings, root / "mosaic.tif", root / "stac", calibration=cal)
        print(f"STAC catalogue, tiny mission ({len(swings)} swings + mosaic): "
              f"{time.perf_counter() - t:.2f} s")
    print("reproduce: .venv/bin/python benchmarks/bench_products.py")


if __name__ == "__main__":
    import argparse
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--mosaic-report", action="store_true",
                    help="only the mosaic report's CPU seconds (48 swings)")
    ap.add_argument("--repeat", type=int, default=3)
    a = ap.parse_args()
    mosaic_report(a.repeat) if a.mosaic_report else main()
