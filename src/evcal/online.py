"""OnEI: online events + intensity calibration with an event-count-driven buffer.

The stream is cut at frame times into *frame intervals*. The **large buffer** is the sliding
set of the most recent whole frame intervals holding at most ``n_large`` events; when a new
interval makes it overflow, the oldest intervals are dropped (the paper's rule). The large
buffer is split into **small buffers** of about ``n_small`` events, each one equation per
pixel: ``dL = c (P + lam Q) + b (E + lam A)`` between the frame that opens it and the frame
that closes it (the OffEI equation with its residual correction, :mod:`evcal.offline`).

The split overlaps: a small buffer opens at *every* frame of the large buffer and closes at the
first later frame by which it holds ``n_small`` events. This is OffEI's overlapping windows
with an event-count instead of a frame-count window, and it is what brings OnEI's error close
to OffEI's: a disjoint split gives each pixel ~``n_large / n_small`` equations, each carrying a
full sub-threshold residual at both ends; the overlapping split uses every frame of the buffer.
Measured at 240x180, 10 s, paper buffer sizes (``tests/test_recovery.py``, seed 7): contrast
RMSE 0.0268 with the disjoint split and smoothing 0.2, 0.0119 with this one and smoothing 0.1
(OffEI: 0.0093); bias RMSE 0.0038 (OffEI: 0.0031).

The per-pixel normal equations (:class:`~evcal.solver.NormalEquations`' sums) are updated
incrementally: a small buffer's equation is added when it closes and subtracted, recomputed
bit-identically from the same stored data, when the frame that opened it leaves the large
buffer; every ``rebuild_every`` removals they are rebuilt from the buffer to shed rounding.
That is rare by default (100 k removals, 67 minutes at 25 Hz): the cross products of counts
and polarities are integers, exact in float64, and only those with ``dL`` round; measured
after 3,000 removals they differ from a rebuild by 3e-15 of their size. A rebuild costs a
frame the work of every equation in the buffer (30 ms at 346x260 with 87 frames buffered),
a latency spike a live service should not see every 20 s.
Per frame the cost is that of the frame's events and pixels, not of the buffer's: two sliding
sums hold the counts of the small buffer closing next and of the one leaving (each interval
enters and leaves each sum once); an equation is queued as those counts, its polarity
regressors and its two frame values (``PENDING_SLOTS`` at most), and the queue is added to the
normal equations at the next solve, block by block in cache, each block then solved at once
(:mod:`evcal._onei_kernels`; the same operations in the same order as adding the equations
one by one, and :mod:`evcal.solver`'s own per-pixel kernels).

State, bounded whatever the rates. Per buffered frame (at most ``max_buffer_frames``): its raw
image and the polarity of each pixel's last event (itemsize + 1 bytes per pixel), and the ON/OFF
counts of the interval that ended at it, sparse (12 bytes per pixel that fired) or, when more
than 2/3 of the pixels fired, dense (8 bytes per pixel): at most 12 bytes per event of the
buffer (``n_large`` events' worth, but for an interval holding more on its own). Per pixel
besides: the normal equations 128 B, the queued equations 72 B (8-bit frames; 120 B for
others), the sliding sums 16 B, the open interval (packed counts, spills, last polarities)
10 B, the buffer's counts 8 B, the smoothed estimate 42 B and the residual-lambda terms 16 B:
292 B per pixel, 292 MB per megapixel (340 MB for frames other than 8-bit).

After every ``n_small`` new events (once a new equation closed) the per-pixel system is
re-solved and the estimate low-pass filtered: ``est <- (1 - smoothing) est + smoothing new`` on
pixels whose new solution is valid, with a start-up correction: a pixel's first
``1 / smoothing`` solutions are averaged with equal weights. The default smoothing 0.1 gives
the filter a memory of about ``10 n_small`` events, close to one large buffer at the paper's
sizes; the estimate follows a change of thresholds within about two large buffers.

Streaming contract: :meth:`OnlineCalibrator.feed_events` takes sorted chunks, time never going
back across chunks; frames may arrive late with respect to events (events after the latest
frame wait in a bounded pending buffer until the frame that closes their interval arrives).
:meth:`OnlineCalibrator.mark_gap` says events were lost: no small buffer spans the loss.
"""

from __future__ import annotations

import itertools
import json
import math
import os
from collections import deque
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import asdict, dataclass, field, replace
from typing import Any

import numba
import numpy as np

from ._onei_kernels import (
    BLOCK,
    COUNT_BITS,
    COUNT_MAX,
    LAST_SHIFT,
    add_dense,
    append_masked,
    apply_blocks,
    close_interval,
    drop_dense,
    drop_interval,
    fill_slot,
    fold_events,
    scatter_interval,
)
from .calibration import (
    DEFAULT_BIAS,
    DEFAULT_CONTRAST,
    Calibration,
    Diagnostics,
    OnEIDiagnostics,
    Reason,
    Special,
)
from .errors import CalibrationError, ConfigError, ErrorReason, StateError
from .events import EVENTS_DTYPE, SensorSize
from .jsonable import to_jsonable
from .recording import Recording
from .solver import (
    NormalEquations,
    PixelSolution,
    SolveLimits,
    _lambda_terms,
    _solve_pixels,
    log_intensity,
    usable,
)
from .special import K_POPULATION, Z_MEASUREMENT, label_one, population_limits
from .stream import StreamError, StreamGuard, frame_intervals

STATE_FORMAT = "evcal.onei.v2"
# state_dict's scalars: JSON key -> attribute (besides sensor, config and the stream's times)
_OFFSET_POOL: ThreadPoolExecutor | None = None


def _offset_pool() -> ThreadPoolExecutor:
    """One worker thread for every calibrator's offset criterion (numpy releases the GIL in
    its array work, so the frame path goes on meanwhile)."""
    global _OFFSET_POOL
    if _OFFSET_POOL is None:
        _OFFSET_POOL = ThreadPoolExecutor(max_workers=1, thread_name_prefix="evcal-offset")
    return _OFFSET_POOL


# a pass over the pixels is split over threads only when each gets this many (handing a
# range to a pool thread and waiting for it costs tens of microseconds: at 346x260 a frame's
# passes take about that each)
PIXELS_PER_THREAD = 1 << 17
MAX_SOLVE_THREADS = 8  # a re-solve's threads at most (it is memory-bound beyond a few)
RANGES_PER_THREAD = 4  # a threaded pass's ranges per thread (see OnlineCalibrator._on_threads)
_SOLVE_POOL: ThreadPoolExecutor | None = None


