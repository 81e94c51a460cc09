"""MCAP files cut short: the whole records before the cut (not public API).

The ``mcap`` library's readers need the summary and footer at the end of the file (the
seeking reader) or stop with an error at the first partial record (the stream reader), so a
file without its end is walked here record by record (opcode uint8, length uint64, content;
the MCAP specification's record framing), reading only the records a reader needs: schemas,
channels, metadata, messages, and the messages inside chunks. Whole chunks are decompressed
and their CRC checked; of a chunk cut short, the whole messages of the part that still
decompresses are read too (zstd and lz4 decode block by block, so all but the last block's
messages are there). Used by evcal's MCAP reader and the ROS 2 bag reader alike.
"""

from __future__ import annotations

import struct
import zlib
from collections.abc import Iterator
from dataclasses import dataclass, field
from io import BytesIO
from pathlib import Path
from typing import Any

from ..recording import RecordingError
from ._partial import Cut, cut_in_header, refuse_empty_file

MCAP_MAGIC = b"\x89MCAP0\r\n"
_FRAMING = struct.Struct("<BQ")  # opcode, content length
_HEADER, _FOOTER, _SCHEMA, _CHANNEL, _MESSAGE, _CHUNK, _METADATA = 1, 2, 3, 4, 5, 6, 12
_NAMES = {1: "header", 2: "footer", 3: "schema", 4: "channel", 5: "message", 6: "chunk",
          7: "message index", 8: "chunk index", 9: "attachment", 10: "attachment index",
          11: "statistics", 12: "metadata", 13: "metadata index", 14: "summary offset",
          15: "data end"}


def mcap_is_whole(path: Path) -> bool:
    """Whether the file at ``path`` ends with the MCAP magic (a finished file); a
    :class:`RecordingError` when it is not MCAP at all, an
    :class:`~evcal.io.EmptyRecordingError` when it is empty or shorter than its magic."""
    size = refuse_empty_file(path)
    with open(path, "rb") as f:
        head = f.read(len(MCAP_MAGIC))
        if size >= 2 * len(MCAP_MAGIC):
            f.seek(size - len(MCAP_MAGIC))
        tail = f.read(len(MCAP_MAGIC))
    if head != MCAP_MAGIC[: len(head)]:
        raise RecordingError(f"{path}: not an MCAP file (it does not start with the MCAP magic)")
    if len(head) < len(MCAP_MAGIC):
        raise cut_in_header(str(path), size, "the 8-byte MCAP magic")
    return tail == MCAP_MAGIC and size >= 2 * len(MCAP_MAGIC)


def _record(cls_name: str, content: bytes | memoryview, length: int) -> Any:
    from mcap import records
    from mcap.data_stream import ReadDataStream

    stream = ReadDataStream(BytesIO(bytes(content)))
    cls = getattr(records, cls_name)
    return cls.read(stream, length) if cls_name == "Message" else cls.read(stream)


def _inner(data: bytes) -> Iterator[tuple[int, memoryview]]:
    """The whole records of a chunk's (possibly partial) uncompressed bytes."""
    view = memoryview(data)
    pos = 0
    while pos + _FRAMING.size <= len(data):
        op, length = _FRAMING.unpack_from(data, pos)
        start = pos + _FRAMING.size
        if start + length > len(data):
            return
        yield op, view[start : start + length]
        pos = start + length


def _chunk_header(content: bytes | memoryview) -> tuple[int, int, str, int] | None:
    """``(uncompressed_size, uncompressed_crc, compression, records_start)`` of a chunk
    record's content; None when it is too short to say."""
    if len(content) < 32:
        return None
    size, crc, n = struct.unpack_from("<QIi", content, 16)
    if len(content) < 32 + n + 8:
        return None
    compression = bytes(content[32 : 32 + n]).decode("utf-8", "replace")
    return size, crc, compression, 32 + n + 8


def _decompress_whole(content: bytes | memoryview, where: str) -> bytes:
    head = _chunk_header(content)
    if head is None:
        raise RecordingError(f"{where}: a chunk record too short for its own fields")
    size, crc, compression, start = head
    (n,) = struct.unpack_from("<Q", content, start - 8)
    raw = bytes(content[start : start + n])
    if compression == "zstd":
        import zstandard

        data: bytes = zstandard.ZstdDecompressor().decompress(raw, max_output_size=size)
    elif compression == "lz4":
        import lz4.frame  # type: ignore[import-untyped]  # a dependency of rosbags and mcap

        data = lz4.frame.decompress(raw)
    elif compression == "":
        data = raw
    else:
        raise RecordingError(f"{where}: a chunk compressed with {compression!r}, which evcal "
                             "cannot decompress")
    if crc and zlib.crc32(data) != crc:
        raise RecordingError(f"{where}: a chunk whose CRC does not match its content (corrupt "
                             "file)")
    return data


