"""The calibration service without the network: per-camera queues, OnEI states and outputs.

:class:`Service` receives raw payloads (``on_sample``), keeps one :class:`Camera` per camera
id, and publishes through a ``publish(key, payload, encoding)`` callable; the zenoh glue is in
:mod:`evcal.service.server`. This module imports neither zenoh nor rerun, so every rule below
is tested without a network.

Threads: ``on_sample`` runs in the transport's receive thread and only copies the payload
into the camera's bounded queue; per camera, a decoder thread decodes and validates the wire
messages (numpy, mostly outside the GIL) and hands them to the camera's worker thread, at most
two messages ahead, which checks them against the camera's state, feeds the camera's
:class:`~evcal.online.OnlineCalibrator` and publishes. The recorder (if any) runs in a thread
of its own (:class:`ObserverThread`), after the publication and never holding it. Queries
read the camera's cached, already-encoded outputs and never wait for a worker.

Back-pressure (per camera, both input keys share the camera's queue of ``queue_bytes``):

- ``on_full="drop"`` (default): a message that does not fit is dropped and counted
  (``dropped``); the receive thread never waits, so one flooding camera cannot stall the
  others, the queryables or the liveliness token.
- ``on_full="block"``: the receive thread waits for room. With publishers using
  ``CongestionControl.BLOCK`` (``evcal replay`` does) this is lossless end to end: zenoh's
  flow control slows the publisher to the service's pace. It stalls the whole session's
  receive path (every camera and query) while any camera's queue is full.

Memory is bounded by ``max_cameras`` x (``queue_bytes`` + two decoded messages + one OnEI
state of at most ``max_pixels`` pixels) plus the recorder's queue (256 MiB of referenced
arrays at most); cameras beyond ``max_cameras`` and sensors beyond ``max_pixels`` are
rejected with an error.
"""

from __future__ import annotations

import json
import logging
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from typing import Any, Protocol

import numpy as np

from ..calibration import Calibration
from ..events import SensorSize
from ..io.wire import (
    WireError,
    decode_events,
    decode_frame,
    encode_calibration,
)
from ..online import OnEIConfig, OnlineCalibrator
from . import keys
from .state import StateStore

log = logging.getLogger("evcal.service")

PublishFn = Callable[[str, bytes, str], None]
MatchFn = Callable[[str, str], bool]  # (key expression, concrete key) -> intersects

ON_FULL = ("drop", "block")
_CAL_MAPS = ("contrast", "bias", "valid", "reason", "stderr_contrast", "stderr_bias", "special",
             "n_events")
# the steps of status.latency_ms.parts_median, in order
LATENCY_PARTS = ("queue", "estimator", "calibration", "encode", "publish")
STATE_FORMAT = "evcal.service.camera.v1"


@dataclass(frozen=True, kw_only=True)
class ServiceConfig:
    """Service parameters (sizes in bytes and pixels, periods in seconds)."""

    prefix: str = "evcal"
    cameras: str = "**"  # key expression of the camera ids this instance claims
    instance: str = ""  # name in the liveliness token; "" = the zenoh session id
    queue_bytes: int = 64 << 20
    on_full: str = "drop"
    max_cameras: int = 64
    max_pixels: int = 1280 * 1024
    max_message_bytes: int = 32 << 20
    status_period_s: float = 1.0
    snapshot_period_s: float = 30.0
    error_rate_hz: float = 20.0
    onei: OnEIConfig = field(default_factory=OnEIConfig)

    def __post_init__(self) -> None:
        if self.on_full not in ON_FULL:
            raise ValueError(f"on_full={self.on_full!r} must be one of {ON_FULL}")
        if not self.prefix.strip("/"):
            raise ValueError("prefix must not be empty")
        for name in ("queue_bytes", "max_cameras", "max_pixels", "max_message_bytes"):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"{name}={getattr(self, name)} must be >= 1")
        if self.max_message_bytes > self.queue_bytes:
            raise ValueError(f"max_message_bytes={self.max_message_bytes} exceeds "
                             f"queue_bytes={self.queue_bytes}: such a message could never be "
                             "queued")
        for name in ("status_period_s", "snapshot_period_s", "error_rate_hz"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name}={getattr(self, name)} must be > 0")


