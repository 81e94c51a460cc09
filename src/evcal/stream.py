"""The streaming contract: cutting events at frame times, and the checks of a live stream.

Two rules hold everywhere in evcal:

- **Events at a frame's time belong after the frame.** The interval of frame ``k`` is
  ``[t_{k-1}, t_k)``: :func:`frame_cuts` gives the index of the first event at or after each
  frame, :func:`frame_intervals` the events of each interval (views, no copy).
- **A live stream is checked once, by one** :class:`StreamGuard` **per camera**: the sensor
  size is fixed by the first message, sequence numbers reveal lost messages and publisher
  restarts, event time never goes back across chunks and frame time always increases. The
  wire decoder checks each chunk on its own (order inside it, coordinates, polarity); the
  guard checks what needs the stream's history; the online calibrator trusts what the guard
  accepted (``feed_events(..., checked=True)``). The service, ``evcal record`` and
  :class:`~evcal.online.OnlineCalibrator`'s own public checks all use this class.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np

from .errors import ConfigError, ErrorReason
from .events import EVENTS_DTYPE, EventError, SensorSize, validate_events

STREAM_KINDS = ("events", "frames")


class StreamError(EventError):
    """A message that breaks its stream's contract (sensor, time order); ``reason`` says how."""


class DuplicateMessage(StreamError):
    """An exact copy of a message the stream already accepted (same sequence number, same
    times): the consumer drops it and counts it as a duplicate, not as an error of the
    stream and not as a publisher restart."""

    default_reason = ErrorReason.REJECTED


class LateMessage(StreamError):
    """A message whose sequence number had been counted lost, arriving after a later one
    (a reordered pair) that cannot be placed: its time is before the stream's. It is
    refused with ``reason`` and is no longer lost: ``recovered`` messages (1) come off the
    consumer's loss count."""

    default_reason = ErrorReason.TIME_BACKWARDS

    def __init__(self, message: str, reason: ErrorReason | None = None, *,
                 recovered: int = 1) -> None:
        super().__init__(message, reason)
        self.recovered = recovered


# ----------------------------------------------------------------------------------------
# cutting events at frame times


def frame_cuts(event_t_us: np.ndarray, frame_t_us: np.ndarray) -> np.ndarray:
    """Index of the first event at or after each frame time (int64, one per frame).

    The events of ``[t_j, t_k)`` are ``events[cuts[j]:cuts[k]]``; those before the first frame
    ``events[:cuts[0]]``, those at or after the last one ``events[cuts[-1]:]``.

    Examples
    --------
    >>> frame_cuts(np.array([0, 5, 10, 10, 12]), np.array([5, 10, 20])).tolist()
    [1, 2, 5]
    """
    return np.searchsorted(np.asarray(event_t_us), np.asarray(frame_t_us, np.int64),
                           side="left").astype(np.int64)


def frame_cut(event_t_us: np.ndarray, frame_t_us: int) -> int:
    """:func:`frame_cuts` of one frame: the index of the first event at or after
    ``frame_t_us``, so that ``events[:cut]`` come before the frame.

    Examples
    --------
    >>> frame_cut(np.array([0, 5, 10, 10, 12]), 10)
    2
    """
    return int(np.searchsorted(event_t_us, frame_t_us, side="left"))


def event_windows(event_t_us: np.ndarray, frame_t_us: np.ndarray) -> np.ndarray:
    """The frame interval of each event: ``k`` with ``t_k <= t < t_{k+1}`` (int64; -1
    before the first frame, the last frame's index at or after it), the per-event view of
    :func:`frame_cuts`.

    Examples
    --------
    >>> event_windows(np.array([0, 5, 10, 10, 12]), np.array([5, 10, 20])).tolist()
    [-1, 0, 1, 1, 1]
    """
    return np.searchsorted(np.asarray(frame_t_us, np.int64), np.asarray(event_t_us),
                           side="right").astype(np.int64) - 1


def frame_intervals(events: np.ndarray, frame_t_us: np.ndarray
                    ) -> Iterator[tuple[int, np.ndarray]]:
    """``(k, events of [t_{k-1}, t_k))`` for every frame ``k`` (views, no copy).

    Frame 0's interval holds every event before it; events at or after the last frame are not
    yielded (they wait for a frame that closes their interval). Intervals may be empty.

    Examples
    --------
    >>> from evcal.events import make_events
    >>> ev = make_events([1, 5, 7, 12], [0, 0, 0, 0], [0, 0, 0, 0], [1, 1, -1, 1])
    >>> [(k, chunk["t_us"].tolist()) for k, chunk in frame_intervals(ev, np.array([5, 10]))]
    [(0, [1]), (1, [5, 7])]
    """
    cuts = frame_cuts(events["t_us"], frame_t_us)
    prev = 0
    for k, end in enumerate(cuts.tolist()):
        yield k, events[prev:end]
        prev = end


