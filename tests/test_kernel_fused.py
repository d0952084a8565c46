"""The fused painter-resampler (swathflow.rectification.paint.paint_gather, through
kernel.resample_leaves) against closed forms: a raw plane resampled at the bilinear
interpolation of each leaf's corners, leaves painted in order (later ones overwrite shared
edges), off-image pixels and nodata taps."""
from __future__ import annotations

import numpy as np
import pytest
from swathflow.rectification import kernel as K
from swathflow.rectification.lattice import Leaves

NL, NE = 40, 60


def _plane(li, ei):
    return 100.0 + 3.0 * li + 2.0 * ei


def _leaves():
    # a coarse 8 x 16 leaf, then two finer ones over its right edge (overwriting it)
    # and a leaf running off the raw image; corners (line, element) are linear maps
    def corners(r, c, sr, sc, f):
        return [f(r, c), f(r, c + sc), f(r + sr, c), f(r + sr, c + sc)]

    def g(r, c):
        return (5.0 + 0.37 * r + 0.11 * c, 4.0 + 0.05 * r + 0.41 * c)

    def h(r, c):                                  # a different (finer) map on its leaves
        return (5.2 + 0.37 * r + 0.11 * c, 4.1 + 0.05 * r + 0.41 * c)

    def off(r, c):                                # runs past the last raw line
        return (30.0 + 2.0 * r, 10.0 + 0.3 * c)
    cells = [(0, 0, 8, 16, g), (0, 16, 4, 4, h), (4, 16, 4, 4, h), (9, 0, 6, 10, off)]
    cl = np.array([c[:4] for c in cells], np.int64)
    co = np.array([corners(*c) for c in cells], float)
    return Leaves(cl, co, (16, 21), 0), cells


def _expected(cells, shape):
    li = np.full(shape, np.nan)
    ei = np.full(shape, np.nan)
    for r, c, sr, sc, f in cells:
        q = [f(r, c), f(r, c + sc), f(r + sr, c), f(r + sr, c + sc)]
        for i in range(min(sr + 1, shape[0] - r)):
            for j in range(min(sc + 1, shape[1] - c)):
                a, b = i / sr, j / sc
                for k in range(2):
                    li_ei = ((1 - a) * (1 - b) * q[0][k] + (1 - a) * b * q[1][k]
                             + a * (1 - b) * q[2][k] + a * b * q[3][k])
                    (li if k == 0 else ei)[r + i, c + j] = li_ei
    off = ~((li >= -0.5) & (li <= NL - 0.5) & (ei >= -0.5) & (ei <= NE - 0.5))
    li[off] = np.nan
    ei[off] = np.nan
    return li, ei


@pytest.mark.parametrize("dtype,out", [(np.float32, np.float32), (np.uint16, np.uint16)])
def test_fused_paint_and_bilinear_match_closed_form(dtype, out):
    li_raw, ei_raw = np.mgrid[0:NL, 0:NE].astype(float)
    raw = _plane(li_raw, ei_raw).astype(dtype)
    lv, cells = _leaves()
    l0, e0 = 2, 3                                 # the window read for the tile
    window = raw[l0:NL, e0:NE][None]
    nodata_out = np.nan if np.dtype(out).kind == "f" else 0
    v, ok = K.resample_leaves(window, lv, l0, e0, NL, NE, "bilinear", None, out, nodata_out)
    li, ei = _expected(cells, lv.shape)
    want = _plane(np.clip(li, l0, NL - 1), np.clip(ei, e0, NE - 1))
    has = ~np.isnan(li)
    assert np.array_equal(ok, has) and has.sum() > 150 and (~has).sum() > 20
    tol = 1e-3 if np.dtype(out).kind == "f" else 0.5 + 1e-6
    assert np.abs(v[0][has] - want[has]).max() <= tol
    assert (v[0][~has] == nodata_out).all() or np.isnan(v[0][~has]).all()


def test_fused_nearest_nodata_taps_and_bands():
    li_raw, ei_raw = np.mgrid[0:NL, 0:NE].astype(float)
    raw = np.stack([_plane(li_raw, ei_raw), 7 - _plane(li_raw, ei_raw)]).astype(np.int16)
    raw[1, 10, 12] = -999                          # a nodata tap in band 2 only
    lv, cells = _leaves()
    v, ok = K.resample_leaves(raw, lv, 0, 0, NL, NE, "bilinear", -999, np.int16, -32768)
    li, ei = _expected(cells, lv.shape)
    touch = (np.floor(li) <= 10) & (np.floor(li) + 1 >= 10) & (np.abs(ei - 12) < 1)
    assert touch.any()
    assert (v[1][touch] == -32768).all() and not ok[touch].any()
    fine = ~np.isnan(li) & ~touch
    assert np.abs(v[0][fine] - _plane(li, ei)[fine]).max() <= 0.5 + 1e-6
    assert np.abs(v[1][fine] - (7 - _plane(li, ei))[fine]).max() <= 0.5 + 1e-6
    n, okn = K.resample_leaves(raw, lv, 0, 0, NL, NE, "nearest", -999, np.int16, -32768)
    near = ~np.isnan(li) & ~((np.floor(li + 0.5) == 10) & (np.floor(ei + 0.5) == 12))
    with np.errstate(invalid="ignore"):         # a coordinate half-way: either tap is right
        tie = (np.abs(li % 1 - 0.5) < 1e-9) | (np.abs(ei % 1 - 0.5) < 1e-9)
    sure = near & ~tie
    assert np.array_equal(n[0][sure], _plane(np.floor(li + 0.5), np.floor(ei + 0.5))[sure])
    assert np.array_equal(okn[~tie], near[~tie])


def test_cubic_and_exact_tiles_are_left_to_the_painter():
    lv, _ = _leaves()
    raw = np.zeros((1, NL, NE), np.float32)
    assert K.resample_leaves(raw, lv, 0, 0, NL, NE, "cubic", None, np.float32, np.nan) is None
    cube = np.zeros((K.FUSED_BANDS + 1, NL, NE), np.uint16)
    assert K.resample_leaves(cube, lv, 0, 0, NL, NE, "bilinear", None, np.uint16, 0) is None
