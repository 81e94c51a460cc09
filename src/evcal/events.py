"""The one event dtype of evcal, and the checks every event array passes.

Invariants (hold everywhere in the package):

- events are a 1-D structured array of :data:`EVENTS_DTYPE`;
- time is integer microseconds (``t_us``), non-decreasing within a stream;
- ``p`` is +1 (ON) or -1 (OFF);
- no events is an empty array of that dtype, never ``None``;
- maps are indexed ``[y, x]``; a sensor size is ``(height, width)`` in code and ``WxH`` on the
  command line.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from .errors import ErrorReason, EvcalError

EVENTS_DTYPE = np.dtype([("t_us", "<i8"), ("x", "<u2"), ("y", "<u2"), ("p", "i1")])


class EventError(EvcalError):
    """Events that break an invariant (order, range, polarity values); ``reason`` says which."""


@dataclass(frozen=True)
class SensorSize:
    """Sensor size in pixels. ``str()`` gives the command-line form ``WxH``."""

    height: int
    width: int

    def __post_init__(self) -> None:
        if not (0 < int(self.height) <= 65535 and 0 < int(self.width) <= 65535):
            raise EvcalError(f"sensor size {self.width}x{self.height} is not in 1..65535",
                             ErrorReason.OUT_OF_RANGE)

    @classmethod
    def parse(cls, text: str) -> SensorSize:
        """Parse ``"346x260"`` (width x height)."""
        try:
            w, h = (int(v) for v in text.lower().split("x"))
        except ValueError:
            raise EvcalError(f"sensor size {text!r} is not of the form WxH, e.g. 346x260",
                             ErrorReason.MALFORMED) from None
        return cls(height=h, width=w)

    @property
    def shape(self) -> tuple[int, int]:
        return (int(self.height), int(self.width))

    @property
    def n_pixels(self) -> int:
        return int(self.height) * int(self.width)

    def __str__(self) -> str:
        return f"{self.width}x{self.height}"


def empty_events() -> np.ndarray:
    """A zero-length event array (what "no events" is)."""
    return np.zeros(0, dtype=EVENTS_DTYPE)


def make_events(t_us: Any, x: Any, y: Any, p: Any) -> np.ndarray:
    """Pack columns into an :data:`EVENTS_DTYPE` array.

    ``p`` may be given as {0, 1} or {-1, +1}; it is stored as {-1, +1}. Only the packing is done
    here; call :func:`validate_events` to check order and range.
    """
    t_us = np.asarray(t_us)
    n = t_us.shape[0]
    for name, col in (("x", x), ("y", y), ("p", p)):
        if np.shape(col) != (n,):
            raise EventError(f"column {name} has shape {np.shape(col)}, expected ({n},) like t_us",
                             ErrorReason.MALFORMED)
    ev = np.empty(n, dtype=EVENTS_DTYPE)
    ev["t_us"] = t_us
    ev["x"] = x
    ev["y"] = y
    p = np.asarray(p)
    if p.dtype == np.bool_:
        ev["p"] = np.where(p, 1, -1)
    else:
        ev["p"] = np.where(p > 0, 1, -1)
    return ev


def validate_events(
    events: np.ndarray,
    sensor: SensorSize | None = None,
    *,
    where: str = "events",
    after_t_us: int | None = None,
) -> np.ndarray:
    """Check dtype, polarity values, time order and coordinate range; return ``events``.

    Raises :class:`EventError` naming the first offending event. ``after_t_us`` is the last
    timestamp of the previous chunk of the same stream (time may not go backwards across
    chunks).
    """
    if not isinstance(events, np.ndarray) or events.dtype != EVENTS_DTYPE or events.ndim != 1:
        dt = getattr(events, "dtype", type(events).__name__)
        raise EventError(f"{where}: expected a 1-D array of EVENTS_DTYPE, got {dt}",
                         ErrorReason.MALFORMED)
    if events.size == 0:
        return events
    t = events["t_us"]
    if t.size > 1:
        back = np.flatnonzero(t[1:] < t[:-1])
        if back.size:
            i = int(back[0]) + 1
            raise EventError(
                f"{where}: timestamps are not sorted: event {i} has t_us={int(t[i])} "
                f"after t_us={int(t[i - 1])}", ErrorReason.UNSORTED
            )
    if after_t_us is not None and int(t[0]) < after_t_us:
        raise EventError(
            f"{where}: time goes backwards: first t_us={int(t[0])} is before the previous "
            f"chunk's last t_us={after_t_us}", ErrorReason.TIME_BACKWARDS
        )
    p = events["p"]
    bad = np.flatnonzero((p != 1) & (p != -1))
    if bad.size:
        i = int(bad[0])
        raise EventError(f"{where}: event {i} has polarity {int(p[i])}, expected +1 or -1",
                         ErrorReason.BAD_POLARITY)
    if sensor is not None:
        h, w = sensor.shape
        bad = np.flatnonzero((events["x"] >= w) | (events["y"] >= h))
        if bad.size:
            i = int(bad[0])
            raise EventError(
                f"{where}: event {i} at (x={int(events['x'][i])}, y={int(events['y'][i])}) is "
                f"outside the {w}x{h} sensor ({bad.size} such events)", ErrorReason.OUT_OF_SENSOR
            )
    return events


def pixel_index(events: np.ndarray, width: int) -> np.ndarray:
    """Flat pixel index ``y * width + x`` (int64)."""
    result: np.ndarray = events["y"].astype(np.int64) * width + events["x"]
    return result
