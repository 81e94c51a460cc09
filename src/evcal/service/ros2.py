"""ROS 2 over rmw_zenoh without ROS: the keys, liveliness tokens and attachments rmw_zenoh
uses, and the CDR in (EventPacket, Image); the calibration maps go out as Images through
:mod:`evcal.service.ros2out`, in the wire described here.

No zenoh here (the session is :mod:`evcal.service.transport`'s): this module makes strings
and bytes. The facts it relies on are rmw_zenoh_cpp's, read at the release tags of each
distribution (github ros2-gbp/rmw_zenoh-release, ``release/<distro>/rmw_zenoh_cpp/<v>-1``:
``liveliness_utils.cpp``, ``attachment_helpers.cpp``, ``qos.cpp``,
``rmw_publisher_data.cpp``, ``rmw_subscription_data.cpp``); what differs between releases
is a :class:`RosDistro` (``--ros-distro``, or ``auto``: :class:`DistroDetector`):

- A topic's data key is ``<domain>/<topic without its leading and trailing '/'>/<dds
  type>/<type hash>``, e.g. ``0/event_camera/events/event_camera_msgs::msg::dds_::
  EventPacket_/RIHS01_d6fa...``; the dds type of ``pkg/msg/Name`` is
  ``pkg::msg::dds_::Name_``, the hash the type's RIHS01 hash (REP 2011) as
  ``rosidl_stringify_type_hash`` writes it (Jazzy and later), ``TypeHashNotSupported`` on
  Humble. A subscriber declares its own exact key, so a publisher with the other hash never
  reaches it. Payloads are CDR (4-byte encapsulation header, then the message).
- Every sample carries an attachment in zenoh's serialization format (a subscriber drops a
  sample without one): the publisher's sequence number (int64, from 1), the source
  timestamp (int64 ns) and the publisher's GID (``std::array<uint8_t, 16>``: LEB128 length
  0x10 then the bytes) -- 33 bytes, from rmw_zenoh 0.1.2 (Humble), 0.2.4 (Jazzy), 0.6
  (Rolling, Kilted). Before, each field came after its name (``"sequence_number"``,
  ``"source_timestamp"``, ``"source_gid"`` as strings), 77 bytes. Each release's
  ``AttachmentData`` throws on the other layout: evcal reads both and writes the one of the
  profile.
- A ROS entity exists for ``ros2 node list`` / ``ros2 topic list`` through a liveliness token
  ``@ros2_lv/<domain>/<zid>/<node id>/<entity id>/<NN|MP|MS>/<enclave>/<namespace>/<node>``,
  followed for a publisher (MP) or subscription (MS) by ``/<topic>/<dds type>/<type
  hash>/<qos>``; names in a token have ``/`` replaced by ``%`` (the root namespace and the
  default enclave are ``%``), the QoS is
  ``<reliability>:<durability>:<history>,<depth>:<deadline s>,<ns>:<lifespan s>,<ns>:
  <liveliness>,<lease s>,<ns>`` (rmw enum values), a field left empty when it is the
  release's default (reliable, keep last 42, infinite durations, automatic liveliness;
  durability TRANSIENT_LOCAL before 0.1.2 and 0.2.3, VOLATILE since). The entity's GID is
  XXH3-128 of its token (:func:`entity_gid`).
- TRANSIENT_LOCAL: a publisher keeps its last ``depth`` samples in zenoh's advanced
  publisher cache, with publisher detection (and, RELIABLE, a 0.5 s sporadic heartbeat); a
  subscription is an advanced subscriber with history that detects late publishers. The
  releases before 0.1.2 and 0.2.2 used zenoh's publication cache (a queryable on
  ``<zid>/<key>``) and a querying subscriber (``*/<key>``, replies on any key).

evcal subscribes with the hash chunk ``*``: any version of a type is received, Humble's
included, and the CDR is decoded with evcal's registered definitions
(:mod:`evcal.io.rosbag`), which name a message that does not decode. It publishes its
calibration images TRANSIENT_LOCAL (depth 1), for each profile active.

Cameras: an EventPacket topic belongs to the camera named by its namespace
(``/lab/rig1/cam0/events`` -> ``lab/rig1/cam0``), an Image topic too when its last name
starts with ``image`` (``image_raw``, ``image_mono``, ...); ``--ros-topic-map TOPIC=CAMERA``
overrides that for a topic, or for a namespace (``/dvs=lab/cam0``: every topic below
``/dvs``, Images still named ``image*``). Topics that map to no camera are ignored (counted).
A camera's calibration goes out on ``/<camera>/calibration/contrast`` and ``.../bias``
(``32FC1``, the maps as published on evcal's key) and ``.../special`` (``mono8``, 50 x the
:class:`~evcal.calibration.Special` code: 0 unobserved, 50 normal, 100 hot, 150 cold,
200 warm, 250 cool), stamped with the sensor time of the frame that closed the update.
"""

