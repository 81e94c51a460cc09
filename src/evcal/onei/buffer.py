"""OnEI's large buffer (:class:`LargeBuffer`): the buffered frames and the intervals that
ended at them, the small buffers they open and close, and the two sliding sums that give each
small buffer's equation its counts.

The large buffer is the sliding set of the most recent whole frame intervals holding at most
``n_large`` events; when a new interval makes it overflow, the oldest intervals are dropped
(the paper's rule). A small buffer opens at *every* frame of the large buffer and closes at
the first later frame by which it holds ``n_small`` events (OffEI's overlapping windows with
an event-count window); its equation is added when it closes and subtracted, recomputed
bit-identically from the same stored data, when the frame that opened it leaves. Per frame
the cost is that of the frame's events and pixels, not of the buffer's: two sliding sums hold
the counts of the small buffer closing next and of the one leaving (each interval enters and
leaves each sum once).
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np

from ..events import SensorSize
from .config import OnEIConfig
from .equations import NormalSums
from .executor import OnEIExecutor
from .intake import EventIntake
from .kernels import add_dense, drop_dense, drop_interval, scatter_interval

OPEN, DROP = 0, 1  # the two sliding sums: the small buffer closing next, the one leaving


@dataclass
class Frame:
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


class LargeBuffer:
    """The frames of the large buffer, the open interval (:class:`EventIntake`) and the
    normal equations of its small buffers (:class:`NormalSums`). Frames are numbered from the
    calibrator's start (or session's): ``frames[0]`` is number ``base``."""

    def __init__(self, sensor: SensorSize, config: OnEIConfig, n_small: int, n_large: int,
                 executor: OnEIExecutor) -> None:
        self.sensor = sensor
        self.config = config
        self.n_small, self.n_large = n_small, n_large
        self.executor = executor
        self.sums = NormalSums(sensor.n_pixels, config, n_large, executor)
        self.frame_cap: int | None = None  # frames kept at most (set by the first frame)
        # the large buffer still holds every event of the stream: a new solution then holds
        # all the evidence of the earlier ones and replaces the estimate
        self.holds_all = True
        self.reset()

    def reset(self) -> None:
        """Empty the large buffer, the open interval, the pending events and the normal
        equations."""
        n = self.sensor.n_pixels
        self.intake = EventIntake(n, self.sensor.width)
        self.sums.reset()
        # sliding sums (ON, OFF) over the intervals (lo, hi] of the small buffer closing next
        # (OPEN) and of the one leaving the buffer (DROP); lo >= self.base always
        self.wins = np.zeros((2, 2, n), np.int32)
        self.win_range = [[0, 0], [0, 0]]
        self.frames: deque[Frame] = deque()
        self.base = 0  # absolute number of self.frames[0]
        self.next_open = 0  # absolute number of the oldest frame whose small buffer is open
        self.cum_events = 0
        self.gap = False  # events were lost in the open interval
        self.since_resolve = 0  # events closed into intervals since the last re-solve
        self.n_equations = 0  # small buffers in the normal equations now

    @property
    def n_events(self) -> int:
        """Events in the buffered intervals."""
        if not self.frames:
            return 0
        return self.frames[-1].cum_events - self.frames[0].cum_events

    @property
    def left(self) -> int | None:
        """Events that have left the buffer (None before the first frame)."""
        return self.frames[0].cum_events if self.frames else None

    @property
    def nbytes(self) -> int:
        """Bytes held by the frames (images, last polarities, sparse interval counts)."""
        return int(sum(f.image.nbytes + f.last_p.nbytes + f.idx.nbytes + f.on.nbytes
                       + f.off.nbytes for f in self.frames))

    def arrays(self) -> list[np.ndarray]:
        """Every per-pixel array held besides the frames (for ``state_bytes``)."""
        it = self.intake
        return [self.wins, it.code, it.spill, it.last_p, *self.sums.arrays()]

    def push(self, t_us: int, image: np.ndarray) -> None:
        """Close the open interval at the frame ``(t_us, image)`` and buffer it."""
        new = self.base + len(self.frames)  # absolute number of this frame
        keep = bool(self.frames)
        add_open = keep and self.win_range[OPEN][1] == new - 1
        idx, f_on, f_off, n_new, dense = self.intake.close(
            keep=keep, counts=self.sums.counts, win=self.wins[OPEN], add_win=add_open)
        if add_open:
            self.win_range[OPEN][1] = new
        self.cum_events += int(n_new)
        self.since_resolve += int(n_new)
        if self.gap and self.frames:
            # the interval just closed lost events: close no small buffer across it
            for f in self.frames:
                if f.closes_at < 0:
                    f.opens = False
            self.next_open = self.base + len(self.frames)
        self.gap = False
        self.frames.append(Frame(t_us, image, self.intake.last_p.copy(), self.cum_events,
                                 idx, f_on, f_off, dense=bool(dense)))
        self.intake.has_frames = True

    def form_all(self, log_offset: float) -> None:
        """Form every small buffer the buffer holds (once the offset became known)."""
        self.sums.clear_equations()
        self.n_equations = 0
        for f in self.frames:
            f.closes_at = -1
        self.next_open = self.base
        for k in range(self.base + 1, self.base + len(self.frames)):
            self.close_small_buffers(log_offset, k)

    def close_small_buffers(self, log_offset: float, k: int | None = None) -> bool:
        """Form the equations of the small buffers that hold ``n_small`` events at frame
        ``k`` (default the newest; usually one)."""
        if k is None:
            k = self.base + len(self.frames) - 1
        newest = self.frames[k - self.base]
        formed = False
        while self.next_open < k:
            j = self.next_open
            fj = self.frames[j - self.base]
            if not fj.opens:
                self.next_open += 1
                continue
            wf = self.config.window_frames
            if (k - j < wf) if wf else (newest.cum_events - fj.cum_events < self.n_small):
                break
            fj.closes_at = k
            self.queue(j, k, +1.0, OPEN, log_offset)
            self.n_equations += 1
            self.next_open += 1
            formed = True
        return formed

    def drop_overflow(self, log_offset: float) -> None:
        """Drop the oldest intervals beyond ``n_large`` events or the frame cap."""
        cap = self.frame_cap or 2
        sums = self.sums
        # the newest interval always stays, even when it alone holds more than n_large events
        while len(self.frames) > 2:
            first, second = self.frames[0], self.frames[1]
            in_buffer = self.frames[-1].cum_events - first.cum_events
            if in_buffer <= self.n_large and len(self.frames) <= cap:
                break
            # drop the oldest interval: its opening frame and the small buffer it opened
            base = self.base
            w_hist = sums.hist_weight(second.cum_events)
            if first.closes_at >= 0:
                slot = self.queue(base, first.closes_at, -1.0, DROP, log_offset)
                self.n_equations -= 1
                sums.removals += 1
                if sums.hist is not None:  # the same slot, into the history
                    sums.hqueued.append((slot, w_hist))
            if sums.hist_counts is not None:
                hc = sums.hist_counts
                if second.dense:
                    hc[: second.on.size] += w_hist * (second.on + second.off)
                else:
                    hc[second.idx] += w_hist * (second.on + second.off)
            # the interval ending at the new first frame leaves the buffer: uncount it, and
            # slide the sums that hold it past it while its counts are still here
            sub = np.array([lo <= base < hi for lo, hi in self.win_range])
            self._uncount(second, sub)
            for rng in self.win_range:
                if rng[0] <= base:
                    rng[0], rng[1] = base + 1, max(rng[1], base + 1)
            self.frames.popleft()
            self.base += 1
            self.holds_all = False
            second.forget_interval()
            self.next_open = max(self.next_open, self.base)
        if sums.hist is not None and sums.hist_exponent(self.left) > sums.HISTORY_RENORMALISE:
            sums.renormalise_history(self.frames[0].cum_events)

    def rebuild(self, log_offset: float) -> None:
        """Recompute the normal equations from the buffer (sheds accumulated rounding)."""
        self.sums.clear_equations()
        for i, f in enumerate(self.frames):
            if f.closes_at >= 0:
                self.queue(self.base + i, f.closes_at, +1.0, DROP, log_offset)
        self.sums.apply_queued()

    def queue(self, j: int, k: int, sign: float, w: int, log_offset: float) -> int:
        """Queue ``sign`` times the equation of the small buffer from frame ``j`` to frame
        ``k``, its counts from sliding sum ``w``; returns its slot."""
        self._slide(w, j, k)
        fj, fk = self.frames[j - self.base], self.frames[k - self.base]
        return self.sums.queue(self.wins[w], fj.image, fk.image, fj.last_p, fk.last_p, sign,
                               log_offset)

    def _slide(self, w: int, lo: int, hi: int) -> None:
        """Make sliding sum ``w`` the counts of the intervals ``(lo, hi]``: forward, interval by
        interval (each interval enters and leaves a sum once), or afresh."""
        rng, sums = self.win_range[w], self.wins[w]
        cur_lo, cur_hi = rng
        if cur_lo >= self.base and lo >= cur_lo and hi >= cur_hi:
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

    def _uncount(self, fr: Frame, sub: np.ndarray) -> None:
        """The interval ``fr`` closed leaves the buffer: off the counts, and off the sliding
        sums ``sub`` marks."""
        counts, wins = self.sums.counts, self.wins
        if fr.dense:
            self.executor.split(fr.on.size, lambda lo, hi: drop_dense(
                counts[lo:hi], wins[:, :, lo:hi], sub, fr.on[lo:hi], fr.off[lo:hi]))
        else:  # ranges of the sorted, distinct pixels: no two threads touch one pixel
            self.executor.split(fr.idx.size, lambda lo, hi: drop_interval(
                counts, wins, sub, fr.idx[lo:hi], fr.on[lo:hi], fr.off[lo:hi]))

    def _scatter(self, sums: np.ndarray, f: int, sign: int) -> None:
        fr = self.frames[f - self.base]
        if fr.dense:
            self.executor.split(fr.on.size, lambda lo, hi: add_dense(
                sums[:, lo:hi], fr.on[lo:hi], fr.off[lo:hi], sign))
        else:
            self.executor.split(fr.idx.size, lambda lo, hi: scatter_interval(
                sums, fr.idx[lo:hi], fr.on[lo:hi], fr.off[lo:hi], sign))
