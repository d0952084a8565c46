"""swathflow.jit: a kernel loads from numba's on-disk cache without numba's compiler
contexts (their modules are not imported), in a fresh interpreter, and computes what the
truth says; a cache miss compiles as numba always does."""
from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
from scipy import ndimage

KERNEL = """
import numpy as np
from swathflow.jit import njit


@njit(cache=True, nogil=True)
def ramp(n, step):
    out = np.empty(n)           # allocates: numba's runtime (NRT) must be started
    for i in range(n):
        out[i] = i * step
    return out
"""

RUN = """
import json, sys
sys.path.insert(0, {folder!r})
import kmod
r = kmod.ramp(5, 0.5)
print(json.dumps(dict(values=[float(v) for v in r],
                      hits=sum(kmod.ramp.stats.cache_hits.values()),
                      misses=sum(kmod.ramp.stats.cache_misses.values()),
                      compiler=[m for m in ("numba.np.arraymath", "numba.np.linalg",
                                            "numba.typed.typeddict") if m in sys.modules])))
"""


def _fresh(code: str) -> dict:
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                       timeout=300)
    assert r.returncode == 0, r.stderr
    return json.loads(r.stdout.strip().splitlines()[-1])


def test_a_cached_kernel_loads_without_the_compiler_contexts(tmp_path):
    (tmp_path / "kmod.py").write_text(KERNEL)
    first = _fresh(RUN.format(folder=str(tmp_path)))
    assert first["values"] == [0.0, 0.5, 1.0, 1.5, 2.0]
    assert (first["hits"], first["misses"]) == (0, 1)     # compiled, contexts refreshed
    assert "numba.np.arraymath" in first["compiler"]
    second = _fresh(RUN.format(folder=str(tmp_path)))
    assert second["values"] == [0.0, 0.5, 1.0, 1.5, 2.0]
    assert (second["hits"], second["misses"]) == (1, 0)   # from the cache
    assert second["compiler"] == []        # numba's own cache would have imported all three


def test_the_mosaic_distance_from_the_cache_is_the_exact_distance():
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
            "    hits=sum(K.capped_distance.stats.cache_hits.values()),\n"
            "    arraymath='numba.np.arraymath' in sys.modules)))\n")
    _fresh(code)                                   # the cache written if it was not
    out = _fresh(code)
    assert out["hits"] == 1 and out["arraymath"] is False
    truth = np.minimum(ndimage.distance_transform_edt(np.pad(ok, 1))[1:-1, 1:-1], 12.0)
    np.testing.assert_allclose(np.array(out["d"]), truth, atol=1e-5)


SORTER = """
import numpy as np
from swathflow.jit import njit


@njit(cache=True, nogil=True)
def order(x):
    return np.argsort(x)        # linked with numba.np.arrayobj's argsort and np.empty
"""

RUN_SORTER = """
import json, sys
import numpy as np
sys.path.insert(0, {folder!r})
import kmod2
x = np.array([3.0, -1.0, 2.0, 7.0, 0.5])
first = kmod2.order(x).tolist()
unloaded = "numba.np.arrayobj" not in sys.modules
import numba
fresh = numba.njit(lambda a: np.argsort(a))(x).tolist()      # compiled, not cached
print(json.dumps(dict(first=first, fresh=fresh, again=kmod2.order(x[::-1].copy()).tolist(),
                      unloaded=unloaded,
                      hits=sum(kmod2.order.stats.cache_hits.values()))))
"""


def test_a_cached_kernel_loads_without_the_numba_modules_it_was_linked_with(tmp_path):
    """A kernel linked with numba's own implementations (argsort, np.empty) loads from the
    cache without importing their module (numba.np.arrayobj), sorts right, and a
    compilation in the same process that needs that module's environment afterwards
    works, as does the cached kernel after it."""
    (tmp_path / "kmod2.py").write_text(SORTER)
    _fresh(RUN_SORTER.format(folder=str(tmp_path)))          # the cache written
    out = _fresh(RUN_SORTER.format(folder=str(tmp_path)))
    truth = np.argsort(np.array([3.0, -1.0, 2.0, 7.0, 0.5]), kind="stable").tolist()
    assert out["hits"] == 1 and out["unloaded"] is True
    assert out["first"] == truth and out["fresh"] == truth
    assert out["again"] == np.argsort(np.array([0.5, 7.0, 2.0, -1.0, 3.0])).tolist()


CALLEE = """
import numpy as np
from swathflow.jit import njit


@njit(cache=True, nogil=True)
def tripled(x):
    out = np.empty_like(x)
    for i in range(x.size):
        out[i] = 3.0 * x[i] + 1.0
    return out
"""

