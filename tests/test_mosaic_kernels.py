"""The compiled mosaic kernels against independent references: scipy's exact Euclidean
distance transform, scipy's spline shift, and the minimum-mean-grey-difference cost
written out shift by shift with numpy's median."""
from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

from swathflow.mosaicking import kernels as K
from swathflow.mosaicking.match_kernels import mmgd_costs


def _masks():
    rng = np.random.default_rng(5)
    yield np.ones((40, 30), bool)
    yield np.zeros((12, 9), bool)
    yield np.ones((1, 17), bool)
    yield np.ones((23, 1), bool)
    for _ in range(6):
        h, w = rng.integers(2, 90, 2)
        m = ndimage.binary_opening(rng.random((h, w)) > 0.15)
        yield m
    m = np.zeros((120, 70), bool)
    m[10:110, 5:60] = True
    m[40:50, 20:24] = False
    yield m


@pytest.mark.parametrize("cap", [3.0, 6.5, 64.0])
def test_capped_distance_is_scipys_exact_edt(cap):
    for m in _masks():
        want = np.minimum(ndimage.distance_transform_edt(np.pad(m, 1))[1:-1, 1:-1], cap)
        got = K.capped_distance(m, cap)
        assert got.dtype == np.float32
        assert np.allclose(got, want, atol=1e-5, rtol=0), np.abs(got - want).max()


@pytest.mark.parametrize("f", [(0.3, 0.7), (0.0, 0.45), (0.6, 0.0), (0.999, 0.001)])
def test_sample_clip_is_the_spline_shift_and_its_validity(f):
    """A smooth image (no clipping): the values are scipy's cubic spline shift, less the
    radiometric offset; valid where both neighbours along each shifted axis are."""
    rr, cc = np.mgrid[0:50, 0:40].astype(float)
    img = 0.5 * rr + 0.2 * cc + 3 * np.sin(rr / 9.0) * np.cos(cc / 11.0)
    ok = np.ones(img.shape, bool)
    ok[20:24, 10:13] = False
    pad = 12
    coef = ndimage.spline_filter(np.pad(img, pad, mode="edge"), order=3, mode="mirror")
    vals, valid = K.sample_clip(coef, img, ok, pad, f[0], f[1], 2.5)
    want = ndimage.shift(img, (-f[0], -f[1]), order=3, mode="nearest") - 2.5
    p = np.pad(ok, ((0, 1), (0, 1)))       # outside the image: invalid
    m = p[:-1, :-1].copy()
    if f[0] >= 1e-6:
        m &= p[1:, :-1]
    if f[1] >= 1e-6:
        m &= p[:-1, 1:]
    if f[0] >= 1e-6 and f[1] >= 1e-6:
        m &= p[1:, 1:]
    assert np.array_equal(valid, m)
    inner = valid.copy()
    inner[:3] = inner[-3:] = False
    inner[:, :3] = inner[:, -3:] = False
    assert np.abs(vals[inner] - want[inner]).max() < 1e-4
    assert np.all(vals[~valid] == 0)


def test_sample_clip_keeps_a_step_within_its_support():
    img = np.zeros((20, 20))
    img[:, 10:] = 100.0
    ok = np.ones(img.shape, bool)
    pad = 12
    coef = ndimage.spline_filter(np.pad(img, pad, mode="edge"), order=3, mode="mirror")
    vals, _ = K.sample_clip(coef, img, ok, pad, 0.0, 0.5, 0.0)
    assert vals.min() >= 0.0 and vals.max() <= 100.0
    # far from the step the spline is exact
    assert np.all(vals[:, :6] == 0.0) and np.all(vals[:, 14:19] == 100.0)