class Observer(Protocol):
    """What the service tells a recorder (the Rerun logger); every method may be a no-op.

    Calls come from one recorder thread (:class:`ObserverThread`), each camera's in stream
    order; ``discard(camera)`` follows calls of that camera that were dropped because the
    recorder fell behind (an open reconstruction window is then incomplete).
    """

    def events(self, camera: str, events: np.ndarray) -> None: ...
    def frame(self, camera: str, t_us: int, image: np.ndarray) -> None: ...
    def updated(self, camera: str, cal: Calibration, t_us: int, status: dict[str, Any]
                ) -> None: ...
    def discard(self, camera: str, dropped: int) -> None: ...
    def close(self) -> None: ...


# ----------------------------------------------------------------------------- queues


class BoundedQueue:
    """FIFO bounded by the total size of its items (``size_of``; 1 per item by default).

    ``put`` drops (returns False) or, with ``block``, waits for room when full; a single item
    larger than the bound is accepted when the queue is empty. After ``close`` puts fail and
    ``get`` still returns what is in, then None at once.
    """

    def __init__(self, limit: int, size_of: Callable[[Any], int] | None = None):
        self.limit = int(limit)
        self._size_of = size_of or (lambda item: 1)
        self.used = 0
        self._items: deque[Any] = deque()
        self._cond = threading.Condition()
        self.closed = False

    def put(self, item: Any, *, block: bool = True) -> bool:
        size = self._size_of(item)
        with self._cond:
            if block:
                while not self.closed and self.used + size > self.limit and self._items:
                    self._cond.wait(0.5)
            if self.closed or (self.used + size > self.limit and self._items):
                return False
            self._items.append(item)
            self.used += size
            self._cond.notify_all()
            return True

    def get(self, timeout_s: float) -> Any | None:
        with self._cond:
            if not self._items and not self.closed:
                self._cond.wait(timeout_s)
            if not self._items:
                return None
            item = self._items.popleft()
            self.used -= self._size_of(item)
            self._cond.notify_all()
            return item

    def __len__(self) -> int:
        return len(self._items)

    def close(self) -> None:
        with self._cond:
            self.closed = True
            self._cond.notify_all()


class CameraQueue(BoundedQueue):
    """A camera's input: ``(kind, payload, t_recv_s)`` bounded in payload bytes."""

    def __init__(self, max_bytes: int):
        super().__init__(max_bytes, lambda item: len(item[1]))

    @property
    def nbytes(self) -> int:
        return self.used


class ObserverThread:
    """Runs the observer's calls in a thread of its own, off the cameras' publication path.

    A camera worker only appends ``(method, args, nbytes)`` to a queue bounded by
    ``max_bytes`` of referenced arrays (the events, frames and maps are not copied: the worker
    never modifies them after the call); when the recorder falls behind, calls are dropped and
    counted (``dropped``), never waited for, and the observer is told with
    ``discard(camera, n)``.
    """

    def __init__(self, call: Callable[..., None], *, max_bytes: int = 256 << 20):
        self._call = call
        self._queue = BoundedQueue(max_bytes, lambda item: item[2])
        self.dropped = 0
        self._dropped_by_camera: dict[str, int] = {}
        self._lock = threading.Lock()  # one submitter at a time: discards stay in order
        self.thread = threading.Thread(target=self._run, name="evcal-recorder", daemon=True)
        self.thread.start()

    @property
    def nbytes(self) -> int:
        return self._queue.used

    @property
    def max_bytes(self) -> int:
        return self._queue.limit

    @max_bytes.setter
    def max_bytes(self, value: int) -> None:
        self._queue.limit = int(value)

    def submit(self, method: str, args: tuple[Any, ...], nbytes: int) -> bool:
        camera = str(args[0])
        with self._lock:
            if self._queue.closed:
                return False
            lost = self._dropped_by_camera.get(camera, 0)
            if lost and self._queue.put(("discard", (camera, lost), 0), block=False):
                del self._dropped_by_camera[camera]
            if self._queue.put((method, args, nbytes), block=False):
                return True
            if not self._queue.closed:
                self.dropped += 1
                self._dropped_by_camera[camera] = self._dropped_by_camera.get(camera, 0) + 1
            return False

    def _run(self) -> None:
        while True:
            item = self._queue.get(0.5)
            if item is None:
                if self._queue.closed:
                    return  # closed and drained
                continue
            method, args, _ = item
            self._call(method, *args)

    def close(self, timeout_s: float = 30.0) -> None:
        """Process what is queued, then stop the thread."""
        self._queue.close()
        self.thread.join(timeout_s)


# ----------------------------------------------------------------------------- errors


