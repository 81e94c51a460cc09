"""One camera as a pure state machine: decoded messages in, output records out.

:class:`CameraState` holds everything the service knows of one camera — its
:class:`~evcal.stream.StreamGuard` (sensor, sequence numbers, time order), its
:class:`~evcal.online.OnlineCalibrator`, its counters and its latest calibration — and nothing
else: no threads, no locks, no network, no reference to the service. The ingest layer
(:mod:`evcal.service.ingest`) calls :meth:`CameraState.on_events` and
:meth:`CameraState.on_frame` from one thread per camera and hands the returned records
(:class:`CalibrationUpdate`, :class:`Rejection`, :class:`Observed`) to the outputs layer
(:mod:`evcal.service.outputs`), which encodes and publishes them. Wall-clock times come in as
arguments, so every rule here is tested without threads or sleeps.
"""

from __future__ import annotations

import json
import logging
import time
from collections import deque
from dataclasses import asdict, dataclass, field, replace
from typing import Any

import numpy as np

from ..calibration import Calibration
from ..errors import CalibrationError, ErrorReason, EvcalError, StateError
from ..events import SensorSize
from ..fusion import FUSABLE, fuse, kept
from ..io.wire import encode_calibration
from ..offe import OffEConfig, StreamingOffE
from ..online import OnEIConfig, OnEIExecutor, OnlineCalibrator
from ..posterior import POSTERIOR_METHODS, LivePosterior, estimate_of, posterior_maps
from ..stream import DuplicateMessage, LateMessage, StreamGuard

log = logging.getLogger("evcal.service")

STATE_FORMAT = "evcal.service.camera.v1"
# the steps of status.latency_ms.parts_median, in order
LATENCY_PARTS = ("queue", "estimator", "calibration", "encode", "publish")

DecodedEvents = tuple[np.ndarray, dict[str, Any]]
DecodedFrame = tuple[int, int, np.ndarray, dict[str, Any]]


class Rejected(EvcalError):
    """An input message refused with a reason code (counted, published on ``errors``)."""

    default_reason = ErrorReason.REJECTED


# ----------------------------------------------------------------------------- output records


@dataclass(frozen=True)
class CalibrationUpdate:
    """A new calibration to publish (the message is encoded once, here)."""

    camera: str
    t_us: int  # sensor time of the frame that triggered it (events-only: its latest event)
    seq: int  # calibration stream counter
    calibration: Calibration
    message: bytes
    t_recv_s: float  # monotonic arrival of the frame
    t_start_s: float  # monotonic start of its processing
    t_fed_s: float  # OnEI done
    t_cal_s: float  # maps built
    t_enc_s: float  # encoded
    from_frame: bool = True  # triggered by a frame (else between frames: no latency)
    # maps beside the calibration's, in the message too (io.wire.EXTRA_MAP_DTYPES): the
    # events-only estimate's noise_rate_hz
    extra_maps: dict[str, np.ndarray] = field(default_factory=dict)


@dataclass(frozen=True)
class Rejection:
    """A refused input (already counted in the camera's counters)."""

    camera: str
    stream: str  # "events" | "frames"
    reason: str
    message: str


@dataclass(frozen=True)
class Observed:
    """A call for the recorder (``events``, ``frame`` or ``updated``), in stream order."""

    method: str
    args: tuple[Any, ...]


Output = CalibrationUpdate | Rejection | Observed


# ----------------------------------------------------------------------------- counters


class RateWindow:
    """Events per second of wall time over the last ``window_s``."""

    def __init__(self, window_s: float = 2.0) -> None:
        self.window_s = window_s
        self._items: deque[tuple[float, int]] = deque()
        self._sum = 0

    def add(self, t: float, n: int) -> None:
        self._items.append((t, n))
        self._sum += n
        self._prune(t)

    def _prune(self, now: float) -> None:
        while self._items and self._items[0][0] < now - self.window_s:
            self._sum -= self._items.popleft()[1]

    def rate(self, now: float) -> float:
        self._prune(now)
        return self._sum / self.window_s


