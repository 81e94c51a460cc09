"""OnEI's per-pixel normal equations (:class:`NormalSums`): blocked sums, the events per
pixel in the buffer, the queue of equations not yet added, and the forgotten history.

An equation is queued as its pixel counts, its polarity regressors and its two frame values
(``PENDING_SLOTS`` at most), and the queue is added to the sums at the next solve (or at every
frame when eager), block by block in cache (:func:`~evcal.onei.kernels.apply_blocks`: the same
operations in the same order as adding the equations one by one).
"""

from __future__ import annotations

import math

import numpy as np

from ..solver import NormalEquations, log_intensity, usable
from .config import OnEIConfig
from .executor import OnEIExecutor
from .kernels import BLOCK, apply_blocks, fill_slot

PENDING_SLOTS = 6  # equations queued before they are added to the normal equations

Queue = tuple[np.ndarray, np.ndarray]  # (slots, weights) as apply_blocks takes them
# the queued slots as the block kernels take them: sums, qa, raw, dl, kinds, lut, slots,
# signs, hslots, hsigns
KernelSlots = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray,
                    np.ndarray, np.ndarray, np.ndarray, np.ndarray]
_NO_HISTORY = np.zeros((0, 16 * BLOCK), np.float64)  # the kernels' hist when it is off
_NO_COUNTS = np.zeros(0, np.float64)


def as_arrays(queue: list[tuple[int, float]]) -> Queue | None:
    """A queue of ``(slot, weight)`` as :func:`apply_blocks`' arrays (None if empty)."""
    if not queue:
        return None
    return (np.array([q[0] for q in queue], np.int64),
            np.array([q[1] for q in queue], np.float64))


