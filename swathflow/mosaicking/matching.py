"""Overlap matching: the systematic offset between two rectified images on one grid.

The method follows You & Li (docs/references.md section 3): the offset is the candidate shift with the
minimum mean grey difference over the overlap. Here that integer search is made robust to a
radiometric offset (the median difference is removed first), then refined to subpixel by
phase correlation (upsampled DFT) and polished by a least-squares gradient fit that also
solves for gain and offset. The overlap is cut into blocks; every block gives one estimate,
blocks with too little texture are dropped (structure-tensor check, aperture problem
included), outlying blocks are rejected (median / MAD), and the survivors give the offset,
its standard error and a quality score.

Sign convention: ``d = (drow, dcol)`` is the displacement of the content of ``mov``
relative to ``ref``, i.e. ``mov[x] == ref[x - d]``. If every image ``k`` is the truth
displaced by ``t_k``, the offset measured between ``i`` (ref) and ``j`` (mov) is
``t_j - t_i``. Radiometric offset ``o``: ``mov ~= ref + o`` after alignment.
"""
from __future__ import annotations

import functools
from dataclasses import dataclass, field

import numpy as np

__all__ = ["BlockMatch", "OverlapMatch", "mmgd_search", "phase_correlation", "median",
           "gradient_refine", "texture_measure", "match_block", "combine_blocks"]


@dataclass
class BlockMatch:
    """One block's estimate (``ok`` False with ``reason`` when it was dropped)."""
    ok: bool
    reason: str = ""
    offset: tuple[float, float] = (np.nan, np.nan)     # (drow, dcol), px
    sigma: tuple[float, float] = (np.nan, np.nan)      # formal standard errors, px
    radiometric: float = np.nan                        # mov - ref (after alignment)
    gain: float = np.nan
    integer: tuple[int, int] = (0, 0)                  # the minimum-grey-difference shift
    phase: tuple[float, float] = (np.nan, np.nan)      # phase-correlation estimate
    peak: float = np.nan                               # phase-correlation peak height
    texture: float = np.nan                            # weakest-direction gradient / noise
    n: int = 0                                         # pixels used
    centre: tuple[float, float] = (np.nan, np.nan)     # block centre (row, col) on the grid


@dataclass
class OverlapMatch:
    """The combined estimate of one overlap."""
    ok: bool
    status: str                         # "ok", "low_texture", "too_small", "inconsistent"
    offset: tuple[float, float] = (np.nan, np.nan)
    sigma: tuple[float, float] = (np.nan, np.nan)
    radiometric: float = np.nan
    radiometric_sigma: float = np.nan
    quality: float = 0.0                # 0..1
    n_blocks: int = 0
    n_textured: int = 0
    n_inliers: int = 0
    spread: float = np.nan              # robust std of the inlier block offsets, px
    blocks: list = field(default_factory=list, repr=False)

    def to_dict(self) -> dict:
        r = lambda v: None if v is None or not np.isfinite(v) else round(float(v), 4)  # noqa: E731
        return {"ok": self.ok, "status": self.status,
                "offset": [r(v) for v in self.offset], "sigma": [r(v) for v in self.sigma],
                "radiometric": r(self.radiometric), "quality": r(self.quality),
                "n_blocks": self.n_blocks, "n_textured": self.n_textured,
                "n_inliers": self.n_inliers, "spread": r(self.spread)}


