"""ROS bag files cut short, read as far as their records are whole (not public API).

``rosbags`` reads a ROS 1 bag from its index at the end and a ROS 2 MCAP file from its summary
and footer, so a bag without its end does not open there. These readers walk such a file from
its start instead and offer what :mod:`evcal.io.rosbag` uses of a ``rosbags`` reader:
``connections`` (``rosbags.interfaces.Connection``) and ``messages(connections=...)`` yielding
``(connection, log time ns, raw bytes)``, in file order, plus ``cut`` (:class:`~evcal.io.
_partial.Cut`).

ROS 1 (the ROS wiki's "Bags/Format/2.0", what ``rosbag reindex`` relies on): after the line
``#ROSBAG V2.0``, records of a uint32 header length, header fields (uint32 length,
``name=value``), a uint32 data length and the data. Chunks (op 0x05, ``compression`` none,
bz2 or lz4) hold connection (0x07) and message data (0x02) records; index data (0x04) follows
each chunk; the index (connections and chunk infos, 0x06) starts at the bag header's
``index_pos``, at the end. A chunk cut short gives the whole messages of its part that still
decompresses.

ROS 2 MCAP: :mod:`evcal.io._mcap_partial`.
"""

from __future__ import annotations

import struct
from collections.abc import Collection, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from ..errors import ErrorReason
from ..recording import RecordingError
from ._mcap_partial import McapPrefix
from ._partial import Cut, cut_in_header

if TYPE_CHECKING:
    from rosbags.interfaces import Connection

ROS1_LINE = b"#ROSBAG V2.0\n"
_U32 = struct.Struct("<I")
_MSGDATA, _BAGHEADER, _CHUNK, _CONNECTION = 0x02, 0x03, 0x05, 0x07
_OPS = {0x02: "message data", 0x03: "bag header", 0x04: "index data", 0x05: "chunk",
        0x06: "chunk info", 0x07: "connection"}


class PartialBagError(RecordingError):
    """A bag record that is whole but cannot be what it says (a corrupt bag)."""

    default_reason = ErrorReason.MALFORMED


@dataclass
class PartialBag:
    """The whole messages of a bag file cut short, as a ``rosbags`` reader offers them."""

    path: Path
    cut: Cut
    connections: list[Connection] = field(default_factory=list)
    message_count: int = 0
    _messages: Any = None  # a callable giving (conn id, time ns, bytes) in file order

    def messages(self, connections: Collection[Connection] = ()
                 ) -> Iterator[tuple[Connection, int, bytes]]:
        wanted = {c.id: c for c in (connections or self.connections)}
        for cid, t_ns, data in self._messages():
            conn = wanted.get(cid)
            if conn is not None:
                yield conn, t_ns, data

    def close(self) -> None:
        """Nothing stays open between calls."""


# ------------------------------------------------------------------------------- ROS 2 MCAP


def partial_mcap_bag(prefix: McapPrefix) -> PartialBag:
    """A ROS 2 MCAP file's whole messages (its :class:`McapPrefix`) as a bag reader."""
    from rosbags.interfaces import (
        Connection,
        ConnectionExtRosbag2,
        MessageDefinition,
        MessageDefinitionFormat,
    )

    bag = PartialBag(prefix.path, prefix.cut, message_count=prefix.n_messages)
    formats = {"ros2msg": MessageDefinitionFormat.MSG, "ros2idl": MessageDefinitionFormat.IDL}
    for cid, channel in sorted(prefix.channels.items()):
        schema = prefix.schemas.get(channel.schema_id)
        name = schema.name if schema is not None else "__schemaless__"
        msgdef = MessageDefinition(formats.get(schema.encoding if schema else "",
                                               MessageDefinitionFormat.NONE),
                                   bytes(schema.data).decode("utf-8", "replace")
                                   if schema is not None else "")
        bag.connections.append(Connection(
            cid, channel.topic, name, msgdef, "", prefix.message_counts.get(cid, 0),
            ConnectionExtRosbag2(channel.message_encoding, []), bag))

    def messages() -> Iterator[tuple[int, int, bytes]]:
        for channel, message in prefix.messages():
            yield channel.id, int(message.log_time), bytes(message.data)

    bag._messages = messages
    return bag


# ------------------------------------------------------------------------------- ROS 1