from __future__ import annotations

import logging
import re
import struct
import threading
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..errors import ConfigError, ErrorReason
from ..io._evcodecs import PacketDecoder, PayloadError
from ..io.bagdecode import (
    CALIBRATION_IMAGES,
    EVENT_PACKET,
    IMAGE,
    decode_packet,
    deserialize_message,
    event_columns,
    image_to_gray,
    packet_decoder,
)
from ..io.ros2msg import ros2_store, type_hash
from .camera import DecodedEvents, DecodedFrame, Rejected

log = logging.getLogger("evcal.service")

ADMIN_SPACE = "@ros2_lv"
NODE_NAME = "evcal"
# rmw_zenoh sets no encoding on its samples (zenoh's default); the payload is CDR
ENCODING = "zenoh/bytes"
# rmw's QoS enums (rmw/types.h), as rmw_zenoh writes them in tokens
RELIABLE, BEST_EFFORT = 1, 2
TRANSIENT_LOCAL, VOLATILE = 1, 2
KEEP_LAST, KEEP_ALL = 1, 2
NO_TYPE_HASH = "TypeHashNotSupported"  # Humble's hash chunk (no type hashes before Iron)
INPUT_TYPES = {EVENT_PACKET: "events", IMAGE: "frames"}
OUTPUT_MAPS = CALIBRATION_IMAGES
SPECIAL_SCALE = 50  # the special image's value per class code
_ATTACHMENT = struct.Struct("<qqB16s")  # seq, source timestamp ns, LEB128(16), GID


def dds_type(msgtype: str) -> str:
    """``pkg/msg/Name`` -> ``pkg::msg::dds_::Name_`` (the type chunk of rmw_zenoh keys)."""
    pkg, sep, name = msgtype.rpartition("/")
    if not sep or not pkg or not name:
        raise ConfigError(f"message type {msgtype!r} is not of the form pkg/msg/Name",
                          ErrorReason.MALFORMED)
    return f"{pkg.replace('/', '::')}::dds_::{name}_"


def ros_type(dds: str) -> str | None:
    """``pkg::msg::dds_::Name_`` -> ``pkg/msg/Name``; None for anything else."""
    head, sep, name = dds.rpartition("::dds_::")
    if not sep or not head or not name.endswith("_") or len(name) < 2:
        return None
    return f"{head.replace('::', '/')}/{name[:-1]}"


def topic_key(domain: int, topic: str, msgtype: str, hash_: str | None = None) -> str:
    """The data key of ``topic`` (``/a/b``) of type ``msgtype`` in ``domain``."""
    name = topic.strip("/")
    if not name:
        raise ConfigError(f"topic {topic!r} has no name", ErrorReason.MALFORMED)
    return f"{int(domain)}/{name}/{dds_type(msgtype)}/{hash_ or type_hash(msgtype)}"


@dataclass(frozen=True)
class TopicKey:
    """A parsed rmw_zenoh data key."""

    domain: int
    topic: str  # "/a/b"
    msgtype: str  # "pkg/msg/Name"
    type_hash: str


def parse_topic_key(key: str) -> TopicKey | None:
    """The parts of a concrete data key, None when it is not one."""
    chunks = key.split("/")
    if len(chunks) < 4 or not chunks[0].isdigit():
        return None
    msgtype = ros_type(chunks[-2])
    if msgtype is None:
        return None
    return TopicKey(int(chunks[0]), "/" + "/".join(chunks[1:-2]), msgtype, chunks[-1])


def subscription_keys(domain: int) -> tuple[str, ...]:
    """The key expressions of every EventPacket and Image topic of ``domain``, any hash."""
    return tuple(f"{int(domain)}/**/{dds_type(t)}/*" for t in INPUT_TYPES)


def mangle(name: str) -> str:
    """A ROS name as one key chunk (``/`` -> ``%``), as in rmw_zenoh's tokens."""
    return name.replace("/", "%")