# --- the paper's search ---------------------------------------------------------------------
def mmgd_search(ref, ref_ok, mov, mov_ok, max_shift: int, min_pixels: int = 64,
                stride: int = 1):
    """Minimum mean grey difference over integer shifts.

    ``ref`` (h, w) and ``mov`` (h + 2S, w + 2S) where ``mov`` is read with a margin of
    ``S = max_shift`` pixels on each side. For every candidate shift ``s`` the mean absolute
    difference ``|ref[x] - mov[x + s] - median(...)|`` is taken over the jointly valid
    pixels (the median removes a radiometric offset). Returns ``(s, cost_map)``; ``s`` is
    None when no shift leaves ``min_pixels`` common pixels. ``stride``: the cost over every
    ``stride``-th row and column of ``ref`` only (``min_pixels`` counts those). Compiled
    (swathflow.mosaicking.match_kernels: no GIL held, so overlaps match on threads).
    """
    from swathflow.mosaicking.match_kernels import mmgd_costs
    S = int(max_shift)
    cost = mmgd_costs(np.ascontiguousarray(ref, float), np.ascontiguousarray(ref_ok, bool),
                      np.ascontiguousarray(mov, float), np.ascontiguousarray(mov_ok, bool),
                      S, int(min_pixels), int(stride))
    if not np.isfinite(cost).any():
        return None, cost
    i, j = np.unravel_index(np.argmin(cost), cost.shape)
    return (int(i) - S, int(j) - S), cost


def _mean_abs_from_median(d):
    """Per row of ``d`` (k, n): mean |d - median(d)| (the median as np.median takes it)."""
    n = d.shape[1]
    k = n // 2
    if n % 2:
        med = np.partition(d, k, axis=1)[:, k]
    else:
        p = np.partition(d, (k - 1, k), axis=1)
        med = 0.5 * (p[:, k - 1] + p[:, k])
    return np.abs(d - med[:, None]).mean(axis=1)


def median(a) -> float:
    """``np.median`` of the values of ``a`` (none NaN), the same value without its
    overheads (a quarter of the cost on the few values of a cost surface or a block
    list): the middle one of a partition, or the mean of the two middle ones."""
    a = np.ravel(a)
    k = a.size // 2
    if a.size % 2:
        return float(np.partition(a, k)[k])
    p = np.partition(a, (k - 1, k))
    return float((p[k - 1] + p[k]) / 2)


# --- phase correlation ------------------------------------------------------------------------
def _upsampled_abs(data, size, factor, offsets):
    """``|DFT|`` of ``data`` upsampled by ``factor`` on a ``size`` region starting at
    ``offsets`` (Guizar-Sicairos et al. 2008): two matrix products, ``rows @ data @
    cols.T``, each factor the size-only part (made once) times one row of phases."""
    (kr, fr), (kc, fc) = (_dft_rows(ups, n, factor) for ups, n in zip(size, data.shape))
    rows = kr * np.exp(2j * np.pi * offsets[0] * fr)
    cols = kc * np.exp(2j * np.pi * offsets[1] * fc)
    return np.abs(rows @ data @ cols.T)


@functools.lru_cache(maxsize=64)
def _dft_rows(ups: int, n_items: int, factor: int):
    f = np.fft.fftfreq(n_items, factor)
    k = np.exp(-2j * np.pi * np.arange(ups)[:, None] * f)
    k.flags.writeable = False
    f.flags.writeable = False
    return k, f


