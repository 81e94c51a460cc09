"""The messages evcal reads from ROS bags and ROS 2 topics, and their decoding (no file
access: :mod:`evcal.io.rosbag` opens the bags, :mod:`evcal.service.ros2` takes the topics).

The message types are registered in a ``rosbags`` typestore from their ``.msg`` text
(:data:`MSG_DEFINITIONS`, :func:`typestore`). EventPacket payloads are decoded by
:mod:`evcal.io._evcodecs` (:func:`packet_decoder`, :func:`decode_packet`; a decoder carries
its state from packet to packet); the event arrays of ``dvs_msgs`` /
``prophesee_event_msgs`` are read straight from the serialised bytes with numpy
(:func:`parse_event_array`, CDR or ROS 1 layout); Images become gray frames
(:func:`image_to_gray`). Times and conversions: :mod:`evcal.io.rosbag`'s docstring.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from ..errors import ErrorReason
from ..events import EVENTS_DTYPE
from ..recording import RecordingError
from ._evcodecs import DecodedPacket, PacketDecoder, PayloadError, make_decoder

if TYPE_CHECKING:
    from rosbags.typesys.store import Typestore

EVENT_PACKET = "event_camera_msgs/msg/EventPacket"
EVENT_ARRAY_LEGACY = "event_array_msgs/msg/EventArray"
DVS_EVENT_ARRAY = "dvs_msgs/msg/EventArray"
PROPHESEE_EVENT_ARRAY = "prophesee_event_msgs/msg/EventArray"
IMAGE = "sensor_msgs/msg/Image"

# event_camera_msgs/msg/EventPacket.msg (ros-event-camera/event_camera_msgs)
_EVENT_PACKET_MSG = """\
std_msgs/Header header
uint32 height
uint32 width
uint64 seq
uint64 time_base
string encoding
bool is_bigendian
uint8[] events
"""
# dvs_msgs (uzh-rpg/rpg_dvs_ros) and prophesee_event_msgs (prophesee-ai/prophesee_ros_wrapper)
# share these two definitions; ``time`` is builtin_interfaces/msg/Time in ROS 2.
_EVENT_MSG = """\
uint16 x
uint16 y
time ts
bool polarity
"""
_EVENT_ARRAY_MSG = """\
std_msgs/Header header
uint32 height
uint32 width
{pkg}/Event[] events
"""
MSG_DEFINITIONS: dict[str, str] = {
    "dvs_msgs/msg/Event": _EVENT_MSG,
    DVS_EVENT_ARRAY: _EVENT_ARRAY_MSG.format(pkg="dvs_msgs"),
    "prophesee_event_msgs/msg/Event": _EVENT_MSG,
    PROPHESEE_EVENT_ARRAY: _EVENT_ARRAY_MSG.format(pkg="prophesee_event_msgs"),
    EVENT_PACKET: _EVENT_PACKET_MSG,
    EVENT_ARRAY_LEGACY: _EVENT_PACKET_MSG,
}
EVENT_TYPES = (EVENT_PACKET, EVENT_ARRAY_LEGACY, DVS_EVENT_ARRAY, PROPHESEE_EVENT_ARRAY)
# the Images `evcal serve --ros2` publishes on <camera>/calibration/<name>: a bag recorded
# from its domain holds them beside the camera's frames, which they are not
CALIBRATION_IMAGES = ("contrast", "bias", "special")


def is_calibration_topic(topic: str) -> bool:
    """Whether ``topic`` is one of evcal's calibration Images (``.../calibration/bias``)."""
    head, _, name = topic.rstrip("/").rpartition("/")
    return name in CALIBRATION_IMAGES and head.endswith("/calibration")
FRAME_ENCODINGS = ("mono8", "mono16", "rgb8", "bgr8")

_LUMA = np.array([0.299, 0.587, 0.114])


class RosbagError(RecordingError):
    """A bag that cannot be read as events and frames: what and where (topic, message)."""


