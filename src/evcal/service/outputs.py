"""What the service says: status documents, query replies, error messages, the recorder.

Every calibration leaves through the one calibration codec: :func:`evcal.io.wire.
encode_calibration` for msgpack messages (published and queried), :func:`evcal.io.calibfile.
calibration_npz_bytes` for ``format=npz`` replies (the layout of ``evcal calibrate --out``).
The functions here read a camera's state (under its lock) and build payloads; they never
change the state. The recorder runs in a thread of its own (:class:`ObserverThread`), after
publication and never holding it.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np

from ..calibration import check_map_names
from ..errors import ErrorReason, EvcalError
from ..io.calibfile import calibration_npz_bytes
from ..io.wire import EXTRA_MAP_DTYPES, encode_calibration
from ..jsonable import strict_dumps
from ..posterior import estimate_of
from . import keys
from .camera import CameraState, Rejected, Rejection
from .ingest import BoundedQueue, CameraWorker

log = logging.getLogger("evcal.service")

QUERY_FORMATS = ("msgpack", "npz")
QUERY_ESTIMATES = ("raw", "posterior")


# ----------------------------------------------------------------------------- status


def camera_status(cam: CameraWorker, *, now_s: float | None = None) -> dict[str, Any]:
    """The ``status`` document of one camera (call with ``cam.lock`` held)."""
    st: CameraState = cam.state
    dropped = cam.dropped_total()  # not folded into the counters: a status changes nothing
    c = st.counters
    lat = np.asarray(st.latency_ms, np.float64)
    cal = st.calibrator
    now = time.monotonic() if now_s is None else now_s
    return {
        "camera": st.id,
        "sensor": str(st.sensor) if st.sensor else None,
        "events": c.events,
        "event_messages": c.event_messages,
        "frames": c.frames,
        "updates": c.updates,
        "bytes_in": c.bytes_in,
        "event_rate_hz": st.rate.rate(now),
        # messages this service's queue refused, and messages missing upstream (sequence
        # gaps, less the service's own drops); "dropped"/"lost" are the older names
        "dropped_messages": dropped,
        "lost_messages": dict(c.lost),
        "dropped": dict(dropped),
        "lost": dict(c.lost),
        "seq_restarts": dict(c.seq_restarts),
        "restarts": dict(c.restarts),  # new sessions: time base (or sensor) changed
        # a restart of the service resumed this camera from its snapshot: how many times,
        # the messages processed after the snapshot and so forgotten, and the last restore
        "restores": c.restores,
        "rolled_back_messages": dict(c.rolled_back),
        "restored": cam.state.restored,
        "errors": dict(c.errors),
        "errors_total": c.errors_total,
        "errors_suppressed": c.errors_suppressed,
        "queue_bytes": cam.queue.nbytes,
        "queue_messages": len(cam.queue),
        # queued, being decoded or processed: 0 means every message received so far is in
        # the counters above (a client confirming delivery waits for it)
        "in_flight_messages": cam.in_flight,
        # how long this camera has been in memory: a client that could not read the
        # counters before its run tells from it whether they count only its messages
        "serving_s": now - cam.started_s,
        "calibration_seq": st.calibration_seq - 1 if st.calibration_msg else None,
        "last_update_t_us": st.calibration_t_us,
        "last_update_wall": st.last_update_wall,
        "latency_ms": {
            "last": float(lat[-1]) if lat.size else None,
            "median": float(np.median(lat)) if lat.size else None,
            "mean": float(lat.mean()) if lat.size else None,
            "p95": float(np.percentile(lat, 95)) if lat.size else None,
            "p99": float(np.percentile(lat, 99)) if lat.size else None,
            "max": float(lat.max()) if lat.size else None,
            "parts_median": st.latency_parts(),
            "slowest": st.slowest_update(),  # of the last 200, with where its time went
        },
        "valid_fraction": (st.calibration.valid_fraction
                           if st.calibration is not None else None),
        # what the published maps hold: "raw" (each pixel's own estimate) or "posterior"
        # (serve --posterior); None before the first update
        "estimate": (estimate_of(st.calibration) if st.calibration is not None
                     else ("posterior" if st.live_posterior is not None else None)),
        "estimator": cal.status() if cal is not None else None,
        # "offe" while the camera has sent no frame (events-only estimate), then "onei"
        "method": "offe" if st.events_only is not None else "onei",
        "events_only": ({"events": st.events_only.n_events,
                         "steps": st.events_only.n_steps}
                        if st.events_only is not None else None),
        # serve --event-timing: OffE's sums of a camera with frames, the sensor time of its
        # latest maps, and why the latest update was not fused (None when it was)
        "event_timing": ({"events": st.timing.n_events, "steps": st.timing.n_steps,
                          "maps_t_us": st.timing_maps_t_us, "not_fused": st.timing_reason}
                         if st.timing is not None else None),
        # ROS 2 input (serve --ros2): messages per topic, events dropped outside the declared
        # size or reordered in a packet, each events topic's encoding
        "ros2": cam.ros.status() if cam.ros is not None else None,
    }


# ----------------------------------------------------------------------------- queries


def parse_query(params: Mapping[str, str]) -> tuple[str, list[str] | None, str | None]:
    """``(format, fields, estimate)`` of a calibration query (:class:`Rejected`
    ``bad_query``); ``estimate`` None: whichever the published maps hold."""
    fmt = params.get("format", "msgpack")
    if fmt not in QUERY_FORMATS:
        raise Rejected(f"format={fmt!r}: expected one of {', '.join(QUERY_FORMATS)}",
                       ErrorReason.BAD_QUERY)
    fields = None
    if params.get("fields"):
        names = [f for f in params["fields"].split(",") if f]
        try:
            # the calibration's maps, and the extra maps of some estimates
            check_map_names(f for f in names if f not in EXTRA_MAP_DTYPES)
        except EvcalError as exc:
            raise Rejected(str(exc), ErrorReason.BAD_QUERY) from None
        fields = names
    estimate = params.get("estimate") or None
    if estimate is not None and estimate not in QUERY_ESTIMATES:
        raise Rejected(f"estimate={estimate!r}: expected one of {', '.join(QUERY_ESTIMATES)}",
                       ErrorReason.BAD_QUERY)
    return fmt, fields, estimate


def no_calibration_message(st: CameraState) -> str:
    """Why a camera has no calibration yet, and what would give it one."""
    head = (f"camera {st.id!r} has no calibration yet ({st.counters.frames:,} frames, "
            f"{st.counters.events:,} events received)")
    cal = st.calibrator
    if cal is None:
        return f"{head}: it needs frames and events"
    return f"{head}: {cal.waiting_for() or 'its first update is being published'}"


def calibration_reply(st: CameraState, fmt: str, fields: list[str] | None,
                      estimate: str | None = None) -> tuple[bytes, str]:
    """The camera's current calibration as ``(payload, encoding)`` (call with its lock held);
    ``estimate``: ``"raw"`` or ``"posterior"`` maps (:meth:`CameraState.calibration_as`),
    None: the published ones.

    Raises :class:`Rejected` ``no_calibration`` before the first update.
    """
    msg = st.calibration_msg
    if msg is None:
        raise Rejected(no_calibration_message(st), ErrorReason.NO_CALIBRATION)
    if fmt == "msgpack" and fields is None and estimate is None:
        return msg, keys.ENC_CALIBRATION
    published = st.current_calibration()
    cal = published if estimate is None else st.calibration_as(estimate)
    assert cal is not None  # msg is not None
    if fmt == "msgpack" and fields is None and cal is published:
        return msg, keys.ENC_CALIBRATION
    t_us = int(st.calibration_t_us or 0)
    # an extra map asked for but not in this estimate (an OnEI camera's noise_rate_hz) is
    # left out, as the published message leaves it out
    extra = {k: v for k, v in st.extra_maps.items() if fields is None or k in fields}
    names = None if fields is None else [f for f in fields if f not in EXTRA_MAP_DTYPES]
    if fmt == "msgpack":
        return (encode_calibration(cal, t_us=t_us, seq=st.calibration_seq - 1, fields=names,
                                   extra_maps=extra), keys.ENC_CALIBRATION)
    return (calibration_npz_bytes(cal, names, extra={"t_us": t_us},
                                  arrays=extra if fields is not None else None),
            keys.ENC_CALIBRATION_NPZ)


def error_reply(exc: EvcalError) -> str:
    """The JSON body of an error reply to a query."""
    return strict_dumps({"reason": str(exc.reason), "message": str(exc)})


# ----------------------------------------------------------------------------- errors


class ErrorLimiter:
    """A token bucket: at most ``rate_hz`` error publications per second (per camera)."""

    def __init__(self, rate_hz: float) -> None:
        self.rate_hz = float(rate_hz)
        self._tokens = self.rate_hz
        self._last = time.monotonic()

    def allow(self, now_s: float | None = None) -> bool:
        now = time.monotonic() if now_s is None else now_s
        self._tokens = min(self.rate_hz, self._tokens + (now - self._last) * self.rate_hz)
        self._last = now
        if self._tokens < 1.0:
            return False
        self._tokens -= 1.0
        return True


def error_body(rec: Rejection, st: CameraState | None) -> bytes:
    """The JSON published on ``<prefix>/<camera>/errors`` for one rejected input."""
    body: dict[str, Any] = {"camera": rec.camera, "stream": rec.stream, "reason": rec.reason,
                            "message": rec.message, "wall_time": time.time()}
    if st is not None:
        body["errors_total"] = st.counters.errors_total
        body["suppressed"] = st.counters.errors_suppressed
    return strict_dumps(body).encode()


# ----------------------------------------------------------------------------- the recorder


class ObserverThread:
    """Runs the recorder's calls in a thread of its own, off the cameras' publication path.

    A camera worker only appends ``(method, args, nbytes)`` to a queue bounded by
    ``max_bytes`` of referenced arrays (the events, frames and maps are not copied: the worker
    never modifies them after the call); when the recorder falls behind, calls are dropped and
    counted (``dropped``), never waited for, and the recorder is told with
    ``discard(camera, n)``.
    """

    def __init__(self, call: Callable[..., None], *, max_bytes: int = 256 << 20) -> None:
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

    def submit(self, method: str, args: tuple[Any, ...]) -> bool:
        """Queue one call; False (and counted) when the recorder is too far behind."""
        camera = str(args[0])
        nbytes = sum(int(a.nbytes) for a in args if isinstance(a, np.ndarray))
        if method == "updated":
            nbytes += sum(int(a.nbytes) for a in args[1].maps().values())
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


__all__ = ["ErrorLimiter", "ObserverThread", "calibration_reply", "camera_status",
           "error_body", "error_reply", "parse_query"]