def _per_stream() -> dict[str, int]:
    return {"events": 0, "frames": 0}


@dataclass
class Counters:
    """Everything counted per camera (published in ``status``, kept in snapshots).

    ``events`` counts events and ``event_messages`` messages; ``dropped`` counts messages the
    service's own queue refused, ``lost`` messages missing in the publisher's sequence numbers
    that never arrived (a refused message arrived: it is in ``errors``, not here; so is an
    exact copy of an accepted message, under ``duplicate``).
    """

    events: int = 0
    event_messages: int = 0
    frames: int = 0
    updates: int = 0
    bytes_in: int = 0
    dropped: dict[str, int] = field(default_factory=_per_stream)
    lost: dict[str, int] = field(default_factory=_per_stream)
    seq_restarts: dict[str, int] = field(default_factory=_per_stream)
    restarts: dict[str, int] = field(default_factory=_per_stream)  # new sessions
    # messages between the snapshot a restart resumed from and the first message after it:
    # processed by the process that died after its last snapshot (their effect went with
    # it) or sent while nobody served the camera; counted here, not as lost
    rolled_back: dict[str, int] = field(default_factory=_per_stream)
    restores: int = 0  # restarts that resumed from a snapshot (with or without a rollback)
    errors: dict[str, int] = field(default_factory=dict)
    errors_published: int = 0
    errors_suppressed: int = 0

    @property
    def errors_total(self) -> int:
        return int(sum(self.errors.values()))


# ----------------------------------------------------------------------------- the camera


