"""Overlap matching against known shifts (procedural truth sampled at exactly shifted
coordinates, so the truth shift is exact)."""
import numpy as np
import pytest

from mosaic_synth import texture
from swathflow.mosaicking.matching import (BlockMatch, combine_blocks, gradient_refine, match_block,
                                mmgd_search, phase_correlation)

SHIFTS = [(0.3, -2.7), (1.45, 3.2), (-4.1, 0.6), (2.5, 2.5), (-0.8, -4.9)]


def _pair(d, shape=(128, 128), margin=0, rad=0.0, gain=1.0, noise=0.0, seed=0, tex=texture):
    rr, cc = np.mgrid[0:shape[0], 0:shape[1]].astype(float)
    ref = tex(rr, cc)
    r2, c2 = np.mgrid[-margin:shape[0] + margin, -margin:shape[1] + margin].astype(float)
    mov = gain * tex(r2 - d[0], c2 - d[1]) + rad
    if noise:
        mov = mov + np.random.default_rng(seed).normal(0, noise, mov.shape)
    return ref, mov


@pytest.mark.parametrize("d", SHIFTS[:3])
def test_phase_correlation_sign_and_subpixel(d):
    ref, mov = _pair(d)
    est, peak = phase_correlation(ref, mov)
    assert np.allclose(est, d, atol=0.1), est       # upsampled DFT: 0.05 px grid
    assert peak > 0.2


def test_phase_correlation_with_mask():
    ref, mov = _pair((1.3, -0.6))
    mask = np.ones(ref.shape, bool)
    mask[:, 90:] = False                            # a ragged common area
    mask[:30, :40] = False
    est, _ = phase_correlation(np.where(mask, ref, 0), np.where(mask, mov, 0), mask)
    assert np.allclose(est, (1.3, -0.6), atol=0.15), est


def test_mmgd_integer_search_ignores_radiometric_offset():
    S = 8
    ref, mov = _pair((3.0, -5.0), margin=S, rad=25.0)
    s, cost = mmgd_search(ref, np.ones(ref.shape, bool), mov, np.ones(mov.shape, bool), S)
    assert s == (3, -5)
    assert cost.shape == (17, 17) and cost[S + 3, S - 5] < 1e-9


def test_gradient_refine_with_gain_offset_and_plane():
    ref, mov = _pair((0.37, -0.61), gain=1.1, rad=12.0)
    rr, cc = np.mgrid[0:128, 0:128]
    mov = mov + 0.05 * rr - 0.03 * cc              # slow illumination trend
    mask = np.zeros(ref.shape, bool)
    mask[6:-6, 6:-6] = True
    d, sig, g, o, rms = gradient_refine(ref, mov, mask)
    assert np.allclose(d, (0.37, -0.61), atol=0.01), d
    assert abs(g - 1.1) < 0.01
    assert max(sig) < 0.01


@pytest.mark.parametrize("d", SHIFTS)
def test_match_block_recovers_shift_with_noise(d):
    S = 8
    ref, mov = _pair(d, margin=S, rad=7.0, noise=1.0, seed=3)
    ref = ref + np.random.default_rng(4).normal(0, 1.0, ref.shape)
    b = match_block(ref, np.ones(ref.shape, bool), mov, np.ones(mov.shape, bool), S)
    assert b.ok, b.reason
    assert np.allclose(b.offset, d, atol=0.05), b.offset
    assert abs(b.radiometric - 7.0) < 0.5
    assert b.integer == tuple(int(round(v)) for v in d) or \
        max(abs(b.integer[0] - d[0]), abs(b.integer[1] - d[1])) <= 1


def test_match_block_irregular_masks():
    S = 8
    ref, mov = _pair((2.2, 1.4), margin=S)
    rok = np.ones(ref.shape, bool)
    rr, cc = np.mgrid[0:128, 0:128]
    rok &= cc < 60 + 10 * np.sin(rr / 15.0)         # a wavy strip edge
    mok = np.ones(mov.shape, bool)
    mok[:, :S + 10] = False
    b = match_block(ref, rok, mov, mok, S)
    assert b.ok and np.allclose(b.offset, (2.2, 1.4), atol=0.05), (b.reason, b.offset)


