"""Peak memory of ``swathflow rectify`` on a 2,048 x 20,000 x 100-band uint16 ENVI BIL
swing (8 GB, written block by block and deleted afterwards): bounded by the tile, not by
the swing. Slow (about 10-20 min on 2 loaded cores): ``pytest -m slow
tests/test_cube_memory.py``."""
from __future__ import annotations

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))


@pytest.mark.slow
def test_8gb_bil_swing_rectifies_under_2gb_rss_and_matches_its_pattern(tmp_path):
    from bench_cube import memory_run
    r = memory_run(lines=20000, elements=2048, bands=100, gsd=1.0, workdir=tmp_path)
    assert r["raw"] == [100, r["raw"][1], 2048] and r["raw"][1] >= 19990
    assert r["peak_rss_mb"] < 2048, r
    # bands 1, 50 and 100 at 4,000 random output pixels: each band its own plane of
    # (line, element); rounding to integers (0.5 + 0.5 DN) and the lattice bound
    # (0.05 px x 2 DN/px) allow about 1.1 DN
    assert r["checked_px"] > 1000 and r["max_err_dn"] <= 1.5, r