def _decompress_part(content: bytes | memoryview) -> bytes:
    """What still decompresses of a chunk record cut short (b"" when nothing does)."""
    head = _chunk_header(content)
    if head is None:
        return b""
    _size, _crc, compression, start = head
    raw = bytes(content[start:])
    try:
        if compression == "zstd":
            import zstandard

            out: bytes = zstandard.ZstdDecompressor().decompressobj().decompress(raw)
            return out
        if compression == "lz4":
            import lz4.frame

            return bytes(lz4.frame.LZ4FrameDecompressor().decompress(raw))
    except Exception:  # lz4/zstd errors on a damaged part: nothing recovered from it
        return b""
    return raw if compression == "" else b""


@dataclass
class McapPrefix:
    """The whole records of an MCAP file that does not end with its footer and magic.

    ``schemas``, ``channels`` (by id, ``mcap.records`` objects) and ``metadata`` (by name)
    are those of the whole part; ``message_counts`` counts the whole messages per channel;
    ``cut`` says where the file ends and what was read. :meth:`messages` yields the whole
    messages in file order.
    """

    path: Path
    cut: Cut
    schemas: dict[int, Any] = field(default_factory=dict)
    channels: dict[int, Any] = field(default_factory=dict)
    metadata: dict[str, dict[str, str]] = field(default_factory=dict)
    message_counts: dict[int, int] = field(default_factory=dict)
    _spans: list[tuple[int, int, int]] = field(default_factory=list)  # opcode, start, length
    _partial: bytes = b""  # what decompressed of a chunk cut short

    @property
    def n_messages(self) -> int:
        return sum(self.message_counts.values())

    def _contents(self) -> Iterator[tuple[int, bytes | memoryview]]:
        """The whole records of interest, chunks opened, in file order."""
        with open(self.path, "rb") as f:
            for op, start, length in self._spans:
                f.seek(start)
                content = f.read(length)
                if op == _CHUNK:
                    yield from _inner(_decompress_whole(content, str(self.path)))
                else:
                    yield op, content
        yield from _inner(self._partial)

    def messages(self) -> Iterator[tuple[Any, Any]]:
        """``(channel, message)`` of every whole message, in file order."""
        for op, content in self._contents():
            if op == _MESSAGE:
                message = _record("Message", content, len(content))
                channel = self.channels.get(message.channel_id)
                if channel is not None:
                    yield channel, message


def scan_mcap_prefix(path: Path) -> McapPrefix:
    """Walk an MCAP file that does not end with its magic (see the module docstring)."""
    where = str(path)
    size = path.stat().st_size
    prefix = McapPrefix(path, Cut(where, size, size, "", ""))
    chunks = 0
    pos = len(MCAP_MAGIC)
    cut: Cut | None = None
    recovered = 0

    def take(op: int, content: bytes | memoryview) -> None:
        if op == _SCHEMA:
            schema = _record("Schema", content, len(content))
            prefix.schemas[schema.id] = schema
        elif op == _CHANNEL:
            channel = _record("Channel", content, len(content))
            prefix.channels[channel.id] = channel
        elif op == _METADATA:
            record = _record("Metadata", content, len(content))
            prefix.metadata.setdefault(record.name, dict(record.metadata))

    def count(op: int, content: bytes | memoryview) -> None:
        if op == _MESSAGE and len(content) >= 2:
            (cid,) = struct.unpack_from("<H", content, 0)
            prefix.message_counts[cid] = prefix.message_counts.get(cid, 0) + 1
        else:
            take(op, content)

    with open(path, "rb") as f:
        while True:
            f.seek(pos)
            framing = f.read(_FRAMING.size)
            read = f"{prefix.n_messages:,} whole messages" + (
                f" ({chunks} whole chunk{'s' if chunks > 1 else ''})" if chunks else "")
            if len(framing) < _FRAMING.size:
                what = (f"the opcode and length of a record ({len(framing)} of their 9 bytes "
                        "present)" if framing else
                        "the rest of its records, its summary and its footer")
                cut = Cut(where, size, pos, read, what)
                break
            op, length = _FRAMING.unpack(framing)
            start = pos + _FRAMING.size
            if start + length > size:  # the partial record
                what = (f"a {_NAMES.get(op, f'opcode {op}')} record ({_FRAMING.size + length:,}"
                        f" bytes with its opcode and length, {size - pos:,} present)")
                if op == _CHUNK:
                    prefix._partial = _decompress_part(f.read(size - start))
                    for inner_op, part in _inner(prefix._partial):
                        recovered += inner_op == _MESSAGE
                        count(inner_op, part)
                cut = Cut(where, size, pos, read, what,
                          f"{recovered:,} whole messages were read from the part that "
                          "decompresses, the rest left out" if recovered else "")
                break
            if op == _FOOTER:  # whole up to its footer: only the closing magic is cut
                cut = Cut(where, size, start + length, read + " and the summary",
                          f"the closing MCAP magic ({size - start - length} "
                          "of its 8 bytes present)")
                break
            if op in (_SCHEMA, _CHANNEL, _MESSAGE, _CHUNK, _METADATA):
                prefix._spans.append((op, start, length))
                content = f.read(length)
                if op == _CHUNK:
                    chunks += 1
                    for inner_op, inner in _inner(_decompress_whole(content, where)):
                        count(inner_op, inner)
                else:
                    count(op, content)
            pos = start + length
    prefix.cut = cut
    return prefix
