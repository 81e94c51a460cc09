"""The calibration service without the network: cameras, their outputs, snapshots.

:class:`Service` receives raw payloads (``on_sample``), keeps one
:class:`~evcal.service.ingest.CameraWorker` (threads and queues, :mod:`evcal.service.ingest`)
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
from collections import OrderedDict
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from ..calibration import Calibration
from ..errors import ConfigError, ErrorReason, EvcalError
from ..offe import OffEConfig
from ..online import OnEIConfig, OnEIExecutor
from . import keys
from .camera import LATENCY_PARTS, CalibrationUpdate, CameraState, Observed, Output, Rejected
from .camera import Rejection as Rejection
from .gcpolicy import GcPolicy
from .ingest import CameraQueue, CameraWorker
from .outputs import (
    ErrorLimiter,
    ObserverThread,
    camera_status,
    error_body,
)
from .replies import ServiceReplies
from .signing import Signer
from .state import Snapshot, StateStore

log = logging.getLogger("evcal.service")

class PublishFn(Protocol):
    """``publish(key, payload, encoding, attachment=None)`` (``Transport.put``)."""

    def __call__(self, key: str, payload: bytes, encoding: str, *,
                 attachment: bytes | None = None) -> None: ...
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
    # (index, count): serve only the cameras with keys.shard_of(id, count) == index, the
    # others' messages are ignored before anything is queued or counted (serve --workers N
    # runs N such shards); None: every camera of the claim
    shard: tuple[int, int] | None = None
    queue_bytes: int = 64 << 20
    on_full: str = "drop"
    max_cameras: int = 64
    max_pixels: int = 1280 * 1024
    max_message_bytes: int = 32 << 20
    status_period_s: float = 1.0
    snapshot_period_s: float = 30.0
    error_rate_hz: float = 20.0
    # a camera idle this long is snapshotted and dropped from memory (0: never); it comes
    # back from its snapshot with its next message
    idle_evict_s: float = 3600.0
    # a camera is on probation until it has sent enough to matter: probation_frames frames
    # and probation_events events accepted (or it has a calibration). On probation it is
    # dropped after probation_s idle (no snapshot), and gives its slot to a new camera when
    # every slot is taken: at once if nothing it sent was accepted data (an empty message,
    # refused input), else once idle for displace_idle_s — so that ids that send once
    # (2,000 valid empty messages) cannot lock a real camera out, while two cameras that
    # both stream do not take each other's slot in turn
    probation_s: float = 10.0
    probation_frames: int = 2
    probation_events: int = 1000
    displace_idle_s: float = 1.0
    # camera ids refused a slot (or displaced) that a status query can still be answered
    # for with the refusal (a replay then knows its camera was refused)
    refused_memory: int = 4096
    # the service estimates each camera's log offset unless told (OnEI's own default is 30),
    # its equations span 5 frame intervals, as OffEI's (OnEI's own default closes them by
    # event count, which ends them in bursts of motion: 1.1-1.5x OffEI's c error on common
    # pixels of v2e recordings with frame windows, 1.5-2.1x with event-count ones); no
    # forgotten history by default (--history 1 takes 3-s v2e recordings from 1.1-1.5x to
    # 1.1-1.2x OffEI's c error, at 2 ms per update at 346x260, 20 ms at 1280x720: over the
    # latency aims; docs/SERVICE.md); each frame's equations added at that frame (eager:
    # an update frame then adds only its own; 1280x720 at 20 M events/s: 29 -> 23 ms)
    onei: OnEIConfig = field(default_factory=lambda: OnEIConfig(log_offset="auto",
                                                                window_frames=5, eager=True))
    # a camera that sends events and no frames gets the events-only estimate (streaming
    # OffE: the same maps as `evcal calibrate --method offe` on the same events), updated
    # every offe_period_us of sensor time; its first frame moves it to OnEI
    offe: OffEConfig = field(default_factory=OffEConfig)
    offe_period_us: int = 1_000_000
    # publish OnEI's updates as posterior maps (evcal.posterior: each pixel pulled toward
    # the sensor's population by how little its own evidence says), the priors taken afresh
    # every posterior_refresh_us of sensor time; a query with estimate=raw gets the raw
    # maps. Off by default: on some recordings (v2e's) the pull shrinks the stated errors
    # below the maps' shared bias (docs/MEASUREMENTS.md)
    posterior: bool = False
    posterior_refresh_us: int = 1_000_000
    # fuse each OnEI update with OffE's maps of the same events (evcal.fusion: when the
    # events fall, which the frame sums throw away), OffE's maps taken again every
    # offe_period_us of sensor time. Off by default: OffE's sums double a camera's work per
    # event (docs/SERVICE.md)
    event_timing: bool = False

    def __post_init__(self) -> None:
        if self.on_full not in ON_FULL:
            raise ConfigError(f"on_full={self.on_full!r} must be one of {ON_FULL}")
        if not self.prefix.strip("/"):
            raise ConfigError("prefix must not be empty")
        if self.shard is not None and not (
                len(self.shard) == 2 and self.shard[1] >= 1 and 0 <= self.shard[0] < self.shard[1]):
            raise ConfigError(f"shard={self.shard!r} must be (index, count) with "
                              "0 <= index < count")
        for name in ("queue_bytes", "max_cameras", "max_pixels", "max_message_bytes",
                     "refused_memory", "offe_period_us"):
            if int(getattr(self, name)) < 1:
                raise ConfigError(f"{name}={getattr(self, name)} must be >= 1")
        if self.max_message_bytes > self.queue_bytes:
            raise ConfigError(f"max_message_bytes={self.max_message_bytes} exceeds "
                             f"queue_bytes={self.queue_bytes}: such a message could never be "
                             "queued")
        for name in ("idle_evict_s", "probation_s", "displace_idle_s", "probation_frames",
                     "probation_events", "posterior_refresh_us"):
            if getattr(self, name) < 0:
                raise ConfigError(f"{name}={getattr(self, name)} must be >= 0")
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
    def updated(self, camera: str, cal: Calibration, t_us: int, status: dict[str, Any],
                extra_maps: Mapping[str, np.ndarray]) -> None: ...
    def discard(self, camera: str, dropped: int) -> None: ...
    def close(self) -> None: ...




@dataclass
class Refusal:
    """Why a camera id has no slot (or lost it): kept for its status queries."""

    reason: str
    message: str
    first_wall: float
    last_wall: float
    messages: int = 0  # its messages refused for want of a slot
    displaced: int = 0  # times it lost its probation slot to a new camera

    def doc(self) -> dict[str, Any]:
        return {"reason": self.reason, "message": self.message, "messages": self.messages,
                "displaced": self.displaced, "first_wall": self.first_wall,
                "last_wall": self.last_wall}


class Service(ServiceReplies):
    """All cameras of one instance. Thread-safe entry points: ``on_sample``,
    ``query_calibration``, ``query_status``, ``cameras_info``, ``tick``; lifecycle:
    ``restore`` -> (samples) -> ``close``."""

    def __init__(self, config: ServiceConfig, publish: PublishFn, *,
                 match: MatchFn | None = None, observer: Observer | None = None,
                 store: StateStore | None = None, instance: str = "",
                 signer: Signer | None = None,
                 on_update: Callable[[str, CalibrationUpdate], None] | None = None) -> None:
        self.config = config
        self._publish = publish
        # also publish each update elsewhere (the ROS 2 images); failures are counted
        self._on_update = on_update
        self._match = match or keys.matches
        self.observer = observer
        self.store = store
        self.instance = instance or config.instance or "evcal"
        # the attachment of calibration messages: the instance, signed when a key was given
        self.signer = signer or Signer(self.instance)
        self.cameras: dict[str, CameraWorker] = {}
        # camera ids refused a slot or displaced, newest last, at most refused_memory
        self.refused: OrderedDict[str, Refusal] = OrderedDict()
        self._limiter = ErrorLimiter(config.error_rate_hz)  # refusals not of one camera
        # one set of OnEI threads for every camera (a pool per camera would hold
        # max_cameras x threads idle threads); closed with the service
        self.executor = OnEIExecutor(config.onei.threads)
        self._lock = threading.Lock()
        self.rejected_cameras = 0
        self.invalid_camera_ids = 0
        # messages that came while the service was stopping: not queued (the drain would
        # wait for them), counted and reported in the last cameras document and the log
        self.refused_while_closing = 0
        self.evicted_cameras = 0
        self.forgotten_cameras = 0
        self.publish_errors = 0
        self.observer_errors = 0
        self.tick_errors = 0
        self._observer_thread = (ObserverThread(self._observe_now) if observer is not None
                                 else None)
        self._closed = False
        self._last_status = 0.0
        self._last_snapshot = time.monotonic()
        self.gc: GcPolicy | None = None  # the process's collector policy (set by the server)
        self.shm: Any = None  # the transport's ShmPool (set by the server): its counters
        self.claim = f"{config.prefix.strip('/')}/{config.cameras}"

    # -- plumbing --------------------------------------------------------------------------

    def attachment(self, key: str, payload: bytes) -> bytes:
        """The attachment of a calibration message on ``key`` (see :mod:`.signing`)."""
        return self.signer.attachment(key, payload)

    def publish(self, key: str, payload: bytes, encoding: str, *,
                attachment: bytes | None = None) -> None:
        try:
            self._publish(key, payload, encoding, attachment=attachment)
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

    def _emit(self, cam: CameraWorker, outputs: Sequence[Output]) -> None:
        """Publish what a camera's state machine returned (its worker thread, its lock held)."""
        for out in outputs:
            if isinstance(out, CalibrationUpdate):
                key = self.key(cam.id, "calibration")
                self.publish(key, out.message, keys.ENC_CALIBRATION,
                             attachment=self.attachment(key, out.message))
                cam.state.published(out, time.monotonic())
                if self._on_update is not None:
                    try:
                        self._on_update(cam.id, out)
                    except Exception as exc:
                        self.publish_errors += 1
                        log.warning("camera %s: cannot publish the update elsewhere: %s",
                                    cam.id, exc)
                if self._observer_thread is not None:
                    self._observer_thread.submit(
                        "updated", (cam.id, out.calibration, out.t_us,
                                    camera_status(cam), out.extra_maps))
            elif isinstance(out, Rejection):
                self._publish_error(out, cam.state)
            elif isinstance(out, Observed) and self._observer_thread is not None:
                self._observer_thread.submit(out.method, out.args)

    def _publish_error(self, rec: Rejection, st: CameraState | None) -> None:
        """Publish a rejected input, at most ``error_rate_hz`` per second per camera."""
        cam = self.cameras.get(rec.camera) if st is not None else None
        limiter = cam.limiter if cam is not None else self._limiter
        if not limiter.allow():
            if st is not None:
                st.counters.errors_suppressed += 1
            return
        if st is not None:
            st.counters.errors_published += 1
        log.warning("camera %s: rejected a %s message: %s (%s)", rec.camera, rec.stream,
                    rec.reason, rec.message)
        self.publish(self.key(rec.camera, "errors"), error_body(rec, st), keys.ENC_ERROR)

    def _new_camera(self, camera_id: str, *, observe: bool) -> CameraWorker:
        cfg = self.config
        state = CameraState(camera_id, onei=cfg.onei, max_pixels=cfg.max_pixels,
                            observe=observe, offe=cfg.offe, offe_period_us=cfg.offe_period_us,
                            executor=self.executor,
                            posterior_refresh_us=(cfg.posterior_refresh_us if cfg.posterior
                                                  else None),
                            event_timing=cfg.event_timing)
        cam = CameraWorker(state, emit=self._emit, queue_bytes=cfg.queue_bytes,
                     max_message_bytes=cfg.max_message_bytes, block=cfg.on_full == "block")
        cam.limiter = ErrorLimiter(cfg.error_rate_hz)
        return cam

    def _restore_into(self, cam: CameraWorker, snap: Snapshot) -> bool:
        """Resume ``cam`` from ``snap``; a snapshot that cannot be used is moved aside."""
        try:
            cam.state.restore(snap.arrays)
        except EvcalError as exc:
            if self.store is not None:
                self.store.quarantine(snap.path, str(exc))
            return False
        return True

    def _make_room(self, now_s: float) -> bool:
        """Take a slot from the least useful camera on probation for a new one (call with
        ``self._lock`` held); False if none may give it up.

        A camera with a message in flight keeps its slot (its first message may be the one
        that matters). Among the others on probation: one that has no accepted data (only
        empty or refused messages) gives way at once, one with data once idle for
        ``displace_idle_s``; the victim is the one with the fewest frames, then events,
        then the oldest last message.
        """
        cfg = self.config
        movable = [c for c in self.cameras.values()
                   if c.in_flight == 0 and self.on_probation(c)
                   and ((c.counters.frames == 0 and c.counters.events == 0)
                        or now_s - c.last_input_s >= cfg.displace_idle_s)]
        if not movable:
            return False
        victim = min(movable, key=lambda c: (c.counters.frames, c.counters.events,
                                             c.last_input_s))
        del self.cameras[victim.id]
        self.evicted_cameras += 1
        self._note_refusal(victim.id, str(ErrorReason.TOO_MANY_CAMERAS),
                           f"camera {victim.id!r} was on probation (frames "
                           f"{victim.counters.frames}, events {victim.counters.events}; it "
                           f"keeps a slot from {cfg.probation_frames} frames and "
                           f"{cfg.probation_events} events) and gave its slot to a new camera: "
                           f"all {cfg.max_cameras} slots were taken (--max-cameras)",
                           displaced=True)
        victim.discard()  # nothing in flight: its threads end on their own
        log.info("camera %s (on probation, idle %.1f s) gave its slot to a new camera",
                 victim.id, now_s - victim.last_input_s)
        return True

    def _note_refusal(self, camera_id: str, reason: str, message: str, *,
                      displaced: bool = False) -> None:
        """Remember why ``camera_id`` has no slot (call with ``self._lock`` held)."""
        now = time.time()
        rec = self.refused.get(camera_id)
        if rec is None:
            rec = self.refused[camera_id] = Refusal(reason, message, now, now)
            while len(self.refused) > self.config.refused_memory:
                self.refused.popitem(last=False)
        else:
            self.refused.move_to_end(camera_id)
            rec.reason, rec.message, rec.last_wall = reason, message, now
        if displaced:
            rec.displaced += 1
        else:
            rec.messages += 1

    def camera(self, camera_id: str, *, create: bool = True) -> CameraWorker | None:
        cam = self.cameras.get(camera_id)
        if cam is not None or not create:
            return cam
        with self._lock:
            cam = self.cameras.get(camera_id)
            if cam is None:
                if self._closed:
                    return None
                if (len(self.cameras) >= self.config.max_cameras
                        and not self._make_room(time.monotonic())):
                    self.rejected_cameras += 1
                    self._note_refusal(
                        camera_id, str(ErrorReason.TOO_MANY_CAMERAS),
                        f"no slot for camera {camera_id!r}: all {self.config.max_cameras} "
                        "slots (--max-cameras) are taken by cameras that are streaming or "
                        "past their probation")
                    return None
                cam = self._new_camera(camera_id, observe=self.observer is not None)
                snap = self.store.load(camera_id) if self.store is not None else None
                if snap is not None and self._restore_into(cam, snap):
                    log.info("camera %s back from its snapshot", camera_id)
                else:
                    log.info("camera %s discovered", camera_id)
                self.cameras[camera_id] = cam
                cam.start()
        return cam

    # -- entry points ----------------------------------------------------------------------

    def on_sample(self, key: str, payload: bytes, encoding: str = "") -> None:
        """A message on ``<prefix>/<camera>/events|frames`` (any thread, returns quickly)."""
        t_recv = time.monotonic()
        parsed = keys.split_camera_key(self.config.prefix, key)
        if parsed is None or parsed[1] not in keys.INPUT_KINDS:
            return
        self._deliver(parsed[0], parsed[1], payload, t_recv, claimed=True)

    def deliver(self, camera_id: str, kind: str, payload: Any, t_recv: float) -> None:
        """Hand one ``kind`` message to a camera (any thread, returns quickly): a camera of
        another shard is ignored, the camera id checked, a camera outside this instance's
        claim ignored, the camera found or
        created; ``payload`` is a wire message or a :class:`~evcal.service.ros2.RosSample`
        (ROS 2 input, decoded in the camera's decoder thread)."""
        self._deliver(camera_id, kind, payload, t_recv, claimed=False)

    def _deliver(self, camera_id: str, kind: str, payload: Any, t_recv: float, *,
                 claimed: bool) -> None:
        if not self.owns(camera_id):  # another shard's camera: not ours to count or refuse
            return
        try:
            keys.check_camera_id(camera_id)
        except ValueError as exc:
            self.invalid_camera_ids += 1
            if self._limiter.allow():
                log.warning("refused a %s message: %s", kind, exc)
            return
        if not claimed and self.config.cameras != "**" and not self.claims(camera_id):
            return
        if self._closed:
            with self._lock:
                self.refused_while_closing += 1
            return
        cam = self.camera(camera_id)
        if cam is None:
            if not self._closed:
                rec = self.refused.get(camera_id)
                self._publish_error(Rejection(
                    camera_id, kind, str(ErrorReason.TOO_MANY_CAMERAS),
                    rec.message if rec is not None else
                    f"this instance already serves {self.config.max_cameras} cameras "
                    "(--max-cameras)"), None)
            return
        cam.enqueue(kind, payload, t_recv)



    def tick(self, *, force: bool = False) -> None:
        """Periodic work (call about every 0.1-1 s): status publication, snapshots, idle
        eviction. Never raises: a failure is logged and counted (``tick_errors``)."""
        now = time.monotonic()
        steps: list[Callable[[], Any]] = []
        if force or now - self._last_status >= self.config.status_period_s:
            self._last_status = now
            steps.append(self._publish_status)
        if self.store is not None and (force or now - self._last_snapshot
                                       >= self.config.snapshot_period_s):
            self._last_snapshot = now
            steps.append(self.snapshot)
        if not force:
            steps.append(self.evict_idle)
        for step in steps:
            try:
                step()
            except Exception:
                self.tick_errors += 1
                log.exception("periodic %s failed (counted in tick_errors)", step.__name__)

    def evict_idle(self, now_s: float | None = None) -> list[str]:
        """Drop cameras idle beyond ``probation_s`` (on probation: nothing worth keeping) or
        ``idle_evict_s`` (snapshotted first, back from it with their next message)."""
        now = time.monotonic() if now_s is None else now_s
        cfg = self.config
        out = []
        for cam in list(self.cameras.values()):
            idle = now - cam.last_input_s
            if cam.in_flight:
                continue
            established = not self.on_probation(cam)
            if (not established and idle > cfg.probation_s) or (
                    established and cfg.idle_evict_s > 0 and idle > cfg.idle_evict_s):
                self._drop(cam, save=established)
                self.evicted_cameras += 1
                out.append(cam.id)
                log.info("camera %s idle for %.0f s: evicted%s", cam.id, idle,
                         " (state kept on disk)" if established and self.store else "")
        return out

    def _drop(self, cam: CameraWorker, *, save: bool) -> None:
        """Stop a camera, snapshot it (``save``), then remove it: a message arriving meanwhile
        is dropped and counted, and one arriving after finds the snapshot."""
        cam.stop(timeout_s=2.0)
        if save and self.store is not None:
            with cam.lock:
                cam.fold_dropped()
                arrays = cam.state.state_arrays()
            if arrays is not None:
                try:
                    self.store.save(cam.id, arrays)
                except OSError as exc:
                    log.error("camera %s: cannot write the snapshot: %s", cam.id, exc)
        with self._lock:
            if self.cameras.get(cam.id) is cam:
                del self.cameras[cam.id]

    def forget(self, camera_id: str) -> bool:
        """Drop a camera's state, in memory and on disk; True if there was any."""
        cam = self.cameras.get(camera_id)
        if cam is not None:
            self._drop(cam, save=False)
        removed = self.store.remove(camera_id) if self.store is not None else False
        with self._lock:
            self.refused.pop(camera_id, None)  # its refusal is history too
        if cam is not None or removed:
            self.forgotten_cameras += 1
            log.info("camera %s forgotten", camera_id)
            return True
        return False

    def snapshot(self) -> int:
        """Write every changed camera's state; returns how many were written."""
        if self.store is None:
            return 0
        n = 0
        for cam in list(self.cameras.values()):
            if self.on_probation(cam):
                continue  # not enough to keep: one-shot ids must not fill the disk either
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
        # a shard reads only its own cameras' files (the directory is shared)
        for snap in self.store.snapshots(want=self.owns if self.config.shard else None):
            camera_id = snap.camera
            try:
                keys.check_camera_id(camera_id)
            except ValueError as exc:
                self.store.quarantine(snap.path, str(exc))
                continue
            if not self.claims(camera_id) or len(self.cameras) >= self.config.max_cameras:
                continue
            cam = self._new_camera(camera_id, observe=self.observer is not None)
            if not self._restore_into(cam, snap):
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
        self.executor.close()  # after the last snapshot: what runs later runs inline
        if self.refused_while_closing:
            log.warning("%d message(s) came while the service was stopping and were not "
                        "processed", self.refused_while_closing)
