"""warm_up also makes what writing a swing's COG makes once a process (rioxarray's
template, the overview kernel's compiled code, the compressed nodata tile, the writer's
modules), so that forked workers find them made: checked in a fresh interpreter."""
from __future__ import annotations

import subprocess
import sys

SCRIPT = r"""
import sys
from numba.extending import is_jitted
from swathflow.ingest.mission import load_mission
from swathflow.rectification import api, halve
m = load_mission(sys.argv[1])
iid = m.image_ids[0]
api.warm_up(m, iid, kernel="bilinear", tile=64, dtype=None)
from swathflow.rectification import tifflayout

def state():
    kernels = {n: len(getattr(halve, n).overloads) for n in dir(halve)
               if is_jitted(getattr(halve, n))}
    return (len(api._RIO_TEMPLATES), sorted(map(repr, tifflayout._NODATA_TILES)), kernels,
            sorted(m for m in sys.modules if m.startswith("swathflow")))

before = state()
api.to_cog(api.rectify(m, iid, dtype=None, tile=64), sys.argv[2], blocksize=64)
after = state()
print("SAME" if after == before else f"CHANGED {before} -> {after}")
print("KERNELS", sum(before[2].values()), "TILES", len(before[1]))
"""


def test_warm_up_makes_what_the_writer_makes_once(tiny_mission, tmp_path):
    r = subprocess.run([sys.executable, "-c", SCRIPT, str(tiny_mission),
                        str(tmp_path / "a.tif")], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr[-3000:]
    assert "SAME" in r.stdout, r.stdout
    assert "KERNELS 1 TILES 1" in r.stdout, r.stdout
