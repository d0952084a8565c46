"""Coarse-to-fine overlap matching: the integer offset found once per overlap on a
block-averaged overview, then each block refined at full resolution in a small window
around that answer (swathflow.matching.match_block with a small search radius).

The minimum-mean-grey-difference search costs ``(2S + 1)**2`` difference images; on an
overview decimated by ``f`` the same radius costs ``(2S/f + 1)**2`` images of ``1/f**2`` the
pixels, and the full-resolution search around the coarse answer needs only a radius of
about ``f/2 + 1``. The sub-pixel steps (phase correlation, least-squares polish, texture
check) are those of the full search, so the recovered offsets are the same.
"""
from __future__ import annotations

import math

import numpy as np

from swathflow.mosaicking.matching import median, mmgd_search

__all__ = ["decimate", "coarse_shift", "block_texture", "pick_blocks", "match_overlap"]


def decimate(val, ok, factor: int, min_valid: float = 1.0):
    """Block mean of ``val`` over ``factor x factor`` cells (valid pixels only) and the
    cells' validity (at least ``min_valid`` of their pixels valid). The trailing partial
    row/column of cells is dropped. Compiled (block_kernels.block_mean)."""
    from swathflow.mosaicking.block_kernels import block_mean
    f = int(factor)
    if val.shape[0] < f or val.shape[1] < f:
        return np.zeros((0, 0)), np.zeros((0, 0), bool)
    return block_mean(np.ascontiguousarray(val, float), np.ascontiguousarray(ok, bool), f,
                      float(min_valid * f * f))


def coarse_shift(ref, ref_ok, mov, mov_ok, max_shift: int, factor: int = 3,
                 min_contrast: float = 0.15, min_cells: int = 48):
    """Integer offset (full-resolution pixels) of ``mov`` against ``ref`` from their
    overviews. ``ref`` (h, w) and ``mov`` (h + 2S, w + 2S) read with a margin of
    ``S = max_shift`` as for :func:`swathflow.matching.mmgd_search`. Returns
    ``(shift, contrast)``; ``shift`` is None when the overview leaves too few common cells
    (contrast NaN) or the cost surface is too flat to trust (``contrast < min_contrast``)."""
    f = int(factor)
    S = int(max_shift)
    Sc = int(math.ceil(S / f))
    # the overview of mov is cut so that cell (i, j) of ref sits on cell (i + Sc, j + Sc)
    m0 = S - Sc * f
    rv, rk = decimate(ref, ref_ok, f)
    mv, mk = decimate(mov[m0:, m0:], mov_ok[m0:, m0:], f)
    h, w = rv.shape
    if h < 2 or w < 2:
        return None, float("nan")
    need = (h + 2 * Sc, w + 2 * Sc)
    if mv.shape[0] < need[0] or mv.shape[1] < need[1]:
        pad = ((0, max(0, need[0] - mv.shape[0])), (0, max(0, need[1] - mv.shape[1])))
        mv, mk = np.pad(mv, pad), np.pad(mk, pad)
    mv, mk = mv[:need[0], :need[1]], mk[:need[0], :need[1]]
    s, cost = mmgd_search(rv, rk, mv, mk, Sc, min_pixels=min_cells)
    if s is None:
        return None, float("nan")
    finite = cost[np.isfinite(cost)]
    med = median(finite)
    contrast = float((med - finite.min()) / max(med, 1e-12))
    if contrast < min_contrast:
        return None, contrast
    # sub-cell vertex of the cost minimum (parabola through its neighbours), to full px
    d = np.array(s, float) + _vertex(cost, s[0] + Sc, s[1] + Sc)
    full = np.round(d * f).astype(int)
    if np.any(np.abs(full) > S):
        return None, contrast
    return (int(full[0]), int(full[1])), contrast


