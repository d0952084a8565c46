"""Mosaic benchmark: memory versus area, peers side by side, and the paper's job.

    python benchmarks/bench_mosaic.py --memory --peers --paper [--peers16] [--regional 1.0]
    python benchmarks/bench_mosaic.py --regional 1.0 --work DIR   # keeps/reuses the swings

--memory  mosaics synthetic areas of 1x, 4x and 16x the base area in fresh subprocesses
          and prints each one's peak RSS (the mosaic is streamed tile by tile, so the peak
          should not grow with the area).
--peers   on the 4x area (48 swings, 3.63 Mpx), one run each, every one a whole command
          timed from start to exit (wall, CPU = user + sys of it and its children, peak RSS)
          and, where it can be timed inside, the call alone ("in-process"): `swathflow
          mosaic` (the CLI: match + network + feather, COG + PNG + report), swathflow's
          mosaic() in one process (threads; the same work), swathflow blending only
          (feather + COG), `rio merge`, gdalbuildvrt + gdal_translate -of COG, gdalwarp -of
          COG, gdal_merge.py, and rasterio.merge.merge + a tiled GTiff write in `python -c`
          (the reference of the ratios; the peers do no blending), and a floor: a
          `python -c` that only starts numba (import, first call of a cached kernel),
          the fixed cost under every swathflow row. Each also with its
          wall time on an idle machine estimated from the scheduler's accounting (the
          machine is shared: under load the wall times say little).
--peers16 the same on 16x the area (768 swings, 58 Mpx).
--quick   with --peers/--peers16: only mosaic() in one process, the blend alone, the floor and
          rasterio.merge (the long 16x run in a few minutes).
--repeat N  with --peers/--peers16: N alternated rounds of swathflow's runs and
          rasterio.merge (the GDAL peers in the first only): the table of medians, then
          each round's ratio of the CLI and of the blend to that round's merge (idle
          estimate and wall), their medians and how many rounds meet issue 15's targets.
--paper   You & Li's job (docs/references.md section 3): 24 strips of 6 km at 2 m pixels, swath of
          a 30 degree field of view from 650 m (348 m = 174 px), 20 % overlap, about 40 km2,
          strips displaced by 1-5 px; simulated as rectified swings and mosaicked end to end.
          Their figure for rectification plus mosaic on 2000 hardware: about 45 minutes.

Inputs are written by tests/mosaic_synth.py (known truth, one swing at a time). Work files
go to --work (default a temp folder, removed unless --keep).
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(HERE, "..", "tests"))

from bench_regional import fast_texture  # noqa: E402
from cputime import children_cpu  # noqa: E402
from mosaic_synth import make_swings, random_shifts  # noqa: E402

SWING_ROWS = 512


def generate(folder, n_strips, length, swath=180, overlap=0.2, seed=1, swing_rows=SWING_ROWS):
    shifts, rads = random_shifts(n_strips, seed=seed)
    n_sw = max(1, int(round(length / swing_rows)))
    t0 = time.perf_counter()
    paths, _, shape = make_swings(folder, n_strips=n_strips, swath=swath, length=length,
                                  overlap=overlap, n_swings=n_sw, swing_overlap=24,
                                  shifts=shifts, rads=rads, drift=3.0, noise=0.5,
                                  footprints=False, seed=seed, truth=fast_texture)
    return dict(paths=paths, shape=shape, shifts=shifts, rads=rads,
                seconds=time.perf_counter() - t0)


_CHILD = r"""
import contextlib, json, sys
from swathflow.cluster import dask_client
from swathflow.mosaicking.mosaic import mosaic
a = json.loads(sys.argv[1])
# as `swathflow mosaic` does: the overlaps are matched on a local Dask cluster
ctx = dask_client() if a.get("cluster") and a.get("match", True) else contextlib.nullcontext()
with ctx:
    rep = mosaic(a["paths"], a["out"], anchors=a.get("anchors", ["0"]),
                 match=a.get("match", True), png=a.get("png", True), workers=a.get("workers"))
