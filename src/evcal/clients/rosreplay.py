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
names other cameras, and delivery is then not confirmed), and the exit code follows the same
table (:data:`evcal.clients.delivery.EXIT_CODES`): the first outcome in its order that applies
to the run or to any camera names the cause. A bag none of whose topics feeds an evcal camera
is unconfirmed (7) when something subscribed.
"""

from __future__ import annotations

import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

from evcal.io.ros2msg import type_hash
from evcal.io.rosbag import bag_topics, iter_bag_messages
from evcal.service import keys
from evcal.service.ros2 import (
    ENCODING,
    INPUT_TYPES,
    DistroDetector,
    RosDistro,
    RosNode,
    RosPublication,
    TopicMap,
)
from evcal.service.ros2 import (
    distro as distro_profile,
)
from evcal.service.transport import Publisher, Transport

from .delivery import (
    CONFIRM_TIMEOUT_S,
    EXIT_CODES,
    EXIT_ERROR,
    EXIT_LOST,
    EXIT_NOBODY,
    EXIT_OK,
    EXIT_UNCONFIRMED,
    STATUS_QUERY_S,
    STOPPED_CONFIRM_S,
    ReplayStats,
    StatusProbe,
    confirm,
    print_account,
    print_outcome,
    probe_status,
)
from .delivery import exit_code as camera_exit_code

NODE = "evcal_replay"
# the exit codes in the order they are judged (EXIT_CODES lists 0 first)
JUDGED = tuple(code for code, _, _ in (*EXIT_CODES[1:], EXIT_CODES[0]))


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
    # camera -> the service's account of its messages (``evcal replay``'s, one per camera:
    # ``delivered``, ``confirmed``, ``refusal``, ...); cameras sent nothing are not in it
    accounts: dict[str, ReplayStats] = field(default_factory=dict)
    stopped: bool = False  # SIGINT/SIGTERM (``stop``) ended the run early
    distro: str = ""  # the rmw_zenoh wire it was published in (ros2.DISTROS)
    send_error: str | None = None  # a put raised (the session failed)

    @property
    def total(self) -> int:
        return sum(self.messages.values())

    @property
    def delivered(self) -> dict[str, dict[str, int]]:
        """camera -> the service's account of its messages (cameras it answered for)."""
        return {c: a.delivered for c, a in self.accounts.items() if a.delivered is not None}

    def camera_messages(self, camera: str) -> int:
        return sum(self.messages.get(t, 0) for t in self.cameras.get(camera, []))


def exit_code(stats: BagReplayStats) -> int:
    """The exit code of a bag replay: ``evcal replay``'s table, judged in its order over the
    run (error, nobody there, messages sent while nobody subscribed) and each camera's
    account (refused, dropped, lost, unconfirmed)."""
    if stats.send_error is not None:
        return EXIT_ERROR
    if not stats.subscribed:
        return EXIT_NOBODY
    codes = [camera_exit_code(acc) for acc in stats.accounts.values()]
    if stats.unmatched_messages:
        codes.append(EXIT_LOST)
    if not stats.accounts and stats.total:
        codes.append(EXIT_UNCONFIRMED)  # sent, but to no evcal camera that could confirm it
    return min(codes, key=JUDGED.index, default=EXIT_OK)


def _hash(msgtype: str) -> str | None:
    try:
        return type_hash(msgtype)
    except ValueError:
        return None


def wire_of(t: Transport, domain: int, name: str) -> RosDistro:
    """The rmw_zenoh wire to publish in: ``--ros-distro NAME``'s, or for ``auto`` the one
    the domain's liveliness tokens say (:class:`~evcal.service.ros2.DistroDetector`; one
    profile: the current wire when tokens of both hash styles, or none, are there)."""
    if name != "auto":
        return distro_profile(name)
    detector = DistroDetector(own_zid=t.zid)
    for token in t.alive(f"@ros2_lv/{domain}/**", timeout_s=1.0):
        detector.seen_token(token)
    return detector.active()[0]


