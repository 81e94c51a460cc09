"""OnEI's re-solve (:func:`resolve`): every block of the normal equations given its queued
equations and solved while in cache, the residual-correction factor estimated first, the
solution folded into the smoothed estimate; one compiled call per range of blocks, ranges on
the executor's threads (disjoint: the same result with any number)."""

from __future__ import annotations

from typing import Any

import numpy as np

from ..solver import _lambda_terms, _solve_pixels
from .config import OnEIConfig
from .equations import NormalSums, Queue, as_arrays
from .estimate import VALID, LowPassEstimate, low_pass
from .kernels import BLOCK, append_masked, apply_blocks, jit

# blocks (of BLOCK pixels) the residual-correction factor is estimated on: all of them up to
# this many, else this many spread evenly over the sensor (131 k pixels): lam is one number for
# the whole sensor, and at 1280x720 a pass over every block only to estimate it cost as much
# again as the solve (the sums do not fit in any cache)
LAMBDA_BLOCKS = 16


@jit(error_model="numpy")
def prepared_block(blk: int, n: int, m: np.ndarray, counts_pad: np.ndarray, apply: bool,
                    sums: np.ndarray, qa: np.ndarray, raw: np.ndarray, dl: np.ndarray,
                    kinds: np.ndarray, lut: np.ndarray, slots: np.ndarray, signs: np.ndarray,
                    hslots: np.ndarray, hsigns: np.ndarray, buf: np.ndarray, hist: np.ndarray,
                    hist_counts: np.ndarray, scale: float, m_tmp: np.ndarray,
                    c_tmp: np.ndarray) -> Any:  # pragma: no cover - compiled
    """Block ``blk``'s sums and event counts as a solve reads them: the queued equations
    (``slots``) and the history's (``hslots``) added first when ``apply``, then the history
    scaled by ``scale`` added (into ``m_tmp``, ``c_tmp``; ``hist`` has no rows when the history
    is off). The operations of the numpy steps they replaced, in the same order."""
    s = blk * BLOCK
    if apply:
        apply_blocks(m, n, blk, blk + 1, sums, qa, raw, dl, kinds, lut, slots, signs, buf)
        if hist.shape[0] > 0:
            apply_blocks(hist, n, blk, blk + 1, sums, qa, raw, dl, kinds, lut, hslots,
                         hsigns, buf)
    mb = m[blk]
    cb = counts_pad[s : s + BLOCK]
    if hist.shape[0] > 0:
        hb = hist[blk]
        for i in range(16 * BLOCK):
            m_tmp[i] = hb[i] * scale + mb[i]
        for i in range(BLOCK):
            c_tmp[i] = np.int64(np.rint(hist_counts[s + i] * scale)) + cb[i]
        return m_tmp, c_tmp
    return mb, cb


@jit(error_model="numpy")
def lambda_blocks(blocks: np.ndarray, n: int, m: np.ndarray, counts_pad: np.ndarray,
                   sums: np.ndarray, qa: np.ndarray, raw: np.ndarray, dl: np.ndarray,
                   kinds: np.ndarray, lut: np.ndarray, slots: np.ndarray, signs: np.ndarray,
                   hslots: np.ndarray, hsigns: np.ndarray, buf: np.ndarray, hist: np.ndarray,
                   hist_counts: np.ndarray, scale: float, m_tmp: np.ndarray, c_tmp: np.ndarray,
                   min_events: int, min_decorrelation: float, min_contrast: float,
                   max_contrast: float, max_bias_ratio: float, res_q: np.ndarray,
                   cq: np.ndarray) -> int:  # pragma: no cover - compiled
    """The residual-correction terms of ``blocks`` (each first given its queued equations):
    :func:`~evcal.solver.correction_lambda`'s trusted pixels' terms appended to ``res_q``
    and ``cq`` in block order; returns how many."""
    end = 0
    for j in range(blocks.size):
        blk = blocks[j]
        mb, cb = prepared_block(blk, n, m, counts_pad, True, sums, qa, raw, dl, kinds, lut,
                                 slots, signs, hslots, hsigns, buf, hist, hist_counts, scale,
                                 m_tmp, c_tmp)
        mask, rq_b, cq_b = _lambda_terms(mb.reshape((16, BLOCK)), cb, min_events,
                                         min_decorrelation, min_contrast, max_contrast,
                                         max_bias_ratio)
        end = append_masked(mask, rq_b, cq_b, min(BLOCK, n - blk * BLOCK), res_q, cq, end)
    return end


