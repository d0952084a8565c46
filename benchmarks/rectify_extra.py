"""Parts of benchmarks/bench_rectify.py: the whole ``swathflow rectify`` command against
GDAL's geolocation warp on a simulated mission, the command's start-up, a 100-band uint16
cube and ``image_to_ground`` on a DEM. Each prints its figures; wall time and CPU time are
both given (the machine is shared: CPU seconds are the fair per-core measure)."""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
import warnings
from pathlib import Path

from cputime import children_cpu  # this folder (the scripts' own)

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
BIN = Path(sys.executable).parent


def _run(cmd, env=None) -> tuple[float, float, str]:
    """(wall s, CPU s of the child, stdout) of a command."""
    c0, t0 = children_cpu(), time.perf_counter()
    p = subprocess.run(cmd, capture_output=True, text=True, env=env)
    wall, cpu = time.perf_counter() - t0, children_cpu() - c0
    if p.returncode:
        raise RuntimeError(f"{' '.join(map(str, cmd))} failed:\n{p.stderr[-2000:]}")
    return wall, cpu, p.stdout


def _run_idle(cmd, env=None) -> tuple[float, float, float]:
    """(wall s, CPU s, idle-machine wall estimate s) of a whole command: the estimate is
    bench_mosaic's (its threads' CPU time over how many of them were runnable, window by
    window, from /proc schedstat), for commands run on the shared, loaded machine."""
    sys.path.insert(0, str(ROOT / "benchmarks"))
    import bench_mosaic as BM
    wall, cpu, _, _ = BM._measured([str(c) for c in cmd], env=env)
    return wall, cpu, BM.LAST_IDLE[0]


# ----------------------------------------------------------------------------------------
# start-up
# ----------------------------------------------------------------------------------------
ENGINE_READY = (
    "import time; t0 = time.perf_counter(); c0 = time.process_time()\n"
    "import numpy as np\n"
    "from swathflow.rectification import kernel as K\n"
    "K.resample_window(np.zeros((1, 8, 8), np.uint16), np.zeros((2, 4, 4), np.float32),"
    " 'bilinear', None, np.uint16, None)\n"
    "from swathflow.rectification import paint as P\n"
    "P.paint_window(np.zeros((1, 4), np.int64) + 1, np.zeros((1, 4, 2)), 4, 4, 0, 0, 8, 8)\n"
    "print(time.perf_counter() - t0, time.process_time() - c0)\n")


def startup(repeat: int = 3, mission_dir=None, preset: str = "demo", baseline=None) -> dict:
    """``swathflow rectify --help`` (the command's own start-up), and the engine's: import
    plus the first call of every kernel, with numba's on-disk cache warm and cold. With
    ``mission_dir``, the whole command's fixed cost too: ``swathflow rectify`` of the
    mission's first swing onto a 2 m grid (start-up, mission loading and validation, the
    swing's set-up, a COG of a few thousand pixels), ours and ``baseline`` alternately."""
    sw = str(BIN / "swathflow")
    fixed = {}
    if mission_dir:
        m = _at_gsd(_mission(mission_dir, preset), 2.0)
        first = next(line.split("=", 1)[1].strip().strip('"') for line in
                     (m / "mission.toml").read_text().splitlines()
                     if line.replace(" ", "").startswith("id="))
        runs = {"ours": sw, **({"baseline": baseline} if baseline else {})}
        times: dict = {k: [] for k in runs}
        with tempfile.TemporaryDirectory() as td:
            for i in range(repeat):
                for k, exe in runs.items():
                    times[k].append(_run([exe, "rectify", str(m), "--images", first, "-q",
                                          "--out", f"{td}/{k}{i}"])[:2])
        for k, t in times.items():
            w, c = min(t, key=lambda p: p[1])
            fixed[f"rectify_one_swing_2m_{k}"] = {"wall_s": round(w, 3), "cpu_s": round(c, 3)}
        fixed["rectify_one_swing_cmd"] = f"{sw} rectify {m} --images {first} -q --out OUT"
    helps = min((_run([sw, "rectify", "--help"])[:2] for _ in range(repeat)))
    warm = min(tuple(map(float, _run([sys.executable, "-c", ENGINE_READY])[2].split()))
               for _ in range(repeat))
    with tempfile.TemporaryDirectory() as td:
        env = dict(os.environ, NUMBA_CACHE_DIR=td)
        cold = tuple(map(float, _run([sys.executable, "-c", ENGINE_READY], env=env)[2].split()))
    r = lambda p: {"wall_s": round(p[0], 3), "cpu_s": round(p[1], 3)}  # noqa: E731
    return {"rectify_help": r(helps), "engine_ready_cache_warm": r(warm),
            "engine_ready_cache_cold_jit": r(cold), **fixed}