def usable_cores() -> int:
    """The cores this process may run on (its affinity: a container's or taskset's limit)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):  # not on Linux
        return max(1, os.cpu_count() or 1)


_NO_HISTORY = np.zeros((0, 16 * BLOCK), np.float64)  # _resolve_blocks' hist when it is off
_NO_COUNTS = np.zeros(0, np.float64)


def _solve_pool() -> ThreadPoolExecutor:
    """Threads for the re-solve's block ranges beyond the caller's own, shared by every
    calibrator of the process (the kernels run without the GIL)."""
    global _SOLVE_POOL
    if _SOLVE_POOL is None:
        _SOLVE_POOL = ThreadPoolExecutor(max_workers=max(1, MAX_SOLVE_THREADS - 1),
                                         thread_name_prefix="evcal-solve")
    return _SOLVE_POOL


def _forget_pools() -> None:
    """In a forked child: the parent's pool threads do not exist there, and a pool that
    believes it has them would never run a job (a re-solve would wait forever)."""
    global _SOLVE_POOL, _OFFSET_POOL
    _SOLVE_POOL = _OFFSET_POOL = None


os.register_at_fork(after_in_child=_forget_pools)


def _offset_windows(pix: np.ndarray, parts: list[tuple[Any, ...]], d: int,
                    saturation_dn: tuple[float, float]) -> tuple[np.ndarray, ...]:
    """The criterion's windows of ``d`` intervals at pixels ``pix`` (sorted) from the
    frames' ``(dense, idx, on, off, last_p, image)``: net polarity, count, change of last
    polarity, the frames at both ends and the weights, ``[window, pixel]``."""
    on = np.zeros((len(parts), pix.size), np.int64)
    off = np.zeros((len(parts), pix.size), np.int64)
    for i, (dense, idx, f_on, f_off, _, _) in enumerate(parts):  # vectorised over pixels
        if dense:
            on[i] = f_on[pix]
            off[i] = f_off[pix]
            continue
        if not idx.size:
            continue
        # the chosen pixels looked up in the interval's sorted pixels (a search per chosen
        # pixel, not a pass over the ~10^5-10^6 that fired)
        at = np.minimum(np.searchsorted(idx, pix), idx.size - 1)
        hit = idx[at] == pix
        on[i, hit] = f_on[at[hit]]
        off[i, hit] = f_off[at[hit]]
    con, coff = np.cumsum(on, 0), np.cumsum(off, 0)
    ks = np.arange(d, len(parts))
    sp = ((con[ks] - coff[ks]) - (con[ks - d] - coff[ks - d])).astype(np.float64)
    se = ((con[ks] + coff[ks]) - (con[ks - d] + coff[ks - d])).astype(np.float64)
    last = np.stack([p[4][pix] for p in parts]).astype(np.float64)
    img = np.stack([p[5][pix] for p in parts]).astype(np.float64)
    ok = usable(img, saturation_dn)
    w = (ok[ks] & ok[ks - d]).astype(np.float64)
    return sp, se, last[ks] - last[ks - d], img[ks - d], img[ks], w


def _offset_criterion(pix: np.ndarray, parts: list[tuple[Any, ...]], d: int,
                      saturation_dn: tuple[float, float], grid: tuple[float, float, int]
                      ) -> tuple[float, dict[str, Any]] | None:
    """``offset_from_windows`` on the windows of :func:`_offset_windows` (both on the
    worker thread: 1280x720 at 20 M events/s, 69 frames, gathering them took 82 ms in the
    frame path)."""
    from .offline import offset_from_windows  # noqa: PLC0415 - offline imports solver only

    sp, se, dq, fj, fk, w = _offset_windows(pix, parts, d, saturation_dn)
    n_pix = int(pix.size)
    try:
        o, info = offset_from_windows(sp, se, dq, fj, fk, w, offset_grid=grid)
    except CalibrationError:  # nothing to judge by yet (a still scene): ask again later
        return None
    info.update(pixels=n_pix, window_frames=d, source="OnEI buffer")
    return o, info


def _opt_int(v: Any) -> int | None:
    return None if v is None else int(v)


_SCALARS: dict[str, tuple[str, Any]] = {
    "lam": ("lam", float), "n_updates": ("n_updates", int), "n_events": ("n_events", int),
    "n_frames": ("n_frames", int), "n_equations": ("n_equations", int),
    "n_gaps": ("n_gaps", int), "gap": ("_gap", bool), "n_folded_late": ("n_folded_late", int),
    "n_refolds": ("n_refolds", int),
    "n_late_events": ("n_late_events", int), "n_sessions": ("n_sessions", int),
    "base": ("_base", int), "next_open": ("_next_open", int),
    "cum_events": ("_cum_events", int), "removals": ("_removals", int),
    "since_resolve": ("_since_resolve", int), "frame_cap": ("_frame_cap", _opt_int),
    "log_offset": ("log_offset", float), "next_offset_check": ("_next_offset_check", int),
    "holds_all": ("_holds_all", bool), "hist_ref": ("_hist_ref", int)}
# absent from the states of earlier versions
_OPTIONAL_SCALARS = frozenset({"n_sessions", "log_offset", "next_offset_check", "holds_all",
                               "hist_ref", "n_refolds"})
_VALID = int(Reason.VALID)
_UNOBSERVED, _NORMAL = int(Special.UNOBSERVED), int(Special.NORMAL)
PENDING_SLOTS = 6  # equations queued before they are added to the normal equations
_OPEN, _DROP = 0, 1  # the two sliding sums: the small buffer closing next, the one leaving


@numba.njit(cache=True, nogil=True)
def _low_pass(c_new: np.ndarray, b_new: np.ndarray, se_c_new: np.ndarray, se_b_new: np.ndarray,
              ok: np.ndarray, reason_new: np.ndarray, smoothing: float, c: np.ndarray,
              b: np.ndarray, se_c: np.ndarray, se_b: np.ndarray, seen: np.ndarray,
              n_solved: np.ndarray, reason: np.ndarray) -> Any:  # pragma: no cover - compiled
    """Fold one solve into the smoothed estimate, in place (OnEI's low-pass with start-up
    correction). New values pass through float32, as they did through a Calibration."""
    for i in range(c.size):
        if ok[i]:
            n_solved[i] += 1
            n = n_solved[i] if n_solved[i] >= 1 else 1
            a = 1.0 / n
            if smoothing >= a:
                a = smoothing
            c[i] += a * (np.float64(np.float32(c_new[i])) - c[i])
            b[i] += a * (np.float64(np.float32(b_new[i])) - b[i])
            se_c[i] = np.float64(np.float32(se_c_new[i]))
            se_b[i] = np.float64(np.float32(se_b_new[i]))
            seen[i] = True
        reason[i] = _VALID if seen[i] else reason_new[i]


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _prepared_block(blk: int, n: int, m: np.ndarray, counts_pad: np.ndarray, apply: bool,
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


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _lambda_blocks(blocks: np.ndarray, n: int, m: np.ndarray, counts_pad: np.ndarray,
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
        mb, cb = _prepared_block(blk, n, m, counts_pad, True, sums, qa, raw, dl, kinds, lut,
                                 slots, signs, hslots, hsigns, buf, hist, hist_counts, scale,
                                 m_tmp, c_tmp)
        mask, rq_b, cq_b = _lambda_terms(mb.reshape((16, BLOCK)), cb, min_events,
                                         min_decorrelation, min_contrast, max_contrast,
                                         max_bias_ratio)
        end = append_masked(mask, rq_b, cq_b, min(BLOCK, n - blk * BLOCK), res_q, cq, end)
    return end


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _resolve_blocks(b_start: int, b_stop: int, n: int, m: np.ndarray, counts_pad: np.ndarray,
                    applied: np.ndarray, sums: np.ndarray, qa: np.ndarray, raw: np.ndarray,
                    dl: np.ndarray, kinds: np.ndarray, lut: np.ndarray, slots: np.ndarray,
                    signs: np.ndarray, hslots: np.ndarray, hsigns: np.ndarray, buf: np.ndarray,
                    hist: np.ndarray, hist_counts: np.ndarray, scale: float, m_tmp: np.ndarray,
                    c_tmp: np.ndarray, lam: float, overlap: float, min_events: int,
                    min_equations: float, min_decorrelation: float, min_contrast: float,
                    max_contrast: float, max_bias_ratio: float, no_reason: np.ndarray,
                    smoothing: float, c: np.ndarray, b: np.ndarray, se_c: np.ndarray,
                    se_b: np.ndarray, seen: np.ndarray, n_solved: np.ndarray,
                    reason: np.ndarray) -> None:  # pragma: no cover - compiled
    """Blocks ``b_start .. b_stop`` of OnEI's re-solve, one call without the GIL (threads
    take disjoint ranges; ``buf``, ``m_tmp`` and ``c_tmp`` are the caller's scratch): each
    block prepared (:func:`_prepared_block`; its queue added unless ``applied``), solved
    (:func:`~evcal.solver.solve_pixels`' kernel) and folded into the estimate
    (:func:`_low_pass`)."""
    for blk in range(b_start, b_stop):
        s = blk * BLOCK
        e = min(s + BLOCK, n)
        mb, cb = _prepared_block(blk, n, m, counts_pad, not applied[blk], sums, qa, raw, dl,
                                 kinds, lut, slots, signs, hslots, hsigns, buf, hist,
                                 hist_counts, scale, m_tmp, c_tmp)
        c_new, b_new, r_new, se_c_new, se_b_new = _solve_pixels(
            mb.reshape((16, BLOCK)), cb, lam, overlap, min_events, min_equations,
            min_decorrelation, min_contrast, max_contrast, max_bias_ratio, no_reason)
        r = r_new[: e - s]
        _low_pass(c_new, b_new, se_c_new, se_b_new, r == _VALID, r, smoothing, c[s:e],
                  b[s:e], se_c[s:e], se_b[s:e], seen[s:e], n_solved[s:e], reason[s:e])


@numba.njit(cache=True, nogil=True)
def _estimate_maps(lo: int, hi: int, c: np.ndarray, b: np.ndarray, se_c: np.ndarray,
                   se_b: np.ndarray, seen: np.ndarray, reason: np.ndarray, z: float,
                   limits: np.ndarray, significant: bool, c32: np.ndarray, b32: np.ndarray,
                   se_c32: np.ndarray, se_b32: np.ndarray, reason_out: np.ndarray,
                   valid_out: np.ndarray,
                   special_out: np.ndarray) -> None:  # pragma: no cover - compiled
    """Pixels ``lo .. hi`` of the calibration maps of the estimate, in one pass (threads
    take disjoint ranges): the float32 contrast, bias and standard errors (inf where not
    valid), the reasons, the valid mask and the special classes (:func:`~evcal.special.
    classify`'s rule with the population's ``limits``)."""
    b_low, b_high, c_low, c_high = limits[0], limits[1], limits[2], limits[3]
    # slices first: a loop from 0 vectorises (indices from lo could be negative, numba's
    # wraparound then costs 3-7x)
    c, b, se_c, se_b = c[lo:hi], b[lo:hi], se_c[lo:hi], se_b[lo:hi]
    seen, reason, c32, b32 = seen[lo:hi], reason[lo:hi], c32[lo:hi], b32[lo:hi]
    se_c32, se_b32, reason_out = se_c32[lo:hi], se_b32[lo:hi], reason_out[lo:hi]
    valid_out, special_out = valid_out[lo:hi], special_out[lo:hi]
    for i in range(hi - lo):
        v = seen[i]
        c32[i] = c[i]
        b32[i] = b[i]
        se_c32[i] = se_c[i] if v else np.inf
        se_b32[i] = se_b[i] if v else np.inf
        reason_out[i] = reason[i]
        valid_out[i] = v
        k = label_one(c[i], b[i], se_c[i], se_b[i], z, b_low, b_high, c_low, c_high)
        k = k if significant else _NORMAL
        special_out[i] = k if v else _UNOBSERVED


class LowPassEstimate:
    """OnEI's smoothed per-pixel estimate (flat maps) and its low-pass update.

    ``est <- (1 - a) est + a new`` on pixels whose new solution is valid, with
    ``a = max(smoothing, 1 / n)`` for a pixel's ``n``-th valid solution (the start-up
    correction: the first ``1 / smoothing`` solutions are averaged with equal weights).
    """

    ARRAYS = ("c", "b", "se_c", "se_b", "seen", "n_solved", "reason")
    # the special-pixel classes' population statistics come from at most about this many
    # pixels (special.classify): exact up to 346x260 and more, 7x fewer medians at 1280x720
    POPULATION_SAMPLE = 1 << 17

    def __init__(self, n_pixels: int) -> None:
        self.c = np.full(n_pixels, DEFAULT_CONTRAST)
        self.b = np.full(n_pixels, DEFAULT_BIAS)
        self.se_c = np.full(n_pixels, np.inf)
        self.se_b = np.full(n_pixels, np.inf)
        self.seen = np.zeros(n_pixels, bool)  # a valid solution was folded in
        self.n_solved = np.zeros(n_pixels, np.int64)  # valid solutions of each pixel so far
        self.reason = np.full(n_pixels, Reason.NO_EVENTS, np.uint8)

    def fold(self, new: PixelSolution, smoothing: float) -> None:
        _low_pass(new.c, new.b, new.se_c, new.se_b, new.valid,
                  new.reason, float(smoothing), self.c, self.b, self.se_c, self.se_b,
                  self.seen, self.n_solved, self.reason)

    def maps(self, shape: tuple[int, int],
             on_threads: Callable[[int, Callable[[int, int, int], None]], None] | None = None
             ) -> dict[str, np.ndarray]:
        """The calibration maps of the estimate (new arrays of the schema's dtypes; defaults
        where never solved), special classes as :func:`~evcal.special.classify`'s, in one
        compiled pass; ``on_threads(n, work)`` may split it into ranges ``work(thread, lo,
        hi)`` (the calibrator's threads)."""
        n = self.c.size
        limits = population_limits(self.c, self.b, self.seen, K_POPULATION,
                                   self.POPULATION_SAMPLE)
        out = {"contrast": np.empty(n, np.float32), "bias": np.empty(n, np.float32),
               "valid": np.empty(n, bool), "reason": np.empty(n, np.uint8),
               "stderr_contrast": np.empty(n, np.float32),
               "stderr_bias": np.empty(n, np.float32), "special": np.empty(n, np.uint8)}

        def work(_i: int, lo: int, hi: int) -> None:
            _estimate_maps(lo, hi, self.c, self.b, self.se_c, self.se_b, self.seen,
                           self.reason, Z_MEASUREMENT,
                           np.zeros(4) if limits is None else limits, limits is not None,
                           out["contrast"], out["bias"], out["stderr_contrast"],
                           out["stderr_bias"], out["reason"], out["valid"], out["special"])

        if on_threads is None:
            work(0, 0, n)
        else:
            on_threads(n, work)
        return {k: v.reshape(shape) for k, v in out.items()}

    def state(self) -> dict[str, np.ndarray]:
        return {name: getattr(self, name) for name in self.ARRAYS}

    def load(self, state: dict[str, np.ndarray]) -> None:
        """Copy a :meth:`state` in (shapes checked; :class:`StateError` otherwise)."""
        for name in self.ARRAYS:
            _load_into(getattr(self, name), state[name], name)


def _load_into(dst: np.ndarray, src: np.ndarray, name: str) -> None:
    if np.shape(src) != dst.shape:
        raise StateError(f"state {name} has shape {np.shape(src)}, expected {dst.shape}")
    dst[:] = src


@dataclass(frozen=True, kw_only=True)
class OnEIConfig:
    """OnEI parameters. ``None`` sizes scale with the sensor as in the paper at 240x180
    (200 k and 1.7 M events for 43,200 pixels).

    ``max_buffer_frames`` caps the frames kept in the large buffer (``None``: as many as
    ``max_buffer_mb`` of frame storage holds, at least 16): with a static scene the event
    count alone would keep frames forever.

    ``history`` (0: off, the paper's sliding buffer) keeps the equations that left the large
    buffer as a forgotten history beside it: each is weighted ``exp(-E / (history *
    n_large))``, ``E`` the events that left the buffer after it, and every solve is of the
    buffer plus the history (recursive least squares with exponential forgetting, by event
    count as the buffer is). A pixel whose events came early in a long buffer then keeps
    their evidence instead of being re-solved from the few events of the recent buffer;
    the cost is a slower response to a drifting threshold (about ``history`` buffers more).
    """

    n_small: int | None = None
    n_large: int | None = None
    window_frames: int | None = None
    smoothing: float = 0.1
    log_offset: float | str = 30.0  # DN, or "auto": estimated online from the buffer
    residual_correction: str | float = "auto"
    saturation_dn: tuple[float, float] = (0.0, 255.0)
    max_pending_events: int = 20_000_000
    max_buffer_frames: int | None = None
    max_buffer_mb: float = 256.0
    rebuild_every: int = 100_000
    history: float = 0.0  # forgotten history's time constant, in large buffers (0: none)
    # threads of a re-solve (0: the cores this process may use, at most MAX_SOLVE_THREADS);
    # the result is the same with any number
    threads: int = 0
    # add each frame's equations to the normal equations at that frame (True), or queue
    # them for a later pass (False: fewer passes through memory, but an update frame adds the
    # queue of the frames before it); None: at every frame when the sums fit in the cache
    # (16 blocks, 131 k pixels). A service sets True: its update frames wait on the least
    eager: bool | None = None
    # log_offset="auto": True applies an online estimate exactly OFFSET_LAG_FRAMES frames
    # after it was started, waiting for it there if need be (runs are reproducible); False
    # as soon as it is done: at the next frame, or at poll_offset() (a live stream never
    # waits)
    offset_wait: bool = True
    limits: SolveLimits = field(default_factory=lambda: SolveLimits(min_events=10,
                                                                    min_equations=3.0))

    def __post_init__(self) -> None:
        if not 0 < self.smoothing <= 1:
            raise ConfigError(f"smoothing={self.smoothing} must be in (0, 1]")
        lo = self.log_offset
        if not (lo == "auto" or (isinstance(lo, (int, float)) and not isinstance(lo, bool)
                                 and lo >= 0)):
            raise ConfigError(f"log_offset={lo!r} must be 'auto' or a number >= 0 (DN)")
        for name in ("n_small", "n_large", "max_buffer_frames", "window_frames"):
            v = getattr(self, name)
            if v is not None and v < 1:
                raise ConfigError(f"{name}={v} must be >= 1")
        if self.n_small and self.n_large and self.n_large < self.n_small:
            raise ConfigError(f"n_large={self.n_large} must be >= n_small={self.n_small}")
        if self.max_buffer_mb <= 0:
            raise ConfigError(f"max_buffer_mb={self.max_buffer_mb} must be > 0")
        if self.rebuild_every < 1:
            raise ConfigError(f"rebuild_every={self.rebuild_every} must be >= 1")
        if not (isinstance(self.history, (int, float)) and 0 <= self.history < math.inf):
            raise ConfigError(f"history={self.history!r} must be a number >= 0 (large "
                              "buffers; 0: none)")
        if self.eager not in (None, True, False):
            raise ConfigError(f"eager={self.eager!r} must be True, False or None (automatic)")
        if isinstance(self.threads, bool) or not isinstance(self.threads, int) or \
                self.threads < 0:
            raise ConfigError(f"threads={self.threads!r} must be an integer >= 0 (0: the "
                              "cores this process may use)")

    def n_threads(self) -> int:
        """Threads a re-solve uses."""
        return max(1, min(self.threads or usable_cores(), MAX_SOLVE_THREADS))

    def sizes(self, sensor: SensorSize) -> tuple[int, int]:
        n_small = self.n_small or max(1000, int(round(200_000 / 43_200 * sensor.n_pixels)))
        n_large = self.n_large or max(n_small, int(round(1_700_000 / 43_200 * sensor.n_pixels)))
        return n_small, n_large

    def frame_cap(self, sensor: SensorSize, image_itemsize: int) -> int:
        if self.max_buffer_frames is not None:
            return max(2, int(self.max_buffer_frames))
        per_frame = sensor.n_pixels * (image_itemsize + 1)
        return max(16, int(self.max_buffer_mb * 2**20 // per_frame))

    def to_json(self) -> str:
        return json.dumps(asdict(self))

    @classmethod
    def from_json(cls, text: str) -> OnEIConfig:
        d = json.loads(text)
        d["saturation_dn"] = tuple(d["saturation_dn"])
        d["limits"] = SolveLimits(**d["limits"])
        return cls(**d)


@dataclass
class _Frame:
    """One frame of the large buffer and the interval that ended at it."""

    t_us: int
    image: np.ndarray  # flat, as received
    last_p: np.ndarray  # int8 flat: polarity of each pixel's last event before the frame
    cum_events: int  # events folded since the calibrator started, up to this frame
    idx: np.ndarray  # int32: pixels with events in the interval ending here (sparse)
    on: np.ndarray  # int32 ON counts at idx (dense: of every pixel)
    off: np.ndarray  # int32 OFF counts at idx (dense: of every pixel)
    opens: bool = True  # a small buffer may open here (False after a gap)
    closes_at: int = -1  # absolute frame number closing the small buffer opened here
    dense: bool = False  # on, off are full maps (more than 2/3 of the pixels fired)

    @property
    def n_events(self) -> int:
        return int(self.on.sum() + self.off.sum())

    def sparse(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(idx, on, off)`` of the interval, sparse."""
        if not self.dense:
            return self.idx, self.on, self.off
        idx = np.flatnonzero((self.on | self.off) != 0).astype(np.int32)
        return idx, self.on[idx], self.off[idx]

    def forget_interval(self) -> None:
        self.idx = np.zeros(0, np.int32)
        self.on = self.off = np.zeros(0, np.int32)
        self.dense = False


class OnlineCalibrator:
    """Per-camera OnEI state: feed events and frames in time order, read the calibration."""

    def __init__(self, sensor: SensorSize, config: OnEIConfig | None = None):
        self.sensor = sensor
        self.config = config or OnEIConfig()
        self.n_small, self.n_large = self.config.sizes(sensor)
        n = sensor.n_pixels
        self._n_blocks = -(-n // BLOCK)
        # normal equations that fit in the last-level cache (16 blocks, 16.8 MB; 346x260 has
        # 11) take the queued equations at every frame: as cheap as in batches there, and an
        # update frame is not left the queue of the frames before it (346x260: 1.3 -> 0.4 ms);
        # larger ones batch them (PENDING_SLOTS), each pass over the sums costing a pass
        # through memory
        eager = self.config.eager
        self._eager = self._n_blocks <= 16 if eager is None else bool(eager)
        self._frame_cap: int | None = None
        # equations queued for the normal equations, per slot: the pixel counts (ON, OFF),
        # the polarity regressors (Q, A) and the two 8-bit frame values (kind True) or dL;
        # zeros, so that what is never used takes no memory
        k = PENDING_SLOTS
        self._slot_sums = np.zeros((k, 2, n), np.int32)
        self._slot_qa = np.zeros((k, 2, n), np.int8)
        self._slot_raw = np.zeros((k, 2, n), np.uint8)
        self._slot_dl = np.zeros((k, n), np.float64)
        self._slot_kind = np.zeros(k, bool)
        self._lut = np.zeros(256)  # log_intensity of the 8-bit values at self._lut_offset
        self._lut_offset = math.nan
        self._no_reason = np.zeros(BLOCK, np.uint8)  # solve_pixels' extra_reason, per block
        # per thread of a re-solve: _resolve_blocks' scratch (_new_scratch), made when needed
        self._scratch: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
        self._lam_terms = np.empty((2, n), np.float64)  # the masked residual-lambda terms
        self._reset_buffer()
        self.estimate = LowPassEstimate(n)  # what calibration() reports
        auto = self.config.log_offset == "auto"
        # the offset of log(I + offset); NaN until estimated (log_offset="auto")
        given = self.config.log_offset
        self.log_offset = float(given) if not isinstance(given, str) else math.nan
        self.offset_info: dict[str, Any] = {"method": "auto" if auto else "given"}
        # where the online estimate stands, for an operator (status)
        self.offset_state = "waiting for frames" if auto else "given"
        self._next_offset_check = 0  # frame count of the next online re-estimate
        # a criterion being computed off the frame path: (frame count to apply it at, job)
        self._offset_job: tuple[int, Future[tuple[float, dict[str, Any]] | None]] | None = None
        self.lam = 0.0
        self.n_updates = 0
        self.n_events = 0
        self.n_frames = 0
        self.n_gaps = 0
        self.n_folded_late = 0  # events folded without their frame (pending overflow)
        self.n_refolds = 0  # frames earlier than events folded ahead (_fold_ahead)
        self.n_late_events = 0  # events that arrived after the frame that ends their interval
        self.n_sessions = 0  # discontinuities of the stream's time base (new_session)
        # the large buffer still holds every event of the stream: a new solution then holds
        # all the evidence of the earlier ones and replaces the estimate (see _resolve)
        self._holds_all = True
        self._guard = StreamGuard(sensor)  # time order of this calibrator's input

    def _reset_buffer(self) -> None:
        """Empty the large buffer, the pending events and the normal equations."""
        n = self.sensor.n_pixels
        # the interval since the latest frame: packed counts (_onei_kernels), the counts that
        # spilled out of them (ON, OFF), and each pixel's latest polarity (Accumulator's maps)
        self._code = np.zeros(n, np.uint8)
        self._spill = np.zeros((2, n), np.int32)
        self._spilled = False
        self._last_p = np.zeros(n, np.int8)
        # the normal equations, blocked (_onei_kernels); pixels past n are padding
        self._m = np.zeros((self._n_blocks, 16 * BLOCK), np.float64)
        self._counts_pad = np.zeros(self._n_blocks * BLOCK, np.int64)
        self._counts = self._counts_pad[:n]  # events per pixel inside the large buffer
        # sliding sums (ON, OFF) over the intervals (lo, hi] of the small buffer closing next
        # (_OPEN) and of the one leaving the buffer (_DROP); lo >= self._base always
        self._wins = np.zeros((2, 2, n), np.int32)
        self._win_range = [[0, 0], [0, 0]]
        self._queued: list[tuple[int, float]] = []  # (slot, sign) not yet in self._m
        self._frames: deque[_Frame] = deque()
        self._base = 0  # absolute number of self._frames[0]
        self._next_open = 0  # absolute number of the oldest frame whose small buffer is open
        self._cum_events = 0
        self._gap = False
        self._removals = 0
        self._since_resolve = 0
        self._pending: deque[np.ndarray] = deque()
        self._n_pending = 0
        # events of the open interval folded ahead of its frame (see _fold_ahead): while any
        # are, the packed counts hold exactly them, and a frame that comes before the last of
        # them has the interval counted again from them
        self._ahead: deque[np.ndarray] = deque()
        self._n_ahead = 0
        self._ahead_ok = False  # folding ahead allowed (from a frame until counts are forced)
        self._frame_dt_us: deque[int] = deque(maxlen=self.AHEAD_INTERVALS)
        self.n_equations = 0  # small buffers in the normal equations now
        self._reset_history()

    def _reset_history(self) -> None:
        """Empty the forgotten history (``OnEIConfig.history``; None when off). Its sums are
        blocked as ``self._m`` and scaled by ``exp((L - ref) / tau)``, ``L`` the events that
        had left the buffer when an equation left it: the weights only grow, and a solve
        scales them by ``exp(-(L_now - ref) / tau)`` (one multiply per block, no pass over
        the history per frame)."""
        on = self.config.history > 0
        self._hist = np.zeros_like(self._m) if on else None
        self._hist_counts = np.zeros(self._counts_pad.size) if on else None
        self._hist_ref = 0  # events left the buffer that the weights are relative to
        self._hqueued: list[tuple[int, float]] = []  # (slot, weight) not yet in self._hist

    def _start_session_keeping_guard(self) -> None:
        guard = self._guard
        self.new_session()
        self._guard = guard  # it already accepted the message that started the session

    def new_session(self) -> None:
        """The stream's time base changed (a camera restarted, a recording replayed again).

        The rule: no equation may span the discontinuity, so the large buffer, the pending
        events and the normal equations are emptied; the smoothed estimate (and so the
        published calibration) is kept and goes on being refined by the new session. A
        change of sensor needs a new calibrator instead.
        """
        self._reset_buffer()
        self._guard = StreamGuard(self.sensor)
        self.n_sessions += 1
        self._holds_all = False

    @property
    def last_event_t_us(self) -> int | None:
        """Time of the latest event fed (None before the first)."""
        return self._guard.last_event_t_us

    @property
    def last_frame_t_us(self) -> int | None:
        """Time of the latest frame fed (None before the first)."""
        return self._guard.last_frame_t_us

    # -- input ------------------------------------------------------------------------------

    def feed_events(self, events: np.ndarray, *, checked: bool = False) -> None:
        """Add a sorted chunk of events (raises :class:`~evcal.events.EventError`).

        ``checked=True`` is for callers whose own :class:`~evcal.stream.StreamGuard` accepted
        the chunk against this sensor (the service does, and a :class:`Recording`'s events are
        validated whole): nothing is checked again.
        """
        if checked:
            self._guard.note_events(events)
        elif self._guard.accept_events(events, what="events").new_session:
            self._start_session_keeping_guard()
        if events.size == 0:
            return
        self.n_events += int(events.size)
        if self.last_frame_t_us is not None and int(events["t_us"][0]) < self.last_frame_t_us:
            # their frame came first: they are counted in the next interval
            self.n_late_events += int(np.searchsorted(events["t_us"], self.last_frame_t_us))
        self._pending.append(events)
        self._n_pending += int(events.size)
        while self._n_pending + self._n_ahead > self.config.max_pending_events and (
                self._ahead or len(self._pending) > 1):
            if self._ahead:  # they stay counted in this interval whenever its frame comes
                self._keep_ahead()
                self._ahead_ok = False
                continue
            old = self._pending.popleft()
            self._n_pending -= int(old.size)
            self._fold(old)
            self.n_folded_late += int(old.size)
        self._fold_ahead()

    def mark_gap(self) -> None:
        """Events were lost since the latest frame: no small buffer will span this interval."""
        self._gap = True
        self.n_gaps += 1

    def feed_frame(self, t_us: int, image: np.ndarray, exposure_us: int = 0) -> bool:
        """Close the frame interval ending at ``t_us``; True when the estimate was re-solved."""
        t_us = int(t_us)
        img = np.asarray(image)
        if img.shape != self.sensor.shape:
            raise StreamError(
                f"frame at t_us={t_us} has shape {img.shape}, the camera is {self.sensor} "
                f"(expected {self.sensor.shape})", ErrorReason.MALFORMED)
        if img.dtype.kind not in "uif":
            raise StreamError(f"frame at t_us={t_us} has dtype {img.dtype}, expected numbers",
                              ErrorReason.MALFORMED)
        if img.dtype.kind == "f" and not np.isfinite(img).all():
            raise StreamError(f"frame at t_us={t_us} contains NaN or infinite values",
                              ErrorReason.BAD_VALUES)
        previous = self.last_frame_t_us
        if self._guard.accept_frame(t_us, what=f"frame at t_us={t_us}").new_session:
            self._start_session_keeping_guard()
            previous = None
        self._fold_pending_before(t_us)
        if previous is not None and t_us > previous:
            self._frame_dt_us.append(t_us - previous)
        self._ahead_ok = True
        self.n_frames += 1
        if self._frame_cap is None:
            self._frame_cap = self.config.frame_cap(self.sensor, img.dtype.itemsize)
        self._push(t_us, img.ravel().copy())
        job = self._offset_job
        first_formed = False  # the first offset estimate formed the buffer's equations
        if job is not None and (self.n_frames >= job[0] if self.config.offset_wait
                                else job[1].done()):
            first_formed = self._apply_offset()
        if self._offset_job is None and self.n_frames >= self._next_offset_check and (
                math.isnan(self.log_offset) or self._next_offset_check > 0):
            self._check_offset()
        formed = (not math.isnan(self.log_offset)) and (self._close_small_buffers()
                                                         or first_formed)
        self._drop_overflow()
        if self._removals >= self.config.rebuild_every:
            self._rebuild()
        if formed and self._since_resolve >= self.n_small:
            self._resolve()
            self._since_resolve = 0
            return True
        if self._eager:
            # the next update (the frame a service waits on) then adds only its own equations
            self._apply_queued()
        return False

    # -- the large buffer ---------------------------------------------------------------------

    # Folding ahead. The events of a frame interval used to be counted when its frame came,
    # on the frame's path (at 1280x720 and 20 M events/s, 800 k events, 2-9 ms). They are
    # counted as they come now, up to a horizon of AHEAD_FRACTION of the shortest of the last
    # AHEAD_INTERVALS frame intervals after the latest frame; the rest wait for their frame as
    # before. A frame earlier than the last event counted ahead (a frame rate that changed)
    # has its interval counted again from the events kept for it: the same counts in every
    # case, only that frame is slower (counted in ``refolds``).
    AHEAD_FRACTION = 0.75
    AHEAD_INTERVALS = 8

    def _fold_ahead(self) -> None:
        """Fold the pending events before the horizon into the open interval, keeping them
        (:meth:`_fold_pending_before` undoes it if their frame comes earlier)."""
        if not self._ahead_ok or not self._frame_dt_us or not self._pending:
            return
        last = self.last_frame_t_us
        if last is None:
            return
        horizon = last + int(self.AHEAD_FRACTION * min(self._frame_dt_us))
        for part in self._take_pending_before(horizon):
            self._fold(part)
            self._ahead.append(part)
            self._n_ahead += part.size

    def _take_pending_before(self, t_us: int) -> list[np.ndarray]:
        """The pending events before ``t_us``, taken off the pending buffer (views)."""
        taken: list[np.ndarray] = []
        while self._pending:
            chunk = self._pending[0]
            t = chunk["t_us"]
            cut = t.size if int(t[-1]) < t_us else int(np.searchsorted(t, t_us, side="left"))
            if cut:
                taken.append(chunk[:cut])
                self._n_pending -= cut
            if cut < chunk.size:
                if cut:
                    self._pending[0] = chunk[cut:]
                break
            self._pending.popleft()
        return taken

    def _keep_ahead(self) -> None:
        """The events folded ahead stay in the open interval (no longer kept to undo)."""
        self._ahead.clear()
        self._n_ahead = 0

    def _fold_pending_before(self, t_us: int) -> None:
        """Fold the pending events before ``t_us`` (they belong to the interval it closes)."""
        if self._ahead:
            if int(self._ahead[-1]["t_us"][-1]) >= t_us:
                # the frame came before events folded ahead: the packed counts hold only
                # them (folding ahead stops once others are forced in): count again
                self._code[:] = 0
                if self._spilled:
                    self._spill[:] = 0
                    self._spilled = False
                self._pending.extendleft(reversed(self._ahead))
                self._n_pending += self._n_ahead
                self.n_refolds += 1
            self._keep_ahead()
        for part in self._take_pending_before(t_us):
            self._fold(part)

    def _fold(self, events: np.ndarray) -> None:
        if not events.size:
            return
        if fold_events(events["x"], events["y"], events["p"], self.sensor.width, self._code,
                       self._spill[0], self._spill[1]):
            self._spilled = True
        if not self._frames:
            self._close_interval(keep=False)  # before the first frame only polarities matter

    def _close_interval(self, *, keep: bool, add_open: bool = False) -> tuple[Any, ...]:
        """``(idx, on, off, n_events, dense)`` of the interval since the latest frame (empty
        unless ``keep``; then also counted in the buffer, and in the open sliding sum when
        ``add_open``); the latest polarities are folded into ``self._last_p``."""
        out = close_interval(self._code, self._spill[0], self._spill[1], self._spilled,
                             self._last_p, keep, self._counts, self._wins[_OPEN], add_open)
        self._spilled = False
        return tuple(out)

    def _push(self, t_us: int, image: np.ndarray) -> None:
        new = self._base + len(self._frames)  # absolute number of this frame
        keep = bool(self._frames)
        add_open = keep and self._win_range[_OPEN][1] == new - 1
        idx, f_on, f_off, n_new, dense = self._close_interval(keep=keep, add_open=add_open)
        if add_open:
            self._win_range[_OPEN][1] = new
        self._cum_events += int(n_new)
        self._since_resolve += int(n_new)
        if self._gap and self._frames:
            # the interval just closed lost events: close no small buffer across it
            for f in self._frames:
                if f.closes_at < 0:
                    f.opens = False
            self._next_open = self._base + len(self._frames)
        self._gap = False
        self._frames.append(_Frame(t_us, image, self._last_p.copy(), self._cum_events,
                                   idx, f_on, f_off, dense=bool(dense)))

    # -- the log offset, online ----------------------------------------------------------------

    AUTO_WINDOW = 5  # frame intervals per window of the offset criterion (OffEI's default d)
    # OffEI's grid (1..400 DN, 21 points) extended down to 0.1 DN at the same spacing
    OFFSET_GRID = (0.1, 400.0, 30)

    # frames after a check is started at which its result is applied: the criterion (a
    # fraction of a second at 4 k pixels, more on a busy machine) runs on a worker thread
    # meanwhile; with OnEIConfig.offset_wait the result lands at this frame in every run
    # (offline runs wait for it there), without it as soon as it is done (at the next frame,
    # or at poll_offset between frames)
    OFFSET_LAG_FRAMES = 8
    OFFSET_FIRST_FRAMES = 2 * AUTO_WINDOW + 1  # buffered frames before the first estimate
    OFFSET_RECHECK_FACTOR = 4  # re-checked when the frames seen have grown this much
    # frames after a criterion that found nothing to explain (a still scene) before it is
    # computed again (it was at once: a camera facing a still scene recomputed it for ever)
    OFFSET_RETRY_FRAMES = 25
    OFFSET_PIXELS = 4000  # busiest pixels the criterion is computed on
    # the first estimate waits for this fraction of the pixels (at most OFFSET_PIXELS) to be
    # busy, or for the large buffer to be full: on v2e recordings that begin still, a first
    # estimate from 33-59 busy pixels was 64-400 DN for a true 0, and stayed until the
    # re-check 50 frames later, which could only restart from one large buffer
    OFFSET_FIRST_BUSY = 0.05
    OFFSET_MAX_WINDOWS = 64  # the newest windows of the buffer

    def _check_offset(self) -> None:
        """Start an estimate of the offset from the buffer (``log_offset="auto"``): first
        once it holds ``2 d + 1`` frames, then again after 4x, 16x, ... as many frames. The
        inputs are copied here (milliseconds); the criterion runs on a worker thread and
        :meth:`_apply_offset` takes its result ``OFFSET_LAG_FRAMES`` frames later."""
        first = math.isnan(self.log_offset)
        if first and len(self._frames) < self.OFFSET_FIRST_FRAMES:
            self.offset_state = f"waiting for {self.OFFSET_FIRST_FRAMES} buffered frames"
            return
        inputs = self._offset_inputs()
        if inputs is None:
            if not first:
                self._next_offset_check = self.n_frames * self.OFFSET_RECHECK_FACTOR
            return
        self._next_offset_check = self.n_frames * self.OFFSET_RECHECK_FACTOR
        self._offset_job = (self.n_frames + self.OFFSET_LAG_FRAMES,
                            _offset_pool().submit(_offset_criterion, *inputs))
        self.offset_state = f"criterion started at frame {self.n_frames}"

    def poll_offset(self) -> bool:
        """Between frames: take an online offset estimate that has finished (only with
        ``offset_wait=False``; a stream that stops would otherwise never see it). True when
        the estimate was re-solved: read :meth:`calibration`."""
        job = self._offset_job
        if self.config.offset_wait or job is None or not job[1].done():
            return False
        before = self.n_updates
        if self._apply_offset() and self._since_resolve >= self.n_small:
            self._resolve()
            self._since_resolve = 0
        return self.n_updates > before

    def _apply_offset(self) -> bool:
        """Take the started estimate; True when it was the first and formed equations (the
        caller re-solves as after any new equation). A changed estimate (by more than 10 % in
        ``log(1 + o)``) rebuilds the equations from the buffer's raw frames, restarts the
        smoothed estimate and re-solves: the solutions folded so far were fitted to log
        changes at the wrong offset, and averaging them with the new ones would keep their
        bias for ``1 / smoothing`` re-solves."""
        assert self._offset_job is not None
        found = self._offset_job[1].result()
        self._offset_job = None
        if found is None:  # nothing to judge by yet (a still scene): ask again later
            self._next_offset_check = self.n_frames + self.OFFSET_RETRY_FRAMES
            self.offset_state = (f"no estimate at frame {self.n_frames}: no window explains "
                                 "a change of the frames (a still scene?); next try at frame "
                                 f"{self._next_offset_check}")
            return False
        first = math.isnan(self.log_offset)
        o, info = found
        self.offset_state = f"estimated at frame {self.n_frames}"
        info.update(frames_seen=self.n_frames, previous=None if first else self.log_offset,
                    estimate=o)
        self.offset_info = info
        if first:
            self.log_offset = o
            self._form_all()
            return self.n_equations > 0
        if abs(math.log1p(o) - math.log1p(self.log_offset)) > 0.1:
            self.log_offset = o
            self._rebuild()
            self._reset_history()  # its log changes were at the old offset
            self.estimate = LowPassEstimate(self.sensor.n_pixels)
            self._resolve()  # at once, from the rebuilt buffer
            self._since_resolve = 0
            info["estimate_restarted"] = True
        return False

    def _offset_inputs(self) -> tuple[Any, ...] | None:
        """What the criterion of ``--log-offset auto`` is computed from: the busiest pixels
        and the newest ``OFFSET_MAX_WINDOWS + AUTO_WINDOW`` buffered frames' intervals,
        polarities and images (:func:`_offset_windows` makes the windows from them)."""
        frames = list(self._frames)[-(self.OFFSET_MAX_WINDOWS + self.AUTO_WINDOW):]
        d = min(self.AUTO_WINDOW, len(frames) - 3)
        limits = self.config.limits
        busy = np.flatnonzero(self._counts >= max(limits.min_events, 2 * d))
        if d < 1 or busy.size < 10:
            self.offset_state = f"waiting for busy pixels: {busy.size} of 10"
            return None
        need = min(self.OFFSET_PIXELS, self.OFFSET_FIRST_BUSY * self.sensor.n_pixels)
        if math.isnan(self.log_offset) and busy.size < need and self._holds_all:
            self.offset_state = f"waiting for busy pixels: {busy.size} of {need:.0f}"
            return None
        rng = np.random.default_rng(0)
        pix = np.sort(rng.choice(busy, size=min(self.OFFSET_PIXELS, busy.size),
                                 replace=False))
        # references, not copies: a buffered interval's arrays are never changed, only
        # replaced (forget_interval); the windows are gathered on the worker thread
        parts = [(f.dense, f.idx, f.on, f.off, f.last_p, f.image) for f in frames]
        return pix, parts, int(d), self.config.saturation_dn, self.OFFSET_GRID

    def _form_all(self) -> None:
        """Form every small buffer the buffer holds (once the offset became known)."""
        self._clear_equations()
        self.n_equations = 0
        for f in self._frames:
            f.closes_at = -1
        self._next_open = self._base
        for k in range(self._base + 1, self._base + len(self._frames)):
            self._close_small_buffers(k)

    def _close_small_buffers(self, k: int | None = None) -> bool:
        """Form the equations of the small buffers that hold ``n_small`` events at frame
        ``k`` (default the newest; usually one)."""
        if k is None:
            k = self._base + len(self._frames) - 1
        newest = self._frames[k - self._base]
        formed = False
        while self._next_open < k:
            j = self._next_open
            fj = self._frames[j - self._base]
            if not fj.opens:
                self._next_open += 1
                continue
            wf = self.config.window_frames
            if (k - j < wf) if wf else (newest.cum_events - fj.cum_events < self.n_small):
                break
            fj.closes_at = k
            self._queue(j, k, +1.0, _OPEN)
            self.n_equations += 1
            self._next_open += 1
            formed = True
        return formed

    def _drop_overflow(self) -> None:
        cap = self._frame_cap or 2
        # the newest interval always stays, even when it alone holds more than n_large events
        while len(self._frames) > 2:
            first, second = self._frames[0], self._frames[1]
            in_buffer = self._frames[-1].cum_events - first.cum_events
            if in_buffer <= self.n_large and len(self._frames) <= cap:
                break
            # drop the oldest interval: its opening frame and the small buffer it opened
            base = self._base
            w_hist = self._hist_weight(second.cum_events)
            if first.closes_at >= 0:
                self._queue(base, first.closes_at, -1.0, _DROP)
                self.n_equations -= 1
                self._removals += 1
                if self._hist is not None:  # the same slot, into the history
                    self._hqueued.append((self._queued[-1][0], w_hist))
            if self._hist_counts is not None:
                hc = self._hist_counts
                if second.dense:
                    hc[: second.on.size] += w_hist * (second.on + second.off)
                else:
                    hc[second.idx] += w_hist * (second.on + second.off)
            # the interval ending at the new first frame leaves the buffer: uncount it, and
            # slide the sums that hold it past it while its counts are still here
            sub = np.array([lo <= base < hi for lo, hi in self._win_range])
            self._uncount(second, sub)
            for rng in self._win_range:
                if rng[0] <= base:
                    rng[0], rng[1] = base + 1, max(rng[1], base + 1)
            self._frames.popleft()
            self._base += 1
            self._holds_all = False
            second.forget_interval()
            self._next_open = max(self._next_open, self._base)
        if self._hist is not None and self._hist_exponent() > self.HISTORY_RENORMALISE:
            self._renormalise_history()

    # -- the forgotten history (OnEIConfig.history) ----------------------------------------------

    HISTORY_RENORMALISE = 300.0  # exponent of the stored weights that folds the scale in

    @property
    def _hist_tau(self) -> float:
        return float(self.config.history) * self.n_large

    def _hist_exponent(self) -> float:
        left = self._frames[0].cum_events if self._frames else self._hist_ref
        return (left - self._hist_ref) / self._hist_tau

    def _hist_weight(self, left: int) -> float:
        """The stored weight of an equation leaving when ``left`` events have left."""
        if self._hist is None:
            return 0.0
        return math.exp((left - self._hist_ref) / self._hist_tau)

    def _hist_scale(self) -> float:
        """The factor that turns the stored history into its weights now."""
        return math.exp(-self._hist_exponent())

    def _renormalise_history(self) -> None:
        """Fold the scale into the stored history (before its weights overflow)."""
        assert self._hist is not None
        assert self._hist_counts is not None
        self._apply_blocks(self._as_arrays(self._hqueued), self._hist)
        self._hqueued.clear()
        scale = self._hist_scale()
        self._hist *= scale
        self._hist_counts *= scale
        self._hist_ref = self._frames[0].cum_events

    # -- the normal equations ------------------------------------------------------------------

    def _slide(self, w: int, lo: int, hi: int) -> None:
        """Make sliding sum ``w`` the counts of the intervals ``(lo, hi]``: forward, interval by
        interval (each interval enters and leaves a sum once), or afresh."""
        rng, sums = self._win_range[w], self._wins[w]
        cur_lo, cur_hi = rng
        if cur_lo >= self._base and lo >= cur_lo and hi >= cur_hi:
            for f in range(cur_lo + 1, min(lo, cur_hi) + 1):
                self._scatter(sums, f, -1)
            start = max(cur_hi, lo)
        else:
            if cur_hi > cur_lo:
                sums.fill(0)
            start = lo
        for f in range(start + 1, hi + 1):
            self._scatter(sums, f, +1)
        rng[0], rng[1] = lo, hi

    def _uncount(self, fr: _Frame, sub: np.ndarray) -> None:
        """The interval ``fr`` closed leaves the buffer: off the counts, and off the sliding
        sums ``sub`` marks."""
        counts, wins = self._counts, self._wins
        if fr.dense:
            self._split(fr.on.size, lambda lo, hi: drop_dense(
                counts[lo:hi], wins[:, :, lo:hi], sub, fr.on[lo:hi], fr.off[lo:hi]))
        else:  # ranges of the sorted, distinct pixels: no two threads touch one pixel
            self._split(fr.idx.size, lambda lo, hi: drop_interval(
                counts, wins, sub, fr.idx[lo:hi], fr.on[lo:hi], fr.off[lo:hi]))

    def _scatter(self, sums: np.ndarray, f: int, sign: int) -> None:
        fr = self._frames[f - self._base]
        if fr.dense:
            self._split(fr.on.size, lambda lo, hi: add_dense(
                sums[:, lo:hi], fr.on[lo:hi], fr.off[lo:hi], sign))
        else:
            self._split(fr.idx.size, lambda lo, hi: scatter_interval(
                sums, fr.idx[lo:hi], fr.on[lo:hi], fr.off[lo:hi], sign))

    def _queue(self, j: int, k: int, sign: float, w: int) -> None:
        """Queue ``sign`` times the equation of the small buffer from frame ``j`` to frame
        ``k`` (OffEI's equation with its residual regressors), its counts from sliding sum
        ``w``; the queue is added to the normal equations when full or when they are read."""
        self._slide(w, j, k)
        if len(self._queued) == PENDING_SLOTS:
            self._apply_queued()
        slot = len(self._queued)
        fj, fk = self._frames[j - self._base], self._frames[k - self._base]
        sums = self._wins[w]
        if fj.image.dtype == np.uint8 and fk.image.dtype == np.uint8:
            # log_intensity's own 8-bit table; the offset changes only with a rebuild, which
            # empties the queue: a queued equation is always added with its own table
            if not self._lut_offset == self.log_offset:
                values = np.arange(256, dtype=np.uint8)
                # NaN at the values usable() refuses: apply_blocks gives such an equation
                # weight 0, as it does one without events
                self._lut = np.where(usable(values, self.config.saturation_dn),
                                     log_intensity(values, self.log_offset), np.nan)
                self._lut_offset = self.log_offset
            s_sums, s_qa, s_raw = self._slot_sums[slot], self._slot_qa[slot], self._slot_raw[slot]
            self._split(self.sensor.n_pixels, lambda lo, hi: fill_slot(
                sums[:, lo:hi], fj.last_p[lo:hi], fk.last_p[lo:hi], fj.image[lo:hi],
                fk.image[lo:hi], s_sums[:, lo:hi], s_qa[:, lo:hi], s_raw[:, lo:hi]))
            self._slot_kind[slot] = True
        else:  # other frame types: dL as _terms computed it (log_intensity's float path)
            raw_j, raw_k = fj.image, fk.image
            w_ok = usable(raw_j, self.config.saturation_dn) & usable(raw_k,
                                                                     self.config.saturation_dn)
            with np.errstate(invalid="ignore"):  # -inf - -inf at black pixels with offset 0
                dl = log_intensity(raw_k, self.log_offset) - log_intensity(raw_j,
                                                                           self.log_offset)
            self._slot_dl[slot] = np.where(w_ok, dl, 0.0)  # clipped pixels weigh nothing
            np.multiply(sums, w_ok, out=self._slot_sums[slot])
            self._slot_qa[slot, 0] = fk.last_p - fj.last_p
            self._slot_qa[slot, 1] = np.abs(fk.last_p) - np.abs(fj.last_p)
            self._slot_kind[slot] = False
        self._queued.append((slot, sign))

    @staticmethod
    def _as_arrays(queue: list[tuple[int, float]]) -> tuple[np.ndarray, np.ndarray] | None:
        """A queue of ``(slot, weight)`` as :func:`apply_blocks`' arrays (None if empty)."""
        if not queue:
            return None
        return (np.array([q[0] for q in queue], np.int64),
                np.array([q[1] for q in queue], np.float64))

    def _apply_blocks(self, queued: tuple[np.ndarray, np.ndarray] | None,
                      target: np.ndarray | None) -> None:
        """Add queued slots to every block of ``target`` (the normal equations, or the
        history's sums; None: nothing, as for a history that is off), on
        :meth:`_on_threads` (blocks are independent: the same sums with any number)."""
        if queued is None or target is None:
            return
        n = self.sensor.n_pixels

        def work(i: int, lo: int, hi: int) -> None:
            apply_blocks(target, n, lo, hi, self._slot_sums, self._slot_qa, self._slot_raw,
                         self._slot_dl, self._slot_kind, self._lut, *queued,
                         self._scratch[i][0])

        self._on_threads(self._n_blocks, work)

    def _apply_queued(self) -> None:
        """Add the queued equations to the normal equations, and those that left the buffer
        to the history."""
        self._apply_blocks(self._as_arrays(self._queued), self._m)
        self._apply_blocks(self._as_arrays(self._hqueued), self._hist)
        self._queued.clear()
        self._hqueued.clear()

    def _clear_equations(self) -> None:
        # the history keeps what left the buffer (its slots are still filled here)
        self._apply_blocks(self._as_arrays(self._hqueued), self._hist)
        self._hqueued.clear()
        self._queued.clear()
        self._m.fill(0.0)
        self._removals = 0

    def _rebuild(self) -> None:
        """Recompute the normal equations from the buffer (sheds accumulated rounding)."""
        self._clear_equations()
        for i, f in enumerate(self._frames):
            if f.closes_at >= 0:
                self._queue(self._base + i, f.closes_at, +1.0, _DROP)
        self._apply_queued()

    def _normal_equations(self) -> NormalEquations:
        """The normal equations as :class:`~evcal.solver.NormalEquations` (a copy)."""
        self._apply_queued()
        n = self.sensor.n_pixels
        ne = NormalEquations(n)
        ne.m[:] = self._rows(self._m)
        return ne

    def _rows(self, blocked: np.ndarray) -> np.ndarray:
        """Blocked sums as ``(16, n)`` rows (a view when it can be: copy to keep)."""
        rows = blocked.reshape(self._n_blocks, 16, BLOCK).transpose(1, 0, 2)
        out: np.ndarray = rows.reshape(16, -1)[:, : self.sensor.n_pixels]
        return out

    def _blocked(self, rows: np.ndarray, out: np.ndarray) -> None:
        """``(16, n)`` rows into blocked sums ``out``."""
        padded = np.zeros((16, self._n_blocks * BLOCK), np.float64)
        padded[:, : self.sensor.n_pixels] = rows
        out[:] = padded.reshape(16, self._n_blocks, BLOCK).transpose(1, 0, 2).reshape(
            self._n_blocks, 16 * BLOCK)

    # blocks (of BLOCK pixels) the residual-correction factor is estimated on: all of them up
    # to this many, else this many spread evenly over the sensor (131 k pixels): lam is one
    # number for the whole sensor, and at 1280x720 a pass over every block only to estimate
    # it cost as much again as the solve (the sums do not fit in any cache)
    LAMBDA_BLOCKS = 16

    def _lambda_block_list(self) -> np.ndarray:
        nb = self._n_blocks
        if nb <= self.LAMBDA_BLOCKS:
            return np.arange(nb)
        return np.unique(np.linspace(0, nb - 1, self.LAMBDA_BLOCKS).round().astype(np.int64))

    def _resolve(self) -> None:
        """Solve every pixel and fold the solution into the estimate: block by block, each
        block updated with the queued equations and solved while in cache. The same kernels
        and sums as ``correction_lambda`` and ``solve_pixels`` on the whole sensor, but for
        ``lam`` estimated on :meth:`_lambda_block_list` (every pixel up to 131 k pixels)."""
        cfg, est = self.config, self.estimate
        queued = self._as_arrays(self._queued)
        hqueued = self._as_arrays(self._hqueued)
        scale = self._hist_scale() if self._hist is not None else 0.0
        applied = np.zeros(self._n_blocks, bool)  # blocks the queue was added to
        setting = cfg.residual_correction
        if setting == "auto":  # correction_lambda: fit without the correction, one step
            blocks = self._lambda_block_list()
            applied[blocks] = True
            res_q, cq = self._terms_of(blocks, queued, hqueued, scale)
            lam = 0.0
            if res_q.size:
                den = float(cq.sum())
                lam = 0.0 if den <= 0 else 0.0 + float(res_q.sum()) / den
                lam = float(np.clip(lam, 0.0, 0.5))
        else:
            lam = 0.0 if setting == "off" else float(setting)
        # consecutive small buffers share their events: divide the degrees of freedom by
        # the number of small buffers each event lies in
        overlap = max(1.0, self.n_equations * self.n_small / max(self.buffer_events, 1))
        if self._holds_all:
            # every solution so far came from a subset of the buffer this one is solved
            # from: it replaces them (averaging in the early, short-buffer solutions with
            # equal weights would only add their noise)
            est.n_solved[:] = 0
        self._solve_blocks(applied, queued, hqueued, scale, lam, float(overlap))
        self._queued.clear()
        self._hqueued.clear()
        self.lam = lam
        self.n_updates += 1

    def _kernel_inputs(self, queued: tuple[np.ndarray, np.ndarray] | None,
                       hqueued: tuple[np.ndarray, np.ndarray] | None
                       ) -> tuple[tuple[Any, ...], np.ndarray, np.ndarray]:
        """The queued slots as the block kernels take them (``sums .. hsigns`` of
        :func:`_prepared_block`), and the history's sums and counts (no rows when it is
        off); ``buf`` between them is per thread."""
        no = (np.empty(0, np.int64), np.empty(0, np.float64))
        slots = (self._slot_sums, self._slot_qa, self._slot_raw, self._slot_dl,
                 self._slot_kind, self._lut, *(queued if queued is not None else no),
                 *(hqueued if hqueued is not None else no))
        hist = self._hist if self._hist is not None else _NO_HISTORY
        hist_counts = self._hist_counts if self._hist_counts is not None else _NO_COUNTS
        return slots, hist, hist_counts

    def _split(self, n_items: int, work: Callable[[int, int], None]) -> None:
        """A per-frame pass ``work(lo, hi)`` over ranges of ``n_items`` pixels (or entries
        of distinct pixels), threaded once each thread gets ``PIXELS_PER_THREAD``."""
        self._on_threads(n_items, lambda _i, lo, hi: work(lo, hi), PIXELS_PER_THREAD)

    def _on_threads(self, n_items: int, work: Callable[[int, int, int], None],
                    per_thread: int = 1) -> None:
        """``work(thread, lo, hi)`` over contiguous ranges of ``n_items`` on up to
        :meth:`OnEIConfig.n_threads` threads, at least ``per_thread`` items each (this one
        among them), each with its own scratch ``self._scratch[thread]``; which thread does
        which range varies from call to call (the ranges' results may not depend on it)."""
        n_threads = max(1, min(self.config.n_threads(), n_items // max(1, per_thread)))
        while len(self._scratch) < n_threads:
            self._scratch.append(self._new_scratch())
        if n_threads == 1:
            work(0, 0, n_items)
            return
        # more ranges than threads, each thread taking the next range left: a thread the
        # machine holds back (a busy core) delays the pass by one range, not by its share
        n_ranges = min(n_items, n_threads * RANGES_PER_THREAD)
        cuts = np.linspace(0, n_items, n_ranges + 1).round().astype(np.int64).tolist()
        next_range = itertools.count()  # next() is atomic under the GIL

        def take(i: int) -> None:
            while (r := next(next_range)) < n_ranges:
                work(i, cuts[r], cuts[r + 1])

        futures = [_solve_pool().submit(take, i) for i in range(1, n_threads)]
        try:
            take(0)
        finally:
            for f in futures:
                f.result()

    def _terms_of(self, blocks: np.ndarray, queued: tuple[np.ndarray, np.ndarray] | None,
                  hqueued: tuple[np.ndarray, np.ndarray] | None,
                  scale: float) -> tuple[np.ndarray, np.ndarray]:
        """The residual-correction terms of ``blocks`` (given their queued equations), in
        block order whatever the threads (the same sums with any number)."""
        lim, n = self.config.limits, self.sensor.n_pixels
        inputs, hist, hist_counts = self._kernel_inputs(queued, hqueued)
        sizes = np.minimum(BLOCK, n - blocks * BLOCK)
        starts = np.concatenate([[0], np.cumsum(sizes)])  # each range's room in the output
        res_q, cq = self._lam_terms
        ends: dict[int, tuple[int, int]] = {}

        def work(i: int, lo: int, hi: int) -> None:
            buf, m_tmp, c_tmp = self._scratch[i]
            at = int(starts[lo])
            got = _lambda_blocks(
                blocks[lo:hi], n, self._m, self._counts_pad, *inputs, buf, hist, hist_counts,
                scale, m_tmp, c_tmp, int(lim.min_events), float(lim.min_decorrelation),
                float(lim.min_contrast), float(lim.max_contrast), float(lim.max_bias_ratio),
                res_q[at:], cq[at:])
            ends[lo] = (at, at + got)

        self._on_threads(blocks.size, work)
        parts = [ends[lo] for lo in sorted(ends)]
        return (np.concatenate([res_q[a:e] for a, e in parts]),
                np.concatenate([cq[a:e] for a, e in parts]))

    def _solve_blocks(self, applied: np.ndarray, queued: tuple[np.ndarray, np.ndarray] | None,
                      hqueued: tuple[np.ndarray, np.ndarray] | None, scale: float, lam: float,
                      overlap: float) -> None:
        """The re-solve's pass over every block (:func:`_resolve_blocks`) on
        :meth:`_on_threads` (the blocks are independent: the same result with any number)."""
        lim, est = self.config.limits, self.estimate
        inputs, hist, hist_counts = self._kernel_inputs(queued, hqueued)

        def work(i: int, lo: int, hi: int) -> None:
            buf, m_tmp, c_tmp = self._scratch[i]
            _resolve_blocks(
                lo, hi, self.sensor.n_pixels, self._m, self._counts_pad, applied, *inputs, buf,
                hist, hist_counts, scale, m_tmp, c_tmp, lam, overlap, int(lim.min_events),
                float(lim.min_equations), float(lim.min_decorrelation),
                float(lim.min_contrast), float(lim.max_contrast), float(lim.max_bias_ratio),
                self._no_reason, float(self.config.smoothing), est.c, est.b, est.se_c,
                est.se_b, est.seen, est.n_solved, est.reason)

        self._on_threads(self._n_blocks, work)

    def _new_scratch(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """A thread's scratch for :func:`_resolve_blocks`: two blocks' dL, and one block's
        sums and counts with the history's (empty when it is off)."""
        on = self._hist is not None
        return (np.zeros((2, BLOCK), np.float64), np.empty(16 * BLOCK if on else 0),
                np.empty(BLOCK if on else 0, np.int64))

    # -- output ------------------------------------------------------------------------------

    @property
    def buffer_events(self) -> int:
        if not self._frames:
            return 0
        return self._frames[-1].cum_events - self._frames[0].cum_events

    def calibration(self) -> Calibration:
        """The current smoothed estimate (defaults where no valid solution was seen yet).

        The maps are copies: the result does not change when the calibrator goes on.
        """
        shape = self.sensor.shape
        return Calibration(
            **self.estimate.maps(shape, lambda n, work: self._on_threads(
                n, work, PIXELS_PER_THREAD)),
            log_offset=self.log_offset,
            method="onei",
            n_events=self._counts.reshape(shape).copy(),
            diagnostics=self.diagnostics(),
        )

    def diagnostics(self) -> OnEIDiagnostics:
        """The figures of :meth:`status` and the configuration, as typed diagnostics."""
        return OnEIDiagnostics(config=json.loads(self.config.to_json()),
                               log_offset_estimation=dict(self.offset_info), **self.status())

    def status(self) -> dict[str, Any]:
        return {
            "n_updates": self.n_updates,
            "n_events": self.n_events,
            "n_frames": self.n_frames,
            "buffer_events": self.buffer_events,
            "buffer_frames": len(self._frames),
            "buffer_equations": self.n_equations,
            "buffer_bytes": self.buffer_bytes,
            "pending_events": self._n_pending + self._n_ahead,
            "refolds": self.n_refolds,
            "folded_late_events": self.n_folded_late,
            "late_events": self.n_late_events,
            "gaps": self.n_gaps,
            "sessions": self.n_sessions,
            "residual_lambda": self.lam,
            "n_small": self.n_small,
            "n_large": self.n_large,
            "last_frame_t_us": self.last_frame_t_us,
            "log_offset": self.log_offset,
            "log_offset_state": self.offset_state,
        }

    @property
    def buffer_bytes(self) -> int:
        """Bytes held by the large buffer (frames, last polarities, sparse interval counts)."""
        return int(sum(f.image.nbytes + f.last_p.nbytes + f.idx.nbytes + f.on.nbytes
                       + f.off.nbytes for f in self._frames))

    @property
    def state_bytes(self) -> int:
        """Bytes of all the calibrator holds: the large buffer and the per-pixel state (normal
        equations, queued equations, sliding sums, open interval, counts, estimate)."""
        arrays: list[np.ndarray] = [
            self._m, self._counts_pad, self._wins, self._code, self._spill, self._last_p,
            self._slot_sums, self._slot_qa, self._slot_raw, self._slot_dl, self._lam_terms,
            *self.estimate.state().values()]
        if self._hist is not None and self._hist_counts is not None:
            arrays += [self._hist, self._hist_counts]
        return self.buffer_bytes + int(sum(a.nbytes for a in arrays))

    # -- persistence -------------------------------------------------------------------------

    def _open_interval_maps(self) -> dict[str, np.ndarray]:
        """The interval since the latest frame as ``Accumulator``'s maps (state format),
        without the events folded ahead (they are saved as pending)."""
        if self._ahead:  # the packed counts and spills hold only those
            zero = np.zeros(self._code.size, np.int32)
            return {"acc_on": zero, "acc_off": zero.copy(), "acc_last_p": self._last_p.copy()}
        code = self._code.astype(np.int32)
        last = code >> LAST_SHIFT
        return {"acc_on": ((code >> COUNT_BITS) & COUNT_MAX) + self._spill[0],
                "acc_off": (code & COUNT_MAX) + self._spill[1],
                "acc_last_p": np.where(last == 1, 1, np.where(last == 2, -1, self._last_p)
                                       ).astype(np.int8)}

    def state_dict(self) -> dict[str, np.ndarray]:
        """Everything needed to resume, as numpy arrays (``np.savez``-able)."""
        frames = list(self._frames)
        n = self.sensor.n_pixels
        sparse = [f.sparse() for f in frames]  # the format's intervals are sparse

        def cat(i: int) -> np.ndarray:
            if not frames:
                return np.zeros(0, np.int32)
            return np.concatenate([sp[i] for sp in sparse]).astype(np.int32)

        waiting = [*self._ahead, *self._pending]  # the events folded ahead wait again
        pending = np.concatenate(waiting) if waiting else np.zeros(0, EVENTS_DTYPE)
        scalars = {"height": self.sensor.height, "width": self.sensor.width,
                   "config": self.config.to_json(),
                   "last_event_t_us": self.last_event_t_us,
                   "last_frame_t_us": self.last_frame_t_us}
        scalars.update({key: getattr(self, attr) for key, (attr, _) in _SCALARS.items()})
        if self._offset_job is not None:  # its result is not saved: check again on restore
            scalars["next_offset_check"] = self.n_frames
        scalars["offset_info"] = to_jsonable(self.offset_info)
        img_dtype = frames[0].image.dtype if frames else np.dtype(np.uint8)
        out: dict[str, np.ndarray] = {
            "format": np.array(STATE_FORMAT),
            "scalars": np.array(json.dumps(scalars)),
            **self._open_interval_maps(),
            "counts": self._counts, **self.estimate.state(),
            "pending": pending, "fr_images": (np.stack([f.image for f in frames]) if frames
                          else np.zeros((0, n), img_dtype)),
            "fr_last_p": (np.stack([f.last_p for f in frames]) if frames
                          else np.zeros((0, n), np.int8)),
            "fr_meta": np.array([[f.t_us, f.cum_events, sp[0].size, int(f.opens), f.closes_at]
                                 for f, sp in zip(frames, sparse, strict=True)],
                                np.int64).reshape(-1, 5),
            "fr_idx": cat(0), "fr_on": cat(1), "fr_off": cat(2),
        }
        for k, v in self._normal_equations().arrays().items():
            out[f"ne_{k}"] = v
        if self._hist is not None and self._hist_counts is not None:
            out["hist_m"] = self._rows(self._hist)  # stored weights, with hist_ref
            out["hist_counts"] = self._hist_counts[:n]
        return {k: np.array(v, copy=True) for k, v in out.items()}

    @classmethod
    def from_state(cls, state: dict[str, np.ndarray]) -> OnlineCalibrator:
        """Rebuild a calibrator from :meth:`state_dict`.

        Raises :class:`~evcal.errors.StateError` if the state is not one or is inconsistent.
        """
        try:
            if str(state["format"]) != STATE_FORMAT:
                raise StateError(f"unknown OnEI state format {state['format']!s} "
                                 f"(this version reads {STATE_FORMAT})")
            s = json.loads(str(state["scalars"]))
            sensor = SensorSize(int(s["height"]), int(s["width"]))
            self = cls(sensor, OnEIConfig.from_json(s["config"]))
            n = sensor.n_pixels
            _load_into(self._spill[0], state["acc_on"], "acc_on")  # as spilled counts
            _load_into(self._spill[1], state["acc_off"], "acc_off")
            self._spilled = bool(self._spill.any())
            _load_into(self._last_p, state["acc_last_p"], "acc_last_p")
            _load_into(self._counts, state["counts"], "counts")
            self.estimate.load(state)
            pending = np.asarray(state["pending"])
            if pending.dtype != EVENTS_DTYPE:
                raise StateError("state pending events have the wrong dtype")
            if pending.size:
                self._pending.append(pending)
            self._n_pending = int(pending.size)
            ne = NormalEquations.from_arrays({k[3:]: v for k, v in state.items()
                                              if k.startswith("ne_")})
            if ne.n_pixels != n:
                raise StateError(f"state normal equations have {ne.n_pixels} pixels, "
                                 f"expected {n}")
            self._blocked(ne.m, self._m)
            if self._hist is not None and self._hist_counts is not None and "hist_m" in state:
                hist_m = np.asarray(state["hist_m"], np.float64)
                if hist_m.shape != (16, n):
                    raise StateError(f"state hist_m has shape {hist_m.shape}, expected "
                                     f"(16, {n})")
                self._blocked(hist_m, self._hist)
                _load_into(self._hist_counts[:n], state["hist_counts"], "hist_counts")
            meta = np.asarray(state["fr_meta"], np.int64).reshape(-1, 5)
            images, last_p = state["fr_images"], state["fr_last_p"]
            if images.shape != (len(meta), n) or last_p.shape != (len(meta), n):
                raise StateError(f"state frames have shapes {images.shape} and {last_p.shape}, "
                                 f"expected ({len(meta)}, {n})")
            bounds = np.concatenate([[0], np.cumsum(meta[:, 2])])
            if bounds[-1] != state["fr_idx"].size:
                raise StateError("state interval counts do not add up")
            for i, (t_us, cum, _, opens, closes_at) in enumerate(meta):
                sl = slice(int(bounds[i]), int(bounds[i + 1]))
                self._frames.append(_Frame(
                    int(t_us), np.array(images[i]), np.array(last_p[i], np.int8), int(cum),
                    np.array(state["fr_idx"][sl], np.int32), np.array(state["fr_on"][sl],
                                                                       np.int32),
                    np.array(state["fr_off"][sl], np.int32), bool(opens), int(closes_at)))
            for key, (attr, conv) in _SCALARS.items():
                if key in s or key not in _OPTIONAL_SCALARS:
                    setattr(self, attr, conv(s[key]))
            if isinstance(s.get("offset_info"), dict):
                self.offset_info = s["offset_info"]
            if self.config.log_offset == "auto" and not math.isnan(self.log_offset):
                self.offset_state = "restored from a saved state"
            self._win_range = [[self._base, self._base], [self._base, self._base]]
            self._guard.last_event_t_us = s["last_event_t_us"]
            self._guard.last_frame_t_us = s["last_frame_t_us"]
        except KeyError as exc:
            raise StateError(f"OnEI state lacks {exc.args[0]!r}") from None
        return self


def onei(rec: Recording, config: OnEIConfig | None = None, *,
         history_every: int = 0) -> Calibration:
    """Run :class:`OnlineCalibrator` over a recording (the path the service uses).

    With ``history_every = n > 0`` the calibration after every n-th update is kept in
    ``diagnostics.history`` as ``(t_us, contrast, bias, valid)`` tuples (for convergence
    plots). A run that never updates (fewer events than one small buffer) returns the defaults
    with a warning saying why.
    """
    if len(rec.frames) < 2:
        raise CalibrationError(f"OnEI needs frames: the recording has {len(rec.frames)}")
    state = OnlineCalibrator(rec.sensor, config)
    history: list[tuple[int, np.ndarray, np.ndarray, np.ndarray]] = []
    for k, chunk in frame_intervals(rec.events, rec.frames.t_us):
        t = int(rec.frames.t_us[k])
        state.feed_events(chunk, checked=True)  # a Recording's events are validated
        updated = state.feed_frame(t, rec.frames.images[k])
        if updated and history_every and state.n_updates % history_every == 0:
            cur = state.calibration()
            history.append((t, cur.contrast.copy(), cur.bias.copy(), cur.valid.copy()))
    cal = state.calibration()
    diagnostics: Diagnostics = replace(state.diagnostics(), history=tuple(history))
    if state.n_updates == 0:
        diagnostics = diagnostics.with_warning(
            f"OnEI made no update: the recording has {rec.n_events} events between its "
            f"frames, fewer than one small buffer of {state.n_small} events (the default "
            "scales the paper's 200 k at 240x180 with the sensor); pass a smaller n_small "
            "(--n-small, and --n-large) or use OffEI")
    return cal.replace(diagnostics=diagnostics)