@jit(error_model="numpy")
def resolve_blocks(b_start: int, b_stop: int, n: int, m: np.ndarray, counts_pad: np.ndarray,
                    applied: np.ndarray, sums: np.ndarray, qa: np.ndarray, raw: np.ndarray,
                    dl: np.ndarray, kinds: np.ndarray, lut: np.ndarray, slots: np.ndarray,
                    signs: np.ndarray, hslots: np.ndarray, hsigns: np.ndarray, buf: np.ndarray,
                    hist: np.ndarray, hist_counts: np.ndarray, scale: float, m_tmp: np.ndarray,
                    c_tmp: np.ndarray, lam: float, overlap: float, min_events: int,
                    min_equations: float, min_decorrelation: float, min_contrast: float,
                    max_contrast: float, max_bias_ratio: float, no_reason: np.ndarray,
                    smoothing: float, c: np.ndarray, b: np.ndarray, se_c: np.ndarray,
                    se_b: np.ndarray, seen: np.ndarray, n_solved: np.ndarray,
                    reason: np.ndarray, track: np.ndarray,
                    corr: float) -> None:  # pragma: no cover - compiled
    """Blocks ``b_start .. b_stop`` of OnEI's re-solve, one call without the GIL (threads
    take disjoint ranges; ``buf``, ``m_tmp`` and ``c_tmp`` are the caller's scratch): each
    block prepared (:func:`prepared_block`; its queue added unless ``applied``), solved
    (:func:`~evcal.solver.solve_pixels`' kernel) and folded into the estimate
    (:func:`~evcal.onei.estimate.low_pass`)."""
    for blk in range(b_start, b_stop):
        s = blk * BLOCK
        e = min(s + BLOCK, n)
        mb, cb = prepared_block(blk, n, m, counts_pad, not applied[blk], sums, qa, raw, dl,
                                 kinds, lut, slots, signs, hslots, hsigns, buf, hist,
                                 hist_counts, scale, m_tmp, c_tmp)
        c_new, b_new, r_new, se_c_new, se_b_new = _solve_pixels(
            mb.reshape((16, BLOCK)), cb, lam, overlap, min_events, min_equations,
            min_decorrelation, min_contrast, max_contrast, max_bias_ratio, no_reason)
        r = r_new[: e - s]
        low_pass(c_new, b_new, se_c_new, se_b_new, r == VALID, r, smoothing, c[s:e],
                  b[s:e], se_c[s:e], se_b[s:e], seen[s:e], n_solved[s:e], reason[s:e],
                  track[:, s:e], corr)


def lambda_block_list(n_blocks: int) -> np.ndarray:
    """The blocks the residual-correction factor is estimated on (:data:`LAMBDA_BLOCKS`)."""
    if n_blocks <= LAMBDA_BLOCKS:
        return np.arange(n_blocks)
    return np.unique(np.linspace(0, n_blocks - 1, LAMBDA_BLOCKS).round().astype(np.int64))


