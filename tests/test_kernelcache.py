"""swathflow's compiled kernels: numba's own ``njit(cache=True)``; a kernel compiles in
the first process and loads from numba's on-disk cache in the next, computing what the
truth says; :mod:`swathflow.kernelcache` tells whether the cache holds a kernel (the first
run's notice) and lets processes take turns compiling."""
from __future__ import annotations

import ast
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
from scipy import ndimage

ROOT = Path(__file__).resolve().parents[1]

KERNEL = """
import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def ramp(n, step):
    out = np.empty(n)
    for i in range(n):
        out[i] = i * step
    return out
"""

RUN = """
import json, sys
sys.path.insert(0, {folder!r})
import kmod
from swathflow.kernelcache import cached
before = cached(kmod.ramp)
r = kmod.ramp(5, 0.5)
print(json.dumps(dict(values=[float(v) for v in r], before=before, after=cached(kmod.ramp),
                      hits=sum(kmod.ramp.stats.cache_hits.values()),
                      misses=sum(kmod.ramp.stats.cache_misses.values()))))
"""


def _fresh(code: str, env=None) -> dict:
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                       timeout=300, env=env)
    assert r.returncode == 0, r.stderr
    return json.loads(r.stdout.strip().splitlines()[-1])


def test_a_kernel_compiles_once_then_loads_from_the_cache(tmp_path):
    """First process: not cached, compiled (a miss), cached after; second: cached before
    the call, loaded (a hit); both give i * step."""
    (tmp_path / "kmod.py").write_text(KERNEL)
    first = _fresh(RUN.format(folder=str(tmp_path)))
    assert first["values"] == [0.0, 0.5, 1.0, 1.5, 2.0]
    assert (first["before"], first["after"]) == (False, True)
    assert (first["hits"], first["misses"]) == (0, 1)
    second = _fresh(RUN.format(folder=str(tmp_path)))
    assert second["values"] == [0.0, 0.5, 1.0, 1.5, 2.0]
    assert (second["before"], second["after"]) == (True, True)
    assert (second["hits"], second["misses"]) == (1, 0)


def test_cached_is_false_for_a_kernel_edited_since(tmp_path):
    """A kernel moved to another line (its source edited) has no index file of its own
    yet: numba compiles it again, and ``cached`` says so beforehand."""
    (tmp_path / "kmod.py").write_text(KERNEL)
    _fresh(RUN.format(folder=str(tmp_path)))
    (tmp_path / "kmod.py").write_text("\n\n" + KERNEL)
    out = _fresh(RUN.format(folder=str(tmp_path)))
    assert (out["before"], out["after"], out["misses"]) == (False, True, 1)


def test_the_mosaic_distance_from_the_cache_is_the_exact_distance(tmp_path):
    """The feather's capped distance, loaded from the cache in a fresh interpreter, equals
    scipy's exact Euclidean distance transform below the cap."""
    ok = np.zeros((60, 90), bool)
    ok[4:-3, 7:-11] = True
    ok[20:30, 40:47] = False
    code = ("import json, sys, numpy as np\n"
            "from swathflow.mosaicking import kernels as K\n"
            f"ok = np.array({ok.astype(int).tolist()}, bool)\n"
            "d = K.capped_distance(ok, 12.0)\n"
            "print(json.dumps(dict(d=d.tolist(),\n"
            "    hits=sum(K.capped_distance.stats.cache_hits.values()))))\n")
    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path))
    _fresh(code, env)                                   # compiled and cached
    out = _fresh(code, env)
    assert out["hits"] == 1
    truth = np.minimum(ndimage.distance_transform_edt(np.pad(ok, 1))[1:-1, 1:-1], 12.0)
    np.testing.assert_allclose(np.array(out["d"]), truth, atol=1e-5)