def classify_wire_error(message: str) -> str:
    """A short reason code for a :class:`WireError` message (see docs/WIRE.md)."""
    m = message
    if "not a valid msgpack" in m or "expected a msgpack map" in m or "empty message" in m:
        return "not_msgpack"
    if "unsupported version" in m:
        return "version"
    if "truncated" in m or "too long" in m:
        return "truncated"
    if "outside the" in m and "sensor" in m:
        return "out_of_sensor"
    if "not sorted" in m:
        return "unsorted"
    if "polarity" in m:
        return "bad_polarity"
    if "NaN or infinite" in m:
        return "bad_values"
    if "is outside" in m:
        return "out_of_range"
    return "malformed"


class Rejected(Exception):
    """An input message refused with a reason code (counted, published on ``errors``)."""

    def __init__(self, reason: str, message: str):
        super().__init__(message)
        self.reason = reason


# ----------------------------------------------------------------------------- one camera


class RateWindow:
    """Events per second of wall time over the last ``window_s``."""

    def __init__(self, window_s: float = 2.0):
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


@dataclass
class Counters:
    """Everything counted per camera (published in ``status``, kept in snapshots)."""

    events: int = 0
    event_messages: int = 0
    frames: int = 0
    updates: int = 0
    bytes_in: int = 0
    dropped: dict[str, int] = field(default_factory=lambda: {"events": 0, "frames": 0})
    lost: dict[str, int] = field(default_factory=lambda: {"events": 0, "frames": 0})
    seq_restarts: dict[str, int] = field(default_factory=lambda: {"events": 0, "frames": 0})
    errors: dict[str, int] = field(default_factory=dict)
    errors_published: int = 0
    errors_suppressed: int = 0

    @property
    def errors_total(self) -> int:
        return int(sum(self.errors.values()))