class NormalSums:
    """The normal equations of the large buffer's small buffers, blocked
    (:mod:`~evcal.onei.kernels`; pixels past ``n_pixels`` are padding), their queue and, with
    ``OnEIConfig.history``, the history of the equations that left the buffer."""

    HISTORY_RENORMALISE = 300.0  # exponent of the stored weights that folds the scale in

    def __init__(self, n_pixels: int, config: OnEIConfig, n_large: int,
                 executor: OnEIExecutor) -> None:
        self.n_pixels = n_pixels
        self.n_blocks = -(-n_pixels // BLOCK)
        self.config = config
        self.n_large = n_large
        self.executor = executor
        # equations queued for the normal equations, per slot: the pixel counts (ON, OFF),
        # the polarity regressors (Q, A) and the two 8-bit frame values (kind True) or dL;
        # zeros, so that what is never used takes no memory
        k, n = PENDING_SLOTS, n_pixels
        self.slot_sums = np.zeros((k, 2, n), np.int32)
        self.slot_qa = np.zeros((k, 2, n), np.int8)
        self.slot_raw = np.zeros((k, 2, n), np.uint8)
        self.slot_dl = np.zeros((k, n), np.float64)
        self.slot_kind = np.zeros(k, bool)
        self.lut = np.zeros(256)  # log_intensity of the 8-bit values at self.lut_offset
        self.lut_offset = math.nan
        self.no_reason = np.zeros(BLOCK, np.uint8)  # solve_pixels' extra_reason, per block
        # per thread of a pass: the block kernels' scratch (new_scratch), made when needed
        self.scratch: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
        self.lam_terms = np.empty((2, n), np.float64)  # the masked residual-lambda terms
        self.reset()

    def reset(self) -> None:
        """No equation, no event counted, no history."""
        self.m = np.zeros((self.n_blocks, 16 * BLOCK), np.float64)
        self.counts_pad = np.zeros(self.n_blocks * BLOCK, np.int64)
        self.counts = self.counts_pad[: self.n_pixels]  # events per pixel in the buffer
        self.queued: list[tuple[int, float]] = []  # (slot, sign) not yet in self.m
        self.removals = 0  # equations subtracted since the sums were last rebuilt
        self.reset_history()

    def reset_history(self) -> None:
        """Empty the forgotten history (``OnEIConfig.history``; None when off). Its sums are
        blocked as ``self.m`` and scaled by ``exp((L - ref) / tau)``, ``L`` the events that
        had left the buffer when an equation left it: the weights only grow, and a solve
        scales them by ``exp(-(L_now - ref) / tau)`` (one multiply per block, no pass over
        the history per frame)."""
        on = self.config.history > 0
        self.hist = np.zeros_like(self.m) if on else None
        self.hist_counts = np.zeros(self.counts_pad.size) if on else None
        self.hist_ref = 0  # events left the buffer that the weights are relative to
        self.hqueued: list[tuple[int, float]] = []  # (slot, weight) not yet in self.hist

    # -- the queue --------------------------------------------------------------------------

    def queue(self, sums: np.ndarray, img_j: np.ndarray, img_k: np.ndarray,
              lp_j: np.ndarray, lp_k: np.ndarray, sign: float, log_offset: float) -> int:
        """Queue ``sign`` times the equation of counts ``sums`` (ON, OFF) between frames
        ``img_j`` and ``img_k`` whose last polarities are ``lp_j``, ``lp_k`` (OffEI's equation
        with its residual regressors); returns its slot. A full queue is added first."""
        if len(self.queued) == PENDING_SLOTS:
            self.apply_queued()
        slot = len(self.queued)
        sat = self.config.saturation_dn
        if img_j.dtype == np.uint8 and img_k.dtype == np.uint8:
            # log_intensity's own 8-bit table; the offset changes only with a rebuild, which
            # empties the queue: a queued equation is always added with its own table
            if not self.lut_offset == log_offset:
                values = np.arange(256, dtype=np.uint8)
                # NaN at the values usable() refuses: apply_blocks gives such an equation
                # weight 0, as it does one without events
                self.lut = np.where(usable(values, sat), log_intensity(values, log_offset),
                                    np.nan)
                self.lut_offset = log_offset
            s_sums, s_qa, s_raw = self.slot_sums[slot], self.slot_qa[slot], self.slot_raw[slot]
            self.executor.split(self.n_pixels, lambda lo, hi: fill_slot(
                sums[:, lo:hi], lp_j[lo:hi], lp_k[lo:hi], img_j[lo:hi], img_k[lo:hi],
                s_sums[:, lo:hi], s_qa[:, lo:hi], s_raw[:, lo:hi]))
            self.slot_kind[slot] = True
        else:  # other frame types: dL as _terms computed it (log_intensity's float path)
            w_ok = usable(img_j, sat) & usable(img_k, sat)
            with np.errstate(invalid="ignore"):  # -inf - -inf at black pixels with offset 0
                dl = log_intensity(img_k, log_offset) - log_intensity(img_j, log_offset)
            self.slot_dl[slot] = np.where(w_ok, dl, 0.0)  # clipped pixels weigh nothing
            np.multiply(sums, w_ok, out=self.slot_sums[slot])
            self.slot_qa[slot, 0] = lp_k - lp_j
            self.slot_qa[slot, 1] = np.abs(lp_k) - np.abs(lp_j)
            self.slot_kind[slot] = False
        self.queued.append((slot, sign))
        return slot

    def ensure_scratch(self) -> None:
        """Scratch for every thread of a pass (:meth:`new_scratch`)."""
        while len(self.scratch) < self.executor.n_threads:
            self.scratch.append(self.new_scratch())

    def new_scratch(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """A thread's scratch for the block kernels: two blocks' dL, and one block's sums and
        counts with the history's (empty when it is off)."""
        on = self.hist is not None
        return (np.zeros((2, BLOCK), np.float64), np.empty(16 * BLOCK if on else 0),
                np.empty(BLOCK if on else 0, np.int64))

    def apply_blocks(self, queued: Queue | None, target: np.ndarray | None) -> None:
        """Add queued slots to every block of ``target`` (the normal equations, or the
        history's sums; None: nothing, as for a history that is off), on the executor's
        threads (blocks are independent: the same sums with any number)."""
        if queued is None or target is None:
            return
        n = self.n_pixels
        self.ensure_scratch()

        def work(i: int, lo: int, hi: int) -> None:
            apply_blocks(target, n, lo, hi, self.slot_sums, self.slot_qa, self.slot_raw,
                         self.slot_dl, self.slot_kind, self.lut, *queued, self.scratch[i][0])

        self.executor.on_threads(self.n_blocks, work)

    def apply_queued(self) -> None:
        """Add the queued equations to the normal equations, and those that left the buffer
        to the history."""
        self.apply_blocks(as_arrays(self.queued), self.m)
        self.apply_blocks(as_arrays(self.hqueued), self.hist)
        self.queued.clear()
        self.hqueued.clear()

    def clear_equations(self) -> None:
        # the history keeps what left the buffer (its slots are still filled here)
        self.apply_blocks(as_arrays(self.hqueued), self.hist)
        self.hqueued.clear()
        self.queued.clear()
        self.m.fill(0.0)
        self.removals = 0

    def kernel_inputs(self, queued: Queue | None, hqueued: Queue | None
                      ) -> tuple[KernelSlots, np.ndarray, np.ndarray]:
        """The queued slots as the block kernels take them (``sums .. hsigns`` of
        :func:`~evcal.onei.solve.prepared_block`), and the history's sums and counts (no rows
        when it is off); ``buf`` between them is per thread."""
        no: Queue = (np.empty(0, np.int64), np.empty(0, np.float64))
        slots: KernelSlots = (
            self.slot_sums, self.slot_qa, self.slot_raw, self.slot_dl, self.slot_kind, self.lut,
            *(queued if queued is not None else no), *(hqueued if hqueued is not None else no))
        hist = self.hist if self.hist is not None else _NO_HISTORY
        hist_counts = self.hist_counts if self.hist_counts is not None else _NO_COUNTS
        return slots, hist, hist_counts

    # -- the forgotten history (OnEIConfig.history) -------------------------------------------

    @property
    def hist_tau(self) -> float:
        return float(self.config.history) * self.n_large

    def hist_exponent(self, left: int | None) -> float:
        """The exponent of the stored weights when ``left`` events have left the buffer
        (None: as at the reference)."""
        return ((self.hist_ref if left is None else left) - self.hist_ref) / self.hist_tau

    def hist_weight(self, left: int) -> float:
        """The stored weight of an equation leaving when ``left`` events have left."""
        if self.hist is None:
            return 0.0
        return math.exp((left - self.hist_ref) / self.hist_tau)

    def hist_scale(self, left: int | None) -> float:
        """The factor that turns the stored history into its weights now."""
        return math.exp(-self.hist_exponent(left))

    def renormalise_history(self, left: int) -> None:
        """Fold the scale into the stored history (before its weights overflow)."""
        assert self.hist is not None
        assert self.hist_counts is not None
        self.apply_blocks(as_arrays(self.hqueued), self.hist)
        self.hqueued.clear()
        scale = self.hist_scale(left)
        self.hist *= scale
        self.hist_counts *= scale
        self.hist_ref = left

    # -- as rows ------------------------------------------------------------------------------

    def normal_equations(self) -> NormalEquations:
        """The normal equations as :class:`~evcal.solver.NormalEquations` (a copy)."""
        self.apply_queued()
        ne = NormalEquations(self.n_pixels)
        ne.m[:] = self.rows(self.m)
        return ne

    def rows(self, blocked: np.ndarray) -> np.ndarray:
        """Blocked sums as ``(16, n)`` rows (a view when it can be: copy to keep)."""
        rows = blocked.reshape(self.n_blocks, 16, BLOCK).transpose(1, 0, 2)
        out: np.ndarray = rows.reshape(16, -1)[:, : self.n_pixels]
        return out

    def blocked(self, rows: np.ndarray, out: np.ndarray) -> None:
        """``(16, n)`` rows into blocked sums ``out``."""
        padded = np.zeros((16, self.n_blocks * BLOCK), np.float64)
        padded[:, : self.n_pixels] = rows
        out[:] = padded.reshape(16, self.n_blocks, BLOCK).transpose(1, 0, 2).reshape(
            self.n_blocks, 16 * BLOCK)

    def arrays(self) -> list[np.ndarray]:
        """Every per-pixel array held (for ``state_bytes``)."""
        out: list[np.ndarray] = [self.m, self.counts_pad, self.slot_sums, self.slot_qa,
                                 self.slot_raw, self.slot_dl, self.lam_terms]
        if self.hist is not None and self.hist_counts is not None:
            out += [self.hist, self.hist_counts]
        return out