def _vertex(cost, i, j):
    """Sub-cell position of a cost minimum at ``(i, j)``: the vertex of the parabola
    through it and its neighbours, per axis (0 where a neighbour is missing)."""
    out = np.zeros(2)
    n = cost.shape[0]
    for axis in (0, 1):
        k = i if axis == 0 else j
        if not 0 < k < n - 1:
            continue
        lo = cost[i - 1, j] if axis == 0 else cost[i, j - 1]
        hi = cost[i + 1, j] if axis == 0 else cost[i, j + 1]
        den = lo - 2 * cost[i, j] + hi
        if np.isfinite(den) and den > 0:
            out[axis] = float(np.clip(0.5 * (lo - hi) / den, -0.5, 0.5))
    return out


def block_texture(val, ok):
    """Texture score of a block: mean squared gradient over its valid pixels (0 if none)."""
    if ok.sum() < 16:
        return 0.0
    gr, gc = np.gradient(np.where(ok, val, val[ok].mean()))
    inner = ok.copy()
    inner[1:] &= ok[:-1]
    inner[:-1] &= ok[1:]
    inner[:, 1:] &= ok[:, :-1]
    inner[:, :-1] &= ok[:, 1:]
    if not inner.any():
        return 0.0
    return float(np.mean(gr[inner] ** 2 + gc[inner] ** 2))


def pick_blocks(windows, scores, max_blocks: int, min_relative: float = 0.1):
    """A sample of well-textured blocks: drop those below ``min_relative`` of the median
    score, then keep at most ``max_blocks``, evenly spread along the overlap (a block's
    place in ``windows`` is its place along the overlap)."""
    scores = np.asarray(scores, float)
    if not len(windows):
        return []
    med = median(scores)
    keep = [k for k, s in enumerate(scores) if s > 0 and s >= min_relative * med]
    if len(keep) > max_blocks:
        pick = np.unique(np.round(np.linspace(0, len(keep) - 1, max_blocks)).astype(int))
        keep = [keep[k] for k in pick]
    return [windows[k] for k in keep]


def _grid_blocks(h, w, block):
    """Block windows (r0, c0, r1, c1) tiling an ``h x w`` area, the last ones flush with
    its far edges when at least half a block is left there (a flush block over a smaller
    remainder would repeat more than half of its neighbour's pixels: a fifth of the
    matching of a strip overlap of 530 rows, for no new ground)."""
    hb, wb = min(block, h), min(block, w)
    rows = list(range(0, h - hb + 1, hb)) or [0]
    cols = list(range(0, w - wb + 1, wb)) or [0]
    if rows[-1] + hb < h and h - (rows[-1] + hb) >= hb // 2:
        rows.append(h - hb)
    if cols[-1] + wb < w and w - (cols[-1] + wb) >= wb // 2:
        cols.append(w - wb)
    return [(r, c, r + hb, c + wb) for r in rows for c in cols]