def encode_attachment(seq: int, t_ns: int, gid: bytes, *, named: bool = False) -> bytes:
    """The attachment of a sample: sequence number, source timestamp (ns), 16-byte GID in
    zenoh's serialization format (33 bytes); ``named``: each field after its name, the
    layout of rmw_zenoh 0.1.0-0.1.1 (Humble) and 0.2.0-0.2.3 (Jazzy), 77 bytes."""
    if len(gid) != 16:
        raise ConfigError(f"a GID has 16 bytes, got {len(gid)}")
    if named:
        return _NAMED_ATTACHMENT.pack(_NAMES[0], int(seq), _NAMES[1], int(t_ns), _NAMES[2],
                                      b"\x10" + gid)
    return _ATTACHMENT.pack(int(seq), int(t_ns), 16, gid)


def entity_gid(token: str) -> bytes:
    """The GID rmw_zenoh gives the entity of liveliness ``token``: XXH3-128 of the token's
    UTF-8 bytes (seed 0), its low then high 64-bit half, each little-endian (``Entity``'s
    constructor in ``liveliness_utils.cpp``; the GID ``ros2 topic info -v`` reports and the
    one in the entity's attachments)."""
    import xxhash  # noqa: PLC0415 - a service dependency, not the core's

    return int(xxhash.xxh3_128_intdigest(token.encode())).to_bytes(16, "little")


@dataclass(frozen=True)
class RosQos:
    """The QoS of a publisher or subscription, as far as evcal's tokens say it (durations:
    rmw_zenoh's defaults, infinite)."""

    reliability: int = RELIABLE
    durability: int = VOLATILE
    history: int = KEEP_LAST
    depth: int = 10


# evcal's calibration images: latched (a late TRANSIENT_LOCAL subscriber gets the last one)
OUTPUT_QOS = RosQos(durability=TRANSIENT_LOCAL, depth=1)
INPUT_QOS = RosQos()  # its subscriptions to the drivers' topics, and replay's publishers
HEARTBEAT_S = 0.5  # rmw_zenoh's sporadic heartbeat of RELIABLE, TRANSIENT_LOCAL publishers


@dataclass(frozen=True)
class RosDistro:
    """What one family of rmw_zenoh releases writes on the wire (read from rmw_zenoh_cpp at
    the release tags of github ros2-gbp/rmw_zenoh-release: ``liveliness_utils.cpp``,
    ``attachment_helpers.cpp``, ``qos.cpp``, ``rmw_publisher_data.cpp``,
    ``rmw_subscription_data.cpp``).

    ``type_hash``: RIHS01 hashes in keys and tokens, else ``TypeHashNotSupported``
    (Humble). ``named_attachment``: each attachment field after its name (77 bytes) instead
    of the 33-byte layout; a subscriber of one layout throws on the other. ``default_durability``:
    the durability a token leaves empty (rmw_zenoh writes a QoS field only when it differs
    from its default: reliable, keep last 42, infinite durations, automatic liveliness, and
    this durability). ``publication_cache``: TRANSIENT_LOCAL through zenoh's publication
    cache and querying subscriber (a queryable on ``<zid>/<key>``, queried on ``*/<key>``)
    as well as through the advanced publisher's cache (0.1.2+ and 0.2.2+ use the latter).
    """

    name: str
    releases: str
    type_hash: bool
    named_attachment: bool
    default_durability: int
    publication_cache: bool

    def hash_of(self, msgtype: str) -> str:
        """The type hash chunk of ``msgtype`` in this distribution's keys and tokens."""
        return type_hash(msgtype) if self.type_hash else NO_TYPE_HASH

    def qos_string(self, qos: RosQos) -> str:
        """The QoS chunk of a token, as rmw_zenoh's ``qos_to_keyexpr`` writes it:
        ``reliability:durability:history,depth:deadline s,ns:lifespan s,ns:liveliness,lease
        s,ns``, a field left empty when it is the default (durations always: infinite)."""

        def field_(value: int, default: int) -> str:
            return "" if value == default else str(int(value))

        return (f"{field_(qos.reliability, RELIABLE)}:"
                f"{field_(qos.durability, self.default_durability)}:"
                f"{field_(qos.history, KEEP_LAST)},{field_(qos.depth, 42)}:,:,:,,")

    def attachment(self, seq: int, t_ns: int, gid: bytes) -> bytes:
        return encode_attachment(seq, t_ns, gid, named=self.named_attachment)




def _current(name: str, releases: str) -> RosDistro:
    """A profile of the current wire: RIHS01 hashes, 33-byte attachments, VOLATILE default."""
    return RosDistro(name, releases, type_hash=True, named_attachment=False,
                     default_durability=VOLATILE, publication_cache=False)