class Camera:
    """One camera: its queue, worker thread, OnEI state, counters and cached outputs."""

    def __init__(self, service: Service, camera_id: str):
        self.service = service
        self.id = camera_id
        cfg = service.config
        self.key_calibration = keys.camera_key(cfg.prefix, camera_id, "calibration")
        self.key_status = keys.camera_key(cfg.prefix, camera_id, "status")
        self.key_errors = keys.camera_key(cfg.prefix, camera_id, "errors")
        self.queue = CameraQueue(cfg.queue_bytes)
        # decoded messages for the worker: decoding runs at most 2 messages ahead of OnEI
        self.handoff = BoundedQueue(2)
        self.in_flight = 0  # messages queued, being decoded or processed
        self._flight_lock = threading.Lock()
        self.lock = threading.Lock()  # guards the calibrator against snapshots
        self.sensor: SensorSize | None = None
        self.calibrator: OnlineCalibrator | None = None
        self.counters = Counters()
        self.next_seq: dict[str, int | None] = {"events": None, "frames": None}
        self.calibration_seq = 0
        self.calibration_msg: bytes | None = None  # last published, all fields
        self.calibration_t_us: int | None = None
        self.calibration: Calibration | None = None
        self.last_update_wall: float | None = None
        self.latency_ms: deque[float] = deque(maxlen=200)
        self.latency_parts_ms: deque[tuple[float, ...]] = deque(maxlen=200)
        self.rate = RateWindow()
        self.started_wall = time.time()
        self.dirty = False  # changed since the last snapshot
        self._err_tokens = cfg.error_rate_hz
        self._err_last = time.monotonic()
        self._stop = threading.Event()
        self.decoder = threading.Thread(target=self._decode_loop,
                                        name=f"evcal-dec-{camera_id}", daemon=True)
        self.thread = threading.Thread(target=self._run, name=f"evcal-cam-{camera_id}",
                                       daemon=True)

    # -- input side (receive thread) -----------------------------------------------------

    def enqueue(self, kind: str, payload: bytes, t_recv: float) -> None:
        cfg = self.service.config
        if len(payload) > cfg.max_message_bytes:
            self.reject(kind, Rejected("too_large", f"{kind} message of {len(payload)} bytes "
                                       f"exceeds the limit of {cfg.max_message_bytes} bytes "
                                       "(--max-message-bytes)"))
            return
        with self._flight_lock:  # counted before the put: the worker may finish it at once
            self.in_flight += 1
        if not self.queue.put((kind, payload, t_recv), block=cfg.on_full == "block"):
            self._done()
            self.counters.dropped[kind] += 1

    def _done(self) -> None:
        with self._flight_lock:
            self.in_flight -= 1

    # -- decoder and worker ----------------------------------------------------------------

    def start(self) -> None:
        self.decoder.start()
        self.thread.start()

    def stop(self, timeout_s: float = 10.0, drain: bool = True) -> None:
        """Stop the decoder and the worker; with ``drain`` they first process what is
        queued."""
        if drain:
            deadline = time.monotonic() + timeout_s
            while (self.in_flight > 0 and time.monotonic() < deadline
                   and self.thread.is_alive() and self.decoder.is_alive()):
                time.sleep(0.01)
        self._stop.set()
        self.queue.close()
        if self.decoder.is_alive():
            self.decoder.join(timeout_s)
        self.handoff.close()  # the worker finishes what the decoder handed over
        if self.thread.is_alive():
            self.thread.join(timeout_s)

    def _decode_loop(self) -> None:
        """Decoder thread: wire decoding and validation, in parallel with the worker."""
        while not self._stop.is_set():
            item = self.queue.get(0.2)
            if item is None:
                continue
            kind, payload, t_recv = item
            decoded: Any
            try:
                decoded = decode_events(payload) if kind == "events" else decode_frame(payload)
            except WireError as exc:
                decoded = Rejected(classify_wire_error(str(exc)), str(exc))
            except Exception as exc:  # a bug must not kill the camera's decoder
                log.exception("camera %s: unexpected error decoding a %s message", self.id,
                              kind)
                decoded = Rejected("internal", f"{type(exc).__name__}: {exc}")
            if not self.handoff.put((kind, decoded, len(payload), t_recv)):
                self._done()
                return

    def _run(self) -> None:
        """Worker thread: checks that need the camera's state, OnEI, publication."""
        while True:
            item = self.handoff.get(0.2)
            if item is None:
                if self.handoff.closed:
                    return
                continue
            kind, decoded, nbytes, t_recv = item
            try:
                if isinstance(decoded, Rejected):
                    raise decoded
                with self.lock:
                    if kind == "events":
                        self._on_events(decoded, nbytes, t_recv)
                    else:
                        self._on_frame(decoded, nbytes, t_recv, time.monotonic())
            except Rejected as exc:
                self.reject(kind, exc)
            except Exception as exc:  # a bug must not kill the camera's worker
                log.exception("camera %s: unexpected error on a %s message", self.id, kind)
                self.reject(kind, Rejected("internal", f"{type(exc).__name__}: {exc}"))
            finally:
                self._done()

    def _check_sensor(self, h: int, w: int, what: str) -> None:
        if self.sensor is None:
            if h * w > self.service.config.max_pixels:
                raise Rejected("sensor_too_large",
                               f"{what}: a {w}x{h} sensor has {h * w} pixels, more than the "
                               f"limit of {self.service.config.max_pixels} (--max-pixels)")
            self.sensor = SensorSize(h, w)
            self.calibrator = OnlineCalibrator(self.sensor, self.service.config.onei)
            log.info("camera %s: %s sensor", self.id, self.sensor)
        elif (h, w) != self.sensor.shape:
            raise Rejected("sensor_changed",
                           f"{what}: a {w}x{h} sensor, but camera {self.id!r} is "
                           f"{self.sensor}; restart the service (or use another camera id) "
                           "for a new sensor")

    def _check_seq(self, kind: str, seq: int) -> None:
        expected = self.next_seq[kind]
        if expected is not None and seq != expected:
            if seq > expected:
                self.counters.lost[kind] += seq - expected
            else:
                self.counters.seq_restarts[kind] += 1
            if kind == "events" and self.calibrator is not None:
                # events went missing (or the publisher restarted): no OnEI equation may
                # span this interval, its counts are incomplete
                self.calibrator.mark_gap()
        self.next_seq[kind] = seq + 1

    def _on_events(self, decoded: tuple[np.ndarray, dict[str, Any]], nbytes: int,
                   t_recv: float) -> None:
        ev, header = decoded
        what = f"events message seq {header['seq']}"
        self._check_sensor(header["height"], header["width"], what)
        assert self.calibrator is not None
        last = self.calibrator.last_event_t_us
        if ev.size and last is not None and int(ev["t_us"][0]) < last:
            raise Rejected("time_backwards",
                           f"{what}: time goes backwards: first t_us={int(ev['t_us'][0])} is "
                           f"before the previous chunk's last t_us={last}")
        self._check_seq("events", header["seq"])
        try:
            # decode_events validated them against the header's sensor, which _check_sensor
            # matched to this camera's
            self.calibrator.feed_events(ev, validated=True)
        except ValueError as exc:
            raise Rejected("rejected", f"{what}: {exc}") from None
        c = self.counters
        c.events += int(ev.size)
        c.event_messages += 1
        c.bytes_in += nbytes
        self.rate.add(time.monotonic(), int(ev.size))
        self.dirty = True
        if ev.size:
            self.service.observe("events", self.id, ev)

    def _on_frame(self, decoded: tuple[int, int, np.ndarray, dict[str, Any]], nbytes: int,
                  t_recv: float, t_start: float | None = None) -> None:
        t_us, exposure_us, image, header = decoded
        what = f"frame message seq {header['seq']}"
        self._check_sensor(header["height"], header["width"], what)
        assert self.calibrator is not None
        last = self.calibrator.last_frame_t_us
        if last is not None and t_us <= last:
            raise Rejected("time_backwards", f"{what}: frame time goes backwards: t_us={t_us} "
                                             f"after t_us={last}")
        self._check_seq("frames", header["seq"])
        try:
            updated = self.calibrator.feed_frame(t_us, image, exposure_us)
        except ValueError as exc:
            raise Rejected("rejected", f"{what}: {exc}") from None
        if updated:
            self._publish_calibration(t_us, t_recv, t_start if t_start is not None else t_recv)
        # counted once its outputs are out: a status showing n frames implies their updates
        self.counters.frames += 1
        self.counters.bytes_in += nbytes
        self.dirty = True
        self.service.observe("frame", self.id, t_us, image)

    def _publish_calibration(self, t_us: int, t_recv: float, t_start: float) -> None:
        """Publish the calibration of the update this frame triggered.

        The Calibration is built once per update and shared by the published message, the
        query cache and the recorder; the recorder runs in its own thread afterwards.
        """
        assert self.calibrator is not None
        t_fed = time.monotonic()
        cal = self.calibrator.calibration()
        t_cal = time.monotonic()
        msg = encode_calibration(cal, t_us=t_us, seq=self.calibration_seq)
        t_enc = time.monotonic()
        self.service.publish(self.key_calibration, msg, keys.ENC_CALIBRATION)
        t_pub = time.monotonic()
        self.latency_ms.append((t_pub - t_recv) * 1e3)
        # where the time went: queue wait, OnEI (fold + re-solve), calibration maps, encode,
        # publish
        self.latency_parts_ms.append((t_start - t_recv, t_fed - t_start, t_cal - t_fed,
                                      t_enc - t_cal, t_pub - t_enc))
        self.calibration_seq += 1
        self.calibration = cal
        self.calibration_msg = msg
        self.calibration_t_us = t_us
        self.last_update_wall = time.time()
        self.counters.updates += 1
        if self.service.observer is not None:
            self.service.observe("updated", self.id, cal, t_us, self.status())

    # -- errors ----------------------------------------------------------------------------

    def reject(self, kind: str, exc: Rejected) -> None:
        """Count a rejected input and publish it (at most ``error_rate_hz`` per second)."""
        c = self.counters
        c.errors[exc.reason] = c.errors.get(exc.reason, 0) + 1
        now = time.monotonic()
        rate = self.service.config.error_rate_hz
        self._err_tokens = min(rate, self._err_tokens + (now - self._err_last) * rate)
        self._err_last = now
        if self._err_tokens < 1.0:
            c.errors_suppressed += 1
            return
        self._err_tokens -= 1.0
        c.errors_published += 1
        body = {"camera": self.id, "stream": kind, "reason": exc.reason, "message": str(exc),
                "errors_total": c.errors_total, "suppressed": c.errors_suppressed,
                "wall_time": time.time()}
        log.warning("camera %s: rejected a %s message: %s (%s)", self.id, kind, exc.reason,
                    exc)
        self.service.publish(self.key_errors, json.dumps(body).encode(), keys.ENC_ERROR)

    # -- outputs ---------------------------------------------------------------------------

    def status(self) -> dict[str, Any]:
        c = self.counters
        lat = np.asarray(self.latency_ms, np.float64)
        cal = self.calibrator
        return {
            "camera": self.id,
            "sensor": str(self.sensor) if self.sensor else None,
            "events": c.events,
            "event_messages": c.event_messages,
            "frames": c.frames,
            "updates": c.updates,
            "bytes_in": c.bytes_in,
            "event_rate_hz": self.rate.rate(time.monotonic()),
            "dropped": dict(c.dropped),
            "lost": dict(c.lost),
            "seq_restarts": dict(c.seq_restarts),
            "errors": dict(c.errors),
            "errors_total": c.errors_total,
            "errors_suppressed": c.errors_suppressed,
            "queue_bytes": self.queue.nbytes,
            "queue_messages": len(self.queue),
            "calibration_seq": self.calibration_seq - 1 if self.calibration_msg else None,
            "last_update_t_us": self.calibration_t_us,
            "last_update_wall": self.last_update_wall,
            "latency_ms": {
                "last": float(lat[-1]) if lat.size else None,
                "median": float(np.median(lat)) if lat.size else None,
                "mean": float(lat.mean()) if lat.size else None,
                "p95": float(np.percentile(lat, 95)) if lat.size else None,
                "max": float(lat.max()) if lat.size else None,
                "parts_median": self._latency_parts(),
            },
            "valid_fraction": (self.calibration.valid_fraction
                               if self.calibration is not None else None),
            "estimator": cal.status() if cal is not None else None,
        }

    def _latency_parts(self) -> dict[str, float] | None:
        """Median ms of each step between a frame's arrival and its calibration's publication
        (over the last 200 updates)."""
        if not self.latency_parts_ms:
            return None
        med = np.median(np.asarray(self.latency_parts_ms, np.float64), axis=0) * 1e3
        return {name: float(v) for name, v in zip(LATENCY_PARTS, med, strict=True)}

    def calibration_reply(self, params: dict[str, str]) -> tuple[bytes, str]:
        """The current calibration in the format and fields a query asks for.

        Raises :class:`Rejected` ("bad_query") for an unknown field or format and
        ("no_calibration") before the first update.
        """
        from ..io.wire import CALIBRATION_MAP_DTYPES

        fmt = params.get("format", "msgpack")
        if fmt not in ("msgpack", "npz"):
            raise Rejected("bad_query", f"format={fmt!r}: expected msgpack or npz")
        fields = None
        if params.get("fields"):
            fields = [f for f in params["fields"].split(",") if f]
            unknown = sorted(set(fields) - set(CALIBRATION_MAP_DTYPES))
            if unknown:
                raise Rejected("bad_query", f"unknown field(s) {unknown}; known: "
                               f"{sorted(CALIBRATION_MAP_DTYPES)}")
        msg, cal, t_us = self.calibration_msg, self.calibration, self.calibration_t_us
        if msg is None:
            raise Rejected("no_calibration", f"camera {self.id!r} has no calibration yet "
                           f"({self.counters.frames} frames, {self.counters.events} events "
                           "received)")
        if fmt == "msgpack" and fields is None:
            return msg, keys.ENC_CALIBRATION
        if cal is None:  # restored from a snapshot: rebuild from the stored message
            from ..io.wire import decode_calibration

            cal, _ = decode_calibration(msg)
            self.calibration = cal
        if fmt == "msgpack":
            return (encode_calibration(cal, t_us=int(t_us or 0), seq=self.calibration_seq - 1,
                                       fields=fields), keys.ENC_CALIBRATION)
        return calibration_npz_bytes(cal, fields, t_us=t_us), keys.ENC_CALIBRATION_NPZ

    # -- snapshots -------------------------------------------------------------------------

    def state_arrays(self) -> dict[str, np.ndarray] | None:
        """Everything to resume this camera (call with ``self.lock`` held)."""
        if self.calibrator is None:
            return None
        meta = {
            "format": STATE_FORMAT, "camera": self.id, "sensor": str(self.sensor),
            "next_seq": self.next_seq, "calibration_seq": self.calibration_seq,
            "calibration_t_us": self.calibration_t_us, "counters": asdict(self.counters),
            "saved_wall": time.time(),
        }
        arrays = {f"est__{k}": v for k, v in self.calibrator.state_dict().items()}
        arrays["service_json"] = np.array(json.dumps(meta))
        arrays["calibration_msg"] = np.frombuffer(self.calibration_msg or b"", np.uint8)
        return arrays

    def restore(self, arrays: dict[str, np.ndarray]) -> None:
        meta = json.loads(str(arrays["service_json"]))
        if meta.get("format") != STATE_FORMAT:
            raise ValueError(f"unknown snapshot format {meta.get('format')!r}")
        est = {k[5:]: v for k, v in arrays.items() if k.startswith("est__")}
        self.calibrator = OnlineCalibrator.from_state(est)
        self.sensor = self.calibrator.sensor
        self.next_seq = {k: meta["next_seq"].get(k) for k in ("events", "frames")}
        self.calibration_seq = int(meta["calibration_seq"])
        self.calibration_t_us = meta["calibration_t_us"]
        cnt = meta["counters"]
        self.counters = Counters(**{k: cnt[k] for k in Counters.__dataclass_fields__
                                    if k in cnt})
        msg = arrays["calibration_msg"].tobytes()
        self.calibration_msg = msg or None


