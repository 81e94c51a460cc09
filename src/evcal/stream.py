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

from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np

from .errors import ErrorReason
from .events import EVENTS_DTYPE, EventError, SensorSize, validate_events

STREAM_KINDS = ("events", "frames")


class StreamError(EventError):
    """A message that breaks its stream's contract (sensor, time order); ``reason`` says how."""


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


@dataclass(frozen=True)
class SeqCheck:
    """What a message's sequence number says: ``lost`` messages before it (a gap), or a
    ``restart`` (a number at or below one already seen: the publisher started again)."""

    lost: int = 0
    restart: bool = False

    @property
    def gap(self) -> bool:
        """The stream is not contiguous here (loss or restart)."""
        return self.lost > 0 or self.restart


class StreamGuard:
    """The history-dependent checks of one camera's event and frame streams.

    Single-threaded: one guard per camera, used by the thread that consumes that camera.
    Every ``accept_*`` method either raises :class:`StreamError` (the message is refused and
    the guard unchanged, but for the sensor, fixed by the first message whatever follows) or
    accepts the message and advances the stream's state.
    """

    def __init__(self, sensor: SensorSize | None = None, *, max_pixels: int | None = None
                 ) -> None:
        self.sensor = sensor
        self.max_pixels = max_pixels
        self.next_seq: dict[str, int | None] = {k: None for k in STREAM_KINDS}
        self.last_event_t_us: int | None = None
        self.last_frame_t_us: int | None = None

    # -- single checks -----------------------------------------------------------------------

    def check_sensor(self, height: int, width: int, what: str) -> SensorSize:
        """The stream's sensor: fixed by the first message, every later one must match."""
        if self.sensor is None:
            n = int(height) * int(width)
            if self.max_pixels is not None and n > self.max_pixels:
                raise StreamError(f"{what}: a {width}x{height} sensor has {n} pixels, more "
                                  f"than the limit of {self.max_pixels} (--max-pixels)",
                                  ErrorReason.SENSOR_TOO_LARGE)
            self.sensor = SensorSize(int(height), int(width))
        elif (int(height), int(width)) != self.sensor.shape:
            raise StreamError(f"{what}: a {width}x{height} sensor, but the stream is "
                              f"{self.sensor}", ErrorReason.SENSOR_CHANGED)
        return self.sensor

    def check_event_order(self, events: np.ndarray, what: str) -> None:
        """The chunk does not start before the previous accepted chunk ended."""
        last = self.last_event_t_us
        if events.size and last is not None and int(events["t_us"][0]) < last:
            raise StreamError(f"{what}: time goes backwards: first t_us="
                              f"{int(events['t_us'][0])} is before the previous chunk's last "
                              f"t_us={last}", ErrorReason.TIME_BACKWARDS)

    def check_frame_order(self, t_us: int, what: str) -> None:
        last = self.last_frame_t_us
        if last is not None and int(t_us) <= last:
            raise StreamError(f"{what}: frame time goes backwards: t_us={int(t_us)} after "
                              f"t_us={last}", ErrorReason.TIME_BACKWARDS)

    def check_seq(self, kind: str, seq: int) -> SeqCheck:
        """Advance the ``kind`` stream's sequence number; what it says about loss."""
        expected = self.next_seq[kind]
        self.next_seq[kind] = int(seq) + 1
        if expected is None or seq == expected:
            return SeqCheck()
        if seq > expected:
            return SeqCheck(lost=int(seq) - expected)
        return SeqCheck(restart=True)

    # -- whole messages ----------------------------------------------------------------------

    def accept_events(self, events: np.ndarray, *, what: str = "events",
                      seq: int | None = None, size: tuple[int, int] | None = None,
                      validated: bool = False) -> SeqCheck:
        """Check and accept one chunk of events.

        ``size`` is the ``(height, width)`` its message declares (checked against the
        stream's sensor); ``validated`` says the chunk on its own was already checked against
        that size (the wire decoder does: order inside the chunk, coordinates, polarity), so
        only what needs the stream's history is checked here. Without it the chunk is
        validated in full against the stream's sensor.
        """
        if size is not None:
            self.check_sensor(size[0], size[1], what)
        if not validated:
            validate_events(events, self.sensor, where=what)  # raises EventError
        elif not (isinstance(events, np.ndarray) and events.dtype == EVENTS_DTYPE):
            raise StreamError(f"{what}: expected an array of EVENTS_DTYPE",
                              ErrorReason.MALFORMED)
        self.check_event_order(events, what)
        check = self.check_seq("events", seq) if seq is not None else SeqCheck()
        if events.size:
            self.last_event_t_us = int(events["t_us"][-1])
        return check

    def accept_frame(self, t_us: int, *, what: str = "frame", seq: int | None = None,
                     size: tuple[int, int] | None = None) -> SeqCheck:
        """Check and accept one frame at ``t_us`` (its image is checked by its consumer)."""
        if size is not None:
            self.check_sensor(size[0], size[1], what)
        self.check_frame_order(t_us, what)
        check = self.check_seq("frames", seq) if seq is not None else SeqCheck()
        self.last_frame_t_us = int(t_us)
        return check

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
                "last_frame_t_us": self.last_frame_t_us}

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
        except (KeyError, TypeError, ValueError, AttributeError) as exc:
            raise StreamError(f"not a stream guard state: {exc}") from None
        return guard