print(json.dumps({k: rep[k] for k in ("seconds", "mpx_per_s", "shape")} |
                 {"nodes": rep.get("nodes"), "skipped": len(rep.get("skipped", [])),
                  "seconds_match": rep.get("seconds_match", 0.0),
                  "seconds_render": rep.get("seconds_render"),
                  "seconds_total": rep.get("seconds_total"),
                  "seconds_quicklook": rep.get("seconds_quicklook")}))
"""


def _sched(pid, out=None) -> dict:
    """(on-CPU ns, run-queue wait ns) of every thread of ``pid`` and its descendants, from
    /proc/PID/task/TID/schedstat (Linux); empty where /proc is missing."""
    out = {} if out is None else out
    try:
        tids = os.listdir(f"/proc/{pid}/task")
    except OSError:
        return out
    for t in tids:
        try:
            with open(f"/proc/{pid}/task/{t}/schedstat") as f:
                a, b = f.read().split()[:2]
            out[(pid, t)] = (int(a), int(b))
            with open(f"/proc/{pid}/task/{t}/children") as f:
                kids = [int(c) for c in f.read().split()]
        except (OSError, ValueError):
            continue
        for c in kids:
            _sched(c, out)
    return out


class _IdleWall:
    """The wall time a command would take on an idle machine of ``cores`` cores, estimated
    from the scheduler's accounting while it runs on a loaded one (the machine is shared):
    per window of at least ``window`` s, its threads' CPU time over the number of them
    that were runnable (on a CPU or waiting for one; threads waiting on a lock or on I/O
    do not count), at most ``cores``. A single thread's estimate is its CPU time; two
    threads always runnable count half. On a loaded machine it ignores what the load
    does besides taking CPUs (caches, memory bandwidth), so compare ratios of commands run
    side by side. A busy loop of 1.03 CPU-s at load 6 gave 1.02. ``seconds`` is NaN where
    /proc is missing."""

    def __init__(self, pid, cores: int = 2, window: float = 0.1):
        self.pid, self.cores, self.window = pid, cores, window
        self.prev = _sched(pid)
        self.t = time.perf_counter()
        self.seconds = 0.0 if self.prev else float("nan")
        self.run = self.wait = 0

    def sample(self, final: bool = False) -> None:
        cur = _sched(self.pid)
        for k, (a, b) in cur.items():
            pa, pb = self.prev.get(k, (0, 0))
            self.run += a - pa
            self.wait += b - pb
        self.prev.update(cur)
        dt = time.perf_counter() - self.t
        if dt >= self.window or final:
            if self.run > 0 and dt > 0:
                n = (self.run + self.wait) / 1e9 / dt
                self.seconds += self.run / 1e9 / min(max(n, 1.0), self.cores)
            self.t += dt
            self.run = self.wait = 0


#: the idle-machine wall estimate (s) of the last command :func:`_measured` ran
LAST_IDLE = [float("nan")]


def _measured(argv, env=None):
    """(wall, cpu, peak RSS MB, stdout) of one whole command (rusage of the children);
    its idle-machine wall estimate (:class:`_IdleWall`) goes to ``LAST_IDLE[0]``."""
    # the peak RSS through GNU time: a child forked from this (large) process would report
    # this process's size as its own peak
    timer = "/usr/bin/time" if os.path.exists("/usr/bin/time") else None
    fd, rss_file = tempfile.mkstemp(suffix=".rss")
    os.close(fd)
    if timer:
        argv = [timer, "-f", "%M", "-o", rss_file, *argv]
    before = children_cpu()
    t0 = time.perf_counter()
    # the command's output goes to files: a pipe could fill while this polls
    fo, fe = tempfile.TemporaryFile("w+"), tempfile.TemporaryFile("w+")
    p = subprocess.Popen(argv, stdout=fo, stderr=fe, text=True, env=env)
    idle = _IdleWall(p.pid, cores=os.cpu_count() or 1)
    while True:
        pid, status, ru = os.wait4(p.pid, os.WNOHANG)
        if pid:
            break
        idle.sample()
        time.sleep(0.005)
    wall = time.perf_counter() - t0
    idle.sample(final=True)             # the last window, up to the command's exit
    LAST_IDLE[0] = idle.seconds
    rss = ru.ru_maxrss / 1024.0
    if timer:
        with open(rss_file) as f:
            lines = f.read().split()
        rss = float(lines[-1]) / 1024.0 if lines and lines[-1].isdigit() else float("nan")
    os.remove(rss_file)
    fo.seek(0)
    fe.seek(0)
    out, err = fo.read(), fe.read()
    fo.close()
    fe.close()
    p.returncode = os.waitstatus_to_exitcode(status)
    if p.returncode != 0:
        raise RuntimeError(f"{' '.join(argv[:3])}: {err[-3000:]}")
    cpu = children_cpu() - before
    return wall, cpu, rss, out


def mosaic_subprocess(paths, out, env=None, **opts):
    """swathflow mosaic in a fresh interpreter: (wall s, peak RSS MB, report) where the
    report also holds ``cpu`` (s, whole process) and ``seconds`` (in-process). ``env``:
    the child's environment (default this process's)."""
    arg = json.dumps(dict(paths=paths, out=out, **opts))
    sec, cpu, rss, stdout = _measured([sys.executable, "-c", _CHILD, arg], env)
    rep = json.loads(stdout.strip().splitlines()[-1])
    rep["cpu"] = cpu
    rep["idle"] = LAST_IDLE[0]
    return sec, rss, rep


def offset_errors(rep, shifts):
    nodes = {n["node"]: np.array(n["offset"]) for n in rep["nodes"]}
    return np.array([np.hypot(*(nodes[str(k)] - shifts[k])) for k in range(len(shifts))])


def bench_memory(work, base_strips=6, base_rows=1024):
    print("\n== peak memory versus area (fresh subprocess per run) ==")
    print(f"{'area':>5} {'grid (rows x cols)':>20} {'Mpx':>7} {'float32 array MB':>17} "
          f"{'peak RSS MB':>12} {'seconds':>8} {'Mpx/s':>6} {'max offset err px':>18}")
    rows = []
    for f, (ks, kr) in ((1, (1, 1)), (4, (2, 2)), (16, (4, 4))):
        d = os.path.join(work, f"mem{f}")
        g = generate(d, base_strips * ks, base_rows * kr)
        H, W = g["shape"]
        sec, rss, rep = mosaic_subprocess(g["paths"], os.path.join(work, f"mem{f}.tif"))
        err = offset_errors(rep, g["shifts"]).max()
        rows.append((f, H, W, rss, sec))
        print(f"{f:>4}x {H:>9} x {W:<9} {H * W / 1e6:>7.2f} {H * W * 4 / 2**20:>17.1f} "
              f"{rss:>12.1f} {sec:>8.1f} {H * W / 1e6 / sec:>6.2f} {err:>18.3f}", flush=True)
        shutil.rmtree(d, ignore_errors=True)
    return rows


_MERGE = (
    "import sys, json, time, rasterio\nfrom rasterio.merge import merge\n"
    "p = json.loads(sys.argv[1]); t0 = time.perf_counter(); c0 = time.process_time()\n"
    "arr, tr = merge(p['paths'])\n"
    "with rasterio.open(p['paths'][0]) as s: prof = s.profile\n"
    "prof.update(height=arr.shape[1], width=arr.shape[2], transform=tr, tiled=True, "
    "blockxsize=512, blockysize=512, compress='deflate')\n"
    "with rasterio.open(p['out'], 'w', **prof) as d: d.write(arr)\n"
    "print(json.dumps({'seconds': time.perf_counter() - t0, "
    "'cpu': time.process_time() - c0}))\n")


def _peer_commands(work, folder, paths):
    """The peers as whole commands: (name, argv list run one after the other)."""
    rio = os.path.join(os.path.dirname(sys.executable), "rio")
    out = []
    if os.path.exists(rio):
        out.append(("rio merge (GTiff, deflate)", [[rio, "merge", "--overwrite", "--co",
                    "compress=deflate", "--co", "tiled=true", "--co", "blockxsize=512",
                    "--co", "blockysize=512", *paths,
                    os.path.join(work, "rio.tif")]]))
    if shutil.which("gdalbuildvrt") and shutil.which("gdal_translate"):
        vrt = os.path.join(work, "m.vrt")
        out.append(("gdalbuildvrt + gdal_translate -of COG", [
            ["gdalbuildvrt", "-q", "-overwrite", "-srcnodata", "-9999", "-vrtnodata",
             "-9999", vrt, *paths],
            ["gdal_translate", "-q", "-of", "COG", "-co", "COMPRESS=DEFLATE", "-co",
             "NUM_THREADS=2", vrt, os.path.join(work, "vrt.tif")]]))
    if shutil.which("gdalwarp"):
        out.append(("gdalwarp -of COG (2 threads)", [
            ["gdalwarp", "-q", "-overwrite", "-srcnodata", "-9999", "-dstnodata", "-9999",
             "-multi", "-wo", "NUM_THREADS=2", "-of", "COG", "-co", "COMPRESS=DEFLATE",
             *paths, os.path.join(work, "warp.tif")]]))
    gm = shutil.which("gdal_merge.py") or shutil.which("gdal_merge")
    if gm:
        out.append(("gdal_merge.py (GTiff, deflate)", [
            [gm, "-q", "-o", os.path.join(work, "gm.tif"), "-n", "-9999", "-a_nodata",
             "-9999", "-co", "COMPRESS=DEFLATE", "-co", "TILED=YES", *paths]]))
    return out


def _peer_round(work, d, g, env, sf, quick, gdal):
    """One round of the side-by-side runs: (rows, mosaic() report, max offset error)."""
    paths = g["paths"]
    rows = []       # (name, whole wall, whole cpu, in-process s, rss, idle-machine wall est.)
    if not quick:
        w, c, r, _ = _measured([sf, "mosaic", d, "--out", os.path.join(work, "cli.tif"),
                                "--anchor", "0", "-q"], env)
        rows.append((CLI_ROW, w, c, None, r, LAST_IDLE[0]))
    # the same environment as the peers' (GDAL_NUM_THREADS=2)
    w, r, rep = mosaic_subprocess(paths, os.path.join(work, "sf1.tif"), env)
    err = offset_errors(rep, g["shifts"]).max()
    rows.append(("swathflow mosaic() one process, threads (same work)", w, rep["cpu"],
                 rep["seconds"], r, rep["idle"]))
    w, r, rb = mosaic_subprocess(paths, os.path.join(work, "sf_blend.tif"), env, match=False,
                                 png=False)
    rows.append((BLEND_ROW, w, rb["cpu"], rb["seconds"], r, rb["idle"]))
    for name, cmds in (_peer_commands(work, d, paths) if gdal else []):
        w = c = r = e = 0.0
        for argv in cmds:
            w1, c1, r1, _ = _measured(argv, env)
            w, c, r, e = w + w1, c + c1, max(r, r1), e + LAST_IDLE[0]
        rows.append((name, w, c, None, r, e))
    # the floor under our rows: an interpreter that only starts numba (import and the first
    # call of a cached kernel: its runtime), no mosaic work at all
    w, c, r, _ = _measured([sys.executable, "-c", _NUMBA_START], env)
    rows.append((FLOOR_ROW, w, c, None, r, LAST_IDLE[0]))
    w, c, r, out = _measured([sys.executable, "-c", _MERGE, json.dumps(dict(
        paths=paths, out=os.path.join(work, "merge.tif")))], env)
    rows.append(("rasterio.merge.merge + write (python -c)", w, c,
                 json.loads(out)["seconds"], r, LAST_IDLE[0]))
    return rows, rep, err


_NUMBA_START = ("from swathflow.mosaicking.mosaic import load_kernels\n"
                "load_kernels()\n")
FLOOR_ROW = "floor: numba's start alone (no mosaic work)"
CLI_ROW = "swathflow mosaic (CLI: match+network+feather, COG+PNG)"
BLEND_ROW = "swathflow blend only (feather, COG)"


def _medians(rounds):
    """Per tool, the median of every column over the rounds that ran it."""
    import statistics
    out = []
    for name, *_ in rounds[0]:
        runs = [row for rows in rounds for row in rows if row[0] == name]
        cols = [None if runs[0][k] is None else statistics.median(row[k] for row in runs)
                for k in range(1, 6)]
        out.append((name, *cols))
    return out


def _ratio_lines(rounds) -> None:
    """Each round's ratio of the CLI and the blend to that round's rasterio.merge (idle
    estimate and wall), their medians and how many rounds meet the targets (issue 15:
    the command within 2x, the blend no slower)."""
    import statistics
    for name, short, target in ((CLI_ROW, "swathflow mosaic (CLI)", 2.0),
                                (BLEND_ROW, "blend alone", 1.0)):
        pairs = [(row, rows[-1]) for rows in rounds for row in rows if row[0] == name]
        if not pairs:
            continue
        for label, k in (("idle est.", 5), ("wall", 1)):
            r = [a[k] / m[k] for a, m in pairs]
            print(f"{short} / merge, {label}: {' '.join(f'{x:.2f}' for x in r)}; median "
                  f"{statistics.median(r):.2f}, {sum(x <= target for x in r)} of {len(r)} "
                  f"rounds within {target:g}x")


def bench_peers(work, n_strips=12, length=2048, label="48 swings", quick=False, repeat=1):
    each = "one run each" if repeat == 1 else \
        f"{repeat} alternated rounds (GDAL peers in the first only), medians"
    print(f"\n== side by side, same inputs ({label}), {each} ==")
    d = os.path.join(work, f"peers{n_strips}")
    g = generate(d, n_strips, length)
    H, W = g["shape"]
    mpx = H * W / 1e6
    paths = g["paths"]
    env = dict(os.environ, GDAL_NUM_THREADS="2")
    sf = os.path.join(os.path.dirname(sys.executable), "swathflow")
    # once before measuring: the first run after an install compiles and caches the numba
    # kernels (a one-off cost of several seconds a user meets once, not per mosaic)
    _measured([sf, "mosaic", d, "--out", os.path.join(work, "warm.tif"), "--anchor", "0",
               "-q", "--no-match"] if quick else
              [sf, "mosaic", d, "--out", os.path.join(work, "warm.tif"), "--anchor", "0",
               "-q"], env)
    rounds = []
    for k in range(max(1, repeat)):
        rows, rep, err = _peer_round(work, d, g, env, sf, quick, gdal=not quick and k == 0)
        rounds.append(rows)
    rows = _medians(rounds) if len(rounds) > 1 else rounds[0]
    ref = rows[-1]
    print(f"grid {H} x {W} = {mpx:.2f} Mpx, {len(paths)} swings; strip offsets recovered to "
          f"{err:.3f} px (max); in one process: match {rep['seconds_match']:.2f} s, render "
          f"{rep['seconds_render']:.2f} s, COG {rep['seconds_total'] - rep['seconds_render']:.2f}"
          f" s, PNGs {rep['seconds_quicklook']:.2f} s")
    print("whole = the command from start to exit (interpreter start-up and imports "
          "included); in-process = the call alone, timed inside; CPU = user + sys of the "
          "process and its children; idle est. = the whole command's wall time on an idle "
          f"machine of {os.cpu_count()} cores, estimated from the scheduler's accounting "
          "(its threads' CPU time over how many were runnable: meaningful under load, when "
          "the wall times are not)")
    print(f"{'tool':<56} {'whole s':>8} {'CPU s':>7} {'in-proc s':>9} {'RSS MB':>7} "
          f"{'whole/merge':>11} {'in-proc/merge':>13} {'idle est. s':>11} {'idle/merge':>10}")
    for name, w, c, ip, r, e in rows:
        ipr = "" if ip is None else f"{ip / ref[3]:.2f}"
        print(f"{name:<56} {w:>8.2f} {c:>7.2f} {'' if ip is None else f'{ip:.2f}':>9} "
              f"{r:>7.0f} {w / ref[1]:>11.2f} {ipr:>13} {e:>11.2f} {e / ref[5]:>10.2f}")
    if len(rounds) > 1:
        _ratio_lines(rounds)
    shutil.rmtree(d, ignore_errors=True)
    return rows


def bench_paper(work):
    print("\n== the paper's job: 24 strips x 6 km, 2 m pixels, 30 deg FOV from 650 m ==")
    swath_m = 2 * 650 * np.tan(np.radians(15))
    swath = int(round(swath_m / 2.0))
    n, length = 24, 3000
    d = os.path.join(work, "paper")
    g = generate(d, n, length, swath=swath, overlap=0.2, swing_rows=500)
    H, W = g["shape"]
    km2 = H * W * 4 / 1e6
    print(f"swath {swath_m:.0f} m = {swath} px, grid {H} x {W} px = {km2:.1f} km2, "
          f"{len(g['paths'])} swings (simulation {g['seconds']:.0f} s)")
    sec, rss, rep = mosaic_subprocess(g["paths"], os.path.join(work, "paper.tif"))
    err = offset_errors(rep, g["shifts"])
    print(f"mosaic end to end (match {len(g['paths'])} swings, network, feather, COG, PNG): "
          f"{sec:.1f} s ({sec / 60:.2f} min) vs about 45 min in 2000; peak RSS {rss:.0f} MB; "
          f"strip offsets recovered to {err.max():.3f} px (max), {np.median(err):.3f} px "
          f"(median); {rep['skipped']} overlaps skipped")
    shutil.rmtree(d, ignore_errors=True)
    return sec


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--memory", action="store_true")
    ap.add_argument("--peers", action="store_true")
    ap.add_argument("--paper", action="store_true")
    ap.add_argument("--peers16", action="store_true",
                    help="the side by side run on 16x the area of --peers (768 swings)")
    ap.add_argument("--quick", action="store_true",
                    help="--peers/--peers16: only swathflow's mosaic() and blend and "
                         "rasterio.merge (no CLI run, no GDAL peers)")
    ap.add_argument("--repeat", type=int, default=1, metavar="N",
                    help="--peers/--peers16: N alternated rounds of swathflow's runs and "
                         "rasterio.merge (the GDAL peers once), the table of medians and "
                         "each round's ratios to merge (the machine is shared: one round "
                         "says little)")
    ap.add_argument("--regional", type=float, metavar="GPX", default=0.0,
                    help="the regional case: a mosaic of GPX gigapixels (cheap texture), "
                         "wall time and peak RSS, and four quarter runs compared pixel "
                         "for pixel with the whole")
    ap.add_argument("--quarters-at-once", type=int, default=1, choices=(1, 2, 4),
                    help="regional case: quarter runs started together (default 1)")
    ap.add_argument("--work", help="work folder (default: a temp folder)")
    ap.add_argument("--keep", action="store_true", help="keep the work folder")
    a = ap.parse_args(argv)
    if not (a.memory or a.peers or a.paper or a.peers16 or a.regional):
        a.memory = a.peers = a.paper = True
    work = a.work or tempfile.mkdtemp(prefix="swathflow-bench-mosaic-")
    os.makedirs(work, exist_ok=True)
    print(f"swathflow mosaic benchmark, {os.cpu_count()} cores, work folder {work}")
    print("reproduce: python benchmarks/bench_mosaic.py "
          + " ".join(f"--{k}" for k in ("memory", "peers", "paper", "peers16") if getattr(a, k))
          + (" --quick" if a.quick else "")
          + (f" --repeat {a.repeat}" if a.repeat > 1 else "")
          + (f" --regional {a.regional}" if a.regional else ""))
    try:
        if a.memory:
            bench_memory(work)
        if a.peers:
            bench_peers(work, quick=a.quick, repeat=a.repeat)
        if a.paper:
            bench_paper(work)
        if a.peers16:
            bench_peers(work, n_strips=48, length=8192, label="16x area, 768 swings",
                        quick=a.quick, repeat=a.repeat)
        if a.regional:
            from bench_regional import bench_regional
            bench_regional(work, a.regional, at_once=a.quarters_at_once)
    finally:
        if not a.keep and not a.work:
            shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
