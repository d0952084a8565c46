"""keep_freed_memory: freed blocks of a few MB are reused, not mapped and zeroed again."""
import platform
import subprocess
import sys

import pytest

from swathflow.rectification import heap

# three 4 MB blocks allocated, touched and freed twice; the page faults of the second round
SCRIPT = """
import resource, sys, numpy as np
if sys.argv[1] == "keep":
    from swathflow.rectification.heap import keep_freed_memory
    assert keep_freed_memory()
def round_():
    a = [np.ones(1 << 20, np.float32) for _ in range(3)]
    del a
round_()
f0 = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
round_()
print(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - f0)
"""


def _faults(mode: str) -> int:
    out = subprocess.run([sys.executable, "-c", SCRIPT, mode], capture_output=True,
                         text=True, check=True, timeout=120)
    return int(out.stdout.split()[-1])


@pytest.mark.skipif(platform.libc_ver()[0] != "glibc", reason="glibc's mallopt only")
def test_freed_blocks_are_reused():
    default = _faults("default")
    if default < 1000:
        pytest.skip(f"this glibc kept the blocks by itself ({default} faults)")
    # 3 x 1024 pages were mapped afresh without the call; with it, next to none
    assert _faults("keep") < 100


def test_other_c_library_unchanged(monkeypatch):
    monkeypatch.setattr(heap.platform, "libc_ver", lambda: ("musl", ""))
    assert heap.keep_freed_memory() is False
