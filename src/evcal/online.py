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

State, bounded whatever the rates: per buffered frame its raw image and the polarity of each
pixel's last event (dense, 1 + itemsize bytes per pixel; at most ``max_buffer_frames``), and
per interval the sparse ON/OFF counts of the pixels that fired (at most ``n_large`` events'
worth). The per-pixel normal equations (:class:`~evcal.solver.NormalEquations`) are updated
incrementally: a small buffer's equation is added when it closes and subtracted, recomputed
bit-identically from the same stored data, when the frame that opened it leaves the large
buffer; every ``rebuild_every`` removals they are rebuilt from the buffer to shed rounding.

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

import json
import math
from collections import deque
from dataclasses import asdict, dataclass, field, replace
from typing import Any

import numba
import numpy as np

from .accumulate import Accumulator
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
    correction_lambda,
    log_intensity,
    solve_pixels,
    usable,
)
from .special import classify
from .stream import StreamError, StreamGuard, frame_intervals

STATE_FORMAT = "evcal.onei.v2"
# state_dict's scalars: JSON key -> attribute (besides sensor, config and the stream's times)
def _opt_int(v: Any) -> int | None:
    return None if v is None else int(v)


_SCALARS: dict[str, tuple[str, Any]] = {
    "lam": ("lam", float), "n_updates": ("n_updates", int), "n_events": ("n_events", int),
    "n_frames": ("n_frames", int), "n_equations": ("n_equations", int),
    "n_gaps": ("n_gaps", int), "gap": ("_gap", bool), "n_folded_late": ("n_folded_late", int),
    "n_late_events": ("n_late_events", int), "n_sessions": ("n_sessions", int),
    "base": ("_base", int), "next_open": ("_next_open", int),
    "cum_events": ("_cum_events", int), "removals": ("_removals", int),
    "since_resolve": ("_since_resolve", int), "frame_cap": ("_frame_cap", _opt_int),
    "log_offset": ("log_offset", float), "next_offset_check": ("_next_offset_check", int)}
# absent from the states of earlier versions
_OPTIONAL_SCALARS = frozenset({"n_sessions", "log_offset", "next_offset_check"})
_VALID = int(Reason.VALID)


@numba.njit(cache=True, nogil=True)
def _sparse_sum(idx: np.ndarray, on: np.ndarray, off: np.ndarray, scratch: np.ndarray) -> Any:
    """Per-pixel sums of sparse ``(idx, on, off)`` entries: ``(pixels, on, off)`` with each
    pixel once, in order of first appearance; ``scratch`` (2, n) is zero before and after."""
    touched = np.empty(idx.size, np.int32)
    n_touched = 0
    for i in range(idx.size):
        k = idx[i]
        if scratch[0, k] == 0 and scratch[1, k] == 0:
            touched[n_touched] = k
            n_touched += 1
        scratch[0, k] += on[i]
        scratch[1, k] += off[i]
    out_idx = touched[:n_touched].copy()
    s_on = np.empty(n_touched, np.float64)
    s_off = np.empty(n_touched, np.float64)
    for j in range(n_touched):
        k = out_idx[j]
        s_on[j] = scratch[0, k]
        s_off[j] = scratch[1, k]
        scratch[0, k] = 0.0
        scratch[1, k] = 0.0
    return out_idx, s_on, s_off


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