def resolve(sums: NormalSums, est: LowPassEstimate, config: OnEIConfig, *, left: int | None,
            overlap: float, replace: bool, corr: float = 0.0) -> float:
    """Solve every pixel and fold the solution into ``est``: block by block, each block
    updated with the queued equations and solved while in cache. The same kernels and sums as
    ``correction_lambda`` and ``solve_pixels`` on the whole sensor, but for ``lam`` estimated
    on :func:`lambda_block_list` (every pixel up to 131 k pixels). ``left``: the events that
    have left the buffer (the history's weights); ``overlap``: the small buffers each event
    lies in; ``replace``: the solution replaces the estimate's earlier ones; ``corr``: the
    correlation of two consecutive solves' errors (:func:`~evcal.onei.estimate.low_pass`).
    Returns ``lam``."""
    queued = as_arrays(sums.queued)
    hqueued = as_arrays(sums.hqueued)
    scale = sums.hist_scale(left) if sums.hist is not None else 0.0
    applied = np.zeros(sums.n_blocks, bool)  # blocks the queue was added to
    setting = config.residual_correction
    if setting == "auto":  # correction_lambda: fit without the correction, one step
        blocks = lambda_block_list(sums.n_blocks)
        applied[blocks] = True
        res_q, cq = _terms_of(sums, config, blocks, queued, hqueued, scale)
        lam = 0.0
        if res_q.size:
            den = float(cq.sum())
            lam = 0.0 if den <= 0 else 0.0 + float(res_q.sum()) / den
            lam = float(np.clip(lam, 0.0, 0.5))
    else:
        lam = 0.0 if setting == "off" else float(setting)
    if replace:
        est.n_solved[:] = 0
    _solve_blocks(sums, est, config, applied, queued, hqueued, scale, lam, overlap, corr)
    sums.queued.clear()
    sums.hqueued.clear()
    return lam


def _terms_of(sums: NormalSums, config: OnEIConfig, blocks: np.ndarray, queued: Queue | None,
              hqueued: Queue | None, scale: float) -> tuple[np.ndarray, np.ndarray]:
    """The residual-correction terms of ``blocks`` (given their queued equations), in block
    order whatever the threads (the same sums with any number)."""
    lim, n = config.limits, sums.n_pixels
    inputs, hist, hist_counts = sums.kernel_inputs(queued, hqueued)
    sizes = np.minimum(BLOCK, n - blocks * BLOCK)
    starts = np.concatenate([[0], np.cumsum(sizes)])  # each range's room in the output
    res_q, cq = sums.lam_terms
    ends: dict[int, tuple[int, int]] = {}
    sums.ensure_scratch()

    def work(i: int, lo: int, hi: int) -> None:
        buf, m_tmp, c_tmp = sums.scratch[i]
        at = int(starts[lo])
        got = lambda_blocks(
            blocks[lo:hi], n, sums.m, sums.counts_pad, *inputs, buf, hist, hist_counts,
            scale, m_tmp, c_tmp, int(lim.min_events), float(lim.min_decorrelation),
            float(lim.min_contrast), float(lim.max_contrast), float(lim.max_bias_ratio),
            res_q[at:], cq[at:])
        ends[lo] = (at, at + got)

    sums.executor.on_threads(blocks.size, work)
    parts = [ends[lo] for lo in sorted(ends)]
    return (np.concatenate([res_q[a:e] for a, e in parts]),
            np.concatenate([cq[a:e] for a, e in parts]))


def _solve_blocks(sums: NormalSums, est: LowPassEstimate, config: OnEIConfig,
                  applied: np.ndarray, queued: Queue | None, hqueued: Queue | None,
                  scale: float, lam: float, overlap: float, corr: float) -> None:
    """The re-solve's pass over every block (:func:`resolve_blocks`) on the executor's
    threads (the blocks are independent: the same result with any number)."""
    lim = config.limits
    inputs, hist, hist_counts = sums.kernel_inputs(queued, hqueued)
    sums.ensure_scratch()

    def work(i: int, lo: int, hi: int) -> None:
        buf, m_tmp, c_tmp = sums.scratch[i]
        resolve_blocks(
            lo, hi, sums.n_pixels, sums.m, sums.counts_pad, applied, *inputs, buf, hist,
            hist_counts, scale, m_tmp, c_tmp, lam, overlap, int(lim.min_events),
            float(lim.min_equations), float(lim.min_decorrelation), float(lim.min_contrast),
            float(lim.max_contrast), float(lim.max_bias_ratio), sums.no_reason,
            float(config.smoothing), est.c, est.b, est.se_c, est.se_b, est.seen,
            est.n_solved, est.reason, est.track, corr)

    sums.executor.on_threads(sums.n_blocks, work)
