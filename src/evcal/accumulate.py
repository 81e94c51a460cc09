"""Per-pixel event accumulation between frames: the inner loop of every estimator.

:class:`Accumulator` keeps, per pixel, running ON and OFF counts and the polarity of the most
recent event (0 before the first one). :func:`frame_snapshots` walks a recording's frames and
events in time order and yields, at each frame, the running maps (events with
``t_us < frame t_us`` belong before the frame).
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import numba
import numpy as np

from .errors import ErrorReason, EvcalError
from .events import SensorSize
from .recording import Recording
from .stream import frame_intervals


@numba.njit(cache=True, nogil=True)
def _accumulate(x: np.ndarray, y: np.ndarray, p: np.ndarray, width: int, on: np.ndarray,
                off: np.ndarray, last_p: np.ndarray) -> Any:  # pragma: no cover - compiled
    for i in range(x.size):
        k = np.int64(y[i]) * width + np.int64(x[i])
        if p[i] > 0:
            on[k] += 1
        else:
            off[k] += 1
        last_p[k] = p[i]


@numba.njit(cache=True, nogil=True)
def _order_by_key(key: np.ndarray, n_keys: int) -> Any:  # pragma: no cover - compiled
    start = np.zeros(n_keys + 1, np.int64)
    for v in key:
        start[v + 1] += 1
    for i in range(n_keys):
        start[i + 1] += start[i]
    out = np.empty(key.size, np.int64)
    for j in range(key.size):
        v = key[j]
        out[start[v]] = j
        start[v] += 1
    return out


def order_by_key(key: np.ndarray, n_keys: int) -> np.ndarray:
    """The stable order of ``key`` (integers in ``[0, n_keys)``, e.g. the pixel of each
    event): a counting sort, linear in the events where ``np.argsort(kind="stable")`` on
    64-bit keys is a merge sort."""
    k = np.ascontiguousarray(key, np.int64)
    if k.size and (int(k.min()) < 0 or int(k.max()) >= n_keys):
        raise EvcalError(f"keys must lie in [0, {n_keys}); got {int(k.min())}..{int(k.max())}",
                         ErrorReason.OUT_OF_RANGE)
    result: np.ndarray = _order_by_key(k, int(n_keys))
    return result


class Accumulator:
    """Running per-pixel ON/OFF counts (int32) and last polarity (int8), flat ``H*W`` maps.

    Events must be validated (inside the sensor, p in {-1, +1}) before :meth:`add`.
    """

    def __init__(self, sensor: SensorSize):
        self.sensor = sensor
        n = sensor.n_pixels
        self.on = np.zeros(n, np.int32)
        self.off = np.zeros(n, np.int32)
        self.last_p = np.zeros(n, np.int8)
        self.n_events = 0

    def add(self, events: np.ndarray) -> None:
        if events.size:
            _accumulate(events["x"], events["y"], events["p"], self.sensor.width,
                        self.on, self.off, self.last_p)
            self.n_events += int(events.size)

    def reset_counts(self) -> None:
        """Zero the counts (the last polarity is kept: it is state, not a sum)."""
        self.on[:] = 0
        self.off[:] = 0


@dataclass(frozen=True)
class Snapshot:
    """Running maps at frame ``k`` (flat ``H*W``; copies, safe to keep)."""

    k: int
    t_us: int
    image: np.ndarray  # [H, W] frame as recorded
    on: np.ndarray  # int32 cumulative ON count since the start
    off: np.ndarray  # int32 cumulative OFF count since the start
    last_p: np.ndarray  # int8 polarity of the last event before the frame (0: none yet)


def frame_snapshots(rec: Recording) -> Iterator[Snapshot]:
    """Yield a :class:`Snapshot` at every frame of ``rec`` (events before it accumulated)."""
    acc = Accumulator(rec.sensor)
    for k, chunk in frame_intervals(rec.events, rec.frames.t_us):
        acc.add(chunk)
        t_f = int(rec.frames.t_us[k])
        yield Snapshot(k, t_f, rec.frames.images[k], acc.on.copy(), acc.off.copy(),
                       acc.last_p.copy())