def test_fill_rows_takes_the_nearest_valid_value_of_the_row():
    val = np.arange(24, dtype=float).reshape(4, 6)
    ok = np.array([[0, 1, 0, 0, 1, 0],
                   [0, 0, 0, 0, 0, 0],
                   [1, 1, 1, 1, 1, 1],
                   [0, 0, 0, 0, 0, 1]], bool)
    out = K.fill_rows(val, ok)
    assert out[0].tolist() == [1, 1, 1, 1, 4, 4]      # previous valid, else the next
    assert out[1].tolist() == out[0].tolist()        # an empty row: the nearest filled one
    assert out[2].tolist() == val[2].tolist()
    assert out[3].tolist() == [23] * 6


def _mmgd_reference(ref, ref_ok, mov, mov_ok, S, min_pixels):
    h, w = ref.shape
    cost = np.full((2 * S + 1, 2 * S + 1), np.inf)
    for i in range(2 * S + 1):
        for j in range(2 * S + 1):
            ok = ref_ok & mov_ok[i:i + h, j:j + w]
            if ok.sum() < max(min_pixels, 1):
                continue
            d = ref[ok] - mov[i:i + h, j:j + w][ok]
            cost[i, j] = np.mean(np.abs(d - np.median(d)))
    return cost


def test_mmgd_costs_are_the_mean_deviation_from_the_median():
    rng = np.random.default_rng(8)
    for S, (h, w) in ((2, (17, 23)), (4, (40, 31)), (1, (6, 5))):
        ref = rng.normal(size=(h, w)) * 20
        mov = rng.normal(size=(h + 2 * S, w + 2 * S)) * 20
        rok = rng.random((h, w)) > 0.2
        mok = rng.random(mov.shape) > 0.2
        want = _mmgd_reference(ref, rok, mov, mok, S, 10)
        got = mmgd_costs(ref, rok, mov, mok, S, 10)
        assert np.array_equal(np.isfinite(got), np.isfinite(want))
        f = np.isfinite(want)
        assert np.allclose(got[f], want[f], rtol=1e-12)


def test_mmgd_finds_a_known_shift():
    rng = np.random.default_rng(9)
    base = ndimage.gaussian_filter(rng.normal(size=(80, 80)), 1.2)
    S = 5
    ref = base[20:60, 20:60]
    # mov[x + s] == ref[x] + 9 for s = (2, -3)
    mov = base[20 - S - 2:60 + S - 2, 20 - S + 3:60 + S + 3] + 9.0
    cost = mmgd_costs(ref, np.ones(ref.shape, bool), mov, np.ones(mov.shape, bool), S, 64)
    i, j = np.unravel_index(np.argmin(cost), cost.shape)
    assert (i - S, j - S) == (2, -3)
    assert cost[i, j] < 1e-9


@pytest.mark.parametrize("shape", [(50, 40), (1, 30), (30, 1), (3, 3), (2, 5), (300, 90)])
def test_prefilter_is_scipys_spline_filter_of_the_edge_padded_image(shape):
    a = np.random.default_rng(3).normal(size=shape) * 50 + 100
    want = ndimage.spline_filter(np.pad(a, 12, mode="edge"), order=3, mode="mirror")
    got = K.prefilter(a, 12)
    assert got.shape == want.shape
    assert np.abs(got - want).max() < 1e-12 * np.abs(want).max()


def test_valid_rectangle_is_all_valid_and_greedy():
    from swathflow.mosaicking.matching import valid_rectangle
    m = np.ones((40, 30), bool)
    m[:5] = False
    m[:, -3:] = False
    rs, cs = valid_rectangle(m)
    assert m[rs, cs].all()
    assert (rs.start, cs.stop) == (5, 27)        # the invalid border rows/columns dropped
    assert valid_rectangle(np.zeros((5, 5), bool)) is None


@pytest.mark.parametrize("shape", [(36, 128), (128, 128), (5, 40), (1, 9), (20, 3)])
@pytest.mark.parametrize("sigma", [1.0, 3.0])
def test_gaussian_is_scipys_gaussian_filter(shape, sigma):
    from swathflow.mosaicking.block_kernels import gaussian
    a = np.random.default_rng(5).normal(size=shape) * 40 + 300
    want = ndimage.gaussian_filter(a, sigma)
    assert np.abs(gaussian(a, sigma) - want).max() < 1e-12 * np.abs(want).max()