def _fields(header: bytes | memoryview, where: str) -> dict[str, bytes]:
    out: dict[str, bytes] = {}
    pos = 0
    while pos + 4 <= len(header):
        (n,) = _U32.unpack_from(header, pos)
        pos += 4
        if pos + n > len(header):
            raise PartialBagError(f"{where}: a record header field runs past its header "
                                  "(corrupt bag)")
        name, sep, value = bytes(header[pos : pos + n]).partition(b"=")
        if not sep:
            raise PartialBagError(f"{where}: a record header field without '=' (corrupt bag)")
        out[name.decode("latin-1")] = value
        pos += n
    return out


def _op(fields: dict[str, bytes], where: str) -> int:
    op = fields.get("op", b"")
    if len(op) != 1:
        raise PartialBagError(f"{where}: a record without its 'op' field (corrupt bag)")
    return op[0]


def _records(buf: bytes) -> Iterator[tuple[dict[str, bytes], memoryview]]:
    """The whole records of a chunk's (possibly partial) uncompressed bytes."""
    view = memoryview(buf)
    pos = 0
    while pos + 4 <= len(buf):
        (hlen,) = _U32.unpack_from(buf, pos)
        if pos + 8 + hlen > len(buf):
            return
        header = view[pos + 4 : pos + 4 + hlen]
        (dlen,) = _U32.unpack_from(buf, pos + 4 + hlen)
        start = pos + 8 + hlen
        if start + dlen > len(buf):
            return
        yield _fields(header, "chunk"), view[start : start + dlen]
        pos = start + dlen


def _decompress(data: bytes, compression: str, whole: bool, where: str) -> bytes:
    """A chunk's records; of a chunk cut short (``whole`` False), what decompresses."""
    try:
        if compression == "none":
            return data
        if compression == "bz2":
            import bz2

            return bz2.decompress(data) if whole else bz2.BZ2Decompressor().decompress(data)
        if compression == "lz4":
            import lz4.frame  # type: ignore[import-untyped]  # a dependency of rosbags

            if whole:
                return bytes(lz4.frame.decompress(data))
            return bytes(lz4.frame.LZ4FrameDecompressor().decompress(data))
    except Exception as exc:  # bz2/lz4 errors
        if not whole:
            return b""
        raise PartialBagError(f"{where}: a {compression} chunk that does not decompress "
                              f"(corrupt bag): {type(exc).__name__}: {exc}") from None
    raise PartialBagError(f"{where}: a chunk compressed with {compression!r}, which evcal "
                          "cannot decompress")


def _topic(name: str) -> str:
    return "/" * name.startswith("/") + "/".join(x for x in name.split("/") if x)


def _ros2_type(name: str) -> str:
    pkg, _, base = name.rpartition("/")
    return name if pkg.endswith("/msg") else f"{pkg}/msg/{base}"


