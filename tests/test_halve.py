"""The overview reduction (swathflow.rectification.halve): the integer kernel gives the
values of the float formula (the mean of the valid pixels of each 2 x 2 cell, rounded half
up) for every integer type it takes, with and without a nodata value, at odd edges."""
from __future__ import annotations

import math

import numpy as np
import pytest
from swathflow.rectification.halve import _halve_any, halve


def _reference(src, nodata, use_nodata):
    """The closed form in numpy, float64: cells clamped at the right and bottom edges."""
    nb, h, w = src.shape
    i, j = np.arange(-(-h // 2)), np.arange(-(-w // 2))
    r0, r1 = 2 * i, np.minimum(2 * i + 1, h - 1)
    c0, c1 = 2 * j, np.minimum(2 * j + 1, w - 1)
    x = src.astype(np.float64)
    four = np.stack([x[:, r][:, :, c] for r in (r0, r1) for c in (c0, c1)])
    ok = ~np.isnan(four)
    if use_nodata:
        ok &= four != nodata
    n = ok.sum(0)
    s = np.where(ok, four, 0.0).sum(0)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(n == 0, nodata, np.floor(s / n + 0.5))


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16, np.int16, np.int32, np.uint32])
@pytest.mark.parametrize("shape", [(1, 64, 64), (2, 33, 47), (1, 1, 5), (1, 6, 1)])
@pytest.mark.parametrize("nodata,use_nodata", [(0.0, True), (3.0, True), (-7.0, True),
                                               (2.5, True), (0.0, False)])
def test_integer_means_match_the_float_formula(dtype, shape, nodata, use_nodata):
    info = np.iinfo(dtype)
    rng = np.random.default_rng(sum(shape) + int(np.dtype(dtype).itemsize))
    # the type's whole range, and small values so that the nodata value is frequent
    src = np.where(rng.random(shape) < 0.5, rng.integers(info.min, info.max, shape,
                                                         endpoint=True, dtype=np.int64),
                   rng.integers(max(info.min, -8), 8, shape, endpoint=True)).astype(dtype)
    out = np.empty((shape[0], -(-shape[1] // 2), -(-shape[2] // 2)), dtype)
    halve(src, nodata, use_nodata, True, True, out)
    want = _reference(src, nodata, use_nodata)
    n_none = (want == nodata).sum() if use_nodata else 0
    with np.errstate(invalid="ignore"):
        fits = (want >= info.min) & (want <= info.max)
    np.testing.assert_array_equal(out[fits], want[fits].astype(dtype))
    assert fits.sum() >= want.size - n_none       # only cells without data may not fit
    any_out = np.empty_like(out)
    _halve_any(src, nodata, use_nodata, True, True, any_out, 0, 0)
    np.testing.assert_array_equal(out[fits], any_out[fits])


def test_every_count_of_valid_pixels_rounds_half_up():
    # cells with 4, 3, 2, 1 and 0 valid pixels (nodata 0), sums at every remainder
    cells = [(5, 6, 7, 9), (5, 6, 0, 8), (0, 5, 6, 0), (0, 0, 0, 7), (0, 0, 0, 0),
             (1, 2, 2, 2), (1, 1, 0, 1), (1, 2, 0, 0), (1, 1, 1, 2), (2, 2, 2, 0)]
    src = np.zeros((1, 2, 2 * len(cells)), np.uint16)
    for k, (a, b, c, d) in enumerate(cells):
        src[0, :, 2 * k:2 * k + 2] = [[a, b], [c, d]]
    out = np.empty((1, 1, len(cells)), np.uint16)
    halve(src, 0.0, True, True, True, out)
    want = []
    for cell in cells:
        v = [x for x in cell if x]
        want.append(math.floor(sum(v) / len(v) + 0.5) if v else 0)
    assert out[0, 0].tolist() == want == [7, 6, 6, 7, 0, 2, 1, 2, 1, 2]


@pytest.mark.parametrize("dtype", [np.uint16, np.float32])
def test_offsets_write_into_the_whole_array_as_far_as_it_reaches(dtype):
    rng = np.random.default_rng(5)
    src = rng.integers(0, 50, (1, 9, 13)).astype(dtype)
    want = _reference(src, 0.0, True).astype(dtype)          # 5 x 7
    out = np.full((1, 8, 10), 99, dtype)
    halve(src, 0.0, True, True, True, out, 2, 1)
    np.testing.assert_array_equal(out[:, 2:7, 1:8], want)
    out[:, 2:7, 1:8] = 99
    assert (out == 99).all()                                  # nothing else touched
    out = np.full((1, 4, 5), 99, dtype)                       # cut at its bottom right
    halve(src, 0.0, True, True, True, out, 1, 2)
    np.testing.assert_array_equal(out[:, 1:, 2:], want[:, :3, :3])
    out[:, 1:, 2:] = 99
    assert (out == 99).all()


def test_the_writer_passes_whole_contiguous_arrays(tmp_path, monkeypatch):
    """Views of the overview level would be another numba type: compiled code each forked
    worker loads again."""
    from swathflow.rectification import writing
    seen = []

    def spy(src, nodata, use_nodata, average, is_int, out, r0=0, c0=0):
        seen.append(src.flags.c_contiguous and out.flags.c_contiguous)
        halve(src, nodata, use_nodata, average, is_int, out, r0, c0)

    monkeypatch.setattr(writing, "_halve", spy)
    import dask.array as da
    # blocks made by a task, as the rectified tiles (a numpy array's blocks are views)
    data = da.map_blocks(lambda x: (x % 997).astype(np.uint16),
                         da.arange(1100 * 1300, chunks=256 * 1300).reshape(1100, 1300)
                         .rechunk(256), dtype=np.uint16)
    writing.write_cogs([{"path": tmp_path / "a.tif", "array": data, "grid": None,
                         "nodata": 0}], blocksize=256, scheduler="sync")
    assert len(seen) > 20 and all(seen)