def replay_bag(t: Transport, path: str | Path, *, domain: int = 0,
               speed: float | None = 1.0, topics: set[str] | None = None,
               stop: threading.Event | None = None, prefix: str = "evcal",
               wait_subscriber_s: float = 5.0,
               confirm_timeout_s: float = CONFIRM_TIMEOUT_S,
               distro: str = "auto") -> BagReplayStats:
    """Publish the bag at ``path`` (``speed=None``: as fast as possible) in the wire of
    ``distro`` (:func:`wire_of`), then ask the service for its account of each camera's
    messages (up to ``confirm_timeout_s``; 1 s once ``stop`` is set), as ``evcal replay``
    does (:func:`evcal.clients.replay.replay`)."""
    stop = stop or threading.Event()
    stats = BagReplayStats()
    types = bag_topics(path)
    chosen = {tp: ty for tp, ty in types.items() if topics is None or tp in topics}
    wire = wire_of(t, domain, distro)
    stats.distro = wire.name
    node = RosNode(zid=t.zid, domain=domain, name=NODE)
    t.token(node.node_token())
    pubs: dict[str, tuple[RosPublication, Publisher]] = {}
    default_map = TopicMap()
    for topic, msgtype in sorted(chosen.items()):
        h = _hash(msgtype)
        if h is None:
            stats.skipped_topics[topic] = f"type {msgtype} is not known to evcal"
            continue
        # (the hash known is what makes a type publishable; Humble's keys do not carry it)
        pub = RosPublication(node, topic, msgtype, h if wire.type_hash else None,
                             distro=wire)
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
    before = {c: probe_status(t, k) for c, k in status_keys.items()}
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
        try:
            zpub.put(m.data, attachment=pub.attachment())
        except Exception as exc:  # a closed or failed session: reported, not raised
            stats.send_error = f"{type(exc).__name__}: {exc}"
            break
        stats.unmatched_messages += not zpub.has_subscribers
        stats.messages[m.topic] += 1
        stats.bytes += len(m.data)
    stats.stopped = stop.is_set()
    stats.seconds = time.monotonic() - wall0
    if stats.send_error is not None:
        return stats
    _confirm_cameras(t, stats, status_keys, before, prefix=prefix,
                     since_s=wall0 - STATUS_QUERY_S,
                     wait_s=STOPPED_CONFIRM_S if stats.stopped else confirm_timeout_s)
    if not stats.accounts:
        # what was put leaves before the session closes (no status reply to wait for)
        t.flush(None, linger_s=0.5)
    return stats


def _confirm_cameras(t: Transport, stats: BagReplayStats, status_keys: dict[str, str],
                     before: dict[str, StatusProbe], *, prefix: str, since_s: float,
                     wait_s: float) -> None:
    """Each camera's account (:func:`evcal.clients.delivery.confirm`), one after the other
    within ``wait_s`` in all; a camera asked after the deadline still gets up to two status
    queries' time (the service answers each within one, once it has processed the
    messages)."""
    deadline = time.monotonic() + wait_s
    floor_s = min(wait_s, 2 * STATUS_QUERY_S)
    for camera, key in status_keys.items():
        sent = stats.camera_messages(camera)
        if sent == 0:
            continue  # nothing of it was sent: nothing to confirm
        acc = ReplayStats(event_messages=sent)  # ``messages``: what its account must hold
        confirm(t, acc, key, before[camera], prefix=prefix, since_s=since_s,
                 deadline=max(deadline, time.monotonic() + floor_s),
                 stop_now=threading.Event())
        stats.accounts[camera] = acc


def report(prog: str, stats: BagReplayStats, wait_subscriber_s: float, domain: int) -> int:
    """Print what was sent and delivered; returns :func:`exit_code` (``evcal replay``'s
    table)."""
    code = exit_code(stats)
    for topic, why in stats.skipped_topics.items():
        print(f"{prog}: skipped {topic}: {why}", file=sys.stderr)
    if not stats.subscribed:
        print(f"{prog}: nobody subscribes to the bag's topics in ROS domain {domain} after "
              f"{wait_subscriber_s:g} s (is `evcal serve --ros2` or a ROS 2 node running and "
              "reachable?); nothing was sent", file=sys.stderr)
        return code
    if stats.send_error is not None:
        print(f"{prog}: sending failed: {stats.send_error}", file=sys.stderr)
    print(f"{prog}: sent {stats.total} messages ({stats.bytes / 1e6:.1f} MB) in "
          f"{stats.seconds:.2f} s on {len(stats.messages)} topics in ROS domain {domain} "
          f"({stats.distro}'s rmw_zenoh wire): "
          + ", ".join(f"{tp} {n}" for tp, n in stats.messages.items())
          + (" (stopped)" if stats.stopped else ""), file=sys.stderr)
    if stats.unmatched_messages:
        print(f"{prog}: {stats.unmatched_messages} messages were sent while nobody subscribed "
              "(lost)", file=sys.stderr)
    if stats.send_error is None and stats.total and not stats.accounts:
        print(f"{prog}: delivery not confirmed: no topic sent feeds an evcal camera (an "
              "EventPacket or Image topic; its namespace names the camera)", file=sys.stderr)
    for camera, acc in stats.accounts.items():
        print_account(prog, acc, camera=camera)
    return print_outcome(prog, code)
