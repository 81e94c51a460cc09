"""``evcal replay BAG --ros2``: publish a ROS bag as its ROS 2 driver would, over rmw_zenoh.

Every topic of the bag (or of ``--topic``) is published unchanged (its CDR; a ROS 1 bag's
messages converted) on rmw_zenoh's key ``<domain>/<topic>/<dds type>/<type hash>``, with
rmw_zenoh's attachment (sequence number from 1, source timestamp, GID) and liveliness tokens
(a node ``evcal_replay`` and a publisher per topic), paced by the bag's log times scaled by
``--speed`` (``--max-rate``: as fast as the subscribers allow, congestion control BLOCK).
A topic of a type evcal does not know (its typestore: the ROS 2 standard types and the
event camera messages), whose hash it cannot compute, is skipped with a note.

Delivery is checked as ``evcal replay`` does it, through the evcal service's status of the
cameras the topics feed by default (their namespaces; a service run with ``--ros-topic-map``
names other cameras, and delivery is then not confirmed).
"""

from __future__ import annotations

import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from evcal.io.ros2msg import type_hash
from evcal.io.rosbag import bag_topics, iter_bag_messages
from evcal.service import keys
from evcal.service.ros2 import ENCODING, INPUT_TYPES, RosNode, RosPublication, TopicMap
from evcal.service.transport import Publisher, Transport

from .replay import _delivered, _status

NODE = "evcal_replay"


@dataclass
class BagReplayStats:
    """What a bag replay sent, per topic, and what the service says it received."""

    messages: dict[str, int] = field(default_factory=dict)
    bytes: int = 0
    seconds: float = 0.0
    subscribed: bool = True
    unmatched_messages: int = 0
    skipped_topics: dict[str, str] = field(default_factory=dict)  # topic -> why
    cameras: dict[str, list[str]] = field(default_factory=dict)  # camera -> its input topics
    delivered: dict[str, dict[str, int]] = field(default_factory=dict)  # camera -> account

    @property
    def total(self) -> int:
        return sum(self.messages.values())

    def camera_messages(self, camera: str) -> int:
        return sum(self.messages.get(t, 0) for t in self.cameras.get(camera, []))


def _hash(msgtype: str) -> str | None:
    try:
        return type_hash(msgtype)
    except ValueError:
        return None


def replay_bag(t: Transport, path: str | Path, *, domain: int = 0,
               speed: float | None = 1.0, topics: set[str] | None = None,
               stop: threading.Event | None = None, prefix: str = "evcal",
               wait_subscriber_s: float = 5.0) -> BagReplayStats:
    """Publish the bag at ``path`` (``speed=None``: as fast as possible)."""
    stop = stop or threading.Event()
    stats = BagReplayStats()
    types = bag_topics(path)
    chosen = {tp: ty for tp, ty in types.items() if topics is None or tp in topics}
    node = RosNode(zid=t.zid, domain=domain, name=NODE)
    t.token(node.node_token())
    pubs: dict[str, tuple[RosPublication, Publisher]] = {}
    default_map = TopicMap()
    for topic, msgtype in sorted(chosen.items()):
        h = _hash(msgtype)
        if h is None:
            stats.skipped_topics[topic] = f"type {msgtype} is not known to evcal"
            continue
        pub = RosPublication(node, topic, msgtype, h)
        t.token(pub.token)
        pubs[topic] = (pub, t.publisher(pub.key, ENCODING, block=True))
        stats.messages[topic] = 0
        kind = INPUT_TYPES.get(msgtype)
        camera = default_map.camera(topic, kind) if kind is not None else None
        if camera is not None:
            stats.cameras.setdefault(camera, []).append(topic)
    deadline = time.monotonic() + wait_subscriber_s
    while not any(p.has_subscribers for _, p in pubs.values()):
        if time.monotonic() > deadline or stop.is_set() or not pubs:
            stats.subscribed = False
            return stats
        time.sleep(0.02)
    status_keys = {c: keys.camera_key(prefix, c, "status") for c in stats.cameras}
    before = {c: _status(t, k) for c, k in status_keys.items()}
    wall0 = time.monotonic()
    t0: int | None = None
    for m in iter_bag_messages(path, topics=set(pubs)):
        if stop.is_set():
            break
        if t0 is None:
            t0 = m.t_ns
        if speed:
            delay = wall0 + (m.t_ns - t0) * 1e-9 / speed - time.monotonic()
            if delay > 0:
                stop.wait(delay)
        pub, zpub = pubs[m.topic]
        zpub.put(m.data, attachment=pub.attachment())
        stats.unmatched_messages += not zpub.has_subscribers
        stats.messages[m.topic] += 1
        stats.bytes += len(m.data)
    # what was put has left before the session closes: a service's reply on the same link
    # (a busy one answers late: up to 30 s), else half a second
    key = next((k for c, k in status_keys.items() if before[c] is not None), None)
    for _ in range(6 if key is not None else 1):
        if t.flush(key, timeout_s=5.0, linger_s=0.0 if key is not None else 0.5):
            break
    stats.seconds = time.monotonic() - wall0
    # a service is up (its liveliness token): a camera it has not answered for yet is being
    # created; else (a recorder only) one try
    wait_s = STATUS_WAIT_S if status_keys and _service_alive(t, prefix) else 0.0
    for camera, key in status_keys.items():
        if _status_soon(t, key, wait_s=wait_s) is not None:
            stats.delivered[camera] = _delivered(t, key, before[camera] or {},
                                                 stats.camera_messages(camera))
    return stats