# ----------------------------------------------------------------------------------------
# the checks of a live stream


@dataclass(frozen=True, kw_only=True)
class StreamPolicy:
    """When a discontinuity of a stream's time starts a new *session* instead of being refused.

    Time going back by at most ``jump_us`` is an error of the publisher (``time_backwards``,
    refused). A larger jump back, or a jump forward of more than ``max_forward_us``, is either
    a glitch (one absurd timestamp, e.g. ``2**62``) or a new time base (a camera power-cycled,
    a recording replayed again): such a message is refused (``time_jump``) until
    ``confirm_messages`` consecutive messages agree on the new time base, and the last of them
    starts a new session. A sequence number going back together with time going back is a
    publisher restart: a new session at once. A new session may change the sensor size.
    """

    jump_us: int = 10_000_000
    max_forward_us: int = 3_600_000_000
    confirm_messages: int = 3

    def __post_init__(self) -> None:
        if self.jump_us < 0 or self.max_forward_us < 1 or self.confirm_messages < 1:
            raise ConfigError(f"{self}: jump_us >= 0, max_forward_us >= 1 and "
                              "confirm_messages >= 1 expected")


@dataclass(frozen=True)
class SeqCheck:
    """What a message says about its stream: ``lost`` messages before it (a sequence gap,
    less the messages of the gap that arrived and were refused), a sequence ``restart`` (a
    number below the expected one that is neither a duplicate nor a late message, or one
    more than :attr:`StreamGuard.MAX_SEQ_GAP` above it), whether
    it starts a ``new_session`` (the stream's time base changed; ``new_sensor``: with another
    size), and ``recovered``: this message had been counted lost (it arrived late, after a
    later one, and its time still fits the stream)."""

    lost: int = 0
    restart: bool = False
    new_session: bool = False
    new_sensor: bool = False
    recovered: int = 0

    @property
    def gap(self) -> bool:
        """The stream is not contiguous here (loss, restart or a new session)."""
        return self.lost > 0 or self.restart or self.new_session


