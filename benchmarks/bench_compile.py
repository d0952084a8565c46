"""A first run on a new machine: the README's first command's job (`swathflow demo`) with
numba's cache empty (every kernel compiled) and then again with it full, side by side with
another build.

    python benchmarks/bench_compile.py                          # ours, cold then warm
    python benchmarks/bench_compile.py --baseline OLD/bin/swathflow --repeat 2
    python benchmarks/bench_compile.py --command "simulate {out}/m --preset tiny"

Each pair gets its own empty ``NUMBA_CACHE_DIR`` (cold), then the same folder again
(warm); every run a new Prefect home (so the two differ by the compilation alone).
Prints wall and CPU seconds (the command and every process it started: Dask's workers
compile what they call too) of each run, the cold run's extra over the warm one, and the
ratio to the baseline. A cache is per machine and
per install (numba keys it by the CPU and each kernel's file), so a fresh clone, a CI job
or a container meets the cold case once.
"""
from __future__ import annotations

import argparse
import os
import shlex
import shutil
import subprocess
import sys
import tempfile
import time

from cputime import children_cpu  # this folder (the scripts' own)


def _run(exe: str, command: str, cache: str, work: str) -> tuple[float, float, int]:
    """Wall and CPU seconds (children included) of ``exe command``; its exit code."""
    out = tempfile.mkdtemp(dir=work)
    env = dict(os.environ, NUMBA_CACHE_DIR=cache, PREFECT_HOME=os.path.join(out, "prefect"))
    argv = [exe, *shlex.split(command.format(out=out)), "-q"]
    before = children_cpu()
    t = time.perf_counter()
    code = subprocess.run(argv, env=env, stdout=subprocess.DEVNULL).returncode
    wall = time.perf_counter() - t
    cpu = children_cpu() - before
    shutil.rmtree(out, ignore_errors=True)
    return wall, cpu, code


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--command", default="demo --out {out}/demo",
                    help="swathflow's arguments ({out}: a temporary folder; default: the "
                         "demo)")
    ap.add_argument("--baseline", help="another build's swathflow executable, run "
                                       "alternately with ours")
    ap.add_argument("--repeat", type=int, default=1, help="cold/warm pairs per build")
    args = ap.parse_args(argv)
    ours = os.path.join(os.path.dirname(sys.executable), "swathflow")
    builds = [("ours", ours)] + ([("baseline", args.baseline)] if args.baseline else [])
    print(f"cpus: {os.cpu_count()}, load average: {os.getloadavg()[0]:.1f}; "
          f"command: swathflow {args.command}")
    figures: dict[str, list[tuple[float, float, float, float]]] = {k: [] for k, _ in builds}
    with tempfile.TemporaryDirectory(prefix="bench_compile.") as work:
        for r in range(args.repeat):
            for name, exe in builds:
                cache = tempfile.mkdtemp(dir=work, prefix="numba.")
                cold = _run(exe, args.command, cache, work)
                warm = _run(exe, args.command, cache, work)
                shutil.rmtree(cache, ignore_errors=True)
                if cold[2] or warm[2]:
                    print(f"{name}: the command failed (exit {cold[2]}, {warm[2]})")
                    return 1
                figures[name].append((cold[0], cold[1], warm[0], warm[1]))
                print(f"round {r + 1} {name:8s}: cold {cold[0]:6.1f} s / {cold[1]:6.1f} "
                      f"CPU-s, warm {warm[0]:6.1f} s / {warm[1]:6.1f} CPU-s; the cold "
                      f"cache's extra {cold[0] - warm[0]:6.1f} s / {cold[1] - warm[1]:6.1f} "
                      f"CPU-s", flush=True)
    best = {k: min(v) for k, v in figures.items()}
    for name, (cw, cc, ww, wc) in best.items():
        print(f"best of {args.repeat} {name:8s}: cold {cw:6.1f} s / {cc:6.1f} CPU-s, "
              f"warm {ww:6.1f} s / {wc:6.1f} CPU-s")
    if args.baseline:
        o, b = best["ours"], best["baseline"]
        print(f"cold run: baseline / ours {b[0] / o[0]:.2f}x wall, {b[1] / o[1]:.2f}x CPU; "
              f"warm run {b[2] / o[2]:.2f}x wall")
    print("reproduce: python benchmarks/bench_compile.py "
          + " ".join(shlex.quote(a) for a in (argv if argv is not None else sys.argv[1:])))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