def scan_ros1(path: Path) -> PartialBag | None:
    """The whole records of a ROS 1 bag file, or None when the file is whole (its index is
    there: a bag that ``rosbags`` refused for another reason)."""
    from rosbags.interfaces import (
        Connection,
        ConnectionExtRosbag1,
        MessageDefinition,
        MessageDefinitionFormat,
    )

    where = str(path)
    size = path.stat().st_size
    chunks: list[tuple[int, int, str]] = []  # data start, length, compression
    partial = b""  # what decompressed of a chunk cut short
    conns: dict[int, tuple[str, dict[str, bytes]]] = {}
    counts: dict[int, int] = {}
    index_pos = -1
    index_records = 0  # the header's conn_count + chunk_count when the index is whole
    n_chunks = 0

    def take(fields: dict[str, bytes], data: memoryview | bytes) -> None:
        op = _op(fields, where)
        if op == _CONNECTION and "conn" in fields:
            cid = _U32.unpack(fields["conn"])[0]
            conns.setdefault(cid, (fields.get("topic", b"").decode(), _fields(data, where)))
        elif op == _MSGDATA and "conn" in fields:
            cid = _U32.unpack(fields["conn"])[0]
            counts[cid] = counts.get(cid, 0) + 1

    with open(path, "rb") as f:
        if f.read(len(ROS1_LINE)) != ROS1_LINE:
            raise cut_in_header(where, size, "the '#ROSBAG V2.0' line, cut")
        pos = len(ROS1_LINE)
        cut: Cut | None = None
        while cut is None:
            n_msgs = sum(counts.values())
            read = f"{n_msgs:,} whole messages" + (
                f" ({n_chunks} whole chunk{'s' if n_chunks > 1 else ''})" if n_chunks else "")
            f.seek(pos)
            head = f.read(4)
            if not head:
                if 0 < index_pos < size and index_records <= 0:
                    return None  # whole, index included
                cut = Cut(where, size, pos, read, "its index (the connection and chunk info "
                          "records after the chunks)")
                break
            hlen = _U32.unpack(head)[0] if len(head) == 4 else 0
            header = f.read(hlen) if len(head) == 4 else b""
            dl = f.read(4)
            section = " of its index" if 0 < index_pos <= pos else ""
            if len(head) < 4 or len(header) < hlen or len(dl) < 4:
                if index_pos < 0:
                    raise cut_in_header(where, size, "the bag header record, cut")
                cut = Cut(where, size, pos, read, f"the header of a record{section} "
                          f"({size - pos} bytes present)")
                break
            fields = _fields(header, where)
            op = _op(fields, where)
            start = pos + 8 + hlen
            (dlen,) = _U32.unpack(dl)
            if op == _BAGHEADER and "index_pos" in fields:
                index_pos = struct.unpack("<Q", fields["index_pos"])[0]
                index_records = sum(_U32.unpack(fields[k])[0] for k in ("conn_count",
                                                                         "chunk_count")
                                    if len(fields.get(k, b"")) == 4)
            elif 0 < index_pos <= pos:
                index_records -= 1
            if start + dlen > size:
                what = (f"a {_OPS.get(op, f'op {op}')} record{section} ({8 + hlen + dlen:,} "
                        f"bytes, {size - pos:,} present)")
                recovered = ""
                if op == _CHUNK:
                    partial = _decompress(f.read(size - start),
                                          fields.get("compression", b"none").decode(), False,
                                          where)
                    before = sum(counts.values())
                    for inner, data in _records(partial):
                        take(inner, data)
                    got = sum(counts.values()) - before
                    if got:
                        recovered = (f"{got:,} whole messages were read from the part that "
                                     "decompresses, the rest left out")
                if op == _BAGHEADER:
                    raise cut_in_header(where, size, f"the bag header record: "
                                        f"{8 + hlen + dlen:,} bytes, {size - pos:,} present")
                cut = Cut(where, size, pos, read, what, recovered)
                break
            if op == _CHUNK:
                compression = fields.get("compression", b"none").decode()
                chunks.append((start, dlen, compression))
                n_chunks += 1
                for inner, data in _records(_decompress(f.read(dlen), compression, True,
                                                        where)):
                    take(inner, data)
            elif op == _CONNECTION:
                take(fields, f.read(dlen))
            elif op == _MSGDATA:
                raise PartialBagError(f"{where}: a message record outside any chunk (not a "
                                      "ROS 1 bag 2.0 file evcal reads)")
            pos = start + dlen
    if index_pos < 0:
        raise cut_in_header(where, size, "the bag header record, missing")

    bag = PartialBag(path, cut, message_count=sum(counts.values()))
    for cid, (topic, info) in sorted(conns.items()):
        def text(key: str, info: dict[str, bytes] = info) -> str:
            return info.get(key, b"").decode("utf-8", "replace")

        latching = text("latching")
        bag.connections.append(Connection(
            cid, _topic(topic), _ros2_type(text("type")),
            MessageDefinition(MessageDefinitionFormat.MSG, text("message_definition")),
            text("md5sum"), counts.get(cid, 0),
            ConnectionExtRosbag1(text("callerid") or None, int(latching) if latching else None),
            bag))

    def messages() -> Iterator[tuple[int, int, bytes]]:
        def from_records(buf: bytes) -> Iterator[tuple[int, int, bytes]]:
            for fields, data in _records(buf):
                if _op(fields, where) == _MSGDATA:
                    sec, nsec = struct.unpack("<II", fields["time"])
                    yield _U32.unpack(fields["conn"])[0], sec * 10**9 + nsec, bytes(data)

        with open(path, "rb") as f:
            for start, length, compression in chunks:
                f.seek(start)
                yield from from_records(_decompress(f.read(length), compression, True, where))
        yield from from_records(partial)

    bag._messages = messages
    return bag