class CameraState:
    """One camera's stream checks, OnEI state, counters and latest calibration."""

    def __init__(self, camera_id: str, *, onei: OnEIConfig | None = None,
                 max_pixels: int | None = None, observe: bool = False,
                 offe: OffEConfig | None = None, offe_period_us: int = 1_000_000,
                 executor: OnEIExecutor | None = None,
                 posterior_refresh_us: int | None = None, event_timing: bool = False) -> None:
        self.id = camera_id
        self.onei = onei or OnEIConfig()
        # OnEI's threads, shared by the service's cameras and closed by the service (None:
        # each calibrator makes and closes its own)
        self.executor = executor
        # events-only cameras: streaming OffE until the camera's first frame (then OnEI),
        # an update every offe_period_us of sensor time
        self.offe_config = offe or OffEConfig()
        self.offe_period_us = int(offe_period_us)
        self.events_only: StreamingOffE | None = None
        self._offe_next_t_us: int | None = None
        self._offe_pending = False  # events fed since its latest update
        # event timing (serve --event-timing): a camera with frames keeps OffE's sums of
        # every event too (the events-only sums go on when its first frame comes), and each
        # OnEI update is fused with OffE's maps (evcal.fusion), those taken afresh every
        # offe_period_us of sensor time
        self.event_timing = bool(event_timing)
        self.timing: StreamingOffE | None = None
        self.timing_maps: Calibration | None = None  # OffE's latest maps of self.timing
        self.timing_maps_t_us: int | None = None  # the sensor time they were taken at
        self.timing_reason: str | None = None  # why the latest update was not fused
        self.guard = StreamGuard(max_pixels=max_pixels)
        self.calibrator: OnlineCalibrator | None = None
        self.counters = Counters()
        self.calibration_seq = 0  # the next calibration message's seq
        self.calibration_msg: bytes | None = None  # last published, all fields
        self.calibration_t_us: int | None = None
        self.calibration: Calibration | None = None
        self.extra_maps: dict[str, np.ndarray] = {}  # of the latest calibration
        # posterior maps (serve --posterior): OnEI's updates are published as posterior
        # maps, priors refreshed every posterior_refresh_us of sensor time; the raw estimate
        # of the latest update stays here for queries (estimate=raw; not kept in snapshots)
        # (the priors' refresh on OnEI's worker thread, the pass on its pixel threads)
        self.live_posterior = (
            LivePosterior(posterior_refresh_us,
                          split=executor.split if executor is not None else None,
                          submit=executor.submit if executor is not None else None)
            if posterior_refresh_us is not None else None)
        self.raw_calibration: Calibration | None = None
        # the posterior a query asked for while the published maps are raw, by update seq:
        # at most one computation per update however many queries come
        self.posterior_cache: tuple[int, Calibration] | None = None
        self.last_update_wall: float | None = None
        self.latency_ms: deque[float] = deque(maxlen=200)
        self.latency_parts_ms: deque[tuple[float, ...]] = deque(maxlen=200)
        self.latency_t_us: deque[int] = deque(maxlen=200)  # the frame of each
        self.rate = RateWindow()
        self.dirty = False  # changed since the last snapshot
        self.observe = observe  # emit Observed records for a recorder
        self.frame_dtype: np.dtype[Any] | None = None  # fixed by the first frame
        # per stream, since its last accepted message: messages this service dropped or
        # refused before reading their sequence number; a gap of that many is not upstream
        # loss
        self._not_lost = {"events": 0, "frames": 0}
        # after a restore, the first message of each stream tells how many were rolled back
        self._after_restore: set[str] = set()
        self.restored: dict[str, Any] | None = None  # what the last restore resumed from

    @property
    def sensor(self) -> SensorSize | None:
        return self.guard.sensor

    def on_probation(self, *, min_frames: int, min_events: int) -> bool:
        """Whether this camera has not yet sent enough to matter: no calibration (published
        or restored) and fewer than ``min_frames`` frames or ``min_events`` events accepted.
        A camera on probation may lose its slot to a new camera (``Service``)."""
        c = self.counters
        return self.calibration_msg is None and (c.frames < min_frames
                                                 or c.events < min_events)

    # -- inputs --------------------------------------------------------------------------------

    def _accept(self, kind: str, header: dict[str, Any], t_first: int | None,
                t_last: int | None, drops_before: int) -> OnlineCalibrator:
        """The stream checks of one message (:meth:`StreamGuard.accept`: sensor, time, sequence
        number) and what they imply for OnEI: a new calibrator for the first message or a new
        sensor, a new session (buffers emptied) for a new time base, a gap for lost events.
        A copy of a recent message is refused as a ``duplicate``, without changing anything."""
        what = f"{'events' if kind == 'events' else 'frame'} message seq {header['seq']}"
        c = self.counters
        self._not_lost[kind] += drops_before
        try:
            check = self.guard.accept(kind, t_first_us=t_first, t_last_us=t_last, what=what,
                                      seq=header["seq"], size=(header["height"],
                                                               header["width"]))
        except DuplicateMessage as exc:
            # a message of the stream arrived twice: dropped, neither a new session nor loss
            raise Rejected(str(exc), ErrorReason.DUPLICATE) from None
        except LateMessage as exc:
            # counted lost when the gap showed; it arrived (refused), so it is not lost
            c.lost[kind] = max(0, c.lost[kind] - exc.recovered)
            raise Rejected(str(exc), exc.reason) from None
        except EvcalError as exc:
            raise Rejected(str(exc), exc.reason) from None
        sensor = self.guard.sensor
        assert sensor is not None  # accept() fixed it
        not_lost, self._not_lost[kind] = self._not_lost[kind], 0
        if check.recovered:
            c.lost[kind] = max(0, c.lost[kind] - check.recovered)
        if self.calibrator is None or check.new_sensor:
            if check.new_sensor:
                # the old sensor's calibration does not describe this one
                self.calibration = self.calibration_msg = None
                self.raw_calibration = self.posterior_cache = None
                if self.live_posterior is not None:
                    self.live_posterior.reset()
                self.extra_maps = {}
                c.restarts[kind] += 1
            # live: the online log offset is taken when it is ready, no frame waits for it
            self.calibrator = OnlineCalibrator(sensor, replace(self.onei, offset_wait=False),
                                               executor=self.executor)
            self.frame_dtype = None
            self._start_events_only(sensor)
            self._start_timing(sensor)
            log.info("camera %s: %s sensor", self.id, sensor)
        elif check.new_session:
            self.calibrator.new_session()
            self.frame_dtype = None
            if self.events_only is not None:
                # its step grid is in the old time base
                self._start_events_only(sensor)
            self._start_timing(sensor)
            c.restarts[kind] += 1
            log.info("camera %s: a new session of its %s stream (time base changed)", self.id,
                     kind)
        lost = check.lost
        if kind in self._after_restore:
            self._after_restore.discard(kind)
            if self.restored is not None:
                self.restored["rolled_back"][kind] = lost
            if lost:  # the gap since the snapshot: rolled back, not lost (still a gap)
                c.rolled_back[kind] += lost
                log.warning("camera %s: %d %s message(s) rolled back: processed after the "
                            "snapshot it resumed from, or sent while it was not served",
                            self.id, lost, kind)
                lost = 0
        if lost:
            # the gap minus the messages this service dropped or refused unread: upstream loss
            c.lost[kind] += max(0, lost - not_lost)
        if check.restart:
            c.seq_restarts[kind] += 1
        if (check.lost or check.restart) and kind == "events" and not check.new_session:
            # events went missing: no OnEI equation may span this interval
            self.calibrator.mark_gap()
        return self.calibrator

    def on_events(self, decoded: DecodedEvents, nbytes: int, *, now_s: float,
                  drops_before: int = 0) -> list[Output]:
        """A decoded events message (the decoder validated the chunk against its header's
        size); raises :class:`Rejected`."""
        ev, header = decoded
        t = ev["t_us"]
        cal = self._accept("events", header, int(t[0]) if t.size else None,
                           int(t[-1]) if t.size else None, drops_before)
        out: list[Output] = []
        if self.events_only is None:
            cal.feed_events(ev, checked=True)
            if self.timing is not None:
                self.timing.feed_events(ev)
        elif ev.size:
            # no frame yet: OnEI would only hold these events pending (up to
            # max_pending_events, 260 MB) for a first frame that may never come
            upd = self._feed_events_only(ev, now_s)
            if upd is not None:
                out.append(upd)
        c = self.counters
        c.events += int(ev.size)
        c.event_messages += 1
        c.bytes_in += nbytes
        self.rate.add(now_s, int(ev.size))
        self.dirty = True
        if self.observe and ev.size:
            out.append(Observed("events", (self.id, ev)))
        return out

    def _start_events_only(self, sensor: SensorSize) -> None:
        """A fresh events-only estimate, unless the camera has sent frames (OnEI's)."""
        if self.counters.frames == 0:
            self.events_only = StreamingOffE(sensor, self.offe_config)
            self._offe_next_t_us = None

    def _start_timing(self, sensor: SensorSize) -> None:
        """Fresh event-timing sums for a camera with frames (with --event-timing); a camera
        without frames yet has them in its events-only sums, which its first frame hands on."""
        self._set_timing(StreamingOffE(sensor, self.offe_config)
                         if self.event_timing and self.events_only is None else None)

    def _set_timing(self, sums: StreamingOffE | None) -> None:
        """``sums`` as the event-timing state, with no OffE maps of it taken yet."""
        self.timing, self.timing_maps = sums, None
        self.timing_maps_t_us = self.timing_reason = None

    def _feed_events_only(self, ev: np.ndarray, now_s: float) -> CalibrationUpdate | None:
        """Events of a camera without frames: into the streaming OffE sums; an update once
        ``offe_period_us`` of sensor time has passed since the previous one (none while no
        pixel has enough events for its regression)."""
        est = self.events_only
        assert est is not None
        t_start = time.monotonic()
        est.feed_events(ev)
        self._offe_pending = True
        t_last = int(ev["t_us"][-1])
        if self._offe_next_t_us is None:
            assert est.t0_us is not None
            self._offe_next_t_us = est.t0_us + self.offe_period_us
        if t_last < self._offe_next_t_us:
            return None
        self._offe_next_t_us = t_last + self.offe_period_us
        return self._events_only_update(now_s, t_start)

    def _events_only_update(self, now_s: float, t_start: float) -> CalibrationUpdate | None:
        """The events-only estimate of the events so far, at its latest event's time."""
        est = self.events_only
        assert est is not None
        assert est.last_t_us is not None
        self._offe_pending = False
        t_fed = time.monotonic()
        try:
            cal = est.calibration()
        except CalibrationError as exc:
            log.debug("camera %s: no events-only calibration yet: %s", self.id, exc)
            return None
        # the per-pixel event rate: on a still scene, the pixels' noise (background
        # activity) rate, the figure an events-only rig is characterised by
        noise = est.event_rate_hz().astype(np.float32)
        return self._publishable(cal, est.last_t_us, now_s, t_start, t_fed, from_frame=False,
                                 extra_maps={"noise_rate_hz": noise})

    def on_frame(self, decoded: DecodedFrame, nbytes: int, *, t_recv_s: float,
                 t_start_s: float, drops_before: int = 0) -> list[Output]:
        """A decoded frame message; raises :class:`Rejected`."""
        t_us, exposure_us, image, header = decoded
        what = f"frame message seq {header['seq']}"
        cal = self._accept("frames", header, t_us, t_us, drops_before)
        if self.frame_dtype is not None and image.dtype != self.frame_dtype:
            raise Rejected(f"{what}: a {image.dtype} frame, but this camera's frames are "
                           f"{self.frame_dtype}", ErrorReason.MALFORMED)
        self.frame_dtype = image.dtype
        try:
            updated = cal.feed_frame(t_us, image, exposure_us, checked=True)
        except EvcalError as exc:
            raise Rejected(f"{what}: {exc}", ErrorReason.REJECTED) from None
        if self.events_only is not None:
            # frames came: OnEI takes over (its first update replaces the events-only one)
            log.info("camera %s: frames arrived, moving from the events-only estimate to "
                     "OnEI", self.id)
            if self.event_timing:  # the same sums: every event since the start
                self._set_timing(self.events_only)
            self.events_only = None
            self._offe_next_t_us = None
        out: list[Output] = []
        if updated:
            out.append(self._update(cal, t_us, t_recv_s, t_start_s))
        self.counters.frames += 1
        self.counters.bytes_in += nbytes
        self.dirty = True
        if self.observe:
            out.append(Observed("frame", (self.id, t_us, image)))
        return out

    def on_idle(self, *, now_s: float) -> list[Output]:
        """Between messages (the worker found its queue empty): an online log-offset
        estimate finished since the last frame is taken now, and its calibration published
        (a stream that stopped, or a replay that outran the estimate, is not left without
        one). So is the events-only estimate of the events that came since its latest update:
        a stream that stopped between two periods is not left without its last events."""
        if self.events_only is not None and self._offe_pending:
            upd = self._events_only_update(now_s, time.monotonic())
            return [upd] if upd is not None else []
        cal = self.calibrator
        if cal is None or cal.last_frame_t_us is None or not cal.poll_offset():
            return []
        return [self._update(cal, cal.last_frame_t_us, now_s, now_s, from_frame=False)]

    def _update(self, cal_state: OnlineCalibrator, t_us: int, t_recv_s: float,
                t_start_s: float, *, from_frame: bool = True) -> CalibrationUpdate:
        """The calibration of the update a frame triggered, built and encoded once: the
        published message, the query cache and the recorder share it."""
        t_fed = time.monotonic()
        cal = cal_state.calibration()
        if self.timing is not None and cal.method in FUSABLE:
            cal = self._fused(cal, t_us)
        raw = None
        if self.live_posterior is not None and cal.method in POSTERIOR_METHODS:
            raw, cal = cal, self.live_posterior.apply(cal, t_us)
        return self._publishable(cal, t_us, t_recv_s, t_start_s, t_fed, from_frame=from_frame,
                                 raw=raw)

    def _fused(self, cal: Calibration, t_us: int) -> Calibration:
        """OnEI's maps fused with OffE's of the same events (:func:`evcal.fusion.fuse`);
        OffE's maps taken again once ``offe_period_us`` of sensor time has passed since they
        were (a new time base starts the sums afresh), OnEI's kept, and why, while OffE has
        none."""
        est = self.timing
        assert est is not None
        last = self.timing_maps_t_us
        if last is None or t_us >= last + self.offe_period_us:
            try:
                self.timing_maps = est.calibration()
                self.timing_reason = None
            except CalibrationError as exc:  # too few events or steps yet
                self.timing_maps, self.timing_reason = None, f"no OffE maps yet: {exc}"
            self.timing_maps_t_us = t_us
        if self.timing_maps is None:
            return kept(cal, {"pixels": 0, "valid": int(cal.valid.sum()),
                              "offe_maps_t_us": None},
                        self.timing_reason or "no OffE maps yet")
        out = fuse(cal, self.timing_maps)
        info = {**out.diagnostics.extra["fusion"], "offe_maps_t_us": self.timing_maps_t_us}
        self.timing_reason = info.get("reason")
        return out.replace(diagnostics=out.diagnostics.updated(
            extra={**out.diagnostics.extra, "fusion": info}))

    def _publishable(self, cal: Calibration, t_us: int, t_recv_s: float, t_start_s: float,
                     t_fed: float, *, from_frame: bool,
                     extra_maps: dict[str, np.ndarray] | None = None,
                     raw: Calibration | None = None) -> CalibrationUpdate:
        """``cal`` (with ``extra_maps``) encoded once, as this camera's latest calibration;
        ``raw``: the raw estimate ``cal`` holds the posterior of."""
        t_cal = time.monotonic()
        extra = extra_maps or {}
        msg = encode_calibration(cal, t_us=t_us, seq=self.calibration_seq, extra_maps=extra)
        t_enc = time.monotonic()
        upd = CalibrationUpdate(self.id, t_us, self.calibration_seq, cal, msg, t_recv_s,
                                t_start_s, t_fed, t_cal, t_enc, from_frame, extra)
        self.calibration_seq += 1
        self.calibration = cal
        self.raw_calibration = raw
        self.posterior_cache = None
        self.extra_maps = extra
        self.calibration_msg = msg
        self.calibration_t_us = t_us
        self.last_update_wall = time.time()
        self.counters.updates += 1
        self.dirty = True  # also an update between frames (on_idle): the snapshot must keep it
        return upd

    def published(self, upd: CalibrationUpdate, t_pub_s: float) -> None:
        """Record the latency of a published update (the outputs layer calls this)."""
        if not upd.from_frame:
            return
        self.latency_ms.append((t_pub_s - upd.t_recv_s) * 1e3)
        self.latency_t_us.append(upd.t_us)
        # where the time went: queue wait, OnEI (fold + re-solve), maps, encode, publish
        self.latency_parts_ms.append((upd.t_start_s - upd.t_recv_s, upd.t_fed_s - upd.t_start_s,
                                      upd.t_cal_s - upd.t_fed_s, upd.t_enc_s - upd.t_cal_s,
                                      t_pub_s - upd.t_enc_s))

    def reject_unread(self, stream: str, exc: EvcalError, drops_before: int = 0
                      ) -> Rejection:
        """Count an input refused before its sequence number was read (undecodable, too
        large): with the messages dropped just before it, the next gap of its stream does not
        count it as lost."""
        self._not_lost[stream] += drops_before + 1
        return self.reject(stream, exc)

    def reject(self, stream: str, exc: EvcalError) -> Rejection:
        """Count a refused input; the record says what to publish."""
        reason = str(exc.reason)
        self.counters.errors[reason] = self.counters.errors.get(reason, 0) + 1
        return Rejection(self.id, stream, reason, str(exc))

    # -- read-outs -----------------------------------------------------------------------------

    def latency_parts(self) -> dict[str, float] | None:
        """Median ms of each step between a frame's arrival and its calibration's publication
        (over the last 200 updates)."""
        if not self.latency_parts_ms:
            return None
        med = np.median(np.asarray(self.latency_parts_ms, np.float64), axis=0) * 1e3
        return {name: float(v) for name, v in zip(LATENCY_PARTS, med, strict=True)}

    def slowest_update(self) -> dict[str, Any] | None:
        """The slowest of the last 200 updates: its frame's time, total and steps (ms)."""
        if not self.latency_ms:
            return None
        i = int(np.argmax(np.asarray(self.latency_ms)))
        parts = self.latency_parts_ms[i]
        return {"t_us": int(self.latency_t_us[i]), "total": float(self.latency_ms[i]),
                "parts": {name: float(v) * 1e3
                          for name, v in zip(LATENCY_PARTS, parts, strict=True)}}

    def calibration_as(self, estimate: str) -> Calibration:
        """The latest calibration holding ``estimate`` (``"raw"`` or ``"posterior"``),
        whichever the published maps hold; raises :class:`Rejected`. Raw maps of published
        posterior ones are those of the latest update (not kept across a restore); posterior
        maps of published raw ones are computed on demand, once per update."""
        cal = self.current_calibration()
        if cal is None:
            raise Rejected(f"camera {self.id!r} has no calibration yet",
                           ErrorReason.NO_CALIBRATION)
        held = estimate_of(cal)
        if held == estimate:
            return cal
        if estimate == "raw":
            if self.raw_calibration is None:
                raise Rejected(f"camera {self.id!r}: the raw maps of its latest calibration "
                               "are not kept across a restart of the service; its next "
                               "update has them", ErrorReason.NO_CALIBRATION)
            return self.raw_calibration
        if cal.method not in POSTERIOR_METHODS:
            raise Rejected(f"camera {self.id!r}: estimate=posterior needs calibrated standard "
                           f"errors ({', '.join(POSTERIOR_METHODS)}); its calibration is "
                           f"{cal.method}'s", ErrorReason.BAD_QUERY)
        seq = self.calibration_seq
        if self.posterior_cache is None or self.posterior_cache[0] != seq:
            self.posterior_cache = (seq, posterior_maps(cal))
        return self.posterior_cache[1]

    def current_calibration(self) -> Calibration | None:
        """The latest calibration (rebuilt from the stored message after a restore)."""
        if self.calibration is None and self.calibration_msg is not None:
            from ..io.wire import EXTRA_MAP_DTYPES, decode_calibration_maps  # noqa: PLC0415

            maps, header = decode_calibration_maps(self.calibration_msg)
            self.calibration = Calibration.from_maps(
                maps, log_offset=header["log_offset"], method=header["method"],
                diagnostics=header["params"])
            self.extra_maps = {k: v for k, v in maps.items() if k in EXTRA_MAP_DTYPES}
        return self.calibration

    # -- snapshots -----------------------------------------------------------------------------

    def state_arrays(self) -> dict[str, np.ndarray] | None:
        """Everything to resume this camera (None before its first message)."""
        if self.calibrator is None:
            return None
        meta = {
            "format": STATE_FORMAT, "camera": self.id, "sensor": str(self.sensor),
            "next_seq": self.guard.next_seq, "guard": self.guard.state(),
            "calibration_seq": self.calibration_seq,
            "calibration_t_us": self.calibration_t_us, "counters": asdict(self.counters),
            "saved_wall": time.time(),
        }
        arrays = {f"est__{k}": v for k, v in self.calibrator.state_dict().items()}
        if self.events_only is not None:
            arrays.update({f"offe__{k}": v for k, v in self.events_only.state_dict().items()})
        if self.timing is not None:
            arrays.update({f"timing__{k}": v for k, v in self.timing.state_dict().items()})
        arrays["service_json"] = np.array(json.dumps(meta))
        arrays["calibration_msg"] = np.frombuffer(self.calibration_msg or b"", np.uint8)
        return arrays

    def restore(self, arrays: dict[str, np.ndarray]) -> None:
        """Resume from :meth:`state_arrays` (:class:`~evcal.errors.StateError` if it is not a
        snapshot of this version)."""
        try:
            meta = json.loads(str(arrays["service_json"]))
            if not isinstance(meta, dict) or meta.get("format") != STATE_FORMAT:
                raise StateError(f"unknown snapshot format "
                                 f"{meta.get('format') if isinstance(meta, dict) else meta!r}")
            est = {k[5:]: v for k, v in arrays.items() if k.startswith("est__")}
            # the sensor is checked against the limits before anything is allocated for it
            scalars = json.loads(str(est["scalars"]))
            h, w = int(scalars["height"]), int(scalars["width"])
            limit = self.guard.max_pixels
            if not (0 < h <= 65535 and 0 < w <= 65535) or (limit is not None
                                                            and h * w > limit):
                raise StateError(f"the snapshot's {w}x{h} sensor exceeds the limit of "
                                 f"{limit} pixels (--max-pixels) or 65535x65535")
            calibrator = OnlineCalibrator.from_state(est, executor=self.executor)
            if "guard" in meta:
                guard = StreamGuard.from_state(meta["guard"], max_pixels=self.guard.max_pixels)
            else:  # snapshots written before the guard was saved
                guard = StreamGuard(calibrator.sensor, max_pixels=self.guard.max_pixels)
                guard.next_seq = {k: meta["next_seq"].get(k) for k in ("events", "frames")}
                guard.last_event_t_us = calibrator.last_event_t_us
                guard.last_frame_t_us = calibrator.last_frame_t_us
            guard.sensor = calibrator.sensor
            counters = Counters(**{k: meta["counters"][k] for k in Counters.__dataclass_fields__
                                   if k in meta["counters"]})
            events_only = None
            offe = {k[6:]: v for k, v in arrays.items() if k.startswith("offe__")}
            if offe:
                events_only = StreamingOffE.from_state(offe)
                if events_only.sensor != calibrator.sensor:
                    raise StateError(f"the events-only state is for a {events_only.sensor} "
                                     f"sensor, the camera's is {calibrator.sensor}")
            elif counters.frames == 0:  # snapshots written before the events-only estimate
                events_only = StreamingOffE(calibrator.sensor, self.offe_config)
            timing = None
            if self.event_timing and events_only is None:
                sums = {k[8:]: v for k, v in arrays.items() if k.startswith("timing__")}
                # a snapshot of a service without event timing: its sums start here
                timing = (StreamingOffE.from_state(sums) if sums
                          else StreamingOffE(calibrator.sensor, self.offe_config))
                if timing.sensor != calibrator.sensor:
                    raise StateError(f"the event-timing state is for a {timing.sensor} "
                                     f"sensor, the camera's is {calibrator.sensor}")
            calibration_seq = int(meta["calibration_seq"])
            calibration_t_us = meta["calibration_t_us"]
            msg = arrays["calibration_msg"].tobytes()
        except StateError:
            raise
        except Exception as exc:  # noqa: BLE001 - whatever is wrong, it is not a snapshot
            raise StateError(f"not a camera snapshot: {type(exc).__name__}: {exc}") from None
        self.calibrator, self.guard, self.counters = calibrator, guard, counters
        self.events_only, self._offe_next_t_us = events_only, None
        self._set_timing(timing)
        self.calibration_seq, self.calibration_t_us = calibration_seq, calibration_t_us
        self.calibration_msg = msg or None
        self.calibration = None
        self.extra_maps = {}  # current_calibration() reads them from the message
        self.raw_calibration = self.posterior_cache = None  # not in snapshots
        if self.live_posterior is not None:
            self.live_posterior.reset()
        now_wall = time.time()
        saved = meta.get("saved_wall")
        self.counters.restores += 1
        self._after_restore = {"events", "frames"}
        self.restored = {
            "snapshot_saved_wall": saved, "restored_wall": now_wall,
            "snapshot_age_s": (round(now_wall - float(saved), 3)
                               if isinstance(saved, int | float) else None),
            "events": counters.events, "event_messages": counters.event_messages,
            "frames": counters.frames, "calibration_t_us": calibration_t_us,
            # filled by the first message of each stream after the restore
            "rolled_back": {"events": None, "frames": None},
        }
