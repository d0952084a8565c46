"""swathflow.tasks.ahead: the mosaic's kernels compiled ahead in a background process on a
new install. Its synthetic swings must exercise the matching for real (their known strip
shifts recovered), the child must fill an empty numba cache so that a mosaic then
compiles none of the mosaic's kernels, and the child is stopped and its folder removed
when the command's block ends."""
from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pytest

from swathflow.tasks import ahead


def test_the_synthetic_mosaic_recovers_the_strips_known_shifts(tmp_path):
    """Strip k's pixel (r, c) shows the texture at grid position (r - 0.8 k, c + 1.3 k):
    the strip is displaced by t_k = (0.8 k, -1.3 k) px, and the matched network (held at
    its mean) must give each strip t_k minus the mean of the t_k."""
    report = ahead.compile_mosaic_kernels(str(tmp_path))
    nodes = {int(n["node"]): n["offset"] for n in report["nodes"]}
    assert sorted(nodes) == list(range(ahead.STRIPS))
    truth = np.array([[0.8 * k, -1.3 * k] for k in range(ahead.STRIPS)])
    truth -= truth.mean(axis=0)
    got = np.array([nodes[k] for k in range(ahead.STRIPS)])
    np.testing.assert_allclose(got, truth, atol=0.05)
    assert (tmp_path / "mosaic.tif").exists()


def test_the_child_is_stopped_and_its_folder_removed_when_the_block_ends(monkeypatch):
    monkeypatch.setattr(ahead, "cold", lambda: True)
    with ahead.in_background() as child:
        assert child is not None and child.poll() is None
        folder = child.args[-1]
        assert os.path.isdir(folder)
        assert child in ahead._CHILDREN
    assert child.returncode is not None                   # stopped (or done), reaped
    assert not os.path.exists(folder)
    assert child not in ahead._CHILDREN


def test_the_childs_command_runs_to_its_end(monkeypatch):
    """The child's command ends with exit code 0, its synthetic mosaic written (the
    kernels compiled and cached on the way), and :func:`ahead.wait` returns when it
    ends."""
    import time
    monkeypatch.setattr(ahead, "cold", lambda: True)
    with ahead.in_background() as child:
        assert child.wait(timeout=600) == 0
        assert os.path.exists(os.path.join(child.args[-1], "mosaic.tif"))
        t = time.monotonic()
        ahead.wait(timeout=60)
        assert time.monotonic() - t < 1


def test_a_child_that_gets_no_cpu_is_not_waited_for(monkeypatch):
    """A child that uses no CPU (here: asleep; in life: starved at its low priority by
    other work) is left after a second or two, not waited for to the timeout."""
    import time
    child = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    monkeypatch.setattr(ahead, "_CHILDREN", [child])
    try:
        t = time.monotonic()
        ahead.wait(timeout=60)
        assert time.monotonic() - t < 10
        assert child.poll() is None
    finally:
        child.kill()
        child.wait()


def test_nothing_starts_when_the_cache_holds_the_kernels(monkeypatch):
    monkeypatch.setattr(ahead, "cold", lambda: False)
    with ahead.in_background() as child:
        assert child is None


COUNT = """
import json, sys
from numba.core import event
compiled = []
class L(event.Listener):
    def on_start(self, ev):
        d = ev.data.get("dispatcher")
        compiled.append(d.py_func.__module__ + "." + d.py_func.__qualname__)
    def on_end(self, ev):
        pass
event.register("numba:compile", L())
from swathflow.tasks import ahead
cold = ahead.cold()
ahead.compile_mosaic_kernels(sys.argv[1])
print(json.dumps(dict(cold=cold, compiled=compiled)))
"""


@pytest.mark.slow
def test_the_child_fills_an_empty_cache_for_the_mosaic(tmp_path):
    """With an empty numba cache (a new install): the child's command, then a mosaic in
    another process compiles none of the mosaic's kernels (it loads them all)."""
    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path / "numba"))
    before = subprocess.run([sys.executable, "-c", "from swathflow.tasks import ahead; "
                             "print(ahead.cold())"], env=env, capture_output=True,
                            text=True, timeout=120)
    assert before.stdout.strip() == "True", before.stderr
    (tmp_path / "a").mkdir()
    subprocess.run([sys.executable, "-m", "swathflow.tasks.ahead", str(tmp_path / "a")],
                   env=env, check=True, timeout=600)
    (tmp_path / "b").mkdir()
    r = subprocess.run([sys.executable, "-c", COUNT, str(tmp_path / "b")], env=env,
                       capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout.strip().splitlines()[-1])
    assert out["cold"] is False
    assert [k for k in out["compiled"] if k.startswith("swathflow.mosaicking")] == []
