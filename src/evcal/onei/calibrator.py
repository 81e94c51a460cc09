"""The OnEI facade: :class:`OnlineCalibrator` (feed events and frames, read the calibration)
and :func:`onei` (the calibrator over a whole recording)."""

from __future__ import annotations

import json
import math
from dataclasses import replace
from types import TracebackType
from typing import Any

import numpy as np

from ..calibration import Calibration, Diagnostics, OnEIDiagnostics
from ..errors import CalibrationError, ErrorReason
from ..events import SensorSize
from ..recording import Recording
from ..stream import StreamError, StreamGuard, frame_cut, frame_intervals
from . import state as state_format
from .buffer import LargeBuffer
from .config import GROW_DIVISOR, OnEIConfig
from .estimate import LowPassEstimate
from .executor import OnEIExecutor
from .offset import OnlineOffset
from .solve import resolve
from .stderr import ErrorScale, error_scales, identity


class OnlineCalibrator:
    """Per-camera OnEI state: feed events and frames in time order, read the calibration.

    Its threads are an :class:`OnEIExecutor`: the caller's when one is passed (the caller
    closes it), else the calibrator's own, shut down by :meth:`close` or at the end of a
    ``with`` block (a closed calibrator still works, on the caller's thread).
    """

    # events are counted ahead of their frame up to this fraction of the shortest recent
    # frame interval after the latest frame (EventIntake.fold_ahead)
    AHEAD_FRACTION = 0.75
    # the standard errors' calibration is measured again after this many updates
    SCALE_EVERY = 8

    def __init__(self, sensor: SensorSize, config: OnEIConfig | None = None, *,
                 executor: OnEIExecutor | None = None) -> None:
        self.sensor = sensor
        self.config = config or OnEIConfig()
        # n_small: the size a growing small buffer grows to (buffer.n_small: its size now)
        self.n_small, self.n_large = self.config.sizes(sensor)
        self._owns_executor = executor is None
        self.executor = executor if executor is not None else OnEIExecutor(
            self.config.threads)
        self.buffer = LargeBuffer(sensor, self.config, self.config.small_for(sensor, 0),
                                  self.n_large, self.executor)
        # normal equations that fit in the last-level cache (16 blocks, 16.8 MB; 346x260 has
        # 11) take the queued equations at every frame: as cheap as in batches there, and an
        # update frame is not left the queue of the frames before it; larger ones batch them
        # (PENDING_SLOTS), each pass over the sums costing a pass through memory
        eager = self.config.eager
        self._eager = self.buffer.sums.n_blocks <= 16 if eager is None else bool(eager)
        self.estimate = LowPassEstimate(sensor.n_pixels)  # what calibration() reports
        self.offset = OnlineOffset(self.config.log_offset)
        self.lam = 0.0
        self.n_updates = 0
        self.n_events = 0
        self.n_frames = 0
        self.n_gaps = 0
        self.n_folded_late = 0  # events folded without their frame (pending overflow)
        self.n_refolds = 0  # frames earlier than events folded ahead (counted again)
        self.n_late_events = 0  # events that arrived after the frame that ends their interval
        self.n_sessions = 0  # discontinuities of the stream's time base (new_session)
        # the stream's latest times; input the caller did not check goes through a guard of
        # the calibrator's own, made at the first such input (a service camera's one guard is
        # its own: it feeds events and frames checked=True)
        self._last_event_t_us: int | None = None
        self._last_frame_t_us: int | None = None
        self._guard: StreamGuard | None = None
        # the last error_scale(): ((sessions, log offset), n_updates, scale)
        self._scale: tuple[tuple[int, float], int, ErrorScale] | None = None

    # -- lifecycle ----------------------------------------------------------------------------

    def __enter__(self) -> OnlineCalibrator:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()

    def close(self) -> None:
        """Shut down the calibrator's own threads (not a caller's executor). Idempotent."""
        if self._owns_executor:
            self.executor.close()

    def new_session(self) -> None:
        """The stream's time base changed (a camera restarted, a recording replayed again).

        The rule: no equation may span the discontinuity, so the large buffer, the pending
        events and the normal equations are emptied; the smoothed estimate (and so the
        published calibration) is kept and goes on being refined by the new session. A
        change of sensor needs a new calibrator instead.
        """
        self.buffer.reset()
        self._guard = None
        self._last_event_t_us = self._last_frame_t_us = None
        self.n_sessions += 1
        self.buffer.holds_all = False

    def _start_session_keeping_guard(self) -> None:
        guard = self._guard
        self.new_session()
        self._guard = guard  # it already accepted the message that started the session

    def _own_guard(self) -> StreamGuard:
        """The guard of input the caller did not check, at the stream's latest times."""
        if self._guard is None:
            self._guard = StreamGuard(self.sensor)
        self._guard.last_event_t_us = self._last_event_t_us
        self._guard.last_frame_t_us = self._last_frame_t_us
        return self._guard

    # -- the parts' figures -------------------------------------------------------------------

    @property
    def log_offset(self) -> float:
        """The offset of ``log(I + offset)`` in DN; NaN until estimated (``"auto"``)."""
        return self.offset.log_offset

    @property
    def offset_info(self) -> dict[str, Any]:
        return self.offset.info

    @property
    def offset_state(self) -> str:
        """Where the online offset estimate stands, for an operator."""
        return self.offset.state

    @property
    def n_equations(self) -> int:
        """Small buffers in the normal equations now."""
        return self.buffer.n_equations

    @property
    def last_event_t_us(self) -> int | None:
        """Time of the latest event fed (None before the first)."""
        return self._last_event_t_us

    @property
    def last_frame_t_us(self) -> int | None:
        """Time of the latest frame fed (None before the first)."""
        return self._last_frame_t_us

    @property
    def buffer_events(self) -> int:
        return self.buffer.n_events

    @property
    def buffer_bytes(self) -> int:
        """Bytes held by the large buffer (frames, last polarities, sparse interval counts)."""
        return self.buffer.nbytes

    @property
    def state_bytes(self) -> int:
        """Bytes of all the calibrator holds: the large buffer and the per-pixel state (normal
        equations, queued equations, sliding sums, open interval, counts, estimate)."""
        arrays = [*self.buffer.arrays(), *self.estimate.state().values()]
        return self.buffer_bytes + int(sum(a.nbytes for a in arrays))

    # -- input --------------------------------------------------------------------------------

    def feed_events(self, events: np.ndarray, *, checked: bool = False) -> None:
        """Add a sorted chunk of events (raises :class:`~evcal.events.EventError`).

        ``checked=True`` is for callers whose own :class:`~evcal.stream.StreamGuard` accepted
        the chunk against this sensor (the service does, and a :class:`Recording`'s events are
        validated whole): nothing is checked again.
        """
        if checked:
            if events.size:
                self._last_event_t_us = int(events["t_us"][-1])
        else:
            guard = self._own_guard()
            if guard.accept_events(events, what="events").new_session:
                self._start_session_keeping_guard()
            self._last_event_t_us = guard.last_event_t_us
        if events.size == 0:
            return
        self.n_events += int(events.size)
        if self.last_frame_t_us is not None and int(events["t_us"][0]) < self.last_frame_t_us:
            # their frame came first: they are counted in the next interval
            self.n_late_events += frame_cut(events["t_us"], self.last_frame_t_us)
        intake = self.buffer.intake
        intake.add(events)
        self.n_folded_late += intake.shed(self.config.max_pending_events)
        intake.fold_ahead(self.last_frame_t_us, self.AHEAD_FRACTION)

    def mark_gap(self) -> None:
        """Events were lost since the latest frame: no small buffer will span this interval."""
        self.buffer.gap = True
        self.n_gaps += 1

    def feed_frame(self, t_us: int, image: np.ndarray, exposure_us: int = 0, *,
                   checked: bool = False) -> bool:
        """Close the frame interval ending at ``t_us``; True when the estimate was re-solved.

        ``checked=True``: the caller's :class:`~evcal.stream.StreamGuard` accepted the frame's
        time (the image is checked here all the same)."""
        t_us = int(t_us)
        img = self._checked_frame(t_us, image)
        previous = self.last_frame_t_us
        if not checked and self._own_guard().accept_frame(
                t_us, what=f"frame at t_us={t_us}").new_session:
            self._start_session_keeping_guard()
            previous = None
        self._last_frame_t_us = t_us
        buffer, offset = self.buffer, self.offset
        if buffer.intake.fold_pending_before(t_us):
            self.n_refolds += 1
        buffer.intake.frame_came(t_us, previous)
        self.n_frames += 1
        if buffer.frame_cap is None:
            buffer.frame_cap = self.config.frame_cap(self.sensor, img.dtype.itemsize)
        buffer.push(t_us, img.ravel().copy())
        buffer.n_small = self.config.small_for(self.sensor, self.n_events)
        first_formed = False  # the first offset estimate formed the buffer's equations
        if offset.ready(self.n_frames, self.config.offset_wait):
            first_formed = self._apply_offset()
        if offset.due(self.n_frames):
            offset.start(buffer, self.sensor.n_pixels, self.n_frames, self.executor)
        formed = offset.known and (buffer.close_small_buffers(self.log_offset)
                                   or first_formed)
        buffer.drop_overflow(self.log_offset)
        if buffer.sums.removals >= self.config.rebuild_every:
            buffer.rebuild(self.log_offset)
        if formed and buffer.since_resolve >= buffer.n_small:
            self._resolve()
            return True
        if self._eager:
            # the next update (the frame a service waits on) then adds only its own equations
            buffer.sums.apply_queued()
        return False

    def _checked_frame(self, t_us: int, image: np.ndarray) -> np.ndarray:
        """``image`` as an array of this sensor's shape and finite numbers (or StreamError)."""
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
        return img

    # -- the log offset, online ---------------------------------------------------------------

    def poll_offset(self) -> bool:
        """Between frames: take an online offset estimate that has finished (only with
        ``offset_wait=False``; a stream that stops would otherwise never see it). True when
        the estimate was re-solved: read :meth:`calibration`."""
        if self.config.offset_wait or not self.offset.ready(self.n_frames, False):
            return False
        before = self.n_updates
        if self._apply_offset() and self.buffer.since_resolve >= self.buffer.n_small:
            self._resolve()
        return self.n_updates > before

    def _apply_offset(self) -> bool:
        """Take the started estimate; True when it was the first and formed equations (the
        caller re-solves as after any new equation). A changed estimate (by more than 10 % in
        ``log(1 + o)``) rebuilds the equations from the buffer's raw frames, restarts the
        smoothed estimate and re-solves: the solutions folded so far were fitted to log
        changes at the wrong offset, and averaging them with the new ones would keep their
        bias for ``1 / smoothing`` re-solves."""
        first = not self.offset.known
        found = self.offset.take(self.n_frames)
        if found is None:
            return False
        o, info = found
        if first:
            self.offset.log_offset = o
            self.buffer.form_all(o)
            return self.n_equations > 0
        if abs(math.log1p(o) - math.log1p(self.log_offset)) > 0.1:
            self.offset.log_offset = o
            self.buffer.rebuild(o)
            self.buffer.sums.reset_history()  # its log changes were at the old offset
            self.estimate = LowPassEstimate(self.sensor.n_pixels)
            self._resolve()  # at once, from the rebuilt buffer
            info["estimate_restarted"] = True
        return False

    def _resolve(self) -> None:
        """Re-solve every pixel and fold the solution into the estimate (:func:`resolve`)."""
        buffer = self.buffer
        overlap = self._overlap()
        # an update every n_small events, a buffer of n_large: solves k updates apart share
        # 1 - k / K of their equations (K = n_large / n_small), and their errors correlate
        # about as much; the low-pass follows a geometric decay corr^k, the one with the
        # same sum over k (what the variance of an average of solves depends on)
        k_buf = max(buffer.n_large / max(buffer.n_small, 1), 1.0)
        corr = (k_buf - 1.0) / (k_buf + 1.0)
        # while the buffer holds the whole stream, every solution so far came from a subset
        # of the buffer this one is solved from: it replaces them (averaging in the early,
        # short-buffer solutions with equal weights would only add their noise)
        self.lam = resolve(buffer.sums, self.estimate, self.config, left=buffer.left,
                           overlap=overlap, replace=buffer.holds_all, corr=corr)
        self.n_updates += 1
        buffer.since_resolve = 0

    def _overlap(self) -> float:
        """The small buffers each event lies in (consecutive small buffers share their
        events: a solve divides its degrees of freedom by this)."""
        return max(1.0, self.n_equations * self.buffer.n_small / max(self.buffer_events, 1))

    def error_scale(self) -> ErrorScale:
        """The factors that calibrate the solves' own standard errors
        (:func:`~evcal.onei.stderr.error_scales`), measured on the buffer at most every
        :attr:`SCALE_EVERY` updates: they are ratios of two formulas on the same equations,
        which move with the scene's statistics, not from one update to the next, and a
        measurement costs a service's update frame as much as its solve."""
        if self.config.history > 0:
            return identity("the solves include a forgotten history the buffer no longer "
                            "holds")
        key = (self.n_sessions, self.log_offset)
        cached = self._scale
        if (cached is not None and cached[0] == key
                and self.n_updates - cached[1] < self.SCALE_EVERY):
            return cached[2]
        buffer, est = self.buffer, self.estimate
        scale = error_scales(buffer.frames, buffer.base, est.se_c, est.se_b, est.seen,
                             self.lam, self.log_offset, self.config.saturation_dn,
                             self._overlap())
        self._scale = (key, self.n_updates, scale)
        return scale

    # -- output -------------------------------------------------------------------------------

    def calibration(self) -> Calibration:
        """The current smoothed estimate (defaults where no valid solution was seen yet).

        The maps are copies: the result does not change when the calibrator goes on.
        """
        shape = self.sensor.shape
        scale = self.error_scale() if self.n_updates else identity("no update yet")
        diagnostics = replace(self.diagnostics(), stderr_calibration=scale.info)
        return Calibration(
            **self.estimate.maps(shape, self.executor.on_pixels, scale=(scale.c, scale.b)),
            log_offset=self.log_offset,
            method="onei",
            n_events=self.buffer.sums.counts.reshape(shape).copy(),
            diagnostics=diagnostics,
        )

    def diagnostics(self) -> OnEIDiagnostics:
        """The figures of :meth:`status` and the configuration, as typed diagnostics."""
        status = self.status()
        for live in ("n_small_target", "waiting_for"):  # the service's, not a result's
            status.pop(live)
        return OnEIDiagnostics(config=json.loads(self.config.to_json()),
                               log_offset_estimation=dict(self.offset_info), **status)

    def status(self) -> dict[str, Any]:
        return {
            "n_updates": self.n_updates,
            "n_events": self.n_events,
            "n_frames": self.n_frames,
            "buffer_events": self.buffer_events,
            "buffer_frames": len(self.buffer.frames),
            "buffer_equations": self.n_equations,
            "buffer_bytes": self.buffer_bytes,
            "pending_events": self.buffer.intake.n_waiting,
            "refolds": self.n_refolds,
            "folded_late_events": self.n_folded_late,
            "late_events": self.n_late_events,
            "gaps": self.n_gaps,
            "sessions": self.n_sessions,
            "residual_lambda": self.lam,
            "n_small": self.buffer.n_small,  # now (a growing small buffer: see the target)
            "n_small_target": self.n_small,
            "n_large": self.n_large,
            "waiting_for": self.waiting_for(),
            "last_frame_t_us": self.last_frame_t_us,
            "log_offset": self.log_offset,
            "log_offset_state": self.offset_state,
        }

    def waiting_for(self) -> str | None:
        """Why there is no calibration yet and what would give one (None after the first
        update), with the figures, e.g. "2 frames needed, 1 received"."""
        if self.n_updates:
            return None
        buffer, wf = self.buffer, self.config.window_frames
        if self.n_frames < 2:
            return (f"OnEI needs frames: 2 at least, {self.n_frames} received (events between "
                    "two frames make an equation)")
        if not self.offset.known:
            return (f"the log offset is being estimated from the frames and events "
                    f"({self.offset_state}; {self.n_frames} frames received): it needs "
                    f"{OnlineOffset.FIRST_FRAMES + OnlineOffset.LAG_FRAMES} frames and pixels "
                    "whose events follow the frames' changes (a moving camera or scene); or "
                    "give the offset (--log-offset)")
        if wf and len(buffer.frames) <= wf:
            return (f"each equation spans {wf} frame intervals: {wf + 1} buffered frames "
                    f"needed, {len(buffer.frames)} held")
        grows = (f", growing to {self.n_small:,} with the events received"
                 if self.config.grows and buffer.n_small < self.n_small else "")
        return (f"{buffer.n_small:,} events needed per small buffer{grows}, "
                f"{buffer.since_resolve:,} received between the buffered frames "
                f"({self.n_events:,} in all): send more events (a moving camera), or a "
                "smaller --n-small")

    # -- persistence (the format: evcal.onei.state) ------------------------------------------

    def state_dict(self) -> dict[str, np.ndarray]:
        """Everything needed to resume, as numpy arrays (``np.savez``-able)."""
        return state_format.state_dict(self)

    @classmethod
    def from_state(cls, state: dict[str, np.ndarray], *,
                   executor: OnEIExecutor | None = None) -> OnlineCalibrator:
        """Rebuild a calibrator from :meth:`state_dict` (on ``executor``, else its own).

        Raises :class:`~evcal.errors.StateError` if the state is not one or is inconsistent.
        """
        return state_format.from_state(cls, state, executor)


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
    config = config or OnEIConfig()
    fitted = config.fitted(rec.sensor, rec.n_events)  # the small buffer sized at once
    history: list[tuple[int, np.ndarray, np.ndarray, np.ndarray]] = []
    with OnlineCalibrator(rec.sensor, fitted) as state:
        for k, chunk in frame_intervals(rec.events, rec.frames.t_us):
            t = int(rec.frames.t_us[k])
            state.feed_events(chunk, checked=True)  # a Recording's events are validated
            updated = state.feed_frame(t, rec.frames.images[k])
            if updated and history_every and state.n_updates % history_every == 0:
                cur = state.calibration()
                history.append((t, cur.contrast.copy(), cur.bias.copy(), cur.valid.copy()))
        cal = state.calibration()
        assert isinstance(cal.diagnostics, OnEIDiagnostics)
        diagnostics: Diagnostics = replace(cal.diagnostics, history=tuple(history))
    target = config.sizes(rec.sensor)[0]
    if fitted.n_small is not None and fitted.n_small < target:
        diagnostics = diagnostics.with_warning(
            f"OnEI's small buffer fitted to the recording: {fitted.n_small:,} events (1/"
            f"{GROW_DIVISOR} of its {rec.n_events:,}); the paper's 200 k at 240x180 scaled "
            f"to {rec.sensor} is {target:,}, more than the recording holds per buffer")
    if state.n_updates == 0:
        diagnostics = diagnostics.with_warning(
            f"OnEI made no update: {state.waiting_for()}; or use OffEI")
    return cal.replace(diagnostics=diagnostics)