DISTROS: dict[str, RosDistro] = {d.name: d for d in (
    RosDistro("humble", "Humble, rmw_zenoh 0.1.2 and later", type_hash=False,
              named_attachment=False, default_durability=VOLATILE, publication_cache=False),
    RosDistro("humble-0.1.1", "Humble, rmw_zenoh 0.1.0-0.1.1", type_hash=False,
              named_attachment=True, default_durability=TRANSIENT_LOCAL,
              publication_cache=True),
    _current("jazzy", "Jazzy, rmw_zenoh 0.2.4 and later"),
    # 0.2.0-0.2.2 default to TRANSIENT_LOCAL, 0.2.3 to VOLATILE: the tokens of this profile
    # write both durabilities out, which every one of them reads alike
    RosDistro("jazzy-0.2.3", "Jazzy, rmw_zenoh 0.2.0-0.2.3", type_hash=True,
              named_attachment=True, default_durability=VOLATILE, publication_cache=True),
    _current("kilted", "Kilted, rmw_zenoh 0.6"),
    _current("rolling", "Rolling, rmw_zenoh 0.6 and later"),
)}
DISTRO_CHOICES = ("auto", *DISTROS)
DEFAULT_DISTRO = DISTROS["jazzy"]
QOS = DEFAULT_DISTRO.qos_string(OUTPUT_QOS)  # the QoS chunk of evcal's image publishers


def distro(name: str) -> RosDistro:
    """The profile of ``--ros-distro NAME`` (not ``auto``)."""
    try:
        return DISTROS[name]
    except KeyError:
        raise ConfigError(f"--ros-distro {name!r}: expected one of "
                          f"{', '.join(DISTRO_CHOICES)}") from None


@dataclass(frozen=True)
class Attachment:
    """What rmw_zenoh attaches to a sample."""

    seq: int
    t_ns: int
    gid: bytes


# the same three fields each after its name as a string (LEB128 length, UTF-8), as rmw_zenoh
# wrote them with zenoh 1.0 before its AttachmentData class (and rmw_zenoh_pico, PX4 still do)
_NAMED_ATTACHMENT = struct.Struct("<16sq17sq11s17s")
_NAMES = (b"\x0fsequence_number", b"\x10source_timestamp", b"\x0asource_gid")


def decode_attachment(raw: bytes | None) -> Attachment | None:
    """The attachment of a sample, in either layout rmw_zenoh has used with zenoh 1.x (None
    when there is none or it is neither)."""
    if raw is None:
        return None
    if len(raw) == _ATTACHMENT.size and raw[16] == 16:
        seq, t_ns, _, gid = _ATTACHMENT.unpack(raw)
        return Attachment(int(seq), int(t_ns), bytes(gid))
    if len(raw) == _NAMED_ATTACHMENT.size:
        n_seq, seq, n_ts, t_ns, n_gid, gid = _NAMED_ATTACHMENT.unpack(raw)
        if (n_seq, n_ts, n_gid) == _NAMES and gid[0] == 16:
            return Attachment(int(seq), int(t_ns), bytes(gid[1:]))
    return None


def default_domain() -> int:
    """``ROS_DOMAIN_ID`` as ROS 2 reads it (0 when unset or empty)."""
    import os

    text = os.environ.get("ROS_DOMAIN_ID", "").strip()
    if not text:
        return 0
    if not text.isdigit():
        raise ValueError(f"ROS_DOMAIN_ID={text!r} is not a domain number")
    return int(text)


@dataclass(frozen=True, kw_only=True)
class Ros2Options:
    """``evcal serve --ros2``: the ROS domain and which topics feed which camera."""

    domain: int = 0
    topic_map: TopicMap = field(default_factory=lambda: TopicMap())
    # which rmw_zenoh to speak to (DISTROS), or "auto": from the tokens and attachments seen
    distro: str = "auto"

    def __post_init__(self) -> None:
        if not 0 <= int(self.domain) <= 232:
            raise ConfigError(f"ROS domain {self.domain} is not in 0..232")
        if self.distro != "auto":
            distro(self.distro)


# ----------------------------------------------------------------------------- tokens


