"""OnEI's parameters (:class:`OnEIConfig`) and the cores a process may use."""

from __future__ import annotations

import json
import math
import os
from dataclasses import asdict, dataclass, field, replace

from ..errors import ConfigError
from ..events import SensorSize
from ..solver import SolveLimits

MAX_SOLVE_THREADS = 8  # a re-solve's threads at most (it is memory-bound beyond a few)
MIN_SMALL = 1000  # events per small buffer at least
# a growing small buffer holds 1/GROW_DIVISOR of the events seen (OnEIConfig.small_for)
GROW_DIVISOR = 8


def usable_cores() -> int:
    """The cores this process may run on (its affinity: a container's or taskset's limit)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):  # not on Linux
        return max(1, os.cpu_count() or 1)


@dataclass(frozen=True, kw_only=True)
class OnEIConfig:
    """OnEI parameters. ``None`` sizes scale with the sensor as in the paper at 240x180
    (200 k and 1.7 M events for 43,200 pixels), and the small buffer with the events at hand:
    a calibrator starts with small buffers of ``1 / GROW_DIVISOR`` of the events it has seen
    (at least ``MIN_SMALL``) and grows them to the scaled size, so that a camera that sends
    fewer events than the paper's buffers hold (a still camera, a short clip) is calibrated
    from what it sent; :func:`~evcal.onei.onei` fits them to a recording's events at once
    (:meth:`fitted`). A size given is kept as given.

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
    # log_offset="auto": True applies an online estimate exactly OnlineOffset.LAG_FRAMES frames
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
        """``(n_small, n_large)``: as given, else the paper's scaled to the sensor (the
        small buffer's size it grows to)."""
        n_small = self.n_small or max(MIN_SMALL,
                                      int(round(200_000 / 43_200 * sensor.n_pixels)))
        n_large = self.n_large or max(n_small, int(round(1_700_000 / 43_200 * sensor.n_pixels)))
        return n_small, n_large

    @property
    def grows(self) -> bool:
        """The small buffer grows with the events seen (its size was not given)."""
        return self.n_small is None

    def small_for(self, sensor: SensorSize, n_events: int) -> int:
        """Events per small buffer once ``n_events`` were seen: the given size, else
        ``n_events / GROW_DIVISOR`` between ``MIN_SMALL`` and the scaled size. The large
        buffer holds about ``GROW_DIVISOR`` small buffers before it first overflows (the
        paper's holds 8.5), so the size stops growing before the buffer slides."""
        target = self.sizes(sensor)[0]
        if not self.grows:
            return target
        return min(target, max(MIN_SMALL, int(n_events) // GROW_DIVISOR))

    def fitted(self, sensor: SensorSize, n_events: int) -> OnEIConfig:
        """This configuration with its small buffer fitted to a recording of ``n_events``
        events (:meth:`small_for`; unchanged when the size was given)."""
        if not self.grows:
            return self
        n_small = self.small_for(sensor, n_events)
        return replace(self, n_small=n_small, n_large=self.sizes(sensor)[1])

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
