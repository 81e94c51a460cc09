"""ROS 2 messages evcal writes: CDR of ``sensor_msgs/msg/Image`` and
``event_camera_msgs/msg/EventPacket``, and ROS 2 bags as one MCAP file.

The types and their CDR come from the ``rosbags`` typestore of :mod:`evcal.io.rosbag` (the
same registered definitions the bag reader decodes with), so what is written here reads back
there. A ROS 2 MCAP file (:class:`Ros2McapWriter`) has profile ``ros2``, one schema per
message type with encoding ``ros2msg`` holding the full concatenated ``.msg`` definition (the
type's own text, then every type it uses after a line of 80 ``=`` and a ``MSG: pkg/Name``
line, as ``ros2 bag`` and Foxglove write and read them), and channels with message encoding
``cdr``. Times: message ``log_time`` in ns (clamped at 0), header stamps from integer ns.

:func:`recording_messages` turns a :class:`~evcal.recording.Recording` into what a ROS 2
driver would publish (EventPackets of :mod:`evcal.io.evencode` and mono8/mono16 Images), for
replays and tests; :func:`write_ros2_bag` writes them to a ROS 2 MCAP file.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from ..errors import ConfigError
from ..recording import Recording, RecordingError
from .bagdecode import EVENT_PACKET, IMAGE, typestore
from .evencode import packets
from .mcap_rec import McapFileWriter

if TYPE_CHECKING:
    from rosbags.typesys.store import Typestore

ROS2_PROFILE = "ros2"
SCHEMA_ENCODING = "ros2msg"
MESSAGE_ENCODING = "cdr"


@lru_cache(maxsize=1)
def ros2_store() -> Typestore:
    """The ROS 2 typestore (Humble's standard types plus evcal's registered definitions)."""
    return typestore(2)


def stamp(t_ns: int) -> Any:
    """A ``builtin_interfaces/msg/Time`` of integer ns (``sec`` floored, ``nanosec`` >= 0)."""
    time_cls = ros2_store().types["builtin_interfaces/msg/Time"]
    sec, nanosec = divmod(int(t_ns), 1_000_000_000)
    return time_cls(sec=sec, nanosec=nanosec)


def _header(t_ns: int, frame_id: str) -> Any:
    return ros2_store().types["std_msgs/msg/Header"](stamp=stamp(t_ns), frame_id=frame_id)


# bytes per pixel of the Image encodings written here, with their numpy dtype
IMAGE_ENCODINGS: dict[str, np.dtype[Any]] = {
    "mono8": np.dtype("u1"), "mono16": np.dtype("<u2"), "32FC1": np.dtype("<f4"),
}


def image_cdr(image: np.ndarray, *, t_ns: int, frame_id: str, encoding: str) -> bytes:
    """The CDR of a ``sensor_msgs/msg/Image`` of a ``[y, x]`` array (``mono8`` uint8,
    ``mono16`` uint16, ``32FC1`` float32; little-endian, rows unpadded)."""
    if encoding not in IMAGE_ENCODINGS:
        raise ConfigError(f"image encoding {encoding!r} is not one evcal writes "
                          f"({', '.join(IMAGE_ENCODINGS)})")
    dt = IMAGE_ENCODINGS[encoding]
    arr = np.ascontiguousarray(image, dtype=dt)
    if arr.ndim != 2:
        raise RecordingError(f"an image is [y, x], got shape {arr.shape}")
    h, w = arr.shape
    store = ros2_store()
    msg = store.types[IMAGE](header=_header(t_ns, frame_id), height=h, width=w,
                             encoding=encoding, is_bigendian=0, step=w * dt.itemsize,
                             data=arr.view(np.uint8).reshape(-1))
    return bytes(store.serialize_cdr(msg, IMAGE))


def event_packet_cdr(payload: bytes, *, encoding: str, seq: int, time_base_ns: int,
                     t_ns: int, height: int, width: int, frame_id: str) -> bytes:
    """The CDR of an ``event_camera_msgs/msg/EventPacket`` (header stamp ``t_ns``)."""
    store = ros2_store()
    msg = store.types[EVENT_PACKET](
        header=_header(t_ns, frame_id), height=height, width=width, seq=seq,
        time_base=time_base_ns, encoding=encoding, is_bigendian=False,
        events=np.frombuffer(payload, np.uint8))
    return bytes(store.serialize_cdr(msg, EVENT_PACKET))


@lru_cache(maxsize=64)
def message_definition(msgtype: str) -> str:
    """The ``ros2msg`` schema text of ``msgtype`` (``pkg/msg/Name``): its definition and
    every type it uses, separated as ``ros2 bag`` writes them (ValueError for an unknown
    type)."""
    store = ros2_store()
    if msgtype not in store.types:
        raise RecordingError(f"message type {msgtype!r} is not known to evcal's typestore (ROS 2 "
                             "standard types and event_camera_msgs, dvs_msgs, "
                             "prophesee_event_msgs)")
    return str(store.generate_msgdef(msgtype, ros_version=2)[0])


@lru_cache(maxsize=64)
def type_hash(msgtype: str) -> str:
    """The RIHS01 type hash of ``msgtype`` (REP 2011: SHA-256 of its type description),
    ``RIHS01_<64 hex digits>``, as rmw_zenoh puts it in keys and ``ros2 bag`` in metadata."""
    message_definition(msgtype)  # refuses unknown types with a clear error
    return str(ros2_store().hash_rihs01(msgtype))


class Ros2McapWriter(McapFileWriter):
    """A ROS 2 bag in one MCAP file, written message by message (a context manager).

    :meth:`add` takes a message's CDR unchanged; a topic's schema and channel are registered
    with its first message. A topic carries one type (another type on it is a ValueError).
    """

    def __init__(self, path: str | os.PathLike[str], *, library: str = "evcal") -> None:
        super().__init__(path, profile=ROS2_PROFILE, library=library)
        self._schemas: dict[str, int] = {}
        self._channels: dict[str, tuple[int, str]] = {}  # topic -> (channel id, type)
        self.counts: dict[str, int] = {}

    def _channel(self, topic: str, msgtype: str) -> int:
        known = self._channels.get(topic)
        if known is not None:
            if known[1] != msgtype:
                raise RecordingError(f"topic {topic} carries {known[1]}, not {msgtype}")
            return known[0]
        sid = self._schemas.get(msgtype)
        if sid is None:
            sid = self._w.register_schema(msgtype, SCHEMA_ENCODING,
                                          message_definition(msgtype).encode())
            self._schemas[msgtype] = sid
        cid: int = self._w.register_channel(topic, MESSAGE_ENCODING, sid, metadata={
            "offered_qos_profiles": "", "topic_type_hash": type_hash(msgtype)})
        self._channels[topic] = (cid, msgtype)
        self.counts[topic] = 0
        return cid

    def add(self, topic: str, msgtype: str, log_time_ns: int, data: bytes, *,
            publish_time_ns: int | None = None) -> None:
        """One message (CDR) on ``topic`` at ``log_time_ns`` (published at
        ``publish_time_ns``, default the log time)."""
        cid = self._channel(topic, msgtype)
        t = max(int(log_time_ns), 0)
        pub = t if publish_time_ns is None else max(int(publish_time_ns), 0)
        n: int = self.counts[topic]
        self._w.add_message(cid, log_time=t, publish_time=pub, sequence=n & 0xFFFFFFFF,
                            data=data)
        self.counts[topic] = n + 1

    def __enter__(self) -> Ros2McapWriter:
        return self


@dataclass(frozen=True)
class RosMessage:
    """One serialised ROS 2 message: its topic, type, time (ns) and CDR bytes."""

    topic: str
    msgtype: str
    t_ns: int
    data: bytes


def recording_messages(rec: Recording, *, namespace: str = "/camera",
                       encoding: str = "libcaer_cmp", packet_us: int = 10_000,
                       frame_id: str = "camera") -> Iterator[RosMessage]:
    """``rec`` as a ROS 2 event camera driver publishes it, in time order.

    ``<namespace>/events``: EventPackets (``seq`` from 0, ``time_base`` the packet's first
    event in ns, header stamp its last event), cut at frame times so that each frame comes
    after the events before it; ``<namespace>/image_raw``: Images, ``mono8`` for uint8
    frames, else ``mono16`` of the 8-bit scale x 257 (float frames rounded, clipped to
    0..255). A message's time is its last event's (a packet) or the frame's time.
    """
    ns = "/" + namespace.strip("/") if namespace.strip("/") else ""
    h, w = rec.sensor.shape
    ev = rec.events
    frames = rec.frames
    f_t = frames.t_us
    images = frames.images
    mono16 = images.dtype != np.uint8
    k = 0
    seq = 0
    for pk in packets(ev, f_t, encoding=encoding, packet_us=packet_us):
        t_last = int(ev["t_us"][pk.i1 - 1])
        while k < len(f_t) and int(f_t[k]) <= int(ev["t_us"][pk.i0]):
            yield _frame_message(ns, int(f_t[k]), images[k], mono16, frame_id)
            k += 1
        yield RosMessage(f"{ns}/events", EVENT_PACKET, t_last * 1000, event_packet_cdr(
            pk.payload, encoding=encoding, seq=seq, time_base_ns=pk.time_base_ns,
            t_ns=t_last * 1000, height=h, width=w, frame_id=frame_id))
        seq += 1
    for j in range(k, len(f_t)):
        yield _frame_message(ns, int(f_t[j]), images[j], mono16, frame_id)


def _frame_message(ns: str, t_us: int, image: np.ndarray, mono16: bool,
                   frame_id: str) -> RosMessage:
    if mono16:
        img = np.clip(np.rint(np.asarray(image, np.float64) * 257.0), 0, 65535)
        data = image_cdr(img.astype(np.uint16), t_ns=t_us * 1000, frame_id=frame_id,
                         encoding="mono16")
    else:
        data = image_cdr(image, t_ns=t_us * 1000, frame_id=frame_id, encoding="mono8")
    return RosMessage(f"{ns}/image_raw", IMAGE, t_us * 1000, data)


def write_ros2_bag(rec: Recording, path: str | os.PathLike[str], **options: Any) -> Path:
    """Write ``rec`` as a ROS 2 MCAP file (:func:`recording_messages` ``options``)."""
    with Ros2McapWriter(path) as out:
        for m in recording_messages(rec, **options):
            out.add(m.topic, m.msgtype, m.t_ns, m.data)
    return Path(path)