@dataclass
class RosNode:
    """evcal as one ROS 2 node: its liveliness tokens and publications' GIDs.

    ``zid`` is the zenoh session id (``Transport.zid``); entity ids count from 1 (0 is the
    node itself).
    """

    zid: str
    domain: int = 0
    name: str = NODE_NAME
    namespace: str = "/"
    enclave: str = "/"
    node_id: int = 0
    _next_id: int = 1
    _lock: threading.Lock = field(default_factory=threading.Lock, repr=False)

    def _head(self, entity_id: int, kind: str) -> str:
        return (f"{ADMIN_SPACE}/{self.domain}/{self.zid}/{self.node_id}/{entity_id}/{kind}/"
                f"{mangle(self.enclave)}/{mangle(self.namespace)}/{mangle(self.name)}")

    def node_token(self) -> str:
        """The token that makes the node visible (``ros2 node list``)."""
        return self._head(self.node_id, "NN")

    def entity(self, kind: str, topic: str, msgtype: str, hash_: str | None = None, *,
               qos: RosQos | None = None, distro: RosDistro = DEFAULT_DISTRO
               ) -> tuple[str, bytes]:
        """``(token, gid)`` of a new publisher (``MP``) or subscription (``MS``) on ``topic``
        as ``distro``'s rmw_zenoh writes it (``hash_`` None: the distribution's hash of
        ``msgtype``; ``qos`` None: :data:`OUTPUT_QOS` for a publisher, :data:`INPUT_QOS` for
        a subscription); the GID is :func:`entity_gid` of the token."""
        if kind not in ("MP", "MS"):
            raise ConfigError(f"entity kind {kind!r} is not MP or MS")
        if qos is None:
            qos = OUTPUT_QOS if kind == "MP" else INPUT_QOS
        with self._lock:
            eid = self._next_id
            self._next_id += 1
        token = (f"{self._head(eid, kind)}/{mangle('/' + topic.strip('/'))}/"
                 f"{dds_type(msgtype)}/{hash_ or distro.hash_of(msgtype)}/"
                 f"{distro.qos_string(qos)}")
        return token, entity_gid(token)


class RosPublication:
    """One topic evcal publishes, as ``distro``'s rmw_zenoh would: its key, token, GID,
    QoS and sequence numbers (thread-safe). ``qos`` None: :data:`INPUT_QOS` (a driver's
    topic, ``evcal replay --ros2``)."""

    def __init__(self, node: RosNode, topic: str, msgtype: str,
                 hash_: str | None = None, *, qos: RosQos | None = None,
                 distro: RosDistro = DEFAULT_DISTRO) -> None:
        self.topic = topic
        self.msgtype = msgtype
        self.distro = distro
        self.qos = qos or INPUT_QOS
        hash_ = hash_ or distro.hash_of(msgtype)
        self.key = topic_key(node.domain, topic, msgtype, hash_)
        self.token, self.gid = node.entity("MP", topic, msgtype, hash_, qos=self.qos,
                                           distro=distro)
        self._seq = 0
        self._lock = threading.Lock()

    def attachment(self) -> bytes:
        """The next sample's attachment (sequence numbers from 1, as rmw_zenoh's)."""
        with self._lock:
            self._seq += 1
            seq = self._seq
        return self.distro.attachment(seq, time.time_ns(), self.gid)


class DistroDetector:
    """Which rmw_zenoh the domain speaks (``--ros-distro auto``), from what evcal sees of it.

    Liveliness tokens of other nodes' publishers and subscriptions tell the type hash style:
    ``TypeHashNotSupported`` (Humble) or RIHS01 (Jazzy and later); the attachments of the
    samples evcal takes (the drivers' topics) tell the attachment layout of each style. Tokens
    do not tell Jazzy 0.2.0-0.2.3 from 0.2.4+ (their subscribers throw on the other layout):
    until a sample says otherwise, the 33-byte layout of the current releases is assumed.

    :meth:`active` is the profiles to publish for: one per hash style seen (RIHS01 when
    nothing was seen), so that Humble and Jazzy subscribers on one router are both served
    (their keys differ). Thread-safe; ``own_zid`` is evcal's session, whose tokens are skipped.
    """

    def __init__(self, own_zid: str = "") -> None:
        self.own_zid = own_zid
        self._hashed: set[bool] = set()  # hash styles seen: True RIHS01, False none
        self._named: dict[bool, bool] = {}  # style -> the latest sample's layout was named
        self._lock = threading.Lock()
        self.version = 0  # counts changes of active()

    def seen_token(self, token: str) -> None:
        """A liveliness token of the domain (``@ros2_lv/...``) appeared."""
        chunks = token.split("/")
        if len(chunks) < 13 or chunks[5] not in ("MP", "MS") or chunks[2] == self.own_zid:
            return
        self._seen(chunks[11] != NO_TYPE_HASH, None)

    def seen_sample(self, key: str, attachment: bytes | None) -> None:
        """A sample on a data key, with its attachment."""
        hashed = key.rpartition("/")[2] != NO_TYPE_HASH
        named = attachment_layout(attachment)
        self._seen(hashed, named)

    def _seen(self, hashed: bool, named: bool | None) -> None:
        with self._lock:
            before = (set(self._hashed), dict(self._named))
            self._hashed.add(hashed)
            if named is not None:
                self._named[hashed] = named
            if before != (self._hashed, self._named):
                self.version += 1

    def styles(self) -> set[bool]:
        """The type-hash styles seen so far (True: RIHS01, False: none)."""
        with self._lock:
            return set(self._hashed)

    def active(self) -> tuple[RosDistro, ...]:
        with self._lock:
            styles = sorted(self._hashed or {True}, reverse=True)
            return tuple(_PROFILE[(h, self._named.get(h, False))] for h in styles)