# ----------------------------------------------------------------------------------------
# the whole command against GDAL on a simulated mission
# ----------------------------------------------------------------------------------------
def _mission(path, preset):
    if not (Path(path) / "mission.toml").exists():
        _run([str(BIN / "swathflow"), "simulate", str(path), "--preset", preset, "--seed", "3"])
    return Path(path)


def _vrt(tmp, image, X, Y, crs_wkt, dtype):
    nl, ne = X.shape
    from swathflow.formats.raster import write_geotiff
    write_geotiff(tmp / "x.tif", X, None, (1, 0, 0, 0, 1, 0))
    write_geotiff(tmp / "y.tif", Y, None, (1, 0, 0, 0, 1, 0))
    wkt = crs_wkt.replace('"', "&quot;")
    vrt = tmp / "raw.vrt"
    vrt.write_text(f"""<VRTDataset rasterXSize="{ne}" rasterYSize="{nl}">
  <Metadata domain="GEOLOCATION">
    <MDI key="SRS">{wkt}</MDI>
    <MDI key="X_DATASET">{tmp / 'x.tif'}</MDI><MDI key="X_BAND">1</MDI>
    <MDI key="Y_DATASET">{tmp / 'y.tif'}</MDI><MDI key="Y_BAND">1</MDI>
    <MDI key="PIXEL_OFFSET">0</MDI><MDI key="LINE_OFFSET">0</MDI>
    <MDI key="PIXEL_STEP">1</MDI><MDI key="LINE_STEP">1</MDI>
  </Metadata>
  <VRTRasterBand dataType="{dtype}" band="1">
    <SimpleSource><SourceFilename>{image}</SourceFilename><SourceBand>1</SourceBand></SimpleSource>
  </VRTRasterBand>
</VRTDataset>
""")
    return vrt


def _geoloc(model, terrain, crs):
    from swathflow.geometry.grid import ecef_to_map
    nl, ne = model.shape
    ll, ee = np.meshgrid(np.arange(nl) - 0.5, np.arange(ne) - 0.5, indexing="ij")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        g = model.image_to_ground(np.stack([ll, ee], axis=-1).astype(float), terrain)
    X, Y, _ = ecef_to_map(g, crs)
    return X, Y


def _at_gsd(mission_dir: Path, gsd: float | None) -> Path:
    """The mission itself, or a copy (links to its files) whose mission.toml asks for
    ``gsd``."""
    import re
    if gsd is None:
        return mission_dir
    out = Path(f"{mission_dir}-gsd{gsd:g}")
    if not out.exists():
        out.mkdir()
        for f in mission_dir.iterdir():
            if f.name != "mission.toml":
                (out / f.name).symlink_to(f.resolve())
        text = (mission_dir / "mission.toml").read_text()
        (out / "mission.toml").write_text(re.sub(r"(?m)^gsd\s*=.*$", f"gsd = {gsd!r}", text,
                                                 count=1))
    return out