@functools.lru_cache(maxsize=64)
def _mirror(shape):
    """Index arrays of the Hermitian half a real signal's rfft2 leaves out: the full
    spectrum's columns ``w // 2 + 1 ..`` are the conjugates of the half's values at
    ``((-r) % h, w - c)``."""
    h, w = shape
    r = ((-np.arange(h)) % h)[:, None]
    c = (w - np.arange(w // 2 + 1, w))[None, :]
    r.flags.writeable = False
    c.flags.writeable = False
    return r, c


def _taper(mask, edge: float = 6.0):
    """Apodisation: the mask softened at its borders times a Tukey-like rectangle edge
    (for a mask valid everywhere, which phase_correlation mostly sees, it depends on the
    shape alone: made once per shape)."""
    if mask.all():
        return _full_taper(mask.shape, float(edge))
    return _make_taper(mask, edge)


@functools.lru_cache(maxsize=64)
def _full_taper(shape, edge: float):
    t = _make_taper(np.ones(shape, bool), edge)
    t.flags.writeable = False
    return t


def _make_taper(mask, edge: float):
    from scipy import ndimage
    t = ndimage.gaussian_filter(mask.astype(float), edge / 2.0) * mask
    h, w = mask.shape
    for axis, n in ((0, h), (1, w)):
        k = max(1, min(int(edge * 2), n // 4))
        ramp = np.ones(n)
        ramp[:k] = 0.5 - 0.5 * np.cos(np.pi * (np.arange(k) + 0.5) / k)
        ramp[n - k:] = ramp[:k][::-1]
        t = t * (ramp[:, None] if axis == 0 else ramp[None, :])
    return t


def valid_rectangle(mask):
    """A large all-valid rectangle inside ``mask`` (greedy: repeatedly drop the border row or
    column with the largest invalid fraction; compiled). Returns slices, or None if nothing
    is left."""
    from swathflow.mosaicking.match_kernels import valid_rectangle_bounds
    r0, r1, c0, c1 = valid_rectangle_bounds(np.ascontiguousarray(mask, bool))
    if r1 <= r0 or c1 <= c0:
        return None
    return slice(int(r0), int(r1)), slice(int(c0), int(c1))


def phase_correlation(ref, mov, mask=None, upsample: int = 20, min_side: int = 16):
    """Subpixel displacement ``d`` with ``mov[x] ~= ref[x - d]`` by phase correlation.

    ``mask``: pixels valid in both (others are filled with the mean and tapered away).
    Returns ``(d, peak)``: the peak of the normalised cross-power spectrum's inverse (1 for
    a perfect pure translation, near 0 for unrelated images).
    """
    ref = np.asarray(ref, float)
    mov = np.asarray(mov, float)
    if mask is None:
        mask = np.ones(ref.shape, bool)
    elif not mask.all():
        # mask edges common to both images would pull the peak to zero: correlate the
        # largest all-valid rectangle when there is one
        rect = valid_rectangle(mask)
        if rect is not None and min(ref[rect].shape) >= min_side:
            ref, mov, mask = ref[rect], mov[rect], np.ones(ref[rect].shape, bool)
    tap = _taper(mask)
    if mask.all():
        a = (ref - ref.ravel().mean()) * tap
        b = (mov - mov.ravel().mean()) * tap
    else:
        a = np.where(mask, ref - ref[mask].mean(), 0.0) * tap
        b = np.where(mask, mov - mov[mask].mean(), 0.0) * tap
    # real signals: half spectra (rfft2), the cross-power spectrum's inverse real
    shape = a.shape
    fa, fb = np.fft.rfft2(a), np.fft.rfft2(b)
    prod = fb * fa.conj()
    mag = np.abs(prod)
    prod /= np.maximum(mag, 1e-12 * mag.max() + 1e-300)
    acc = np.abs(np.fft.irfft2(prod, s=shape))
    peak_idx = np.unravel_index(np.argmax(acc), shape)
    size_ = np.array(shape)
    d = np.array(peak_idx, float)
    d[d > size_ // 2] -= size_[d > size_ // 2]
    if upsample > 1:
        d = np.round(d * upsample) / upsample
        size = int(np.ceil(upsample * 1.5))
        centre = np.fix(size / 2.0)
        # the conjugate of the whole spectrum, its left-out half from the rfft2's
        half = prod.shape[1]
        r, c = _mirror(shape)
        conj = np.empty(shape, complex)
        conj[:, :half] = prod.conj()
        conj[:, half:] = prod[r, c]
        up = _upsampled_abs(conj, (size, size), upsample, centre - d * upsample)
        idx = np.array(np.unravel_index(np.argmax(up), up.shape), float)
        d = d + (idx - centre) / upsample
    peak = float(acc.max())
    return (float(d[0]), float(d[1])), peak


# --- least-squares polish ----------------------------------------------------------------
class _Shifter:
    """``out[x] = img[x - d]`` (cubic spline, edges extended: ``ndimage.shift(img, d,
    order=3, mode="nearest")``) for many ``d`` of one image: the B-spline prefilter is
    computed once, and each shift is one 4-tap correlation per axis over just the rows and
    columns it reads (the recipe of swathflow.mosaicking.blend.shift_cubic, same values)."""

    def __init__(self, img, pad: int = 12):
        self.img, self.pad = img, int(pad)
        self.coef = None

    def __call__(self, d):
        from scipy import ndimage
        from swathflow.mosaicking.blend import _b3
        f = -np.asarray(d, float)
        a = np.floor(f).astype(int)
        if np.any(np.abs(a) > self.pad - 3):
            return ndimage.shift(self.img, -f, order=3, mode="nearest")
        if self.coef is None:
            self.coef = ndimage.spline_filter(np.pad(self.img, self.pad, mode="edge"),
                                              order=3, mode="mirror")
        h, w = self.img.shape
        p = self.pad
        c = self.coef[p + a[0] - 1:p + a[0] + h + 2, p + a[1] - 1:p + a[1] + w + 2]
        for axis in (0, 1):
            k = _b3(float(f[axis] - a[axis]) - (np.arange(4) - 1))
            c = ndimage.correlate1d(c, k, axis=axis, mode="mirror", origin=-1)
        return c[1:h + 1, 1:w + 1]


def _shift(img, d):
    """``out[x] = img[x - d]`` (cubic spline, edges extended: ``ndimage.shift(img, d,
    order=3, mode="nearest")``, computed as one 4-tap correlation per axis)."""
    return _Shifter(img)(d)


def gradient_refine(ref, mov, mask, d0=(0.0, 0.0), iterations: int = 8, tol: float = 1e-4,
                    planar: bool = True):
    """Least-squares fit of ``mov[x] = g * ref[x - d] + o(x)`` over ``mask`` (Gauss-Newton).

    ``o(x)`` is a constant, or with ``planar`` a plane in (row, col): a radiometric
    difference that varies slowly across the block (illumination, drift) then neither biases
    the offset nor inflates the residual. Returns ``(d, sigma_d, g, o_mean, rms)`` with
    formal standard errors ``sigma_d`` (px); ``o_mean`` is ``o`` at the mask's centroid.
    The mask should stay a few pixels inside both images' valid areas.
    """
    return _polish(ref, mov, mask, d0, iterations, tol, planar)[:5]


def _polish(ref, mov, mask, d0=(0.0, 0.0), iterations: int = 8, tol: float = 1e-4,
            planar: bool = True):
    """:func:`gradient_refine` and ``ref`` shifted by the final ``d`` (cubic spline, as
    :func:`_shift`). The Gauss-Newton loop is compiled, the mask's pixels gathered there
    too (swathflow.mosaicking.match_kernels.polish; no GIL held), and so is the B-spline
    prefilter (swathflow.mosaicking.kernels.prefilter, scipy's to 1e-15), once per
    block."""
    from swathflow.mosaicking.kernels import prefilter
    from swathflow.mosaicking.match_kernels import polish
    ref = np.asarray(ref, float)
    mov = np.ascontiguousarray(mov, float)
    mask = np.ascontiguousarray(mask, bool)
    h, w = ref.shape
    pad = 12
    while True:
        coef = prefilter(np.ascontiguousarray(ref), pad)
        st, d, g, o, cov, rms, shifted = polish(coef, pad, mov, mask, bool(planar),
                                                np.array(d0, float), int(iterations),
                                                float(tol))
        if st != 2 or pad > 64:
            break
        need = float(np.max(np.abs(d)))       # the shift left the padding: pad it again,
        if not np.isfinite(need) or need > max(h, w):   # unless it diverged (a shift
            break                             # beyond the block: no overlap, a failure)
        pad = 12 + int(np.ceil(need)) + 8
    if st != 0:
        return d, (np.inf, np.inf), float(g), float(o[0]), np.inf, None
    sig = np.sqrt(np.diag(cov)[:2]) * rms
    return d, tuple(float(v) for v in sig), float(g), float(o[0]), float(rms), shifted


def texture_measure(img, mask, noise: float) -> float:
    """Gradient in the weakest direction (structure tensor of the sigma=1 smoothed image)
    over ``noise``: small for flat areas and for one-directional texture (aperture problem).
    (swathflow.mosaicking.block_kernels.weakest_gradient: scipy.ndimage and a compiled tensor).
    """
    from swathflow.mosaicking.block_kernels import weakest_gradient
    lam = weakest_gradient(np.ascontiguousarray(img, float), np.ascontiguousarray(mask, bool))
    return _texture(lam, noise)


def _texture(lam, noise) -> float:
    """The texture figure from the structure tensor's smallest eigenvalue ``lam`` (NaN: too
    few pixels) and the noise."""
    if np.isnan(lam):
        return 0.0
    return float(np.sqrt(max(lam, 0.0)) / max(noise, 1e-12))


def match_block(ref, ref_ok, mov, mov_ok, max_shift: int, min_texture: float = 1.0,
                min_pixels: int = 256, abs_floor: float = 1e-6,
                min_contrast: float = 0.15, stride: int = 1) -> BlockMatch:
    """Offset of one block. ``ref`` (h, w); ``mov`` (h + 2S, w + 2S) read with a margin of
    ``S = max_shift`` (so ``mov[S:S+h, S:S+w]`` is the same ground as ``ref``).
    ``stride``: the integer search over every ``stride``-th row and column only (the
    sub-pixel steps use every pixel): for a small search around a known answer."""
    from scipy import ndimage

    from swathflow.mosaicking.block_kernels import noise_texture
    S = int(max_shift)
    h, w = ref.shape
    s, cost = mmgd_search(ref, ref_ok, mov, mov_ok, S,
                          min_pixels=max(1, min_pixels // (2 * stride * stride)), stride=stride)
    if s is None:
        return BlockMatch(False, "too_small")
    finite = cost[np.isfinite(cost)]
    med = median(finite)
    contrast = (med - finite.min()) / max(med, 1e-12)
    if contrast < min_contrast:
        # a flat cost surface: nothing in the overlap pins the shift down
        return BlockMatch(False, "low_texture", integer=s)
    if abs(s[0]) == S or abs(s[1]) == S:
        return BlockMatch(False, "search_edge", integer=s)
    m = mov[S + s[0]:S + s[0] + h, S + s[1]:S + s[1] + w]
    m_ok = mov_ok[S + s[0]:S + s[0] + h, S + s[1]:S + s[1] + w]
    joint = ref_ok & m_ok
    inner = ndimage.binary_erosion(joint, iterations=3)
    if inner.sum() < min_pixels:
        return BlockMatch(False, "too_small", integer=s, n=int(inner.sum()))
    fill_r = np.where(ref_ok, ref, ref[ref_ok].mean())
    fill_m = np.where(m_ok, m, m[m_ok].mean())
    # phase correlation on the residual (|d - s| < 1 px): d_pc relative to s
    (pr, pc), peak = phase_correlation(fill_r, fill_m, joint)
    if abs(pr) > 1.5 or abs(pc) > 1.5:
        pr, pc = 0.0, 0.0          # a wild peak: start the polish from the integer shift
    dres, sig, g, o, rms, aligned = _polish(fill_r, fill_m, inner, (pr, pc))
    if aligned is None:
        aligned = _shift(fill_r, dres)
    # noise: the high-passed difference of the aligned images (slow radiometric trends
    # out); texture: the structure tensor's weakest direction (compiled, one call)
    noise, lam = noise_texture(fill_r, fill_m, np.ascontiguousarray(aligned), float(g), inner,
                               joint)
    noise = max(noise, abs_floor * (np.ptp(ref[ref_ok]) + 1.0))
    tex = _texture(lam, noise)
    centre = (h / 2.0, w / 2.0)
    common = dict(integer=s, phase=(s[0] + pr, s[1] + pc), peak=peak, texture=tex,
                  n=int(inner.sum()), centre=centre)
    if not (tex >= min_texture):
        return BlockMatch(False, "low_texture", **common)
    if not np.all(np.isfinite(dres)) or np.max(np.abs(dres)) > 2.0 or not (0.2 < g < 5.0):
        return BlockMatch(False, "diverged", **common)
    # radiometric offset at the mean level of the block (gain ~ 1 for offset-only data)
    rad = median(m[inner] - aligned[inner])
    return BlockMatch(True, "", offset=(s[0] + float(dres[0]), s[1] + float(dres[1])),
                      sigma=sig, radiometric=rad, gain=g, **common)


def _failed_status(blocks) -> str:
    reasons = [b.reason for b in blocks]
    if "low_texture" in reasons:
        return "low_texture"
    if not reasons or all(r == "too_small" for r in reasons):
        return "too_small"
    return "no_match"


def _inlier_stats(good, inl, floor_sigma):
    """Weighted mean of the inlier offsets, its sigma (the larger of the formal and the
    scatter-based one, never below ``floor_sigma``) and the scatter (std per axis)."""
    di = np.array([b.offset for b in good])[inl]
    sig = np.array([b.sigma for b in good])[inl]
    w = 1.0 / np.maximum(sig, 1e-3) ** 2
    mean = (w * di).sum(axis=0) / w.sum(axis=0)
    formal = 1.0 / np.sqrt(w.sum(axis=0))
    n = len(di)
    spread = np.sqrt(((di - mean) ** 2).sum(axis=0) / max(n - 1, 1)) if n > 1 else np.zeros(2)
    sigma = np.maximum.reduce([formal, spread / np.sqrt(n), np.full(2, floor_sigma)])
    return mean, sigma, spread


def combine_blocks(blocks: list[BlockMatch], min_blocks: int = 1, min_inlier_fraction=0.5,
                   tolerance: float = 0.25, floor_sigma: float = 0.02,
                   max_spread: float = 1.0) -> OverlapMatch:
    """Robust combination of block estimates: median / MAD outlier rejection, then the
    weighted mean of the inliers. ``sigma`` is the larger of the formal error and the
    scatter-based one (never below ``floor_sigma``). An overlap whose inlier blocks still
    scatter by more than ``max_spread`` px (std) is "inconsistent" and not used."""
    good = [b for b in blocks if b.ok]
    n_tex = sum(1 for b in blocks if b.ok or b.reason not in ("low_texture", "too_small"))
    res = OverlapMatch(False, "", n_blocks=len(blocks), n_textured=n_tex, blocks=blocks)
    if not good:
        res.status = _failed_status(blocks)
        return res
    d = np.array([b.offset for b in good])
    med = np.array([median(d[:, 0]), median(d[:, 1])])
    dev = np.abs(d - med)
    mad = 1.4826 * np.array([median(dev[:, 0]), median(dev[:, 1])])
    lim = np.maximum(3.0 * mad, tolerance)
    inl = np.all(np.abs(d - med) <= lim, axis=1)
    res.n_inliers = int(inl.sum())
    if res.n_inliers < min_blocks or (len(good) >= 3 and inl.mean() < min_inlier_fraction):
        res.status = "inconsistent"
        res.offset = tuple(float(v) for v in med)
        return res
    mean, sigma, spread = _inlier_stats(good, inl, floor_sigma)
    res.spread = float(np.hypot(*spread))
    res.offset = (float(mean[0]), float(mean[1]))
    if res.spread > max_spread:
        res.status = "inconsistent"
        return res
    n = res.n_inliers
    rad = np.array([b.radiometric for b in good])[inl]
    res.ok = True
    res.status = "ok"
    res.sigma = (float(sigma[0]), float(sigma[1]))
    res.radiometric = median(rad)
    res.radiometric_sigma = float(1.2533 * rad.std() / np.sqrt(n)) if n > 1 else np.nan
    res.quality = float(n / len(good) * np.exp(-np.hypot(*sigma) / 0.1) *
                        min(1.0, np.mean([b.peak for b in np.array(good)[inl]]) * 5))
    return res
