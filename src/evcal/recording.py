"""A recording: sensor size, events, intensity frames and metadata (no file I/O here)."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .errors import EvcalError, reraise_as
from .events import EVENTS_DTYPE, EventError, SensorSize, empty_events, validate_events


class RecordingError(EvcalError):
    """A recording whose parts do not fit together (frame sizes, time order, counts)."""


@dataclass(frozen=True)
class Frames:
    """Intensity frames, ``images[k]`` is frame ``k`` indexed ``[y, x]``.

    ``t_us`` is the time the frame represents (the middle of its exposure when the exposure is
    known). ``exposure_us`` is the exposure time, 0 where unknown. ``images`` keep their
    recorded dtype (uint8 for DAVIS APS frames, float32 for synthetic ones); 8-bit full scale
    is 255.
    """

    t_us: np.ndarray
    images: np.ndarray
    exposure_us: np.ndarray

    def __post_init__(self) -> None:
        t = np.asarray(self.t_us, dtype=np.int64)
        images = np.asarray(self.images)
        if images.ndim != 3:
            raise RecordingError(f"frames: images have shape {images.shape}, expected (n, H, W)")
        if t.shape != (images.shape[0],):
            raise RecordingError(
                f"frames: {t.shape[0] if t.ndim else t} timestamps for {images.shape[0]} images"
            )
        exp = np.asarray(self.exposure_us, dtype=np.int64)
        if exp.shape != t.shape:
            raise RecordingError(f"frames: exposure_us has shape {exp.shape}, expected {t.shape}")
        if t.size > 1:
            bad = np.flatnonzero(np.diff(t) <= 0)
            if bad.size:
                i = int(bad[0]) + 1
                raise RecordingError(
                    f"frames: timestamps must increase: frame {i} has t_us={int(t[i])} after "
                    f"t_us={int(t[i - 1])}"
                )
        if images.dtype.kind == "f" and images.size and not np.isfinite(images).all():
            k = int(np.flatnonzero(~np.isfinite(images).reshape(images.shape[0], -1).all(1))[0])
            raise RecordingError(f"frames: frame {k} contains NaN or infinite values")
        object.__setattr__(self, "t_us", t)
        object.__setattr__(self, "images", images)
        object.__setattr__(self, "exposure_us", exp)

    @classmethod
    def empty(cls, height: int, width: int) -> Frames:
        return cls(
            t_us=np.zeros(0, np.int64),
            images=np.zeros((0, height, width), np.uint8),
            exposure_us=np.zeros(0, np.int64),
        )

    def __len__(self) -> int:
        return int(self.t_us.shape[0])

    @property
    def shape(self) -> tuple[int, int]:
        return (int(self.images.shape[1]), int(self.images.shape[2]))

    def select(self, index: slice | np.ndarray) -> Frames:
        return Frames(self.t_us[index], self.images[index], self.exposure_us[index])


@dataclass(frozen=True)
class Recording:
    """Events and frames of one camera.

    Invariants: events are sorted by ``t_us`` and inside the sensor; every frame has the
    sensor's shape. No events is an empty array; no frames is an empty :class:`Frames`.
    """

    sensor: SensorSize
    events: np.ndarray = field(default_factory=empty_events)
    frames: Frames = field(default_factory=lambda: Frames.empty(0, 0))
    metadata: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        try:
            validate_events(self.events, self.sensor, where="recording events")
        except EventError as exc:
            raise reraise_as(exc, RecordingError) from None
        frames = self.frames
        if frames is None or (len(frames) == 0 and frames.shape != self.sensor.shape):
            # no frames: an empty Frames of the sensor's shape (``None`` is accepted as such)
            frames = Frames.empty(*self.sensor.shape)
            object.__setattr__(self, "frames", frames)
        if len(frames) and frames.shape != self.sensor.shape:
            h, w = frames.shape
            raise RecordingError(
                f"frames have shape ({h}, {w}) (a {w}x{h} image), the sensor is {self.sensor}"
            )

    @property
    def n_events(self) -> int:
        return int(self.events.shape[0])

    @property
    def t_range_us(self) -> tuple[int, int]:
        """First and last time of anything in the recording (events or frames)."""
        ts = []
        if self.n_events:
            ts += [int(self.events["t_us"][0]), int(self.events["t_us"][-1])]
        if len(self.frames):
            ts += [int(self.frames.t_us[0]), int(self.frames.t_us[-1])]
        if not ts:
            return (0, 0)
        return (min(ts), max(ts))

    @property
    def duration_s(self) -> float:
        t0, t1 = self.t_range_us
        return (t1 - t0) * 1e-6

    def iter_events(self, chunk_events: int = 1_000_000) -> Iterator[np.ndarray]:
        """Events in time-ordered chunks of at most ``chunk_events`` (views, no copy)."""
        n = self.n_events
        for i in range(0, n, chunk_events):
            yield self.events[i : i + chunk_events]

    def events_between(self, t0_us: int, t1_us: int) -> np.ndarray:
        """Events with ``t0_us <= t_us < t1_us`` (a view)."""
        t = self.events["t_us"]
        i0, i1 = np.searchsorted(t, [t0_us, t1_us], side="left")
        return self.events[i0:i1]

    def with_events(self, events: np.ndarray) -> Recording:
        return Recording(self.sensor, events, self.frames, dict(self.metadata))

    def frame_window(self, k0: int, k1: int, *, copy: bool = False) -> Recording:
        """Frames ``k0`` to ``k1`` (both kept) and the events from the first's time to the
        last's (included): a view of the events, or a copy that does not keep the whole
        recording's alive."""
        fr = self.frames.select(slice(k0, k1 + 1))
        events = self.events_between(int(fr.t_us[0]), int(fr.t_us[-1]) + 1)
        return Recording(self.sensor, events.copy() if copy else events, fr,
                         dict(self.metadata))


def concat_events(chunks: list[np.ndarray]) -> np.ndarray:
    """Concatenate event chunks; an empty list gives an empty array."""
    if not chunks:
        return empty_events()
    return np.concatenate(chunks).astype(EVENTS_DTYPE, copy=False)