def typestore(ros_version: int) -> Typestore:
    """The standard types of ROS 1 Noetic or ROS 2 Humble plus :data:`MSG_DEFINITIONS`."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.ROS1_NOETIC if ros_version == 1 else Stores.ROS2_HUMBLE)
    types: dict[str, Any] = {}
    for name, text in MSG_DEFINITIONS.items():
        types.update(get_types_from_msg(text, name))
    store.register(types)
    return store



# ------------------------------------------------------------------------------- decoding


def stamp_ns(msg: Any) -> int:
    return int(msg.header.stamp.sec) * 1_000_000_000 + int(msg.header.stamp.nanosec)


_ROS1_EVENT = np.dtype([("x", "<u2"), ("y", "<u2"), ("sec", "<u4"), ("nsec", "<u4"),
                        ("p", "u1")])  # packed, 13 bytes
_EVENT_COLUMNS = np.dtype([("x", "<u2"), ("y", "<u2"), ("sec", "<i8"), ("nsec", "<i8"),
                           ("p", "u1")])


def _cdr_event(order: str, first: bool) -> np.dtype:
    # CDR aligns every primitive to its size, counted from the end of the 4-byte encapsulation
    # header. The array starts 4-aligned (after its uint32 length): the first Event is
    # x@0 y@2 sec@4 nanosec@8 polarity@12 (13 bytes), every later one starts 2 mod 4 and is
    # x@0 y@2 (pad 2) sec@6 nanosec@10 polarity@14, 16 bytes with the pad before the next.
    offsets = [0, 2, 4, 8, 12] if first else [0, 2, 6, 10, 14]
    return np.dtype({"names": ["x", "y", "sec", "nsec", "p"],
                     "formats": [order + "u2", order + "u2", order + "i4", order + "u4", "u1"],
                     "offsets": offsets, "itemsize": 13 if first else 16})


class _Cursor:
    """Reads a serialised message's leading fields, with errors that say where it ended."""

    def __init__(self, raw: bytes | memoryview, order: str, origin: int) -> None:
        self.buf = bytes(raw)
        self.order = order
        self.origin = origin  # CDR alignment is counted from here
        self.pos = origin

    def align(self, n: int) -> None:
        self.pos += (-(self.pos - self.origin)) % n

    def u32(self, what: str, align: bool) -> int:
        if align:
            self.align(4)
        if self.pos + 4 > len(self.buf):
            raise PayloadError(f"the message ends ({len(self.buf)} bytes) inside {what}",
                               ErrorReason.TRUNCATED)
        value = int.from_bytes(self.buf[self.pos:self.pos + 4],
                               "little" if self.order == "<" else "big")
        self.pos += 4
        return value

    def skip(self, n: int, what: str) -> None:
        if self.pos + n > len(self.buf):
            raise PayloadError(f"the message ends ({len(self.buf)} bytes) inside {what} "
                               f"({n} bytes from byte {self.pos})", ErrorReason.TRUNCATED)
        self.pos += n