def test_demo_says_once_that_the_first_run_compiles(tmp_path):
    """`swathflow demo`'s notice: printed while numba's cache lacks the engine's kernels
    (an empty NUMBA_CACHE_DIR), not once they are cached."""
    code = ("import json, sys, types, numpy as np\n"
            "from swathflow.flows.cli import commands\n"
            "from swathflow.rectification.paint import paint_window\n"
            "args = types.SimpleNamespace(quiet=False, verbose=False)\n"
            "commands._first_run_notice(args)\n"
            "paint_window(np.ones((1, 4), np.int64), np.zeros((1, 4, 2)), 2, 2, 0, 0, 4, 4)\n"
            "print(json.dumps(0))\n")
    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path))
    runs = [subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                           timeout=300, env=env) for _ in range(2)]
    assert [r.returncode for r in runs] == [0, 0], runs[0].stderr
    assert "first run of this install" in runs[0].stderr
    assert "first run of this install" not in runs[1].stderr


TURN = """
import json, sys, time
sys.path.insert(0, {folder!r})
import kmod
from swathflow.kernelcache import compiling_alone
with compiling_alone(kmod.ramp) as cold:
    got = time.time()
    time.sleep({hold})                  # holding the turn before compiling
    values = kmod.ramp(3, 1.0).tolist()
    out = time.time()
print(json.dumps(dict(cold=cold, got=got, out=out, values=values,
                      misses=sum(kmod.ramp.stats.cache_misses.values()))))
"""


def _start(code: str):
    return subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)


def _result(p) -> dict:
    out, err = p.communicate(timeout=300)
    assert p.returncode == 0, err
    return json.loads(out.strip().splitlines()[-1])


def test_processes_take_turns_only_while_the_kernel_is_not_cached(tmp_path):
    """Two processes in compiling_alone with the kernel not cached: the second (started
    while the first holds its turn, before the first compiles) enters when the first
    has left, finds the kernel cached and loads it (no compilation).
    With it cached, both run the block at once (their intervals overlap). The first holds
    its turn 5 s: the second's start and imports fit in that on a loaded CI machine."""
    (tmp_path / "kmod.py").write_text(KERNEL)
    first = _start(TURN.format(folder=str(tmp_path), hold=5.0))
    time.sleep(0.5)
    second = _start(TURN.format(folder=str(tmp_path), hold=0.0))
    a, b = _result(first), _result(second)
    assert a["cold"] is True and b["cold"] is True
    assert b["got"] >= a["out"]                       # waited for the first to leave
    assert (a["misses"], b["misses"]) == (1, 0)       # compiled once, then loaded
    assert a["values"] == b["values"] == [0.0, 1.0, 2.0]
    p = _start(TURN.format(folder=str(tmp_path), hold=5.0))
    time.sleep(0.5)
    q = _start(TURN.format(folder=str(tmp_path), hold=0.0))
    c, d = _result(p), _result(q)
    assert c["cold"] is False and d["cold"] is False
    assert d["got"] < c["out"]                        # no turns: inside at the same time


PRODUCT = ("swathflow", "flows", "tasks", "sensors",
           "plugins/rotating-mirror/swathflow_rotating_mirror")


def _njit_uses(path: Path):
    """(line, what) of each use of ``njit`` in ``path`` that is not numba's own
    ``njit(cache=True, ...)``."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and any(a.name == "njit" for a in node.names) \
                and node.module != "numba":
            out.append((node.lineno, f"njit imported from {node.module}"))
        for dec in getattr(node, "decorator_list", []):
            call = dec if isinstance(dec, ast.Call) else None
            name = ast.unparse(call.func if call else dec)
            if name.split(".")[-1] not in ("njit", "jit"):
                continue
            cache = call and any(k.arg == "cache" and isinstance(k.value, ast.Constant)
                                 and k.value.value is True for k in call.keywords)
            if not cache:
                out.append((dec.lineno, f"@{ast.unparse(dec)} without cache=True"))
    return out


def test_every_kernel_is_numbas_njit_with_its_cache(tmp_path):
    found = [f"{p.relative_to(ROOT)}:{line}: {what}"
             for d in PRODUCT for p in sorted((ROOT / d).rglob("*.py"))
             for line, what in _njit_uses(p)]
    assert found == []
    bad = tmp_path / "snippet.py"              # the check can fail
    bad.write_text("from numba import njit\n@njit\ndef f(x):\n    return x\n")
    assert [w for _, w in _njit_uses(bad)] == ["@njit without cache=True"]
    bad.write_text("from mylib import njit\n@njit(cache=True)\ndef f(x):\n    return x\n")
    assert [w for _, w in _njit_uses(bad)] == ["njit imported from mylib"]