class DistroMismatch:
    """An explicit ``--ros-distro`` watched against the domain: warns once when other nodes'
    tokens (publishers and subscriptions) show the other type-hash style only -- Humble's
    keys and Jazzy's never meet, so those nodes would hear nothing of evcal and evcal
    nothing of them, silently. ``warned``: the styles warned of."""

    def __init__(self, distro: RosDistro, own_zid: str = "") -> None:
        self.distro = distro
        self.detector = DistroDetector(own_zid=own_zid)
        self.warned: set[bool] = set()
        self._matching_seen = False

    def seen_token(self, token: str) -> str | None:
        """Feed a token; the warning's text when this token makes one (None otherwise)."""
        self.detector.seen_token(token)
        styles = self.detector.styles()
        if self.distro.type_hash in styles:
            self._matching_seen = True
        other = not self.distro.type_hash
        if self._matching_seen or other not in styles or other in self.warned:
            return None
        self.warned.add(other)
        theirs = "RIHS01 type hashes (Jazzy or later)" if other else \
            "no type hashes (Humble)"
        text = (f"--ros-distro {self.distro.name}: the domain's other nodes use {theirs}; "
                "their topics and evcal's are on different keys and never meet (no data "
                "either way): use --ros-distro auto, or the distro they run")
        log.warning(text)
        return text


_PROFILE = {(True, False): DISTROS["jazzy"], (True, True): DISTROS["jazzy-0.2.3"],
            (False, False): DISTROS["humble"], (False, True): DISTROS["humble-0.1.1"]}


def attachment_layout(raw: bytes | None) -> bool | None:
    """True for the named attachment layout, False for the 33-byte one, None for neither."""
    if raw is None:
        return None
    if len(raw) == _ATTACHMENT.size and raw[16] == 16:
        return False
    if len(raw) == _NAMED_ATTACHMENT.size and raw.startswith(_NAMES[0]):
        return True
    return None


# ----------------------------------------------------------------------------- inputs

_IMAGE_NAME = re.compile(r"^image")


def _namespace(topic: str) -> str:
    return topic.strip("/").rpartition("/")[0]


@dataclass(frozen=True)
class TopicMap:
    """Which camera a ROS topic feeds (see the module docstring): explicit entries
    ``(topic or namespace, camera)``, the longest matching one first, else the topic's
    namespace."""

    entries: tuple[tuple[str, str], ...] = ()

    @classmethod
    def parse(cls, items: Iterable[str]) -> TopicMap:
        """From ``--ros-topic-map TOPIC=CAMERA`` values (ValueError naming a bad one)."""
        from .keys import check_camera_id

        out = []
        for item in items:
            topic, sep, camera = item.partition("=")
            topic = "/" + topic.strip().strip("/")
            camera = camera.strip().strip("/")
            if not sep or topic == "/" or not camera:
                raise ValueError(f"--ros-topic-map {item!r}: expected TOPIC=CAMERA, e.g. "
                                 "/dvs/events=lab/rig1/cam0 or /dvs=lab/rig1/cam0")
            try:
                check_camera_id(camera)
            except ValueError as exc:
                raise ValueError(f"--ros-topic-map {item!r}: {exc}") from None
            out.append((topic, camera))
        return cls(tuple(sorted(out, key=lambda e: -len(e[0]))))

    def camera(self, topic: str, kind: str) -> str | None:
        """The camera of ``topic`` carrying ``kind`` ("events" or "frames"), or None."""
        topic = "/" + topic.strip("/")
        image_named = _IMAGE_NAME.match(topic.rpartition("/")[2]) is not None
        for name, camera in self.entries:
            if topic == name:
                return camera
            if topic.startswith(name + "/"):
                return camera if kind == "events" or image_named else None
        if kind == "frames" and not image_named:
            return None
        return _namespace(topic) or None