def match_overlap(ref, ref_ok, mov, mov_ok, margin: int, max_shift: int = 12,
                  block: int = 128, max_blocks: int = 16, min_texture: float = 1.0,
                  min_pixels: int = 256, factor: int = 3, min_fraction: float = 0.3,
                  coarse_side: int = 768, full_min: int = 2048):
    """Block matches of one overlap, coarse to fine. ``ref`` (h, w) is the overlap of the
    reference swing, ``mov`` (h + 2M, w + 2M) the moving swing's read with a margin of
    ``M = margin >= max_shift + factor // 2 + 2`` pixels. Returns ``(blocks, coarse)``:
    the :class:`~swathflow.matching.BlockMatch` list (offsets and centres relative to
    ``ref``'s first pixel) and the coarse integer shift. When the overview gives no answer
    the overlap is refused at once if it is flat (``low_texture``) or a sliver of fewer
    than ``full_min`` valid pixels (``too_small``, e.g. the corner of two swings); a larger
    narrow overlap, or one where no block confirmed the overview's answer, gets the full
    search over the whole radius (coarse None)."""
    from swathflow.mosaicking.matching import BlockMatch, match_block
    S, M = int(max_shift), int(margin)
    h, w = ref.shape
    # the overview search on at most coarse_side x coarse_side pixels around the centre
    a0, b0 = max(0, (h - coarse_side) // 2), max(0, (w - coarse_side) // 2)
    a1, b1 = min(h, a0 + coarse_side), min(w, b0 + coarse_side)
    c, contrast = coarse_shift(ref[a0:a1, b0:b1], ref_ok[a0:a1, b0:b1],
                        mov[M - S + a0:M + S + a1, M - S + b0:M + S + b1],
                        mov_ok[M - S + a0:M + S + a1, M - S + b0:M + S + b1], S, factor)
    if c is not None:
        fine = factor // 2 + 2
        # the integer search around the overview's answer on every other row and column
        # (a quarter of the cost; it only seeds the sub-pixel steps, which use every pixel)
        blocks = _match_blocks(ref, ref_ok, mov, mov_ok, M, c, fine, block, max_blocks,
                               min_texture, min_pixels, min_fraction, stride=2)
        if any(b.ok for b in blocks):
            return blocks, c
    if c is None and not (np.isnan(contrast) and (ref_ok.sum() >= full_min)):
        # flat, or a sliver too small to match (a corner of two swings): no full search
        return [BlockMatch(False, "too_small" if np.isnan(contrast) else "low_texture")], None
    # no block confirmed the overview's answer, or a narrow overlap: the full search
    blocks = _match_blocks(ref, ref_ok, mov, mov_ok, M, (0, 0), S, block, 48,
                           min_texture, min_pixels, min_fraction, match_block, rank=False)
    return blocks, None


def _match_blocks(ref, ref_ok, mov, mov_ok, M, c, radius, block, max_blocks, min_texture,
                  min_pixels, min_fraction, match=None, rank=True, stride=1):
    """Match the blocks of the overlap with the search centred on shift ``c`` and a search
    radius of ``radius`` pixels (the integer search over every ``stride``-th pixel)."""
    from swathflow.mosaicking.matching import match_block
    match = match or match_block
    h, w = ref.shape
    wins, scores = [], []
    for r0, c0, r1, c1 in _grid_blocks(h, w, block):
        rok = ref_ok[r0:r1, c0:c1]
        mok = mov_ok[M + c[0] + r0:M + c[0] + r1, M + c[1] + c0:M + c[1] + c1]
        if (rok & mok).mean() < min_fraction:
            continue
        wins.append((r0, c0, r1, c1))
        scores.append(block_texture(ref[r0:r1, c0:c1], rok) if rank else 1.0)
    out = []
    for r0, c0, r1, c1 in pick_blocks(wins, scores, max_blocks, 0.1 if rank else 0.0):
        rok = ref_ok[r0:r1, c0:c1]
        if rok.sum() < min_pixels:
            continue
        a0, b0 = M + c[0] + r0 - radius, M + c[1] + c0 - radius
        mv = mov[a0:a0 + (r1 - r0) + 2 * radius, b0:b0 + (c1 - c0) + 2 * radius]
        mk = mov_ok[a0:a0 + (r1 - r0) + 2 * radius, b0:b0 + (c1 - c0) + 2 * radius]
        m = match(ref[r0:r1, c0:c1], rok, mv, mk, radius, min_texture=min_texture,
                  min_pixels=min(min_pixels, (r1 - r0) * (c1 - c0) // 4), stride=stride)
        if m.ok:
            m.offset = (m.offset[0] + c[0], m.offset[1] + c[1])
        m.integer = (m.integer[0] + c[0], m.integer[1] + c[1])
        m.phase = (m.phase[0] + c[0], m.phase[1] + c[1])
        m.centre = ((r0 + r1) / 2.0, (c0 + c1) / 2.0)
        out.append(m)
    return out
