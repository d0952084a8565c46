"""What the run's readable products cost: the calibration report (figures drawn on
swathflow.drawing, inlined as SVG) on the simulated paper mission, and the STAC catalogue
of the tiny mission's rectified swings and mosaic (footprints traced from the nodata mask).

    .venv/bin/python benchmarks/bench_products.py

Prints the report's size and render time and the catalogue's write time (the machine is
shared: the load average is printed too).
"""
from __future__ import annotations

import os
import tempfile
import time
import warnings
from pathlib import Path


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
    main()
