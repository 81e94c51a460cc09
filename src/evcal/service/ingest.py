"""Getting messages to a camera's state machine: bounded queues, decoder and worker threads.

Per camera, :meth:`CameraWorker.enqueue` (called in the transport's receive thread) only copies
the payload reference into the camera's bounded queue; a decoder thread decodes and
validates the wire messages (numpy, mostly outside the GIL) and hands them to the camera's
worker thread, at most two messages ahead; the worker runs the camera's
:class:`~evcal.service.camera.CameraState` and passes the records it returns to ``emit``
(the outputs layer). Nothing else touches the state but under ``CameraWorker.lock`` (snapshots,
status), so the state machine itself stays single-threaded.

Back-pressure (both input keys share the camera's queue of ``queue_bytes``): with
``block=False`` a message that does not fit is dropped and counted (``dropped``), the receive
thread never waits; with ``block=True`` the receive thread waits for room (lossless with
blocking publishers, but it stalls the session's whole receive path meanwhile).
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from collections.abc import Callable, Sequence
from typing import Any

from ..errors import ErrorReason, EvcalError
from ..io.wire import decode_events, decode_frame
from .camera import CameraState, Output, Rejected
from .ros2 import RosDecoder, RosSample

log = logging.getLogger("evcal.service")

EmitFn = Callable[["CameraWorker", Sequence[Output]], None]


class BoundedQueue:
    """FIFO bounded by the total size of its items (``size_of``; 1 per item by default).

    ``put`` drops (returns False) or, with ``block``, waits for room when full; a single item
    larger than the bound is accepted when the queue is empty. After ``close`` puts fail and
    ``get`` still returns what is in, then None at once.
    """

    def __init__(self, limit: int, size_of: Callable[[Any], int] | None = None) -> None:
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


def _payload_bytes(item: tuple[str, Any, float]) -> int:
    payload = item[1]  # bytes, a RosSample, or an EvcalError (a refusal, 0 bytes)
    return 0 if isinstance(payload, BaseException) else len(payload)


class CameraQueue(BoundedQueue):
    """A camera's input: ``(kind, payload, t_recv, drops_before)`` bounded in payload bytes
    (``drops_before``: messages of that kind this queue refused just before this one).

    A payload may also be an :class:`~evcal.errors.EvcalError` (a message refused on arrival,
    0 bytes): it goes through the queue so that the worker counts it in stream order; or a
    :class:`~evcal.service.ros2.RosSample` (a ROS 2 message, decoded from its CDR).
    """

    def __init__(self, max_bytes: int) -> None:
        super().__init__(max_bytes, _payload_bytes)

    @property
    def nbytes(self) -> int:
        return self.used


class CameraWorker:
    """One camera's threads and queues around its :class:`CameraState`."""

    def __init__(self, state: CameraState, *, emit: EmitFn, queue_bytes: int,
                 max_message_bytes: int, block: bool) -> None:
        self.state = state
        self.id = state.id
        self._emit = emit
        self.max_message_bytes = int(max_message_bytes)
        self.block = block
        self.queue = CameraQueue(queue_bytes)
        # decoded messages for the worker: decoding runs at most 2 messages ahead of OnEI
        self.handoff = BoundedQueue(2)
        self.in_flight = 0  # messages queued, being decoded or processed
        # messages the queue refused (written by receive threads only, under _flight_lock)
        self.dropped = {"events": 0, "frames": 0}
        self._drops_since = {"events": 0, "frames": 0}
        self._flight_lock = threading.Lock()
        self.lock = threading.Lock()  # the state machine: worker, snapshots, status
        self.started_wall = time.time()
        self.started_s = time.monotonic()
        self.last_input_s = self.started_s  # monotonic time of the latest message
        self.limiter: Any = None  # the outputs' error limiter of this camera
        self._ros: RosDecoder | None = None  # ROS 2 decoding state (decoder thread only)
        self._stop = threading.Event()
        self.decoder = threading.Thread(target=self._decode_loop,
                                        name=f"evcal-dec-{self.id}", daemon=True)
        self.thread = threading.Thread(target=self._run, name=f"evcal-cam-{self.id}",
                                       daemon=True)

    # the state's read-outs, for operators and tests
    @property
    def counters(self) -> Any:
        return self.state.counters

    @property
    def calibration(self) -> Any:
        return self.state.calibration

    @property
    def sensor(self) -> Any:
        return self.state.sensor

    @property
    def ros(self) -> RosDecoder | None:
        """The camera's ROS 2 decoding state (None until a ROS 2 message came)."""
        return self._ros

    # -- input side (receive thread) -----------------------------------------------------------

    def enqueue(self, kind: str, payload: bytes | RosSample, t_recv: float) -> None:
        """Queue one message (any receive thread; never touches the state)."""
        self.last_input_s = t_recv
        item: Any = payload
        if len(payload) > self.max_message_bytes:
            item = Rejected(f"{kind} message of {len(payload)} bytes exceeds the limit of "
                            f"{self.max_message_bytes} bytes (--max-message-mb)",
                            ErrorReason.TOO_LARGE)
        with self._flight_lock:  # counted before the put: the worker may finish it at once
            self.in_flight += 1
            drops_before = self._drops_since[kind]
            self._drops_since[kind] = 0
        if not self.queue.put((kind, item, t_recv, drops_before), block=self.block):
            with self._flight_lock:
                self.in_flight -= 1
                self.dropped[kind] += 1
                # the next accepted message's sequence gap includes this one: not upstream loss
                self._drops_since[kind] += drops_before + 1

    def fold_dropped(self) -> None:
        """Move the receive threads' drop counts into the state's counters (call with
        ``self.lock`` held: before a status or a snapshot)."""
        with self._flight_lock:
            for kind, n in self.dropped.items():
                self.state.counters.dropped[kind] += n
                self.dropped[kind] = 0

    def dropped_total(self) -> dict[str, int]:
        """The messages dropped so far, per stream: those in the state's counters and those
        the receive threads counted since the last :meth:`fold_dropped` (changes nothing)."""
        with self._flight_lock:
            counted = self.state.counters.dropped
            return {kind: counted.get(kind, 0) + self.dropped.get(kind, 0)
                    for kind in {**counted, **self.dropped}}

    def _done(self) -> None:
        with self._flight_lock:
            self.in_flight -= 1

    # -- threads -------------------------------------------------------------------------------

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

    def discard(self) -> None:
        """End the decoder and the worker without waiting for them or for what is queued
        (a camera dropped with nothing in flight: it costs no thread and no wait in the
        receive thread that needs its slot)."""
        self._stop.set()
        self.queue.close()
        self.handoff.close()

    def _decode_loop(self) -> None:
        """Decoder thread: wire decoding and validation, in parallel with the worker."""
        while not self._stop.is_set():
            item = self.queue.get(0.2)
            if item is None:
                continue
            kind, payload, t_recv, drops_before = item
            decoded: Any
            try:
                if isinstance(payload, EvcalError):
                    decoded = payload
                elif isinstance(payload, RosSample):
                    if self._ros is None:
                        self._ros = RosDecoder()
                    decoded = self._ros.decode(kind, payload)
                elif kind == "events":
                    decoded = decode_events(payload)
                else:
                    decoded = decode_frame(payload)
            except EvcalError as exc:
                decoded = exc
            except Exception as exc:  # a bug must not kill the camera's decoder
                log.exception("camera %s: unexpected error decoding a %s message", self.id,
                              kind)
                decoded = Rejected(f"{type(exc).__name__}: {exc}", ErrorReason.INTERNAL)
            if not self.handoff.put((kind, decoded, _payload_bytes(item), t_recv,
                                     drops_before)):
                self._done()
                return

    def _idle(self) -> None:
        """The worker's work between messages (:meth:`CameraState.on_idle`)."""
        with self.lock:
            try:
                out = self.state.on_idle(now_s=time.monotonic())
                if out:
                    self._emit(self, out)
            except Exception:  # a bug must not kill the camera's worker
                log.exception("camera %s: unexpected error between messages", self.id)

    def _run(self) -> None:
        """Worker thread: the state machine, then the outputs."""
        while True:
            item = self.handoff.get(0.2)
            if item is None:
                if self.handoff.closed:
                    return
                self._idle()
                continue
            kind, decoded, nbytes, t_recv, drops_before = item
            # the outputs go out under the lock: a status that counts a frame comes after the
            # publication of the calibration that frame triggered
            with self.lock:
                out: Sequence[Output] = ()
                try:
                    if isinstance(decoded, EvcalError):  # refused before its seq was read
                        out = [self.state.reject_unread(kind, decoded, drops_before)]
                    elif kind == "events":
                        out = self.state.on_events(decoded, nbytes, now_s=time.monotonic(),
                                                   drops_before=drops_before)
                    else:
                        out = self.state.on_frame(decoded, nbytes, t_recv_s=t_recv,
                                                  t_start_s=time.monotonic(),
                                                  drops_before=drops_before)
                except EvcalError as exc:
                    out = [self.state.reject(kind, exc)]
                except Exception as exc:  # a bug must not kill the camera's worker
                    log.exception("camera %s: unexpected error on a %s message", self.id, kind)
                    out = [self.state.reject(kind, Rejected(f"{type(exc).__name__}: {exc}",
                                                            ErrorReason.INTERNAL))]
                try:
                    if out:
                        self._emit(self, out)
                except Exception:  # the outputs must not kill the worker either
                    log.exception("camera %s: unexpected error publishing outputs", self.id)
            self._done()