@pytest.mark.parametrize("iterations", [1, 2, 3])
def test_erode_is_scipys_binary_erosion(iterations):
    from swathflow.mosaicking.block_kernels import erode
    rng = np.random.default_rng(6)
    m = ndimage.gaussian_filter(rng.normal(size=(60, 45)), 3) > -0.1
    m[:, :2] = True
    want = ndimage.binary_erosion(m, iterations=iterations, border_value=0)
    np.testing.assert_array_equal(erode(m, iterations), want)


def test_noise_texture_is_the_scipy_recipe():
    """The compiled noise and texture figures of a block equal the numpy/scipy recipe they
    replace (match_block's high-passed difference MAD; texture_measure's structure tensor)."""
    from swathflow.mosaicking.block_kernels import noise_texture
    rng = np.random.default_rng(7)
    ref = ndimage.gaussian_filter(rng.normal(size=(36, 128)), 1.5) * 50 + 200
    mov = 1.1 * ref + rng.normal(size=ref.shape) + 5
    joint = np.ones(ref.shape, bool)
    joint[:, :7] = False
    inner = ndimage.binary_erosion(joint, iterations=3, border_value=0)
    g = 1.1
    diff = mov - g * ref
    diff = diff - ndimage.gaussian_filter(np.where(inner, diff, np.median(diff[inner])), 3.0)
    v = diff[inner]
    want_noise = 1.4826 * np.median(np.abs(v - np.median(v))) / np.sqrt(2.0)
    sm = ndimage.gaussian_filter(ref, 1.0)
    gr, gc = np.gradient(sm)
    m = ndimage.binary_erosion(joint, iterations=2)
    j = np.array([[np.mean(gr[m] ** 2), np.mean(gr[m] * gc[m])],
                  [np.mean(gr[m] * gc[m]), np.mean(gc[m] ** 2)]])
    want_lam = np.linalg.eigvalsh(j)[0]
    noise, lam = noise_texture(ref, mov, ref, g, inner, joint)
    assert abs(noise - want_noise) < 1e-12 * want_noise
    assert abs(lam - want_lam) < 1e-9 * abs(want_lam)
    few = np.zeros(ref.shape, bool)
    few[:3, :4] = True
    assert np.isnan(noise_texture(ref, mov, ref, g, inner, few)[1])


@pytest.mark.parametrize("shape", [(36, 128), (24, 44)])
def test_upsampled_dft_is_the_matrix_dft(shape):
    """The upsampled DFT's magnitude (its size-only factors made once, two matrix
    products) equals that of the direct matrix DFT of Guizar-Sicairos et al. at the
    requested offsets."""
    from swathflow.mosaicking.matching import _upsampled_abs
    rng = np.random.default_rng(2)
    data = rng.normal(size=shape) + 1j * rng.normal(size=shape)
    off = np.array([15.0, 15.0]) - np.array([0.35, -0.2]) * 20
    want = data
    for n, o in list(zip(data.shape, off))[::-1]:
        kern = (np.arange(30) - o)[:, None] * np.fft.fftfreq(n, 20)
        want = np.tensordot(np.exp(-2j * np.pi * kern), want, axes=(1, -1))
    got = _upsampled_abs(data, (30, 30), 20, off)
    assert np.abs(got - np.abs(want)).max() < 1e-12 * np.abs(want).max()


@pytest.mark.parametrize("shape", [(36, 128), (24, 44), (17, 9), (128, 45)])
def test_mirror_completes_the_real_spectrum(shape):
    """The half spectrum of a real signal (rfft2) and its mirrored conjugates give the
    whole spectrum (fft2), odd and even sides."""
    from swathflow.mosaicking.matching import _mirror
    a = np.random.default_rng(4).normal(size=shape)
    half = np.fft.rfft2(a)
    r, c = _mirror(shape)
    whole = np.concatenate([half, half[r, c].conj()], axis=1)
    assert np.abs(whole - np.fft.fft2(a)).max() < 1e-12 * np.abs(half).max()