# how long a camera new to the service may take to answer for itself after the run (a busy
# service creates it when its first message is taken off the queue)
STATUS_WAIT_S = 10.0


def _service_alive(t: Transport, prefix: str) -> bool:
    try:
        return bool(t.alive(keys.service_token_key(prefix), timeout_s=1.0))
    except Exception:  # noqa: BLE001 - a diagnosis only
        return False


def _status_soon(t: Transport, key: str, *, wait_s: float) -> dict[str, Any] | None:
    """The camera's status, asked again for up to ``wait_s`` (None: nobody answered)."""
    deadline = time.monotonic() + wait_s
    while True:
        st = _status(t, key)
        if st is not None or time.monotonic() > deadline:
            return st
        time.sleep(0.2)


def report(prog: str, stats: BagReplayStats, wait_subscriber_s: float, domain: int) -> int:
    """Print what was sent and delivered; the exit code (as ``evcal replay``'s)."""
    for topic, why in stats.skipped_topics.items():
        print(f"{prog}: skipped {topic}: {why}", file=sys.stderr)
    if not stats.subscribed:
        print(f"{prog}: nobody subscribes to the bag's topics in ROS domain {domain} after "
              f"{wait_subscriber_s:g} s (is `evcal serve --ros2` or a ROS 2 node running and "
              "reachable?); nothing was sent", file=sys.stderr)
        return 3
    print(f"{prog}: sent {stats.total} messages ({stats.bytes / 1e6:.1f} MB) in "
          f"{stats.seconds:.2f} s on {len(stats.messages)} topics in ROS domain {domain}: "
          + ", ".join(f"{tp} {n}" for tp, n in stats.messages.items()), file=sys.stderr)
    code = 0
    if stats.unmatched_messages:
        print(f"{prog}: {stats.unmatched_messages} messages were sent while nobody subscribed "
              "(lost)", file=sys.stderr)
        code = 4
    for camera in stats.cameras:
        d: dict[str, Any] | None = stats.delivered.get(camera)
        if d is None:
            print(f"{prog}: camera {camera}: delivery not confirmed (no evcal service "
                  "answered for it)", file=sys.stderr)
            continue
        sent = stats.camera_messages(camera)
        print(f"{prog}: camera {camera}: the service processed {d['event_messages']} event "
              f"messages ({d['events']} events) and {d['frames']} frames, dropped "
              f"{d['dropped_messages']} and rejected {d['rejected_messages']} of {sent}",
              file=sys.stderr)
        if d["accounted_messages"] < sent or d["dropped_messages"] or d["rejected_messages"]:
            code = 4
    return code
