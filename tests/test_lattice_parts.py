"""The lattice's small compiled parts written by hand (so that numba need not compile its
merge sort, binary search and boolean indexing in every process) against numpy's own."""
import numpy as np
import pytest

from swathflow.rectification.cells import _inside, _items, _rows
from swathflow.rectification.paint import _bisect, _by_row


@pytest.mark.parametrize("n", [0, 1, 2, 7, 300])
@pytest.mark.parametrize("lo,hi", [(0, 4), (0, 512), (-7, 3)])
def test_by_row_is_numpys_stable_argsort(n, lo, hi):
    rng = np.random.default_rng(n + hi)
    cells = rng.integers(0, 9, (n, 4)).astype(np.int64)
    cells[:, 0] = rng.integers(lo, hi, n)
    assert np.array_equal(_by_row(cells), np.argsort(cells[:, 0], kind="mergesort"))


@pytest.mark.parametrize("n", [0, 1, 2, 9, 100])
def test_bisect_is_numpys_searchsorted(n):
    a = np.sort(np.random.default_rng(n).integers(-5, 20, n)).astype(np.int64)
    for x in range(-8, 24):
        assert _bisect(a, x, False) == np.searchsorted(a, x, side="left")
        assert _bisect(a, x, True) == np.searchsorted(a, x, side="right")


def test_rows_items_and_inside_are_boolean_indexing():
    rng = np.random.default_rng(3)
    cells = rng.integers(0, 40, (50, 4)).astype(np.int64)
    keep = rng.random(50) < 0.4
    flags = rng.random(50) < 0.5
    assert np.array_equal(_rows(cells, keep), cells[keep])
    assert np.array_equal(_items(flags, keep), flags[keep])
    inside = (cells[:, 0] <= 29) & (cells[:, 1] <= 19)
    assert np.array_equal(_inside(cells, 30, 20), cells[inside])
    assert _inside(cells, 40, 40) is cells or np.array_equal(_inside(cells, 40, 40), cells)
