"""evcal's calibrations as ROS 2 Images over rmw_zenoh (``evcal serve --ros2``): for each
camera, its contrast, bias and special maps on ``/<camera>/calibration/{contrast,bias,
special}`` (``sensor_msgs/Image``, TRANSIENT_LOCAL), in the wire of each rmw_zenoh profile
served (:mod:`evcal.service.ros2`: keys, tokens, attachments, distributions).
"""

from __future__ import annotations

import logging
import re
import threading
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from ..calibration import Calibration
from ..io.bagdecode import IMAGE
from ..io.ros2msg import image_cdr
from .camera import CalibrationUpdate
from .ros2 import (
    DEFAULT_DISTRO,
    ENCODING,
    HEARTBEAT_S,
    OUTPUT_MAPS,
    OUTPUT_QOS,
    SPECIAL_SCALE,
    RosDistro,
    RosNode,
    RosPublication,
)

log = logging.getLogger("evcal.service")

_ROS_CHUNK = re.compile(r"[^A-Za-z0-9_]")


def ros_name(camera: str) -> str:
    """A camera id as a ROS namespace (``/lab/rig1/cam0``): characters other than letters,
    digits and ``_`` become ``_``, a chunk starting with a digit gets a leading ``_``."""
    chunks = []
    for chunk in camera.strip("/").split("/"):
        c = _ROS_CHUNK.sub("_", chunk)
        chunks.append("_" + c if c[:1].isdigit() else c)
    return "/" + "/".join(chunks)


def output_topic(camera: str, name: str) -> str:
    """The ROS 2 topic of one of a camera's calibration maps (:data:`OUTPUT_MAPS`)."""
    return f"{ros_name(camera)}/calibration/{name}"


PutFn = Callable[..., None]  # put(key, payload, encoding, *, attachment=...)


class Declared(Protocol):
    """Something declared on the session that can be undeclared (a token, a queryable)."""

    def undeclare(self) -> None: ...


class Latched(Declared, Protocol):
    """A publisher whose last sample reaches late joiners (``transport.LatchedPublisher``)."""

    def put(self, payload: bytes, *, attachment: bytes | None = None) -> None: ...


class RosSession(Protocol):
    """What the ROS publisher needs of the transport (``transport.Transport`` has it)."""

    def latched(self, key: str, encoding: str, *, depth: int = 1, block: bool = False,
                heartbeat_s: float | None = None) -> Latched: ...

    def token(self, key: str) -> Declared: ...

    def queryable(self, key: str, callback: Callable[[Any], None], *,
                  complete: bool = True) -> Declared: ...


@dataclass
class _Output:
    """One calibration map of one camera as one distribution's publication."""

    pub: RosPublication
    handles: list[Declared]
    latched: Latched | None = None
    last: tuple[bytes, bytes] | None = None  # (CDR, attachment) for publication caches