def parse_event_array(raw: bytes | memoryview, ros_version: int
                      ) -> tuple[int, int, int, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``(height, width, stamp_ns, t_us, x, y, on)`` of a serialised dvs_msgs /
    prophesee_event_msgs ``EventArray`` (ROS 1 or CDR), without a Python loop per event."""
    if ros_version == 1:
        cur = _Cursor(raw, "<", 0)
        cur.u32("header.seq", False)
        sec = cur.u32("header.stamp", False)
        nsec = cur.u32("header.stamp", False)
        cur.skip(cur.u32("header.frame_id", False), "header.frame_id")
        height = cur.u32("height", False)
        width = cur.u32("width", False)
        n = cur.u32("the event count", False)
        end = cur.pos + 13 * n
        if end > len(cur.buf):
            raise PayloadError(f"the message ends ({len(cur.buf)} bytes) inside event "
                               f"{(len(cur.buf) - cur.pos) // 13} of {n} (13 bytes each from "
                               f"byte {cur.pos})", ErrorReason.TRUNCATED)
        if end != len(cur.buf):
            raise PayloadError(f"{len(cur.buf) - end} bytes after the {n} events",
                               ErrorReason.MALFORMED)
        ev = np.frombuffer(cur.buf, _ROS1_EVENT, count=n, offset=cur.pos)
        stamp = sec * 1_000_000_000 + nsec
    else:
        if len(raw) < 4 or bytes(raw[:1]) != b"\x00" or bytes(raw[1:2]) not in (b"\x00", b"\x01"):
            raise PayloadError("not a CDR message (encapsulation header)", ErrorReason.MALFORMED)
        order = "<" if bytes(raw[1:2]) == b"\x01" else ">"
        cur = _Cursor(raw, order, 4)
        sec = cur.u32("header.stamp", True)
        sec = sec - (1 << 32) if sec >= 1 << 31 else sec  # int32 in ROS 2
        nsec = cur.u32("header.stamp", True)
        cur.skip(cur.u32("header.frame_id", True), "header.frame_id")
        height = cur.u32("height", True)
        width = cur.u32("width", True)
        n = cur.u32("the event count", True)
        end = cur.pos + (16 * n - 3 if n else 0)
        if end > len(cur.buf):
            got = 0 if len(cur.buf) < cur.pos + 13 else 1 + (len(cur.buf) - cur.pos - 14) // 16
            raise PayloadError(f"the message ends ({len(cur.buf)} bytes) inside event {got} of "
                               f"{n} (from byte {cur.pos})", ErrorReason.TRUNCATED)
        if len(cur.buf) - end > 3:  # at most the padding to 4 bytes
            raise PayloadError(f"{len(cur.buf) - end} bytes after the {n} events",
                               ErrorReason.MALFORMED)
        if n:
            first = np.frombuffer(cur.buf, _cdr_event(order, True), count=1, offset=cur.pos)
            # one zero byte past the end so that the last, 15-byte Event reads as 16
            later = np.frombuffer(cur.buf + b"\x00", _cdr_event(order, False), count=n - 1,
                                  offset=cur.pos + 14)
            ev = np.concatenate([first.astype(_EVENT_COLUMNS), later.astype(_EVENT_COLUMNS)])
        else:
            ev = np.zeros(0, _EVENT_COLUMNS)
        stamp = sec * 1_000_000_000 + nsec
    t_us = ev["sec"].astype(np.int64) * 1_000_000 + ev["nsec"].astype(np.int64) // 1000
    return (int(height), int(width), int(stamp), t_us, ev["x"].astype(np.uint16),
            ev["y"].astype(np.uint16), ev["p"] != 0)


def image_to_gray(msg: Any) -> np.ndarray:
    """A ``sensor_msgs/msg/Image`` as a ``[y, x]`` gray image (see the module docstring)."""
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    enc = str(msg.encoding)
    if enc not in FRAME_ENCODINGS:
        raise PayloadError(f"image encoding {enc!r} is not one evcal reads "
                           f"({', '.join(FRAME_ENCODINGS)})", ErrorReason.MALFORMED)
    depth = {"mono8": 1, "mono16": 2, "rgb8": 3, "bgr8": 3}[enc]
    data = np.asarray(msg.data, np.uint8)
    if h < 1 or w < 1:
        raise PayloadError(f"image of size {w}x{h}", ErrorReason.OUT_OF_RANGE)
    if step < w * depth:
        raise PayloadError(f"image step {step} is less than width {w} x {depth} bytes",
                           ErrorReason.MALFORMED)
    if data.size < h * step:
        raise PayloadError(f"image data has {data.size} bytes, {h} rows of step {step} need "
                           f"{h * step}", ErrorReason.TRUNCATED)
    rows = data[:h * step].reshape(h, step)[:, :w * depth]
    if enc == "mono8":
        return np.ascontiguousarray(rows)
    if enc == "mono16":
        values = rows.copy().view(">u2" if msg.is_bigendian else "<u2")
        result: np.ndarray = (values.astype(np.float32) / np.float32(257.0))
        return result
    rgb = rows.reshape(h, w, 3).astype(np.float64)
    if enc == "bgr8":
        rgb = rgb[:, :, ::-1]
    luma: np.ndarray = np.clip(np.rint(rgb @ _LUMA), 0, 255).astype(np.uint8)
    return luma


@dataclass
class EventStream:
    """What the event messages of one topic accumulated."""

    msgtype: str
    chunks: list[np.ndarray] = field(default_factory=list)
    size: tuple[int, int] | None = None  # (height, width)
    decoder: PacketDecoder | None = None
    encoding: str | None = None
    last_seq: int | None = None
    lost: int = 0
    seq_gaps: list[tuple[int, int]] = field(default_factory=list)
    seq_back: int = 0
    dropped: int = 0
    triggers: int = 0


def packet_decoder(decoder: PacketDecoder | None, msg: Any) -> PacketDecoder:
    """The decoder of a topic's next deserialised EventPacket ``msg``: ``decoder``, or a new
    one for the message's encoding when it is None.

    Raises :class:`~evcal.io._evcodecs.PayloadError` (``malformed``): a big-endian payload,
    an encoding evcal does not decode, or an encoding other than the topic's.
    """
    if msg.is_bigendian:
        raise PayloadError("is_bigendian payloads are not supported (the drivers write "
                           "little-endian words)", ErrorReason.MALFORMED)
    enc = str(msg.encoding)
    if decoder is None:
        return make_decoder(enc)
    if enc != decoder.encoding:
        raise PayloadError(f"encoding {enc!r}, the topic's earlier messages are "
                           f"{decoder.encoding!r}", ErrorReason.MALFORMED)
    return decoder


def decode_packet(decoder: PacketDecoder, msg: Any) -> DecodedPacket:
    """The events of a deserialised EventPacket (:class:`PayloadError` if they do not
    decode), with the topic's decoder from :func:`packet_decoder`."""
    return decoder.decode(msg.events, time_base=int(msg.time_base), width=int(msg.width),
                          height=int(msg.height), stamp_ns=stamp_ns(msg))


def packet_events(stream: EventStream, msg: Any, where: str) -> np.ndarray:
    try:
        stream.decoder = packet_decoder(stream.decoder, msg)
    except PayloadError as exc:
        raise RosbagError(f"{where}: {exc}", exc.reason) from None
    stream.encoding = stream.decoder.encoding
    seq = int(msg.seq)
    if stream.last_seq is not None:
        if seq > stream.last_seq + 1:
            stream.lost += seq - stream.last_seq - 1
            stream.seq_gaps.append((stream.last_seq, seq))
        elif seq <= stream.last_seq:
            stream.seq_back += 1
    stream.last_seq = seq
    try:
        pk = decode_packet(stream.decoder, msg)
    except PayloadError as exc:
        raise RosbagError(f"{where} (seq {seq}): {exc}", exc.reason) from None
    stream.dropped += pk.dropped
    stream.triggers += int(pk.trigger_t_us.size)
    return event_columns(pk.t_us, pk.x, pk.y, pk.on)


def event_columns(t_us: np.ndarray, x: np.ndarray, y: np.ndarray, on: np.ndarray
                  ) -> np.ndarray:
    """Decoded columns (``on`` True for ON) as an :data:`~evcal.events.EVENTS_DTYPE` array."""
    ev = np.empty(t_us.shape[0], EVENTS_DTYPE)
    ev["t_us"] = t_us
    ev["x"] = x
    ev["y"] = y
    ev["p"] = np.where(on, 1, -1)
    return ev


def sorted_events(chunks: list[np.ndarray]) -> tuple[np.ndarray, int]:
    """Concatenated events sorted by time (stable) and how many were late."""
    if not chunks:
        return np.zeros(0, EVENTS_DTYPE), 0
    events = np.concatenate(chunks)
    t = events["t_us"]
    if t.size > 1 and (t[1:] < t[:-1]).any():
        late = int(np.count_nonzero(t[1:] < np.maximum.accumulate(t)[:-1]))
        return events[np.argsort(t, kind="stable")], late
    return events, 0


def deserialize_message(deser: Any, raw: bytes | memoryview, msgtype: str, where: str) -> Any:
    """``deser(raw, msgtype)`` (a typestore's ``deserialize_cdr`` or ``deserialize_ros1``);
    :class:`RosbagError` (``truncated``) naming ``where`` when the bytes do not deserialise."""
    try:
        return deser(raw, msgtype)
    except Exception as exc:  # rosbags SerdeError, struct/index errors of a cut message
        raise RosbagError(f"{where}: cannot deserialise {len(raw)} bytes as {msgtype} "
                          f"(truncated or another definition?): {type(exc).__name__}: {exc}",
                          ErrorReason.TRUNCATED) from None