@dataclass(frozen=True)
class RosSample:
    """A ROS 2 message for a camera's decoder thread: CDR of ``msgtype`` from ``topic``, with
    the publisher's sequence number when its attachment said it."""

    data: bytes
    msgtype: str
    topic: str
    seq: int | None = None

    def __len__(self) -> int:
        return len(self.data)


DeliverFn = Callable[[str, str, Any, float], None]  # (camera, kind, payload, t_recv_s)


class RosRouter:
    """Routes samples on rmw_zenoh keys to cameras (the transport's receive thread).

    ``deliver(camera, kind, RosSample, t_recv_s)`` is :meth:`Service.deliver`. Keys are parsed
    once (a bounded cache); topics that feed no camera are counted in :attr:`ignored` and
    logged once. Each new input topic gets a subscription token (``MS``, so that
    ``ros2 topic info`` lists evcal), declared by :meth:`declare_pending` from a thread
    that may call the transport (never the receive thread).

    ``owns(camera)`` (a shard's :meth:`Service.owns`) leaves other shards' cameras alone:
    their topics are neither delivered, counted as ignored, logged nor given a token, and
    :meth:`accepts` tells the transport so before it copies a payload.
    """

    MAX_ROUTES = 4096

    def __init__(self, node: RosNode, deliver: DeliverFn, topic_map: TopicMap | None = None,
                 *, owns: Callable[[str], bool] | None = None,
                 detector: DistroDetector | None = None,
                 distro: RosDistro | None = None) -> None:
        self.node = node
        self.deliver = deliver
        self.topic_map = topic_map or TopicMap()
        self._owns = owns
        self.detector = detector  # told of every sample's attachment (--ros-distro auto)
        self.distro = distro  # the tokens' profile; None: as the topic's publisher writes
        self._routes: dict[str, tuple[str, str, str, str] | None] = {}
        self._foreign: set[str] = set()  # keys of other shards' cameras (bounded as _routes)
        self.ignored: dict[str, int] = {}
        self._pending: list[tuple[str, str, str]] = []
        self._lock = threading.Lock()

    def accepts(self, key: str) -> bool:
        """False for a key whose topic feeds another shard's camera (any thread)."""
        if self._owns is None:
            return True
        if key in self._foreign:
            return False
        target = self._target(key)
        if target is None or target[2] is None or self._owns(target[2]):
            return True  # on_sample delivers it or counts it as ignored
        if len(self._foreign) < self.MAX_ROUTES:
            self._foreign.add(key)
        return False

    def _target(self, key: str) -> tuple[TopicKey, str | None, str | None] | None:
        """``(parsed key, input kind, camera)`` of a data key of this node's domain."""
        parsed = parse_topic_key(key)
        if parsed is None or parsed.domain != self.node.domain:
            return None
        kind = INPUT_TYPES.get(parsed.msgtype)
        return parsed, kind, (self.topic_map.camera(parsed.topic, kind) if kind is not None
                              else None)

    def _route(self, key: str) -> tuple[str, str, str, str] | None:
        target = self._target(key)
        if target is None:
            return None
        parsed, kind, camera = target
        if kind is None or camera is None:
            log.info("ROS 2 topic %s (%s) feeds no camera: ignored (--ros-topic-map maps it)",
                     parsed.topic, parsed.msgtype)
            return None
        with self._lock:
            self._pending.append((parsed.topic, parsed.msgtype, parsed.type_hash))
        log.info("ROS 2 topic %s (%s) -> camera %s %s", parsed.topic, parsed.msgtype, camera,
                 kind)
        return camera, kind, parsed.topic, parsed.msgtype

    def on_sample(self, key: str, payload: bytes, encoding: str,
                  attachment: bytes | None) -> None:
        """A sample on a subscribed key (any receive thread; returns quickly)."""
        t_recv = time.monotonic()
        if self._owns is not None and not self.accepts(key):
            return
        if key in self._routes:
            route = self._routes[key]
        else:
            route = self._route(key)
            if len(self._routes) < self.MAX_ROUTES:
                self._routes[key] = route
        if route is None:
            self.ignored[key] = self.ignored.get(key, 0) + 1
            return
        camera, kind, topic, msgtype = route
        if self.detector is not None:
            self.detector.seen_sample(key, attachment)
        att = decode_attachment(attachment)
        self.deliver(camera, kind, RosSample(payload, msgtype, topic,
                                             att.seq if att is not None else None), t_recv)

    def declare_pending(self, declare: Callable[[str], Any]) -> int:
        """Declare the subscription tokens of the topics seen since the last call."""
        with self._lock:
            pending, self._pending = self._pending, []
        for topic, msgtype, hash_ in pending:
            profile = self.distro or (DISTROS["humble"] if hash_ == NO_TYPE_HASH
                                      else DEFAULT_DISTRO)
            declare(self.node.entity("MS", topic, msgtype, hash_, distro=profile)[0])
        return len(pending)