class StreamGuard:
    """The history-dependent checks of one camera's event and frame streams.

    Single-threaded: one guard per camera, used by the thread that consumes that camera.
    :meth:`accept` either raises :class:`StreamError` (the message is refused and the guard
    unchanged, but for a pending time-base candidate and the note that its sequence number
    arrived) or accepts the message and advances the stream's state. The sensor is fixed by
    the first message; it may change only with a new session (:class:`StreamPolicy`).

    Sequence numbers say what happened to each message, and each is counted once:

    - a gap is ``lost`` messages, less those of the gap that arrived and were refused (a
      refused message is not lost: one ``t_us = 2**62`` glitch is one ``time_jump``);
    - a number of the last ``RECENT_MESSAGES`` accepted, with the same times, is a
      :class:`DuplicateMessage` (dropped, counted by the consumer; not a restart);
    - a number counted lost in the last ``MISSING_WINDOW`` that arrives after all is late
      (a swapped pair): accepted when its time still fits the stream (``recovered``), else a
      :class:`LateMessage` (refused, no longer lost) — never a new session;
    - any other number below the expected one is a publisher restart.
    """

    RECENT_MESSAGES = 64  # accepted (seq, t_first, t_last) kept per stream for duplicates
    MISSING_WINDOW = 1024  # how far back a late message may fill a sequence gap
    # a forward jump of the sequence number beyond this is a numbering that started anew (a
    # publisher's counter reset to a random or wrapped value, a forged number), not loss:
    # a million messages is many minutes of any camera's stream
    MAX_SEQ_GAP = 1 << 20

    def __init__(self, sensor: SensorSize | None = None, *, max_pixels: int | None = None,
                 policy: StreamPolicy | None = None) -> None:
        self.sensor = sensor
        self.max_pixels = max_pixels
        self.policy = policy or StreamPolicy()
        self.next_seq: dict[str, int | None] = {k: None for k in STREAM_KINDS}
        self.last_event_t_us: int | None = None
        self.last_frame_t_us: int | None = None
        self.sessions = 0  # new sessions started after the first
        # per stream: (last t_us, messages) of a time base that differs from the accepted one
        self._candidate: dict[str, tuple[int, int] | None] = {k: None for k in STREAM_KINDS}
        n = self.RECENT_MESSAGES
        # per stream: the last accepted messages (seq, t_first_us, t_last_us), for duplicates
        self._recent: dict[str, deque[tuple[int, int | None, int | None]]] = {
            k: deque(maxlen=n) for k in STREAM_KINDS}
        # numbers counted lost (a set for lookups, a deque in increasing order for pruning)
        self._missing: dict[str, set[int]] = {k: set() for k in STREAM_KINDS}
        self._missing_order: dict[str, deque[int]] = {k: deque() for k in STREAM_KINDS}
        # numbers at or after the expected one that arrived and were refused, increasing
        self._refused: dict[str, deque[int]] = {k: deque() for k in STREAM_KINDS}

    def _reset_windows(self, kinds: tuple[str, ...] = STREAM_KINDS) -> None:
        """Forget the sequence windows of ``kinds`` (at a restart or a new session: numbers
        of the old session say nothing about the new one)."""
        for k in kinds:
            self._recent[k].clear()
            self._missing[k].clear()
            self._missing_order[k].clear()
            self._refused[k].clear()

    def _last(self, kind: str) -> int | None:
        return self.last_event_t_us if kind == "events" else self.last_frame_t_us

    def _set_last(self, kind: str, t_us: int) -> None:
        if kind == "events":
            self.last_event_t_us = t_us
        else:
            self.last_frame_t_us = t_us

    # -- single checks -----------------------------------------------------------------------

    def _check_size(self, height: int, width: int, what: str, *, new_session: bool) -> bool:
        """Whether the size differs from the stream's (allowed with a new session only)."""
        n = int(height) * int(width)
        if self.max_pixels is not None and n > self.max_pixels:
            raise StreamError(f"{what}: a {width}x{height} sensor has {n} pixels, more "
                              f"than the limit of {self.max_pixels} (--max-pixels)",
                              ErrorReason.SENSOR_TOO_LARGE)
        if self.sensor is None or (int(height), int(width)) == self.sensor.shape:
            return False
        if not new_session:
            raise StreamError(f"{what}: a {width}x{height} sensor, but the stream is "
                              f"{self.sensor} (a new sensor is accepted when its publisher "
                              "restarts: sequence numbers from 0 again)",
                              ErrorReason.SENSOR_CHANGED)
        return True

    def check_sensor(self, height: int, width: int, what: str) -> SensorSize:
        """The stream's sensor: fixed by the first message, every later one must match."""
        self._check_size(height, width, what, new_session=False)
        if self.sensor is None:
            self.sensor = SensorSize(int(height), int(width))
        return self.sensor

    def _time(self, kind: str, t_first: int, t_last: int, restart: bool, what: str) -> bool:
        """Check the message's time against the stream's; True when it starts a new session.
        Raises :class:`StreamError` for a refused message."""
        last = self._last(kind)
        strict = kind == "frames"  # frame times increase, event times may repeat
        pol = self.policy
        if t_last - t_first > pol.max_forward_us:
            # one absurd timestamp inside a message (2**62 at its end): judged by its first
            # event alone it would pass, become the stream's last time, and refuse the
            # messages after it as a jump back until they confirmed a new session
            raise StreamError(f"{what}: its times span t_us={t_first} to t_us={t_last}, "
                              f"more than {pol.max_forward_us} us within one message: a "
                              "timestamp glitch", ErrorReason.TIME_JUMP)
        if last is None:
            return False
        back = t_first < last or (strict and t_first == last)
        if not back and t_first - last <= pol.max_forward_us:
            self._candidate[kind] = None
            return False
        if back and restart:
            return True  # the publisher restarted: sequence numbers and time went back
        if back and last - t_first <= pol.jump_us:
            if kind == "events":
                raise StreamError(f"{what}: time goes backwards: first t_us={t_first} is "
                                  f"before the previous chunk's last t_us={last}",
                                  ErrorReason.TIME_BACKWARDS)
            raise StreamError(f"{what}: frame time goes backwards: t_us={t_first} after "
                              f"t_us={last}", ErrorReason.TIME_BACKWARDS)
        # a jump: a glitch, or a new time base once enough messages agree on it
        cand = self._candidate[kind]
        if cand is not None and t_first >= cand[0] and t_first - cand[0] <= pol.max_forward_us:
            cand = (t_last, cand[1] + 1)
        else:
            cand = (t_last, 1)
        self._candidate[kind] = cand
        if cand[1] >= pol.confirm_messages:
            return True
        raise StreamError(f"{what}: time jumps from t_us={last} to t_us={t_first}; refused "
                          f"unless {pol.confirm_messages} consecutive messages confirm the new "
                          f"time base ({cand[1]} so far)", ErrorReason.TIME_JUMP)

    def check_seq(self, kind: str, seq: int) -> SeqCheck:
        """Advance the ``kind`` stream's sequence number; what it says about loss."""
        expected = self.next_seq[kind]
        seq = int(seq)
        self.next_seq[kind] = seq + 1
        refused = self._refused[kind]
        n_refused = 0  # numbers of the gap that arrived (and were refused): not lost
        while refused and refused[0] < seq:
            n_refused += refused.popleft() >= (expected if expected is not None else seq)
        if refused and refused[0] == seq:  # refused once, accepted now (sent again)
            refused.popleft()
        if expected is None or seq == expected:
            return SeqCheck()
        if seq > expected + self.MAX_SEQ_GAP:
            self._reset_windows((kind,))
            return SeqCheck(restart=True)
        if seq > expected:
            self._note_missing(kind, expected, seq)
            return SeqCheck(lost=seq - expected - n_refused)
        self._reset_windows((kind,))  # a restart: the old numbers mean nothing any more
        return SeqCheck(restart=True)

    def _note_missing(self, kind: str, expected: int, seq: int) -> None:
        """Remember the numbers of a gap (the last ``MISSING_WINDOW``) that were not refused,
        so that a late one is recognised; forget those too old to come."""
        missing, order = self._missing[kind], self._missing_order[kind]
        floor = seq - self.MISSING_WINDOW
        while order and order[0] < floor:
            missing.discard(order.popleft())
        for s in range(max(expected, floor), seq):
            missing.add(s)
            order.append(s)

    def _note_refused(self, kind: str, seq: int | None) -> None:
        """A refused message at or after the expected number arrived: not lost."""
        expected = self.next_seq[kind]
        if seq is None or expected is None or seq < expected:
            return
        refused = self._refused[kind]
        if not refused or refused[-1] < seq:  # numbers increase; a repeat is noted once
            refused.append(int(seq))
            if len(refused) > self.MISSING_WINDOW:
                refused.popleft()

    def _earlier(self, kind: str, seq: int, t_first: int | None, t_last: int | None
                 ) -> str | None:
        """What a number below the expected one is: ``"duplicate"``, ``"late"`` or None
        (a restart). A duplicate of number 0 that is not the latest message is taken for a
        restart: a publisher that restarts sends the same first messages again."""
        if seq in self._missing[kind]:
            return "late"
        recent = self._recent[kind]
        if (seq, t_first, t_last) in recent and (seq > 0 or recent[-1][0] == seq):
            return "duplicate"
        return None

    def _accept_late(self, kind: str, seq: int, t_first: int | None, t_last: int | None,
                     size: tuple[int, int] | None, what: str) -> SeqCheck:
        """A message counted lost that arrived after a later one: accepted when its time
        fits after the stream's (the sequence goes on from where it was), else refused as a
        :class:`LateMessage`; either way it is no longer lost."""
        self._missing[kind].discard(seq)
        last = self._last(kind)
        latest = (self.next_seq[kind] or 1) - 1
        try:
            if size is not None:
                self._check_size(size[0], size[1], what, new_session=False)
            if t_first is not None and last is not None and (
                    t_first < last or (kind == "frames" and t_first == last)):
                raise StreamError(
                    f"{what}: arrived after seq {latest} (out of order) and its "
                    f"t_us={t_first} is before the stream's t_us={last}: refused (not "
                    "counted lost)", ErrorReason.TIME_BACKWARDS)
        except StreamError as exc:
            raise LateMessage(str(exc), exc.reason, recovered=1) from None
        if t_last is not None:
            self._set_last(kind, int(t_last))
        self._recent[kind].append((seq, t_first, t_last))
        return SeqCheck(recovered=1)

    def new_session(self) -> None:
        """Forget both streams' time and sequence state (a new time base starts)."""
        self.next_seq = {k: None for k in STREAM_KINDS}
        self.last_event_t_us = self.last_frame_t_us = None
        self._candidate = {k: None for k in STREAM_KINDS}
        self._reset_windows()
        self.sessions += 1

    # -- whole messages ----------------------------------------------------------------------

    def accept(self, kind: str, *, t_first_us: int | None, t_last_us: int | None,
               what: str, seq: int | None = None, size: tuple[int, int] | None = None
               ) -> SeqCheck:
        """Check and accept one message of the ``kind`` stream (``"events"``/``"frames"``).

        ``t_first_us``/``t_last_us`` are its first and last times (None for an empty events
        message: only sensor and sequence are checked), ``seq`` its sequence number, ``size``
        the ``(height, width)`` it declares. Returns what the message says about the stream;
        a ``new_session`` has already reset the guard's time and sequence state. Raises
        :class:`DuplicateMessage` for a copy of a recent message, :class:`LateMessage` for a
        late one that cannot be placed, :class:`StreamError` for any other refusal.
        """
        t_first = None if t_first_us is None else int(t_first_us)
        t_last = None if t_last_us is None else int(t_last_us)
        expected = self.next_seq[kind] if seq is not None else None
        restart = expected is not None and seq is not None and seq < expected
        if restart:
            assert seq is not None  # restart implies it
            earlier = self._earlier(kind, int(seq), t_first, t_last)
            if earlier == "duplicate":
                raise DuplicateMessage(f"{what}: a copy of the message accepted with this "
                                       "sequence number (same times): dropped")
            if earlier == "late":
                return self._accept_late(kind, int(seq), t_first, t_last, size, what)
        new = False
        try:
            if t_first is not None and t_last is not None:
                new = self._time(kind, t_first, t_last, restart, what)
            new_sensor = False
            if size is not None:
                new_sensor = self._check_size(size[0], size[1], what,
                                              new_session=new or (restart and seq == 0))
                new = new or new_sensor
        except StreamError:
            self._note_refused(kind, seq)  # it arrived: a later gap does not count it lost
            raise
        if new:
            self.new_session()
        if size is not None and (self.sensor is None or new_sensor):
            self.sensor = SensorSize(int(size[0]), int(size[1]))
        check = self.check_seq(kind, seq) if seq is not None else SeqCheck()
        if t_last is not None:
            self._set_last(kind, t_last)
        if seq is not None:
            self._recent[kind].append((int(seq), t_first, t_last))
        if new:
            return SeqCheck(restart=restart, new_session=True, new_sensor=new_sensor)
        return check

    def accept_events(self, events: np.ndarray, *, what: str = "events",
                      seq: int | None = None, size: tuple[int, int] | None = None,
                      validated: bool = False) -> SeqCheck:
        """:meth:`accept` for a chunk of events.

        ``validated`` says the chunk on its own was already checked against ``size`` (the
        wire decoder does: order inside the chunk, coordinates, polarity), so only what needs
        the stream's history is checked here. Without it the chunk is validated in full
        against the stream's sensor.
        """
        if not validated:
            validate_events(events, self.sensor, where=what)  # raises EventError
        elif not (isinstance(events, np.ndarray) and events.dtype == EVENTS_DTYPE):
            raise StreamError(f"{what}: expected an array of EVENTS_DTYPE",
                              ErrorReason.MALFORMED)
        t = events["t_us"]
        return self.accept("events", t_first_us=int(t[0]) if t.size else None,
                           t_last_us=int(t[-1]) if t.size else None, what=what, seq=seq,
                           size=size)

    def accept_frame(self, t_us: int, *, what: str = "frame", seq: int | None = None,
                     size: tuple[int, int] | None = None) -> SeqCheck:
        """:meth:`accept` for a frame at ``t_us`` (its image is checked by its consumer)."""
        return self.accept("frames", t_first_us=int(t_us), t_last_us=int(t_us), what=what,
                           seq=seq, size=size)

    def note_events(self, events: np.ndarray) -> None:
        """Record a chunk accepted by another guard (the stream's time moves on)."""
        if events.size:
            self.last_event_t_us = int(events["t_us"][-1])

    def note_frame(self, t_us: int) -> None:
        self.last_frame_t_us = int(t_us)

    # -- persistence -------------------------------------------------------------------------

    def state(self) -> dict[str, Any]:
        """The guard as JSON-able values (for snapshots)."""
        return {"sensor": str(self.sensor) if self.sensor is not None else None,
                "next_seq": dict(self.next_seq), "last_event_t_us": self.last_event_t_us,
                "last_frame_t_us": self.last_frame_t_us, "sessions": self.sessions}

    @classmethod
    def from_state(cls, state: dict[str, Any], *, max_pixels: int | None = None
                   ) -> StreamGuard:
        """A guard from :meth:`state` (:class:`StreamError` if it is not one)."""
        try:
            sensor = SensorSize.parse(state["sensor"]) if state.get("sensor") else None
            guard = cls(sensor, max_pixels=max_pixels)
            seqs = state.get("next_seq") or {}
            for kind in STREAM_KINDS:
                v = seqs.get(kind)
                guard.next_seq[kind] = None if v is None else int(v)
            for name in ("last_event_t_us", "last_frame_t_us"):
                v = state.get(name)
                setattr(guard, name, None if v is None else int(v))
            guard.sessions = int(state.get("sessions", 0))
        except (KeyError, TypeError, ValueError, AttributeError) as exc:
            raise StreamError(f"not a stream guard state: {exc}") from None
        return guard