class LowPassEstimate:
    """OnEI's smoothed per-pixel estimate (flat maps) and its low-pass update.

    ``est <- (1 - a) est + a new`` on pixels whose new solution is valid, with
    ``a = max(smoothing, 1 / n)`` for a pixel's ``n``-th valid solution (the start-up
    correction: the first ``1 / smoothing`` solutions are averaged with equal weights).
    """

    ARRAYS = ("c", "b", "se_c", "se_b", "seen", "n_solved", "reason")

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

    def maps(self, shape: tuple[int, int]) -> dict[str, np.ndarray]:
        """The calibration maps of the estimate (copies; defaults where never solved)."""
        valid = self.seen.copy()
        special = classify(self.c, self.b, self.se_c, self.se_b, valid)
        special[~valid] = Special.UNOBSERVED
        return {"contrast": self.c.reshape(shape),  # float32 copies (Calibration casts)
                "bias": self.b.reshape(shape), "valid": valid.reshape(shape),
                "reason": self.reason.reshape(shape).copy(),
                "stderr_contrast": np.where(valid, self.se_c, np.inf).reshape(shape),
                "stderr_bias": np.where(valid, self.se_b, np.inf).reshape(shape),
                "special": special.reshape(shape)}

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
    """

    n_small: int | None = None
    n_large: int | None = None
    smoothing: float = 0.1
    log_offset: float | str = 30.0  # DN, or "auto": estimated online from the buffer
    residual_correction: str | float = "auto"
    saturation_dn: tuple[float, float] = (0.0, 255.0)
    max_pending_events: int = 20_000_000
    max_buffer_frames: int | None = None
    max_buffer_mb: float = 256.0
    rebuild_every: int = 500
    limits: SolveLimits = field(default_factory=lambda: SolveLimits(min_events=10,
                                                                    min_equations=3.0))

    def __post_init__(self) -> None:
        if not 0 < self.smoothing <= 1:
            raise ConfigError(f"smoothing={self.smoothing} must be in (0, 1]")
        lo = self.log_offset
        if not (lo == "auto" or (isinstance(lo, (int, float)) and not isinstance(lo, bool)
                                 and lo >= 0)):
            raise ConfigError(f"log_offset={lo!r} must be 'auto' or a number >= 0 (DN)")
        for name in ("n_small", "n_large", "max_buffer_frames"):
            v = getattr(self, name)
            if v is not None and v < 1:
                raise ConfigError(f"{name}={v} must be >= 1")
        if self.n_small and self.n_large and self.n_large < self.n_small:
            raise ConfigError(f"n_large={self.n_large} must be >= n_small={self.n_small}")
        if self.max_buffer_mb <= 0:
            raise ConfigError(f"max_buffer_mb={self.max_buffer_mb} must be > 0")
        if self.rebuild_every < 1:
            raise ConfigError(f"rebuild_every={self.rebuild_every} must be >= 1")

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
    idx: np.ndarray  # int32: pixels with events in the interval ending here
    on: np.ndarray  # int32 ON counts at idx
    off: np.ndarray  # int32 OFF counts at idx
    opens: bool = True  # a small buffer may open here (False after a gap)
    closes_at: int = -1  # absolute frame number closing the small buffer opened here

    @property
    def n_events(self) -> int:
        return int(self.on.sum() + self.off.sum())


class OnlineCalibrator:
    """Per-camera OnEI state: feed events and frames in time order, read the calibration."""

    def __init__(self, sensor: SensorSize, config: OnEIConfig | None = None):
        self.sensor = sensor
        self.config = config or OnEIConfig()
        self.n_small, self.n_large = self.config.sizes(sensor)
        n = sensor.n_pixels
        self._scratch = np.zeros((2, n), np.float64)  # zero between uses
        self._frame_cap: int | None = None
        self._reset_buffer()
        self.estimate = LowPassEstimate(n)  # what calibration() reports
        auto = self.config.log_offset == "auto"
        # the offset of log(I + offset); NaN until estimated (log_offset="auto")
        given = self.config.log_offset
        self.log_offset = float(given) if not isinstance(given, str) else math.nan
        self.offset_info: dict[str, Any] = {"method": "auto" if auto else "given"}
        self._next_offset_check = 0  # frame count of the next online re-estimate
        self.lam = 0.0
        self.n_updates = 0
        self.n_events = 0
        self.n_frames = 0
        self.n_gaps = 0
        self.n_folded_late = 0  # events folded without their frame (pending overflow)
        self.n_late_events = 0  # events that arrived after the frame that ends their interval
        self.n_sessions = 0  # discontinuities of the stream's time base (new_session)
        self._guard = StreamGuard(sensor)  # time order of this calibrator's input

    def _reset_buffer(self) -> None:
        """Empty the large buffer, the pending events and the normal equations."""
        n = self.sensor.n_pixels
        self._acc = Accumulator(self.sensor)  # counts of the interval since the latest frame
        self._ne = NormalEquations(n)
        self._counts = np.zeros(n, np.int64)  # events per pixel inside the large buffer
        self._frames: deque[_Frame] = deque()
        self._base = 0  # absolute number of self._frames[0]
        self._next_open = 0  # absolute number of the oldest frame whose small buffer is open
        self._cum_events = 0
        self._gap = False
        self._removals = 0
        self._since_resolve = 0
        self._pending: deque[np.ndarray] = deque()
        self._n_pending = 0
        self.n_equations = 0  # small buffers in the normal equations now

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
        while self._n_pending > self.config.max_pending_events and len(self._pending) > 1:
            old = self._pending.popleft()
            self._n_pending -= int(old.size)
            self._fold(old)
            self.n_folded_late += int(old.size)

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
        if self._guard.accept_frame(t_us, what=f"frame at t_us={t_us}").new_session:
            self._start_session_keeping_guard()
        self._fold_pending_before(t_us)
        self.n_frames += 1
        if self._frame_cap is None:
            self._frame_cap = self.config.frame_cap(self.sensor, img.dtype.itemsize)
        self._push(t_us, img.ravel().copy())
        if math.isnan(self.log_offset) or self.n_frames >= self._next_offset_check > 0:
            self._check_offset()
        formed = (not math.isnan(self.log_offset)) and self._close_small_buffers()
        self._drop_overflow()
        if self._removals >= self.config.rebuild_every:
            self._rebuild()
        if formed and self._since_resolve >= self.n_small:
            self._resolve()
            self._since_resolve = 0
            return True
        return False

    # -- the large buffer ---------------------------------------------------------------------

    def _fold_pending_before(self, t_us: int) -> None:
        """Fold the pending events before ``t_us`` (they belong to the interval it closes)."""
        while self._pending:
            chunk = self._pending[0]
            if int(chunk["t_us"][-1]) < t_us:
                self._pending.popleft()
                self._n_pending -= int(chunk.size)
                self._fold(chunk)
                continue
            cut = int(np.searchsorted(chunk["t_us"], t_us, side="left"))
            if cut:
                self._fold(chunk[:cut])
                self._pending[0] = chunk[cut:]
                self._n_pending -= cut
            break

    def _fold(self, events: np.ndarray) -> None:
        if not events.size:
            return
        self._acc.add(events)
        if not self._frames:
            self._acc.reset_counts()  # before the first frame only the last polarity matters

    def _push(self, t_us: int, image: np.ndarray) -> None:
        on, off = self._acc.on, self._acc.off
        if self._frames:
            idx = np.flatnonzero((on | off) != 0).astype(np.int32)
            f_on, f_off = on[idx].copy(), off[idx].copy()
        else:
            idx = np.zeros(0, np.int32)
            f_on = f_off = np.zeros(0, np.int32)
        n_new = int(f_on.sum() + f_off.sum())
        self._cum_events += n_new
        self._since_resolve += n_new
        self._counts[idx] += (f_on + f_off).astype(np.int64)
        self._acc.reset_counts()
        if self._gap and self._frames:
            # the interval just closed lost events: close no small buffer across it
            for f in self._frames:
                if f.closes_at < 0:
                    f.opens = False
            self._next_open = self._base + len(self._frames)
        self._gap = False
        self._frames.append(_Frame(t_us, image, self._acc.last_p.copy(), self._cum_events,
                                   idx, f_on, f_off))

    # -- the log offset, online ----------------------------------------------------------------

    AUTO_WINDOW = 5  # frame intervals per window of the offset criterion (OffEI's default d)

    def _check_offset(self) -> None:
        """Estimate the offset from the buffer (``log_offset="auto"``): first once it holds
        ``2 d + 1`` frames, then again after 4x, 16x, ... as many frames; a changed estimate
        (by more than 10 % in ``log(1 + o)``) rebuilds the equations from the buffer's raw
        frames (the smoothed estimate goes on from there)."""
        first = math.isnan(self.log_offset)
        if first and len(self._frames) < 2 * self.AUTO_WINDOW + 1:
            return
        found = self._offset_from_buffer()
        if found is None:
            if not first:
                self._next_offset_check = self.n_frames * 4
            return
        o, info = found
        self._next_offset_check = self.n_frames * 4
        info.update(frames_seen=self.n_frames, previous=None if first else self.log_offset)
        self.offset_info = info
        if first:
            self.log_offset = o
            self._form_all()
        elif abs(math.log1p(o) - math.log1p(self.log_offset)) > 0.1:
            self.log_offset = o
            self._rebuild()

    def _offset_from_buffer(self) -> tuple[float, dict[str, Any]] | None:
        """The criterion of ``--log-offset auto`` on the frames and interval counts the large
        buffer holds (busiest pixels, windows of ``AUTO_WINDOW`` intervals)."""
        from .offline import offset_from_windows  # noqa: PLC0415 - offline imports solver only

        frames = list(self._frames)
        d = min(self.AUTO_WINDOW, len(frames) - 3)
        limits = self.config.limits
        busy = np.flatnonzero(self._counts >= max(limits.min_events, 2 * d))
        if d < 1 or busy.size < 10:
            return None
        rng = np.random.default_rng(0)
        pix = np.sort(rng.choice(busy, size=min(10_000, busy.size), replace=False))
        pos = np.full(self.sensor.n_pixels, -1, np.int64)
        pos[pix] = np.arange(pix.size)
        on = np.zeros((len(frames), pix.size), np.int64)
        off = np.zeros((len(frames), pix.size), np.int64)
        for i, f in enumerate(frames):  # loop over buffered frames, vectorised over pixels
            m = pos[f.idx]
            sel = m >= 0
            on[i, m[sel]] = f.on[sel]
            off[i, m[sel]] = f.off[sel]
        con, coff = np.cumsum(on, 0), np.cumsum(off, 0)
        ks = np.arange(d, len(frames))
        sp = ((con[ks] - coff[ks]) - (con[ks - d] - coff[ks - d])).astype(np.float64)
        se = ((con[ks] + coff[ks]) - (con[ks - d] + coff[ks - d])).astype(np.float64)
        last = np.stack([f.last_p[pix] for f in frames]).astype(np.float64)
        img = np.stack([f.image[pix] for f in frames]).astype(np.float64)
        sat = self.config.saturation_dn
        ok = usable(img, sat)
        w = (ok[ks] & ok[ks - d]).astype(np.float64)
        o, info = offset_from_windows(sp, se, last[ks] - last[ks - d], img[ks - d], img[ks], w)
        info.update(pixels=int(pix.size), window_frames=int(d), source="OnEI buffer")
        return o, info

    def _form_all(self) -> None:
        """Form every small buffer the buffer holds (once the offset became known)."""
        self._ne = NormalEquations(self.sensor.n_pixels)
        self.n_equations = 0
        self._removals = 0
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
            if newest.cum_events - fj.cum_events < self.n_small:
                break
            fj.closes_at = k
            self._apply(j, k, +1.0)
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
            if first.closes_at >= 0:
                self._apply(self._base, first.closes_at, -1.0)
                self.n_equations -= 1
                self._removals += 1
            self._counts[second.idx] -= (second.on + second.off).astype(np.int64)
            self._frames.popleft()
            self._base += 1
            # the new first frame's interval lies outside the buffer now
            second.idx = np.zeros(0, np.int32)
            second.on = second.off = np.zeros(0, np.int32)
            self._next_open = max(self._next_open, self._base)

    def _terms(self, j: int, k: int) -> tuple[np.ndarray, ...]:
        """Sparse ``(idx, P, E, Q, A, dL, w)`` of the small buffer from frame j to frame k."""
        frames = [self._frames[i - self._base] for i in range(j + 1, k + 1)]
        fj, fk = self._frames[j - self._base], self._frames[k - self._base]
        if len(frames) == 1:
            idx = frames[0].idx
            on = frames[0].on.astype(np.float64)
            off = frames[0].off.astype(np.float64)
        else:
            idx, on, off = _sparse_sum(np.concatenate([f.idx for f in frames]),
                                       np.concatenate([f.on for f in frames]),
                                       np.concatenate([f.off for f in frames]), self._scratch)
        qk = fk.last_p[idx].astype(np.float64)
        qj = fj.last_p[idx].astype(np.float64)
        raw_j, raw_k = fj.image[idx], fk.image[idx]
        off_log = self.log_offset
        sat = self.config.saturation_dn
        w = (usable(raw_j, sat) & usable(raw_k, sat)).astype(np.float64)
        with np.errstate(invalid="ignore"):  # -inf - -inf at black pixels with offset 0
            dl = log_intensity(raw_k, off_log) - log_intensity(raw_j, off_log)
        dl = np.where(w > 0, dl, 0.0)  # clipped pixels weigh nothing (and never NaN)
        return idx, on - off, on + off, qk - qj, np.abs(qk) - np.abs(qj), dl, w

    def _apply(self, j: int, k: int, sign: float) -> None:
        idx, p, e, q, a, dl, w = self._terms(j, k)
        self._ne.add(p, e, q, a, dl, w, idx=idx, sign=sign)

    def _rebuild(self) -> None:
        """Recompute the normal equations from the buffer (sheds accumulated rounding)."""
        self._ne = NormalEquations(self.sensor.n_pixels)
        for i, f in enumerate(self._frames):
            if f.closes_at >= 0:
                self._apply(self._base + i, f.closes_at, +1.0)
        self._removals = 0

    def _resolve(self) -> None:
        cfg = self.config
        self.lam = correction_lambda(self._ne, cfg.residual_correction, cfg.limits, self._counts)
        # consecutive small buffers share their events: divide the degrees of freedom by
        # the number of small buffers each event lies in
        overlap = max(1.0, self.n_equations * self.n_small / max(self.buffer_events, 1))
        new = solve_pixels(self._ne, self._counts, limits=cfg.limits, overlap=overlap,
                           residual_lambda=self.lam)
        # low-pass with a start-up correction: a pixel's first 1/smoothing solutions are
        # averaged with equal weights (the first one is not trusted more than the later ones)
        self.estimate.fold(new, cfg.smoothing)
        self.n_updates += 1

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
            **self.estimate.maps(shape),
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
            "pending_events": self._n_pending,
            "folded_late_events": self.n_folded_late,
            "late_events": self.n_late_events,
            "gaps": self.n_gaps,
            "sessions": self.n_sessions,
            "residual_lambda": self.lam,
            "n_small": self.n_small,
            "n_large": self.n_large,
            "last_frame_t_us": self.last_frame_t_us,
            "log_offset": self.log_offset,
        }

    @property
    def buffer_bytes(self) -> int:
        """Bytes held by the large buffer (frames, last polarities, sparse interval counts)."""
        return int(sum(f.image.nbytes + f.last_p.nbytes + f.idx.nbytes + f.on.nbytes
                       + f.off.nbytes for f in self._frames))

    # -- persistence -------------------------------------------------------------------------

    def state_dict(self) -> dict[str, np.ndarray]:
        """Everything needed to resume, as numpy arrays (``np.savez``-able)."""
        frames = list(self._frames)
        n = self.sensor.n_pixels

        def cat(name: str, dtype: Any) -> np.ndarray:
            if not frames:
                return np.zeros(0, dtype)
            return np.concatenate([getattr(f, name) for f in frames]).astype(dtype)

        pending = (np.concatenate(list(self._pending)) if self._pending
                   else np.zeros(0, EVENTS_DTYPE))
        scalars = {"height": self.sensor.height, "width": self.sensor.width,
                   "config": self.config.to_json(),
                   "last_event_t_us": self.last_event_t_us,
                   "last_frame_t_us": self.last_frame_t_us}
        scalars.update({key: getattr(self, attr) for key, (attr, _) in _SCALARS.items()})
        scalars["offset_info"] = to_jsonable(self.offset_info)
        img_dtype = frames[0].image.dtype if frames else np.dtype(np.uint8)
        out: dict[str, np.ndarray] = {
            "format": np.array(STATE_FORMAT),
            "scalars": np.array(json.dumps(scalars)),
            "acc_on": self._acc.on, "acc_off": self._acc.off, "acc_last_p": self._acc.last_p,
            "counts": self._counts, **self.estimate.state(),
            "pending": pending, "fr_images": (np.stack([f.image for f in frames]) if frames
                          else np.zeros((0, n), img_dtype)),
            "fr_last_p": (np.stack([f.last_p for f in frames]) if frames
                          else np.zeros((0, n), np.int8)),
            "fr_meta": np.array([[f.t_us, f.cum_events, f.idx.size, int(f.opens), f.closes_at]
                                 for f in frames], np.int64).reshape(-1, 5),
            "fr_idx": cat("idx", np.int32), "fr_on": cat("on", np.int32),
            "fr_off": cat("off", np.int32),
        }
        for k, v in self._ne.arrays().items():
            out[f"ne_{k}"] = v
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
            _load_into(self._acc.on, state["acc_on"], "acc_on")
            _load_into(self._acc.off, state["acc_off"], "acc_off")
            _load_into(self._acc.last_p, state["acc_last_p"], "acc_last_p")
            _load_into(self._counts, state["counts"], "counts")
            self.estimate.load(state)
            pending = np.asarray(state["pending"])
            if pending.dtype != EVENTS_DTYPE:
                raise StateError("state pending events have the wrong dtype")
            if pending.size:
                self._pending.append(pending)
            self._n_pending = int(pending.size)
            self._ne = NormalEquations.from_arrays({k[3:]: v for k, v in state.items()
                                                    if k.startswith("ne_")})
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
