"""The events of the open frame interval (:class:`EventIntake`): their packed counts, the
pending events waiting for the frame that closes their interval, and those counted ahead of it.

Folding ahead: the events of the open interval are counted as they come, up to a horizon (a
fraction of the shortest recent frame interval after the latest frame, chosen by the
calibrator); the rest wait for their frame. A frame earlier than the last event counted ahead
(a frame rate that changed) has its interval counted again from the events kept for it: the
same counts in every case, only that frame is slower.
"""

from __future__ import annotations

from collections import deque
from typing import Any

import numpy as np

from ..stream import frame_cut
from .kernels import COUNT_BITS, COUNT_MAX, LAST_SHIFT, close_interval, fold_events

AHEAD_INTERVALS = 8  # recent frame intervals the horizon of folding ahead is taken from


class EventIntake:
    """The open interval since the latest frame and the events not yet counted in it.

    No events is an empty deque of chunks, never ``None``; a chunk is a view of the
    caller's sorted events.
    """

    def __init__(self, n_pixels: int, width: int) -> None:
        self.width = width
        # the interval since the latest frame: packed counts (kernels), the counts that
        # spilled out of them (ON, OFF), and each pixel's latest polarity (Accumulator's maps)
        self.code = np.zeros(n_pixels, np.uint8)
        self.spill = np.zeros((2, n_pixels), np.int32)
        self.spilled = False
        self.last_p = np.zeros(n_pixels, np.int8)
        self.has_frames = False  # before the first frame only polarities matter
        self.pending: deque[np.ndarray] = deque()
        self.n_pending = 0
        # events of the open interval folded ahead of its frame: while any are, the packed
        # counts hold exactly them, and a frame that comes before the last of them has the
        # interval counted again from them
        self.ahead: deque[np.ndarray] = deque()
        self.n_ahead = 0
        self.ahead_ok = False  # folding ahead allowed (from a frame until counts are forced)
        self.frame_dt_us: deque[int] = deque(maxlen=AHEAD_INTERVALS)
        # close_interval's counts and sliding sum while nothing is kept (never written)
        self._no_counts = np.zeros(0, np.int64)
        self._no_win = np.zeros((2, 0), np.int32)

    @property
    def n_waiting(self) -> int:
        """Events fed but not yet closed into a frame interval."""
        return self.n_pending + self.n_ahead

    def add(self, events: np.ndarray) -> None:
        self.pending.append(events)
        self.n_pending += int(events.size)

    def shed(self, max_events: int) -> int:
        """Keep at most ``max_events`` waiting: the oldest are counted in the open interval
        without their frame. Returns how many pending events were so folded late."""
        folded = 0
        while self.n_waiting > max_events and (self.ahead or len(self.pending) > 1):
            if self.ahead:  # they stay counted in this interval whenever its frame comes
                self.keep_ahead()
                self.ahead_ok = False
                continue
            old = self.pending.popleft()
            self.n_pending -= int(old.size)
            self.fold(old)
            folded += int(old.size)
        return folded

    def frame_came(self, t_us: int, previous_t_us: int | None) -> None:
        """A frame at ``t_us`` closed the interval (``previous_t_us``: the frame before)."""
        if previous_t_us is not None and t_us > previous_t_us:
            self.frame_dt_us.append(t_us - previous_t_us)
        self.ahead_ok = True

    def fold_ahead(self, last_frame_t_us: int | None, fraction: float) -> None:
        """Fold the pending events before the horizon, ``fraction`` of the shortest recent
        frame interval after the latest frame, into the open interval, keeping them
        (:meth:`fold_pending_before` undoes it if their frame comes earlier)."""
        if not self.ahead_ok or not self.frame_dt_us or not self.pending:
            return
        if last_frame_t_us is None:
            return
        horizon = last_frame_t_us + int(fraction * min(self.frame_dt_us))
        for part in self.take_pending_before(horizon):
            self.fold(part)
            self.ahead.append(part)
            self.n_ahead += part.size

    def take_pending_before(self, t_us: int) -> list[np.ndarray]:
        """The pending events before ``t_us``, taken off the pending buffer (views)."""
        taken: list[np.ndarray] = []
        while self.pending:
            chunk = self.pending[0]
            t = chunk["t_us"]
            cut = t.size if int(t[-1]) < t_us else frame_cut(t, t_us)
            if cut:
                taken.append(chunk[:cut])
                self.n_pending -= cut
            if cut < chunk.size:
                if cut:
                    self.pending[0] = chunk[cut:]
                break
            self.pending.popleft()
        return taken

    def keep_ahead(self) -> None:
        """The events folded ahead stay in the open interval (no longer kept to undo)."""
        self.ahead.clear()
        self.n_ahead = 0

    def fold_pending_before(self, t_us: int) -> bool:
        """Fold the pending events before ``t_us`` (they belong to the interval it closes).
        True when the interval was counted again (the frame came before events folded
        ahead)."""
        refolded = False
        if self.ahead:
            if int(self.ahead[-1]["t_us"][-1]) >= t_us:
                # the packed counts hold only them (folding ahead stops once others are
                # forced in): count again
                self.code[:] = 0
                if self.spilled:
                    self.spill[:] = 0
                    self.spilled = False
                self.pending.extendleft(reversed(self.ahead))
                self.n_pending += self.n_ahead
                refolded = True
            self.keep_ahead()
        for part in self.take_pending_before(t_us):
            self.fold(part)
        return refolded

    def fold(self, events: np.ndarray) -> None:
        if not events.size:
            return
        if fold_events(events["x"], events["y"], events["p"], self.width, self.code,
                       self.spill[0], self.spill[1]):
            self.spilled = True
        if not self.has_frames:
            self.close(keep=False)

    def close(self, *, keep: bool, counts: np.ndarray | None = None,
              win: np.ndarray | None = None, add_win: bool = False) -> tuple[Any, ...]:
        """``(idx, on, off, n_events, dense)`` of the interval since the latest frame (empty
        unless ``keep``; then also added to ``counts``, and to the sliding sum ``win`` when
        ``add_win``); the latest polarities are folded into ``last_p``."""
        out = close_interval(self.code, self.spill[0], self.spill[1], self.spilled,
                             self.last_p, keep,
                             self._no_counts if counts is None else counts,
                             self._no_win if win is None else win, add_win)
        self.spilled = False
        return tuple(out)

    def waiting(self) -> list[np.ndarray]:
        """The events not yet closed into an interval, in order (those folded ahead first:
        a saved state has them wait again)."""
        return [*self.ahead, *self.pending]

    def open_interval_maps(self) -> dict[str, np.ndarray]:
        """The interval since the latest frame as ``Accumulator``'s maps (state format),
        without the events folded ahead (they are saved as pending)."""
        if self.ahead:  # the packed counts and spills hold only those
            zero = np.zeros(self.code.size, np.int32)
            return {"acc_on": zero, "acc_off": zero.copy(), "acc_last_p": self.last_p.copy()}
        code = self.code.astype(np.int32)
        last = code >> LAST_SHIFT
        return {"acc_on": ((code >> COUNT_BITS) & COUNT_MAX) + self.spill[0],
                "acc_off": (code & COUNT_MAX) + self.spill[1],
                "acc_last_p": np.where(last == 1, 1, np.where(last == 2, -1, self.last_p)
                                       ).astype(np.int8)}