def _truth_on(grid, truth) -> np.ndarray:
    """The truth ortho on ``grid`` (cubic where the grid is finer, average where coarser:
    no shift either way), NaN outside it."""
    from rasterio.warp import Resampling, reproject
    out = np.full(grid.shape, np.nan)
    finer = abs(grid.transform.a) < abs(truth.transform.a) - 1e-9
    reproject(np.where(np.isfinite(truth.data), truth.data, np.nan), out,
              src_transform=truth.transform, src_crs=grid.crs, dst_transform=grid.transform,
              dst_crs=grid.crs, src_nodata=np.nan, dst_nodata=np.nan,
              resampling=Resampling.cubic if finer else Resampling.average)
    return out


def _shift(a, grid, truth, crop: int = 768):
    """Shift report (raw-output pixels) of ``a`` against the truth on its grid, on the
    central ``crop`` x ``crop`` window (the same window for every method)."""
    sys.path.insert(0, str(ROOT / "tests"))      # tests/shifts.py
    from shifts import shift_report
    t = _truth_on(grid, truth)
    h, w = a.shape
    r0, c0 = max((h - crop) // 2, 0), max((w - crop) // 2, 0)
    win = (slice(r0, r0 + crop), slice(c0, c0 + crop))
    a, t = a[win], t[win]
    a = np.where(np.isfinite(t), a, np.nan)
    t = np.where(np.isfinite(t), t, np.nanmean(t))
    return shift_report(a, t, tile=64, margin=16)


def _read(path):
    import rasterio
    with rasterio.open(path) as src:
        return src.read(1, masked=True).astype(float).filled(np.nan)


def _peers(rows, grid, mission, model, iid, truth, threads, dtype):
    """gdalwarp -geoloc and rasterio.warp.reproject on one swing's grid."""
    from rasterio.crs import CRS
    from rasterio.warp import Resampling, reproject
    import rasterio
    n = grid.shape[0] * grid.shape[1]
    X, Y = _geoloc(model, mission.terrain, grid.crs)       # free for the peers
    crs = CRS.from_wkt(grid.pyproj_crs.to_wkt())
    src_path = mission.images[iid].file
    gdal = shutil.which("gdalwarp")
    if gdal:
        tmp = Path(tempfile.mkdtemp(prefix="bench-gdal-"))
        vrt = _vrt(tmp, src_path, X, Y, grid.pyproj_crs.to_wkt(), "UInt16")
        xmin, ymin, xmax, ymax = grid.bounds
        cmd = [gdal, "-q", "-overwrite", "-geoloc", "-t_srs", grid.pyproj_crs.to_string(),
               "-te", str(xmin), str(ymin), str(xmax), str(ymax), "-ts", str(grid.width),
               str(grid.height), "-r", "bilinear", "-dstnodata", "0", "-ot", dtype,
               "-multi", "-wo", f"NUM_THREADS={threads}", "-co", "TILED=YES",
               "-co", "COMPRESS=DEFLATE", str(vrt), str(tmp / "gdal.tif")]
        w, c, idle = _run_idle(cmd)
        r = rows["gdalwarp"]
        r["wall"] += w
        r["cpu"] += c
        r["idle"] += idle
        r["px"] += n
        g = _read(tmp / "gdal.tif")
        r["shifts"].append(_shift(np.where(g > 0, g, np.nan), grid, truth))
        r["cmd"] = " ".join(cmd)
        shutil.rmtree(tmp)
    with rasterio.open(src_path) as s:
        raw = s.read(1)
    dst = np.zeros(grid.shape, raw.dtype)
    c0, t0 = time.process_time(), time.perf_counter()
    reproject(raw, dst, src_geoloc_array=np.stack([X, Y]), src_crs=crs,
              dst_transform=grid.transform, dst_crs=crs, dst_nodata=0,
              resampling=Resampling.bilinear, num_threads=threads)
    r = rows["rasterio"]
    r["wall"] += time.perf_counter() - t0
    r["cpu"] += time.process_time() - c0
    r["px"] += n
    r["shifts"].append(_shift(np.where(dst > 0, dst.astype(float), np.nan), grid, truth))


def command(mission_dir, preset="demo", threads=2, gsd=None, baseline=None,
            peers=True, repeat: int = 1, zstd: bool = False) -> dict:
    """``swathflow rectify`` (a subprocess: start-up, every swing, COG writing) against
    ``gdalwarp -geoloc`` and ``rasterio.warp.reproject`` on the same swings and grids, the
    peers given their geolocation arrays (pixel corners, our model) for free. ``gsd``:
    the output pixel size (default the mission's); ``baseline``: another ``swathflow``
    executable (e.g. main's) run the same way beside ours, the two alternately ``repeat``
    times (best wall, CPU and idle-machine estimate kept, each run's in ``runs``);
    ``zstd``: ours also with ``--compress zstd`` (``ours_zstd``), alternated the same way."""
    from swathflow.formats.calibfile import calibration_priors, read_calibration
    from swathflow.formats.raster import read_raster
    from swathflow.geometry.grid import Grid
    from swathflow.ingest.mission import load_mission
    import rasterio
    m = _at_gsd(_mission(mission_dir, preset), gsd)
    cal = m / "truth" / "calibration.json"
    truth = read_raster(m / "truth" / "ortho.tif", masked_to_nan=True)
    out = Path(tempfile.mkdtemp(prefix="bench-rect-"))
    env = dict(os.environ, DASK_NUM_WORKERS=str(threads))
    runs = {"ours": (str(BIN / "swathflow"), [])}
    if zstd:
        runs["ours_zstd"] = (str(BIN / "swathflow"), ["--compress", "zstd"])
    if baseline:
        runs["baseline"] = (baseline, [])
    rows = {k: dict(wall=0.0, cpu=0.0, idle=0.0, px=0, shifts=[]) for k in
            list(runs) + ["gdalwarp", "rasterio"]}
    rows["rasterio"]["idle"] = float("nan")      # in this process: no command to watch
    seen: dict = {k: [] for k in runs}
    for _ in range(max(repeat, 1)):
        for k, (exe, extra) in runs.items():
            shutil.rmtree(out / k, ignore_errors=True)
            seen[k].append(_run_idle([exe, "rectify", m, "--calibration", cal,
                                      "--out", out / k, *extra], env=env)
                           + (os.getloadavg()[0],))
    for k, (exe, extra) in runs.items():
        rows[k].update(wall=min(t[0] for t in seen[k]), cpu=min(t[1] for t in seen[k]),
                       idle=min(t[2] for t in seen[k]),
                       runs=[[round(v, 2) for v in t] for t in seen[k]],
                       cmd=" ".join([exe, "rectify", str(m), "--calibration", str(cal),
                                     "--out", "OUT", *extra]))
    mission = load_mission(m)
    params = mission.priors.updated(calibration_priors(read_calibration(cal)))
    for iid in mission.image_ids:
        ours = out / "ours" / f"{iid}.tif"
        with rasterio.open(ours) as src:
            grid = Grid(mission.crs, src.transform, src.shape)
            dtype = src.dtypes[0]
        for k in runs:
            a = _read(out / k / f"{iid}.tif")
            rows[k]["px"] += a.size
            rows[k]["shifts"].append(_shift(a, grid, truth))
        if peers:
            _peers(rows, grid, mission, mission.model(iid, params), iid, truth, threads, dtype)
    shutil.rmtree(out)
    return _table(rows, gsd=mission.gsd)


def _table(rows, gsd) -> dict:
    res = {"gsd": gsd}
    for k, r in rows.items():
        if not r["px"]:
            continue
        sh = r.pop("shifts")
        res[k] = {"wall_s": round(r["wall"], 2), "cpu_s": round(r["cpu"], 2),
                  "idle_wall_s": round(r.get("idle", float("nan")), 2),
                  "out_mpx": round(r["px"] / 1e6, 2),
                  "mpx_per_cpu_s": round(r["px"] / 1e6 / max(r["cpu"], 1e-9), 2),
                  "median_whole_shift_px": round(float(np.median([s["whole_px"] for s in sh])), 4),
                  "worst_tile_px": round(float(np.nanmax([s["worst_tile_px"] for s in sh])), 4)}
        if "runs" in r:
            res[k]["runs_wall_cpu_idle_load"] = r["runs"]
        if "cmd" in r:
            res[k]["cmd"] = r["cmd"][:200]
    for mine in ("ours", "ours_zstd"):
        o = res.get(mine)
        for k in ("baseline", "gdalwarp", "rasterio"):
            if o and k in res and not (mine == "ours_zstd" and k == "baseline"):
                res[f"{mine}_faster_than_{k}"] = {
                    "wall": round(res[k]["wall_s"] / max(o["wall_s"], 1e-9), 2),
                    "cpu": round(res[k]["cpu_s"] / max(o["cpu_s"], 1e-9), 2),
                    "idle_wall": round(res[k]["idle_wall_s"] / max(o["idle_wall_s"], 1e-9),
                                       2)}
    return res


# ----------------------------------------------------------------------------------------
# the command's timeline: its serial start, then the forked workers
# ----------------------------------------------------------------------------------------
_TIMELINE = r"""
import json, sys, time
t0, c0 = time.perf_counter(), time.process_time()
marks = []
def mark(name):
    marks.append((name, time.perf_counter() - t0, time.process_time() - c0))
import swathflow.flows.cli.commands as C
command = C.rectify
def rectify(args):
    mark("command parsed")
    import swathflow.rectification.mission as M
    mark("engine imported")
    load, warm, run = M.load_mission, M._warm, M._run
    def load_(*a, **k):
        m = load(*a, **k); mark("mission loaded and checked (numba's first call)"); return m
    def warm_(*a, **k):
        warm(*a, **k); mark("kernels warmed: workers fork")
    def run_(*a, **k):
        yield from run(*a, **k); mark("workers done")
    M.load_mission, M._warm, M._run = load_, warm_, run_
    return command(args)
C.rectify = rectify
from swathflow.flows.cli import main
sys.argv = ["swathflow", "rectify", *sys.argv[1:]]
try:
    main()
except SystemExit as e:
    if e.code:
        raise
mark("command returned")
print(json.dumps(marks))
"""


def timeline(mission_dir, preset="demo", gsd=None, threads=2, repeat: int = 3) -> dict:
    """Where the wall time of ``swathflow rectify`` goes, in a fresh interpreter: the
    serial start (imports, the mission loaded and checked, the kernels warmed) before the
    workers fork, then the workers. Median seconds since the interpreter ran the first
    line (wall and the parent's CPU), over ``repeat`` runs; the whole command's wall too."""
    import statistics
    m = _at_gsd(_mission(mission_dir, preset), gsd)
    cal = m / "truth" / "calibration.json"
    env = dict(os.environ, DASK_NUM_WORKERS=str(threads))
    runs, walls = [], []
    with tempfile.TemporaryDirectory() as td:
        for i in range(max(repeat, 1)):
            wall, _, out = _run([sys.executable, "-c", _TIMELINE, str(m), "--calibration",
                                 str(cal), "--out", f"{td}/{i}", "-q"], env=env)
            runs.append(json.loads(out.strip().splitlines()[-1]))
            walls.append(wall)
    names = [n for n, _, _ in runs[0]]
    return {"mission": str(m), "runs": len(runs),
            "whole_command_wall_s": round(statistics.median(walls), 3),
            "marks_wall_s_parent_cpu_s": {
                n: [round(statistics.median(r[k][1] for r in runs), 3),
                    round(statistics.median(r[k][2] for r in runs), 3)]
                for k, n in enumerate(names)}}


# ----------------------------------------------------------------------------------------
# a 100-band uint16 cube
# ----------------------------------------------------------------------------------------
def cube(bands=100, lines=1200, elements=256, threads=1) -> dict:
    """Output Mpx x bands per second of a uint16 cube at about the raw resolution."""
    import dask
    sys.path.insert(0, str(ROOT / "tests"))
    from test_rectify import scene_model

    from swathflow.geometry.grid import footprint_grid
    from swathflow.geometry.terrain import ConstantHeight
    from swathflow.rectification import rectify as R
    model = scene_model(n_lines=lines, n_elements=elements, swing=15.0, pixel_pitch=30e-6)
    terrain = ConstantHeight(5.0)
    b, li, ei = np.ogrid[0:bands, 0:lines, 0:elements]
    raw = (2000 + 7 * b + 300 * np.sin(li / 9.0) * np.cos(ei / 7.0)).astype(np.uint16)
    g0 = footprint_grid(model, terrain, 1.0)
    gsd = float(np.sqrt(g0.shape[0] * g0.shape[1] / (lines * elements)))
    grid = footprint_grid(model, terrain, gsd)
    sched = "sync" if threads == 1 else "threads"
    with dask.config.set(scheduler=sched, num_workers=threads):
        R.rectify(model, raw, grid, terrain, tile=512).compute()            # warm-up
        c0, t0 = time.process_time(), time.perf_counter()
        out = R.rectify(model, raw, grid, terrain, tile=512).compute()
        wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    assert out.dtype == np.uint16 and out.shape[0] == bands
    mpxb = grid.shape[0] * grid.shape[1] * bands / 1e6
    return {"raw": [bands, lines, elements], "grid": list(grid.shape), "gsd": round(gsd, 3),
            "threads": threads, "wall_s": round(wall, 3), "cpu_s": round(cpu, 3),
            "mpx_bands_per_s_per_core_wall": round(mpxb / wall / threads, 1),
            "mpx_bands_per_cpu_s": round(mpxb / cpu, 1)}


# ----------------------------------------------------------------------------------------
# image_to_ground on a DEM
# ----------------------------------------------------------------------------------------
def igm(points=200_000) -> dict:
    """Points per second of ``image_to_ground`` on a DEM (the hills DEM of the tests)."""
    sys.path.insert(0, str(ROOT / "tests"))
    from test_rectify import hills_dem, scene_model

    from swathflow.geometry.grid import footprint_grid
    from swathflow.geometry.terrain import ConstantHeight
    model = scene_model(n_lines=600, n_elements=192)
    with tempfile.TemporaryDirectory() as td:
        dem = hills_dem(Path(td) / "hills.tif", footprint_grid(model, ConstantHeight(5.0), 1.5))
        rng = np.random.default_rng(0)
        img = np.stack([rng.uniform(0, 599, points), rng.uniform(0, 191, points)], axis=-1)
        model.image_to_ground(img[:1000], dem)
        c0, t0 = time.process_time(), time.perf_counter()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            model.image_to_ground(img, dem)
        wall, cpu = time.perf_counter() - t0, time.process_time() - c0
        # before: the same rays through the numpy marching (intersect(compiled=False))
        from swathflow.geometry.intersect import intersect
        c1 = time.process_time()
        o, d = model.ray(img)
        intersect(o, d, dem, compiled=False)
        cpu_before = time.process_time() - c1
    return {"points": points, "wall_s": round(wall, 3), "cpu_s": round(cpu, 3),
            "points_per_cpu_s": round(points / cpu),
            "numpy_marching_points_per_cpu_s": round(points / cpu_before)}


def main(what: str, **kw) -> None:
    fn = {"startup": startup, "command": command, "cube": cube, "igm": igm,
          "timeline": timeline}[what]
    r = fn(**kw)
    print(json.dumps(r, indent=1))
