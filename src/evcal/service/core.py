"""The calibration service without the network: cameras, their outputs, snapshots.

:class:`Service` receives raw payloads (``on_sample``), keeps one
:class:`~evcal.service.ingest.Camera` (threads and queues, :mod:`evcal.service.ingest`)
around one :class:`~evcal.service.camera.CameraState` (the pure per-camera state machine,
:mod:`evcal.service.camera`) per camera id, and turns the records the state machines return
into publications through a ``publish(key, payload, encoding)`` callable
(:mod:`evcal.service.outputs` builds the payloads). The zenoh glue is in
:mod:`evcal.service.server`. This module imports neither zenoh nor rerun, so every rule below
is tested without a network.

The path of one message: transport receive thread -> :meth:`Service.on_sample` -> the
camera's bounded queue -> its decoder thread (wire decoding, per-chunk validation) -> its
worker thread (:class:`~evcal.service.camera.CameraState`: stream guard, OnEI) -> records ->
:meth:`Service._emit` (publish calibration / errors, hand recorder calls to the
:class:`~evcal.service.outputs.ObserverThread`).

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

import logging
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from ..calibration import Calibration
from ..errors import ConfigError, ErrorReason, EvcalError
from ..online import OnEIConfig
from . import keys
from .camera import LATENCY_PARTS, CalibrationUpdate, CameraState, Observed, Output, Rejected
from .camera import Rejection as Rejection
from .ingest import Camera, CameraQueue
from .outputs import (
    ErrorLimiter,
    ObserverThread,
    calibration_reply,
    camera_status,
    error_body,
    parse_query,
)
from .state import StateStore

log = logging.getLogger("evcal.service")

PublishFn = Callable[[str, bytes, str], None]
MatchFn = Callable[[str, str], bool]  # (key expression, concrete key) -> intersects

ON_FULL = ("drop", "block")

__all__ = ["LATENCY_PARTS", "ON_FULL", "CameraQueue", "Observer", "Rejected", "Service",
           "ServiceConfig"]


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
            raise ConfigError(f"on_full={self.on_full!r} must be one of {ON_FULL}")
        if not self.prefix.strip("/"):
            raise ConfigError("prefix must not be empty")
        for name in ("queue_bytes", "max_cameras", "max_pixels", "max_message_bytes"):
            if int(getattr(self, name)) < 1:
                raise ConfigError(f"{name}={getattr(self, name)} must be >= 1")
        if self.max_message_bytes > self.queue_bytes:
            raise ConfigError(f"max_message_bytes={self.max_message_bytes} exceeds "
                             f"queue_bytes={self.queue_bytes}: such a message could never be "
                             "queued")
        for name in ("status_period_s", "snapshot_period_s", "error_rate_hz"):
            if not getattr(self, name) > 0:
                raise ConfigError(f"{name}={getattr(self, name)} must be > 0")


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




class Service:
    """All cameras of one instance. Thread-safe entry points: ``on_sample``,
    ``query_calibration``, ``query_status``, ``cameras_info``, ``tick``; lifecycle:
    ``restore`` -> (samples) -> ``close``."""

    def __init__(self, config: ServiceConfig, publish: PublishFn, *,
                 match: MatchFn | None = None, observer: Observer | None = None,
                 store: StateStore | None = None, instance: str = "") -> None:
        self.config = config
        self._publish = publish
        self._match = match or keys.matches
        self.observer = observer
        self.store = store
        self.instance = instance or config.instance or "evcal"
        self.cameras: dict[str, Camera] = {}
        self._limiters: dict[str, ErrorLimiter] = {}
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

    def key(self, camera: str, kind: str) -> str:
        return keys.camera_key(self.config.prefix, camera, kind)

    def publish(self, key: str, payload: bytes, encoding: str) -> None:
        try:
            self._publish(key, payload, encoding)
        except Exception as exc:  # a closed session at shutdown, a transport hiccup
            self.publish_errors += 1
            log.warning("cannot publish on %s: %s", key, exc)

    @property
    def observer_dropped(self) -> int:
        return self._observer_thread.dropped if self._observer_thread is not None else 0

    def _observe_now(self, method: str, *args: Any) -> None:
        """Call the recorder (in its thread); its failures are logged and counted, never an
        input's fault."""
        fn = getattr(self.observer, method, None)
        if fn is None:  # an observer without the optional ``discard``
            return
        try:
            fn(*args)
        except Exception:
            self.observer_errors += 1
            if self.observer_errors <= 3:
                log.exception("the recorder failed in %s (logged 3 times at most)", method)

    def _emit(self, cam: Camera, outputs: Sequence[Output]) -> None:
        """Publish what a camera's state machine returned (its worker thread, its lock held)."""
        for out in outputs:
            if isinstance(out, CalibrationUpdate):
                self.publish(self.key(cam.id, "calibration"), out.message, keys.ENC_CALIBRATION)
                cam.state.published(out, time.monotonic())
                if self._observer_thread is not None:
                    self._observer_thread.submit(
                        "updated", (cam.id, out.calibration, out.t_us,
                                    camera_status(cam)))
            elif isinstance(out, Rejection):
                self._publish_error(out, cam.state)
            elif isinstance(out, Observed) and self._observer_thread is not None:
                self._observer_thread.submit(out.method, out.args)

    def _publish_error(self, rec: Rejection, st: CameraState | None) -> None:
        """Publish a rejected input, at most ``error_rate_hz`` per second per camera."""
        limiter = self._limiters.get(rec.camera)
        if limiter is None:
            limiter = self._limiters.setdefault(rec.camera,
                                                ErrorLimiter(self.config.error_rate_hz))
        if not limiter.allow():
            if st is not None:
                st.counters.errors_suppressed += 1
            return
        if st is not None:
            st.counters.errors_published += 1
        log.warning("camera %s: rejected a %s message: %s (%s)", rec.camera, rec.stream,
                    rec.reason, rec.message)
        self.publish(self.key(rec.camera, "errors"), error_body(rec, st), keys.ENC_ERROR)

    def claims(self, camera: str) -> bool:
        return self._match(self.claim, f"{self.config.prefix.strip('/')}/{camera}")

    def _new_camera(self, camera_id: str, *, observe: bool) -> Camera:
        cfg = self.config
        state = CameraState(camera_id, onei=cfg.onei, max_pixels=cfg.max_pixels,
                            observe=observe)
        return Camera(state, emit=self._emit, queue_bytes=cfg.queue_bytes,
                      max_message_bytes=cfg.max_message_bytes, block=cfg.on_full == "block")

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
                cam = self._new_camera(camera_id, observe=self.observer is not None)
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
                self._publish_error(Rejection(
                    camera_id, kind, str(ErrorReason.TOO_MANY_CAMERAS),
                    f"this instance already serves {self.config.max_cameras} cameras "
                    "(--max-cameras)"), None)
            return
        cam.enqueue(kind, payload, t_recv)

    def query_calibration(self, query_key: str, params: dict[str, str]
                          ) -> list[tuple[str, bytes, str]]:
        """Replies ``(key, payload, encoding)`` for every camera whose calibration key
        intersects ``query_key``; raises :class:`Rejected` if the query is malformed or no
        matching camera has a calibration yet."""
        fmt, fields = parse_query(params)
        out, problems = [], []
        for cam in list(self.cameras.values()):
            key = self.key(cam.id, "calibration")
            if not self._match(query_key, key):
                continue
            try:
                with cam.lock:
                    payload, enc = calibration_reply(cam.state, fmt, fields)
            except EvcalError as exc:
                problems.append(str(exc))
                continue
            out.append((key, payload, enc))
        if not out and problems:
            raise Rejected("; ".join(problems), ErrorReason.NO_CALIBRATION)
        return out

    def status(self, cam: Camera) -> dict[str, Any]:
        with cam.lock:
            return camera_status(cam)

    def query_status(self, query_key: str) -> list[tuple[str, bytes, str]]:
        import json  # noqa: PLC0415

        return [(self.key(cam.id, "status"), json.dumps(self.status(cam)).encode(),
                 keys.ENC_STATUS)
                for cam in list(self.cameras.values())
                if self._match(query_key, self.key(cam.id, "status"))]

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
                         "last_update_t_us": c.state.calibration_t_us}
                        for c in sorted(self.cameras.values(), key=lambda c: c.id)],
        }

    def tick(self, *, force: bool = False) -> None:
        """Periodic work (call about every 0.1-1 s): status publication, snapshots."""
        now = time.monotonic()
        if force or now - self._last_status >= self.config.status_period_s:
            self._last_status = now
            for key, payload, enc in self.query_status("**"):
                self.publish(key, payload, enc)
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
            with cam.lock:
                if not cam.state.dirty:
                    continue
                cam.fold_dropped()
                arrays = cam.state.state_arrays()
                cam.state.dirty = False
            if arrays is None:
                continue
            try:
                self.store.save(cam.id, arrays)
                n += 1
            except OSError as exc:
                cam.state.dirty = True
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
            cam = self._new_camera(camera_id, observe=self.observer is not None)
            try:
                cam.state.restore(arrays)
            except EvcalError as exc:
                log.error("camera %s: cannot restore the snapshot: %s", camera_id, exc)
                continue
            with self._lock:
                self.cameras[camera_id] = cam
            cam.start()
            done.append(camera_id)
            log.info("camera %s restored (calibration seq %s, t_us=%s)", camera_id,
                     cam.state.calibration_seq - 1, cam.state.calibration_t_us)
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