def _flat(r, c):
    return 100.0 + 0 * np.asarray(r, float) * np.asarray(c, float)


def _stripes(r, c):                                 # texture in one direction only
    return 100.0 + 30 * np.sin(np.asarray(c, float) / 3.0) + 0 * np.asarray(r, float)


@pytest.mark.parametrize("tex,noise", [(_flat, 0.0), (_flat, 2.0), (_stripes, 0.5)])
def test_low_texture_is_refused(tex, noise):
    S = 6
    ref, mov = _pair((1.5, 2.5), margin=S, tex=tex, noise=noise)
    if noise:
        ref = ref + np.random.default_rng(9).normal(0, noise, ref.shape)
    b = match_block(ref, np.ones(ref.shape, bool), mov, np.ones(mov.shape, bool), S)
    assert not b.ok and b.reason in ("low_texture", "search_edge"), (b.reason, b.offset)


def test_combine_blocks_rejects_outlier_and_reports():
    good = [BlockMatch(True, offset=(1.0 + e, -2.0 - e), sigma=(0.02, 0.02), radiometric=5.0,
                       peak=0.5) for e in (-0.01, 0.0, 0.01, 0.02, -0.02)]
    bad = BlockMatch(True, offset=(3.0, 1.0), sigma=(0.02, 0.02), radiometric=9.0, peak=0.5)
    res = combine_blocks(good + [bad, BlockMatch(False, "low_texture")])
    assert res.ok and res.n_inliers == 5 and res.n_blocks == 7
    assert np.allclose(res.offset, (1.0, -2.0), atol=0.01)
    assert 0 < res.quality <= 1 and res.sigma[0] >= 0.02
    assert abs(res.radiometric - 5.0) < 1e-9


def test_combine_blocks_all_low_texture():
    res = combine_blocks([BlockMatch(False, "low_texture")] * 3)
    assert not res.ok and res.status == "low_texture"
    res = combine_blocks([BlockMatch(True, offset=(0.0, float(k)), sigma=(0.02, 0.02),
                                     radiometric=0.0, peak=0.5) for k in range(5)])
    assert not res.ok and res.status == "inconsistent"


def test_mmgd_cost_map_is_the_definition():
    """The batched search gives, shift by shift, the definition's cost (masks, radiometric
    offset through the median, too few common pixels -> inf)."""
    rng = np.random.default_rng(3)
    for trial in range(12):
        h, w, S = int(rng.integers(8, 40)), int(rng.integers(8, 40)), int(rng.integers(1, 5))
        ref = rng.normal(size=(h, w))
        mov = rng.normal(size=(h + 2 * S, w + 2 * S)) + 7.0
        rok = rng.random((h, w)) > (0.0 if trial % 3 == 0 else rng.uniform(0, 0.5))
        mok = rng.random(mov.shape) > (0.0 if trial % 2 == 0 else rng.uniform(0, 0.5))
        want = np.full((2 * S + 1, 2 * S + 1), np.inf)
        for i, dr in enumerate(range(-S, S + 1)):
            for j, dc in enumerate(range(-S, S + 1)):
                m = mov[S + dr:S + dr + h, S + dc:S + dc + w]
                ok = rok & mok[S + dr:S + dr + h, S + dc:S + dc + w]
                if ok.sum() >= 10:
                    diff = ref[ok] - m[ok]
                    want[i, j] = np.mean(np.abs(diff - np.median(diff)))
        _, got = mmgd_search(ref, rok, mov, mok, S, min_pixels=10)
        assert np.array_equal(np.isfinite(got), np.isfinite(want)), trial
        f = np.isfinite(want)
        assert np.allclose(got[f], want[f], rtol=1e-12, atol=1e-12), trial


def test_median_is_numpys():
    """The matching's median: np.median's value, odd and even sizes, ties, one value."""
    from swathflow.mosaicking.matching import median
    rng = np.random.default_rng(6)
    for n in (1, 2, 3, 4, 7, 48, 49, 1000, 1001):
        for a in (rng.normal(size=n), rng.integers(0, 3, n).astype(float)):
            assert median(a) == np.median(a), (n, a)
    two = rng.normal(size=(5, 4))
    assert median(two) == np.median(two)