@pytest.mark.parametrize("min_valid", [1.0, 0.5])
def test_decimate_is_the_valid_block_mean(min_valid):
    """The overview's cells: the mean of their valid pixels where enough are valid (the
    numpy recipe written out), the trailing partial cells dropped."""
    from swathflow.mosaicking.coarse import decimate
    rng = np.random.default_rng(8)
    val = rng.normal(size=(40, 29)) * 30 + 100
    ok = rng.random((40, 29)) > 0.2
    f = 3
    h, w = 39, 27
    v = np.where(ok, val, 0.0)[:h, :w].reshape(13, f, 9, f)
    n = ok[:h, :w].reshape(13, f, 9, f).sum(axis=(1, 3))
    good = n >= min_valid * f * f
    want = np.where(good, v.sum(axis=(1, 3)) / np.maximum(n, 1), 0.0)
    got, got_good = decimate(val, ok, f, min_valid)
    np.testing.assert_array_equal(got_good, good)
    assert np.abs(got - want).max() < 1e-12 * np.abs(want).max()
    assert decimate(val[:2], ok[:2], 3)[0].shape == (0, 0)


@pytest.mark.parametrize("n", [1, 2, 3, 300, 1151, 1152])
def test_median_is_numpys_with_ties_and_equal_values(n):
    """The in-place quickselect median equals np.median, with heavy ties, all values equal
    and sorted input (where a Lomuto partition would otherwise degrade)."""
    from swathflow.mosaicking.match_kernels import _median
    rng = np.random.default_rng(n)
    for x in (rng.normal(size=n) * 30, np.round(rng.normal(size=n) * 1.5), np.full(n, 3.0),
              np.sort(np.round(rng.normal(size=n) * 10))):
        a = x.copy()
        assert _median(a, n) == np.median(x)
        assert np.array_equal(np.sort(a), np.sort(x))


def _fresh(code: str) -> str:
    """The stdout of ``code`` run in a fresh interpreter."""
    import subprocess
    import sys
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          check=True).stdout


def test_kernels_load_and_compiled_blas_code_still_works():
    """After load_kernels (numba started, the mosaic's kernels loaded), compiled code using
    BLAS (np.dot, through scipy.linalg's cython_blas) still compiles and gives the
    matrix product."""
    out = _fresh(
        "import sys\n"
        "from swathflow.mosaicking.mosaic import load_kernels\n"
        "load_kernels()\n"
        "import numba, numpy as np, scipy.linalg\n"
        "print(scipy.linalg.cython_blas.__name__)\n"
        "f = numba.njit(lambda a: np.dot(a, a))\n"
        "a = np.arange(9.0).reshape(3, 3)\n"
        "print(bool(np.allclose(f(a), [[15, 18, 21], [42, 54, 66], [69, 90, 111]])))\n")
    assert out.split() == ["scipy.linalg.cython_blas", "True"]


def test_blend_modules_do_not_import_the_matching():
    """The mosaic module imports the matching's modules on first use only; they stay
    reachable through it."""
    out = _fresh(
        "import sys\n"
        "from swathflow.mosaicking import mosaic as M\n"
        "print(sorted(m for m in ('overlaps', 'matching', 'network', 'seams')\n"
        "             if 'swathflow.mosaicking.' + m in sys.modules))\n"
        "from swathflow.mosaicking.mosaic import plan, Network\n"
        "print(M.seam_lines.__module__, plan.__module__, Network.__module__)\n")
    lines = out.splitlines()
    assert lines[0] == "[]"
    assert lines[1].split() == ["swathflow.mosaicking.seams", "swathflow.mosaicking.overlaps",
                                "swathflow.mosaicking.network"]