class RosCalibrationPublisher:
    """Publishes each calibration update as ROS 2 Images (see the module docstring), for each
    rmw_zenoh profile of ``distros()`` (``--ros-distro``: one; ``auto``:
    :meth:`DistroDetector.active`).

    Called from the cameras' worker threads (:meth:`publish`); a camera's publications and
    their tokens are made with its first update, per profile, and undeclared when a profile is
    no longer active. With ``session`` (a ``Transport``) the images are TRANSIENT_LOCAL as
    rmw_zenoh makes them: an advanced publisher keeping the last image of each topic for
    subscribers that join later (and, for the profiles of the releases that had it, a
    publication cache's queryable on ``<zid>/<key>``); congestion control DROP, so a slow ROS
    subscriber never stalls a camera. Without it, ``put`` (``Transport.put``) and ``declare``
    (``Transport.token``) publish plain samples (tests).
    """

    def __init__(self, node: RosNode, put: PutFn, declare: Callable[[str], Any], *,
                 session: RosSession | None = None,
                 distros: Callable[[], tuple[RosDistro, ...]] | None = None) -> None:
        self.node = node
        self._put = put
        self._declare = declare
        self._session = session
        self._distros = distros or (lambda: (DEFAULT_DISTRO,))
        self._outs: dict[str, dict[tuple[str, str], _Output]] = {}  # camera -> (distro, map)
        self._lock = threading.Lock()
        self.published = 0
        self.profiles: tuple[str, ...] = ()  # the profiles of the latest publication

    def _output(self, camera: str, name: str, profile: RosDistro) -> _Output:
        pub = RosPublication(self.node, output_topic(camera, name), IMAGE, qos=OUTPUT_QOS,
                             distro=profile)
        if self._session is None:
            self._declare(pub.token)
            return _Output(pub, [])
        s = self._session
        latched = s.latched(pub.key, ENCODING, depth=OUTPUT_QOS.depth, heartbeat_s=HEARTBEAT_S)
        out = _Output(pub, [latched, s.token(pub.token)], latched)
        if profile.publication_cache:
            # rmw_zenoh 0.1.0-0.1.1 and 0.2.0-0.2.1: a TRANSIENT_LOCAL subscriber queries
            # "*/<key>" (and "<zid>/<key>" for each new publisher), accepting replies on any key
            def answer(req: Any, out: _Output = out) -> None:
                last = out.last
                if last is not None:
                    req.reply(out.pub.key, last[0], ENCODING, attachment=last[1])

            out.handles.append(s.queryable(f"{self.node.zid}/{pub.key}", answer))
        return out

    def _publications(self, camera: str) -> list[_Output]:
        profiles = self._distros()
        want = {(d.name, m) for d in profiles for m in OUTPUT_MAPS}
        with self._lock:
            names = tuple(d.name for d in profiles)
            if names != self.profiles:
                log.info("ROS 2 calibration images as rmw_zenoh of %s",
                         ", ".join(f"{d.name} ({d.releases})" for d in profiles))
                self.profiles = names
            outs = self._outs.setdefault(camera, {})
            for gone in [k for k in outs if k not in want]:
                self._undeclare(outs.pop(gone))
            for d in profiles:
                for m in OUTPUT_MAPS:
                    if (d.name, m) not in outs:
                        outs[(d.name, m)] = self._output(camera, m, d)
            return [outs[(d.name, m)] for d in profiles for m in OUTPUT_MAPS]

    @staticmethod
    def _undeclare(out: _Output) -> None:
        for h in out.handles:
            try:
                h.undeclare()
            except Exception:  # the session is closing
                log.debug("undeclaring %s failed", out.pub.key, exc_info=True)

    def forget(self, camera: str) -> None:
        """Undeclare a camera's publications: late joiners get its images no more."""
        with self._lock:
            outs = self._outs.pop(camera, {})
        for out in outs.values():
            self._undeclare(out)

    def images(self, camera: str, upd: CalibrationUpdate) -> dict[str, bytes]:
        """The CDR of the update's three Images, by map name."""
        return self._images(camera, upd.calibration, upd.t_us)

    def _images(self, camera: str, cal: Calibration, t_us: int) -> dict[str, bytes]:
        t_ns = int(t_us) * 1000
        frame_id = ros_name(camera).strip("/")
        special = (cal.special.astype(np.uint16) * SPECIAL_SCALE).astype(np.uint8)
        return {
            "contrast": image_cdr(cal.contrast, t_ns=t_ns, frame_id=frame_id, encoding="32FC1"),
            "bias": image_cdr(cal.bias, t_ns=t_ns, frame_id=frame_id, encoding="32FC1"),
            "special": image_cdr(special, t_ns=t_ns, frame_id=frame_id, encoding="mono8"),
        }

    def publish(self, camera: str, upd: CalibrationUpdate) -> None:
        """Publish one update (raises what the transport raises; the service counts it)."""
        self.publish_calibration(camera, upd.calibration, upd.t_us)

    def publish_calibration(self, camera: str, cal: Calibration, t_us: int) -> None:
        """Publish ``cal`` (sensor time ``t_us``) as the camera's images: an update's, or a
        calibration restored from a snapshot, for late joiners."""
        outs = self._publications(camera)
        images = self._images(camera, cal, t_us)
        for out in outs:
            data = images[out.pub.topic.rpartition("/")[2]]
            att = out.pub.attachment()
            out.last = (data, att)
            if out.latched is not None:
                out.latched.put(data, attachment=att)
            else:
                self._put(out.pub.key, data, ENCODING, attachment=att)
        self.published += 1
