"""What a service answers for and says of its cameras: which cameras and keys are its own,
calibration and status replies, the status it publishes, the cameras document.
:class:`ServiceReplies` is a base of :class:`~evcal.service.core.Service`: it reads the
cameras (each under its lock) and never changes them; taking in samples, slots, snapshots
and the lifecycle are the service's own.
"""

from __future__ import annotations

import logging
import os
from collections import OrderedDict
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from ..errors import ErrorReason, EvcalError
from ..jsonable import strict_dumps
from . import keys
from .camera import Rejected
from .ingest import CameraWorker
from .outputs import calibration_reply, camera_status, parse_query

log = logging.getLogger("evcal.service")

if TYPE_CHECKING:
    from .core import Observer, Refusal, ServiceConfig
    from .gcpolicy import GcPolicy
    from .state import StateStore


class ServiceReplies:
    """The replies of :class:`~evcal.service.core.Service` (which sets these attributes)."""

    config: ServiceConfig
    instance: str
    cameras: dict[str, CameraWorker]
    refused: OrderedDict[str, Refusal]
    store: StateStore | None
    observer: Observer | None
    gc: GcPolicy | None
    shm: Any
    _match: Callable[[str, str], bool]
    rejected_cameras: int
    invalid_camera_ids: int
    refused_while_closing: int
    evicted_cameras: int
    forgotten_cameras: int
    tick_errors: int
    publish_errors: int
    observer_errors: int

    claim: str  # the key expression of the cameras it claims

    @property
    def observer_dropped(self) -> int:
        raise NotImplementedError

    def publish(self, key: str, payload: bytes, encoding: str, *,
                attachment: bytes | None = None) -> None:
        raise NotImplementedError

    def claims(self, camera: str) -> bool:
        """Whether this instance serves ``camera``: inside its ``cameras`` claim and, with a
        shard, the shard's own."""
        return self.owns(camera) and self._match(self.claim,
                                                 f"{self.config.prefix.strip('/')}/{camera}")

    def owns(self, camera: str) -> bool:
        """Whether ``camera`` falls in this instance's shard (always, without a shard)."""
        shard = self.config.shard
        return shard is None or keys.shard_of(camera, shard[1]) == shard[0]

    def accepts_key(self, key: str) -> bool:
        """Whether a sample on ``key`` is for this instance's shard, judged from the key alone
        (the transport asks before copying the payload). Keys that are not
        ``<prefix>/<camera>/<kind>`` are accepted, for :meth:`on_sample` to refuse."""
        if self.config.shard is None:
            return True
        parsed = keys.split_camera_key(self.config.prefix, key)
        return parsed is None or self.owns(parsed[0])

    def _publish_status(self) -> None:
        for cam in list(self.cameras.values()):
            try:
                payload = strict_dumps(self.status(cam)).encode()
            except Exception:
                self.tick_errors += 1
                log.exception("camera %s: status failed", cam.id)
                continue
            self.publish(self.key(cam.id, "status"), payload, keys.ENC_STATUS)

    def key(self, camera: str, kind: str) -> str:
        return keys.camera_key(self.config.prefix, camera, kind)

    def on_probation(self, cam: CameraWorker) -> bool:
        """Whether ``cam`` has not yet sent enough to keep its slot (see ``ServiceConfig``)."""
        return cam.state.on_probation(min_frames=self.config.probation_frames,
                                      min_events=self.config.probation_events)

    def query_calibration(self, query_key: str, params: dict[str, str]
                          ) -> list[tuple[str, bytes, str]]:
        """Replies ``(key, payload, encoding)`` for every camera whose calibration key
        intersects ``query_key``; raises :class:`Rejected` if the query is malformed or no
        matching camera has a calibration yet."""
        fmt, fields, estimate = parse_query(params)
        out, problems = [], []
        for cam in list(self.cameras.values()):
            key = self.key(cam.id, "calibration")
            if not self._match(query_key, key):
                continue
            try:
                with cam.lock:
                    payload, enc = calibration_reply(cam.state, fmt, fields, estimate)
            except EvcalError as exc:
                problems.append(exc)
                continue
            out.append((key, payload, enc))
        if not out and problems:
            # one reason for all (a query the cameras cannot answer as asked: bad_query),
            # else none has a calibration to give
            reasons = {str(p.reason) for p in problems}
            reason = (problems[0].reason if len(reasons) == 1
                      else ErrorReason.NO_CALIBRATION)
            raise Rejected("; ".join(map(str, problems)), reason)
        return out

    def status(self, cam: CameraWorker) -> dict[str, Any]:
        with cam.lock:
            doc = camera_status(cam)
        doc["probation"] = self.on_probation(cam)
        rec = self.refused.get(cam.id)
        doc["refused"] = rec.doc() if rec is not None else None  # refused before, or displaced
        return doc

    def refused_status(self, camera_id: str) -> dict[str, Any] | None:
        """The ``status`` document of a camera id that has no slot: its refusal (None if it
        was never refused or is served now)."""
        rec = self.refused.get(camera_id)
        if rec is None or camera_id in self.cameras:
            return None
        return {"camera": camera_id, "state": "refused", "refused": rec.doc()}

    def query_status(self, query_key: str) -> list[tuple[str, bytes, str]]:
        """Status replies for the cameras whose status key intersects ``query_key``; a query
        for one camera id without a slot is answered with its refusal, so that its publisher
        learns why nothing is processed (only for an exact key: a wildcard query lists the
        cameras served)."""
        out = [(self.key(cam.id, "status"), strict_dumps(self.status(cam)).encode(),
                keys.ENC_STATUS)
               for cam in list(self.cameras.values())
               if self._match(query_key, self.key(cam.id, "status"))]
        if not out and "*" not in query_key:
            parsed = keys.split_camera_key(self.config.prefix, query_key)
            doc = (self.refused_status(parsed[0])
                   if parsed is not None and parsed[1] == "status" else None)
            if doc is not None:
                out.append((query_key, strict_dumps(doc).encode(), keys.ENC_STATUS))
        return out

    def cameras_info(self) -> dict[str, Any]:
        return {
            "instance": self.instance,
            "prefix": self.config.prefix,
            "claims": self.config.cameras,
            "shard": (f"{self.config.shard[0]}/{self.config.shard[1]}"
                      if self.config.shard is not None else None),
            "pid": os.getpid(),
            "rejected_cameras": self.rejected_cameras,
            "refused_camera_ids": len(self.refused),
            "invalid_camera_ids": self.invalid_camera_ids,
            "refused_while_closing": self.refused_while_closing,
            "evicted_cameras": self.evicted_cameras,
            "forgotten_cameras": self.forgotten_cameras,
            "bad_snapshots": self.store.bad if self.store is not None else 0,
            "tick_errors": self.tick_errors,
            "publish_errors": self.publish_errors,
            "recorder_errors": self.observer_errors,
            "recorder_dropped": self.observer_dropped,
            "recorder": (self.observer.state()
                         if self.observer is not None and hasattr(self.observer, "state")
                         else None),
            "gc": self.gc.stats() if self.gc is not None else None,
            "shm": self.shm.stats() if self.shm is not None else None,
            "cameras": [{"id": c.id, "sensor": str(c.sensor) if c.sensor else None,
                         "updates": c.counters.updates, "events": c.counters.events,
                         "last_update_t_us": c.state.calibration_t_us}
                        for c in sorted(self.cameras.values(), key=lambda c: c.id)],
        }
