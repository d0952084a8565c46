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


# inside one_heap a 20 MB block comes from the heap and, freed, stays there; afterwards the
# free memory is given back
ONE_HEAP = """
import ctypes, numpy as np
from swathflow.rectification.heap import one_heap
class Info(ctypes.Structure):
    _fields_ = [(n, ctypes.c_size_t) for n in ("arena", "ordblks", "smblks", "hblks",
                "hblkhd", "usmblks", "fsmblks", "uordblks", "fordblks", "keepcost")]
libc = ctypes.CDLL(None)
libc.mallinfo2.restype = Info
with one_heap() as ok:
    a = np.ones(20 << 17)
    mapped = libc.mallinfo2().hblkhd
    del a
    kept = libc.mallinfo2().arena
after = libc.mallinfo2().arena
print(ok, mapped >> 20, kept >> 20, after >> 20)
"""


@pytest.mark.skipif(platform.libc_ver()[0] != "glibc", reason="glibc's mallopt only")
def test_one_heap_keeps_a_swings_blocks_then_gives_them_back():
    out = subprocess.run([sys.executable, "-c", ONE_HEAP], capture_output=True, text=True,
                         check=True, timeout=120).stdout.split()
    ok, mapped, kept, after = out[0] == "True", *map(int, out[1:])
    assert ok
    assert mapped < 20          # a fresh process maps a 20 MB block by itself
    assert kept >= 20           # freed, it stays in the heap for the next one
    assert after < 20           # given back on leaving