def calibration_npz_bytes(cal: Calibration, fields: list[str] | None = None, *,
                          t_us: int | None = None) -> bytes:
    """The ``.npz`` layout of :func:`evcal.io.save_calibration`, in memory.

    With ``fields`` only those maps (plus ``log_offset``, ``method``, ``params_json``) are
    included, and such a file is not loadable by ``load_calibration``.
    """
    import io

    from ..io._util import to_jsonable
    from ..io.calibfile import MAP_DTYPES

    names = list(MAP_DTYPES) if fields is None else fields
    arrays: dict[str, Any] = {k: np.asarray(getattr(cal, k), MAP_DTYPES[k]) for k in names}
    arrays["log_offset"] = np.float64(cal.log_offset)
    arrays["method"] = np.array(str(cal.method))
    params = dict(cal.params)
    if t_us is not None:
        params["t_us"] = int(t_us)
    arrays["params_json"] = np.array(json.dumps(to_jsonable(params), default=repr,
                                                sort_keys=True))
    buf = io.BytesIO()
    np.savez_compressed(buf, **arrays)
    return buf.getvalue()


# ----------------------------------------------------------------------------- the service


class Service:
    """All cameras of one instance. Thread-safe entry points: ``on_sample``, ``on_query_*``,
    ``tick``; lifecycle: ``restore`` -> (samples) -> ``close``."""

    def __init__(self, config: ServiceConfig, publish: PublishFn, *,
                 match: MatchFn | None = None, observer: Observer | None = None,
                 store: StateStore | None = None, instance: str = ""):
        self.config = config
        self._publish = publish
        self._match = match or keys.matches
        self.observer = observer
        self.store = store
        self.instance = instance or config.instance or "evcal"
        self.cameras: dict[str, Camera] = {}
        self._lock = threading.Lock()
        self.rejected_cameras = 0
        self.publish_errors = 0
        self.observer_errors = 0
        self._observer_thread = (ObserverThread(self._observe_now) if observer is not None
                                 else None)
        self._closed = False
        self._last_status = 0.0
        self._last_snapshot = time.monotonic()
        self.claim = f"{config.prefix.strip('/')}/{config.cameras}"

    # -- plumbing --------------------------------------------------------------------------

    def publish(self, key: str, payload: bytes, encoding: str) -> None:
        try:
            self._publish(key, payload, encoding)
        except Exception as exc:  # a closed session at shutdown, a transport hiccup
            self.publish_errors += 1
            log.warning("cannot publish on %s: %s", key, exc)

    def observe(self, method: str, *args: Any) -> None:
        """Hand a call to the recorder's thread (returns at once; see :class:`ObserverThread`)."""
        if self._observer_thread is None:
            return
        nbytes = sum(int(a.nbytes) for a in args if isinstance(a, np.ndarray))
        if method == "updated":
            nbytes += sum(int(getattr(args[1], name).nbytes) for name in _CAL_MAPS)
        self._observer_thread.submit(method, args, nbytes)

    @property
    def observer_dropped(self) -> int:
        return self._observer_thread.dropped if self._observer_thread is not None else 0

    def _observe_now(self, method: str, *args: Any) -> None:
        """Call the recorder (in its thread); its failures are logged and counted, never an
        input's fault."""
        assert self.observer is not None
        fn = getattr(self.observer, method, None)
        if fn is None:  # an observer without the optional ``discard``
            return
        try:
            fn(*args)
        except Exception:
            self.observer_errors += 1
            if self.observer_errors <= 3:
                log.exception("the recorder failed in %s (logged 3 times at most)", method)

    def claims(self, camera: str) -> bool:
        return self._match(self.claim, f"{self.config.prefix.strip('/')}/{camera}")

    def camera(self, camera_id: str, *, create: bool = True) -> Camera | None:
        cam = self.cameras.get(camera_id)
        if cam is not None or not create:
            return cam
        with self._lock:
            cam = self.cameras.get(camera_id)
            if cam is None:
                if self._closed:
                    return None
                if len(self.cameras) >= self.config.max_cameras:
                    self.rejected_cameras += 1
                    return None
                cam = Camera(self, camera_id)
                self.cameras[camera_id] = cam
                cam.start()
                log.info("camera %s discovered", camera_id)
        return cam

    # -- entry points ----------------------------------------------------------------------

    def on_sample(self, key: str, payload: bytes, encoding: str = "") -> None:
        """A message on ``<prefix>/<camera>/events|frames`` (any thread, returns quickly)."""
        t_recv = time.monotonic()
        parsed = keys.split_camera_key(self.config.prefix, key)
        if parsed is None or parsed[1] not in keys.INPUT_KINDS:
            return
        camera_id, kind = parsed
        try:
            keys.check_camera_id(camera_id)
        except ValueError:
            return
        cam = self.camera(camera_id)
        if cam is None:
            if not self._closed:
                body = {"camera": camera_id, "stream": kind, "reason": "too_many_cameras",
                        "message": f"this instance already serves {self.config.max_cameras} "
                                   "cameras (--max-cameras)", "wall_time": time.time()}
                self.publish(keys.camera_key(self.config.prefix, camera_id, "errors"),
                             json.dumps(body).encode(), keys.ENC_ERROR)
            return
        cam.enqueue(kind, payload, t_recv)

    def query_calibration(self, query_key: str, params: dict[str, str]
                          ) -> list[tuple[str, bytes, str]]:
        """Replies ``(key, payload, encoding)`` for every camera whose calibration key
        intersects ``query_key``; raises :class:`Rejected` if the query is malformed or no
        matching camera has a calibration yet."""
        out, problems = [], []
        for cam in list(self.cameras.values()):
            if not self._match(query_key, cam.key_calibration):
                continue
            try:
                payload, enc = cam.calibration_reply(params)
            except Rejected as exc:
                if exc.reason == "bad_query":
                    raise
                problems.append(str(exc))
                continue
            out.append((cam.key_calibration, payload, enc))
        if not out and problems:
            raise Rejected("no_calibration", "; ".join(problems))
        return out

    def query_status(self, query_key: str) -> list[tuple[str, bytes, str]]:
        return [(cam.key_status, json.dumps(cam.status()).encode(), keys.ENC_STATUS)
                for cam in list(self.cameras.values())
                if self._match(query_key, cam.key_status)]

    def cameras_info(self) -> dict[str, Any]:
        return {
            "instance": self.instance,
            "prefix": self.config.prefix,
            "claims": self.config.cameras,
            "rejected_cameras": self.rejected_cameras,
            "publish_errors": self.publish_errors,
            "recorder_errors": self.observer_errors,
            "recorder_dropped": self.observer_dropped,
            "cameras": [{"id": c.id, "sensor": str(c.sensor) if c.sensor else None,
                         "updates": c.counters.updates, "events": c.counters.events,
                         "last_update_t_us": c.calibration_t_us}
                        for c in sorted(self.cameras.values(), key=lambda c: c.id)],
        }

    def tick(self, *, force: bool = False) -> None:
        """Periodic work (call about every 0.1-1 s): status publication, snapshots."""
        now = time.monotonic()
        if force or now - self._last_status >= self.config.status_period_s:
            self._last_status = now
            for cam in list(self.cameras.values()):
                self.publish(cam.key_status, json.dumps(cam.status()).encode(),
                             keys.ENC_STATUS)
        if self.store is not None and (force or now - self._last_snapshot
                                       >= self.config.snapshot_period_s):
            self._last_snapshot = now
            self.snapshot()

    def snapshot(self) -> int:
        """Write every changed camera's state; returns how many were written."""
        if self.store is None:
            return 0
        n = 0
        for cam in list(self.cameras.values()):
            if not cam.dirty:
                continue
            with cam.lock:
                arrays = cam.state_arrays()
                cam.dirty = False
            if arrays is None:
                continue
            try:
                self.store.save(cam.id, arrays)
                n += 1
            except OSError as exc:
                cam.dirty = True
                log.error("camera %s: cannot write the snapshot: %s", cam.id, exc)
        return n

    def restore(self) -> list[str]:
        """Load the snapshots of the cameras this instance claims; returns their ids."""
        if self.store is None:
            return []
        done = []
        for camera_id, arrays in self.store.load_all().items():
            if not self.claims(camera_id):
                continue
            cam = Camera(self, camera_id)
            try:
                cam.restore(arrays)
            except (ValueError, KeyError) as exc:
                log.error("camera %s: cannot restore the snapshot: %s", camera_id, exc)
                continue
            with self._lock:
                self.cameras[camera_id] = cam
            cam.start()
            done.append(camera_id)
            log.info("camera %s restored (calibration seq %s, t_us=%s)", camera_id,
                     cam.calibration_seq - 1, cam.calibration_t_us)
        return done

    def close(self, *, drain_s: float = 10.0) -> None:
        """Stop the workers (after draining their queues), publish a last status, snapshot."""
        with self._lock:
            self._closed = True
        for cam in list(self.cameras.values()):
            cam.stop(timeout_s=drain_s)
        if self._observer_thread is not None:
            self._observer_thread.close()  # the recorder finishes what the cameras handed it
        self.tick(force=True)