RUN_CALLER = """
import json, sys
import numpy as np
sys.path.insert(0, {folder!r})
import kmod3
import swathflow.jit as J
x = np.array([0.0, 1.0, -2.0, 0.25])
cached = kmod3.tripled(x).tolist()
lib = kmod3.tripled.overloads[kmod3.tripled.signatures[0]].library
unparsed = type(lib) is J._LinkedLater and "_bitcode" in lib.__dict__
import numba
caller = numba.njit(lambda a: kmod3.tripled(a).sum() + kmod3.tripled(a)[0])  # links it
print(json.dumps(dict(cached=cached, unparsed=unparsed, linked=float(caller(x)),
                      parsed="_bitcode" not in lib.__dict__,
                      hits=sum(kmod3.tripled.stats.cache_hits.values()))))
"""


def test_a_cached_kernel_is_linked_into_a_new_compilation_from_its_bitcode(tmp_path):
    """A kernel from the cache loads without its bitcode parsed (``_LinkedLater``); a
    kernel compiled afterwards in the same process that calls it links that bitcode then,
    and both compute the truth: 3x + 1."""
    (tmp_path / "kmod3.py").write_text(CALLEE)
    _fresh(RUN_CALLER.format(folder=str(tmp_path)))           # the cache written
    out = _fresh(RUN_CALLER.format(folder=str(tmp_path)))
    x = np.array([0.0, 1.0, -2.0, 0.25])
    assert out["hits"] == 1 and out["unparsed"] is True
    assert out["cached"] == (3 * x + 1).tolist()
    assert out["linked"] == float((3 * x + 1).sum() + 1.0)
    assert out["parsed"] is True


RUN_RUNTIME = """
import glob, json, os, sys
import numpy as np
from numba.core.runtime import nrtdynmod
built = []
create = nrtdynmod.create_nrt_module
nrtdynmod.create_nrt_module = lambda ctx: built.append(1) or create(ctx)
sys.path.insert(0, {folder!r})
import kmod
import numba
from numba.core.caching import FunctionCache
import swathflow.jit as J
ramp = kmod.ramp(4, 0.25).tolist()                     # cached, allocates
fresh = float(numba.njit(lambda n: np.ones(n).sum())(7))   # compiled now, links the runtime
folder = FunctionCache(J._anchor)._cache_path
print(json.dumps(dict(ramp=ramp, fresh=fresh, built=len(built),
                      files=glob.glob(os.path.join(folder, "jit.nrt-*.nbo")))))
"""


def test_numbas_runtime_starts_from_its_kept_object_code(tmp_path):
    """numba's runtime functions are compiled once and kept beside the kernels' cache: a
    fresh interpreter then starts the runtime from that file (numba's runtime module not
    built), runs a cached kernel that allocates and compiles a new one that links the
    runtime; a damaged file is compiled again, and replaced."""
    (tmp_path / "kmod.py").write_text(KERNEL)
    first = _fresh(RUN_RUNTIME.format(folder=str(tmp_path)))
    assert len(first["files"]) == 1, first
    out = _fresh(RUN_RUNTIME.format(folder=str(tmp_path)))
    assert (out["ramp"], out["fresh"], out["built"]) == ([0.0, 0.25, 0.5, 0.75], 7.0, 0)
    path = out["files"][0]
    tmp = path + ".test.tmp"
    with open(tmp, "wb") as f:
        f.write(b"not a pickle")
    os.replace(tmp, path)                                  # damaged, atomically
    again = _fresh(RUN_RUNTIME.format(folder=str(tmp_path)))
    assert (again["ramp"], again["fresh"], again["built"]) == ([0.0, 0.25, 0.5, 0.75], 7.0, 1)
    after = _fresh(RUN_RUNTIME.format(folder=str(tmp_path)))
    assert after["built"] == 0 and after["fresh"] == 7.0


def test_cached_says_whether_numbas_cache_holds_the_kernel(tmp_path):
    """``cached`` is False before a kernel's first compilation into an empty cache folder
    (what `swathflow demo` tells a new install about), True after it and in the next
    process."""
    code = ("import json, numpy as np\nfrom swathflow.jit import cached\n"
            "from swathflow.rectification.paint import _by_row\nbefore = cached(_by_row)\n"
            "order = _by_row(np.array([[2, 0, 1, 1], [0, 0, 1, 1]], np.int64))\n"
            "print(json.dumps([before, cached(_by_row), order.tolist()]))")
    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path))
    runs = [subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                           timeout=300, env=env) for _ in range(2)]
    assert [r.returncode for r in runs] == [0, 0], runs[0].stderr
    first, second = (json.loads(r.stdout.strip().splitlines()[-1]) for r in runs)
    assert first == [False, True, [1, 0]]
    assert second == [True, True, [1, 0]]


TURN = """
import json, sys, time
sys.path.insert(0, {folder!r})
import kmod
from swathflow.jit import compiling_alone
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
    import time
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