class RosDecoder:
    """One camera's decoding of ROS 2 messages (its decoder thread only): CDR to the decoded
    records :class:`~evcal.service.camera.CameraState` takes.

    EventPackets: each topic has its own stateful payload decoder, started afresh when the
    topic's ``seq`` goes back (the driver restarted); the events are sorted (stable) when a
    packet is not; ``seq`` is the message's own (loss detection). Images: to gray
    (:func:`~evcal.io.rosbag.image_to_gray`), time the header stamp floored to µs, ``seq`` the
    publisher's sequence number from the attachment (None without one).

    Errors are :class:`~evcal.errors.EvcalError` naming the topic (malformed CDR:
    ``truncated``; an unknown or changed encoding, a big-endian payload: ``malformed``; a
    size out of 1..65535: ``out_of_range``; payload errors with their own reason).
    """

    def __init__(self) -> None:
        self._decoders: dict[str, PacketDecoder] = {}
        self._last_seq: dict[str, int] = {}
        self.messages: dict[str, int] = {}  # per topic, refused ones included
        self.reordered_events = 0
        self.dropped_events = 0  # outside the declared size, dropped as the drivers' decoders do

    def status(self) -> dict[str, Any]:
        """The camera's ROS 2 input, for its ``status`` document."""
        return {"messages": dict(self.messages), "dropped_events": self.dropped_events,
                "reordered_events": self.reordered_events,
                "encodings": {t: d.encoding for t, d in self._decoders.items()}}

    def decode(self, kind: str, sample: RosSample) -> DecodedEvents | DecodedFrame:
        where = f"ROS 2 topic {sample.topic}"
        self.messages[sample.topic] = self.messages.get(sample.topic, 0) + 1
        msg = deserialize_message(ros2_store().deserialize_cdr, sample.data, sample.msgtype,
                                  where)
        if kind == "events":
            return self._events(msg, sample, where)
        return self._frame(msg, sample, where)

    @staticmethod
    def _size(msg: Any, where: str) -> tuple[int, int]:
        h, w = int(msg.height), int(msg.width)
        if not (0 < h <= 65535 and 0 < w <= 65535):
            raise Rejected(f"{where}: declares a {w}x{h} sensor (1..65535 each)",
                           ErrorReason.OUT_OF_RANGE)
        return h, w

    def _events(self, msg: Any, sample: RosSample, where: str) -> DecodedEvents:
        h, w = self._size(msg, where)
        seq = int(msg.seq)
        topic = sample.topic
        dec = self._decoders.get(topic)
        last = self._last_seq.get(topic)
        if dec is not None and last is not None and seq <= last:
            dec = None  # the publisher restarted: so did its encoder's state
        try:
            dec = packet_decoder(dec, msg)
            pk = decode_packet(dec, msg)
        except PayloadError as exc:
            raise Rejected(f"{where} (seq {seq}): {exc}", exc.reason) from None
        self._decoders[topic] = dec
        self._last_seq[topic] = seq
        self.dropped_events += pk.dropped
        ev = event_columns(pk.t_us, pk.x, pk.y, pk.on)
        t = ev["t_us"]
        if t.size > 1 and (t[1:] < t[:-1]).any():
            self.reordered_events += int(np.count_nonzero(t[1:] < np.maximum.accumulate(t)[:-1]))
            ev = ev[np.argsort(t, kind="stable")]
        return ev, {"seq": seq, "height": h, "width": w, "n": int(ev.size)}

    def _frame(self, msg: Any, sample: RosSample, where: str) -> DecodedFrame:
        h, w = self._size(msg, where)
        try:
            image = image_to_gray(msg)
        except PayloadError as exc:
            raise Rejected(f"{where}: {exc}", exc.reason) from None
        stamp_ns = int(msg.header.stamp.sec) * 1_000_000_000 + int(msg.header.stamp.nanosec)
        return stamp_ns // 1000, 0, image, {"seq": sample.seq, "height": h, "width": w,
                                            "dtype": str(image.dtype)}
