"""AEDAT4 files (iniVation DV) through the ``aedat`` decoder: events and APS frames.

Only the first event stream and the first frame stream are read; IMU and trigger streams are
skipped. The sensor size is the event stream's ``width x height``.

Real DAVIS recordings occasionally hold a few events out of time order across packets. They
are sorted (stable, so equal times keep their file order) and their number is recorded in
``metadata["reordered_events"]`` (0 for a file in order) instead of failing.

A file cut short is read up to its last whole packet. The layout relied on for that (DV's
AEDAT 4.0 description, and the ``aedat`` decoder's ``src/aedat_core.rs``): the 14-byte magic
``#!AER-DAT4.0\r\n``, a uint32 LE length and the IOHeader flatbuffer (``compression`` int32,
``file_data_position`` int64, -1 when there is no file data table, ``description``), then
packets of an int32 stream id, a uint32 length and that many (compressed) bytes, then, at
``file_data_position``, the file data table (an index of the packets, compressed as they are)
to the end of the file.
"""

from __future__ import annotations

import os
import struct
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import ErrorReason
from ..events import EVENTS_DTYPE, SensorSize
from ..recording import Frames, Recording, RecordingError
from ._partial import (
    Cut,
    cut_in_header,
    header_only,
    nothing_whole,
    refuse_empty_file,
    report_cut,
)
from ._util import check_sensor_arg, file_recording

AEDAT4_MAGIC = b"#!AER-DAT4.0\r\n"
_COMPRESSIONS = {0: "none", 1: "lz4", 2: "lz4", 3: "zstd", 4: "zstd"}

# ITU-R BT.601 luma, as Pillow's "L" conversion.
_LUMA = np.array([0.299, 0.587, 0.114])


def _gray(pixels: np.ndarray) -> np.ndarray:
    """A uint8 ``[y, x]`` image from ``(H, W)`` gray or ``(H, W, k)`` colour pixels."""
    if pixels.ndim == 2:
        return np.asarray(pixels, np.uint8)
    if pixels.ndim == 3 and pixels.shape[2] == 1:
        return np.asarray(pixels[:, :, 0], np.uint8)
    if pixels.ndim == 3 and pixels.shape[2] >= 3:
        luma = pixels[:, :, :3].astype(np.float64) @ _LUMA
        result: np.ndarray = np.clip(np.rint(luma), 0, 255).astype(np.uint8)
        return result
    if pixels.ndim == 3 and pixels.shape[2] == 2:  # gray + alpha
        return np.asarray(pixels[:, :, 0], np.uint8)
    raise RecordingError(f"pixels of shape {pixels.shape} are not an image")


def _frame_time(frame: dict[str, Any]) -> tuple[int, int]:
    """``(t_us, exposure_us)``: the middle of the exposure when its stamps are present."""
    b, e = frame.get("exposure_begin_t"), frame.get("exposure_end_t")
    if b is not None and e is not None and int(e) >= int(b) > 0:
        return (int(b) + int(e)) // 2, int(e) - int(b)
    return int(frame["t"]), 0


def _ioheader(buf: bytes) -> tuple[int, int]:
    """``(compression, file_data_position)`` of an IOHeader flatbuffer (their defaults, 0 and
    -1, where a field is absent or the buffer is not readable)."""
    try:
        table = struct.unpack_from("<I", buf, 0)[0]
        vtable = table - struct.unpack_from("<i", buf, table)[0]
        vt_size = struct.unpack_from("<H", buf, vtable)[0]
        fields = [struct.unpack_from("<H", buf, vtable + 4 + 2 * i)[0] if 4 + 2 * i < vt_size
                  else 0 for i in range(2)]
        compression = struct.unpack_from("<i", buf, table + fields[0])[0] if fields[0] else 0
        position = struct.unpack_from("<q", buf, table + fields[1])[0] if fields[1] else -1
    except struct.error:
        return 0, -1
    return int(compression), int(position)


def _table_is_whole(tail: bytes, compression: int) -> bool:
    """Whether the file data table (``tail``, to the end of the file) is one whole compressed
    frame; True when it cannot be told (no compression)."""
    name = _COMPRESSIONS.get(compression)
    try:
        if name == "lz4":
            import lz4.frame  # type: ignore[import-untyped]  # a dependency of rosbags and mcap

            lz = lz4.frame.LZ4FrameDecompressor()
            lz.decompress(tail)
            return bool(lz.eof)
        if name == "zstd":
            import zstandard

            zs = zstandard.ZstdDecompressor().decompressobj()
            zs.decompress(tail)
            return bool(zs.eof)
    except Exception:  # lz4/zstd errors of a damaged table: not whole
        return False
    return True


def _packet_cut(path: Path, size: int, header_end: int, packets: int, table_at: int
                ) -> Cut | None:
    """Where the packets of a file whose decoder failed after ``packets`` packets end: the cut
    when the next packet does not fit in the file, None when it does (a corrupt packet)."""
    with open(path, "rb") as f:
        pos = header_end
        for _ in range(packets):  # one read per packet header, none of their bytes
            f.seek(pos)
            head = f.read(8)
            if len(head) < 8:  # cannot happen for packets the decoder read
                return None
            pos += 8 + struct.unpack_from("<I", head, 4)[0]
        f.seek(pos)
        head = f.read(8)
    read = f"{packets:,} whole packets"
    if pos >= size:
        table = f" and the file data table at byte {table_at:,}" if table_at > -1 else ""
        return Cut(str(path), size, pos, read, f"the packet after packet {packets - 1}{table}")
    if len(head) < 8:
        return Cut(str(path), size, pos, read, f"the 8-byte header of packet {packets} "
                   f"({size - pos} bytes of it present)")
    stream_id, length = struct.unpack("<iI", head)
    if pos + 8 + length <= size:
        return None
    return Cut(str(path), size, pos, read, f"packet {packets} (stream {stream_id}; "
               f"{8 + length:,} bytes with its header, {size - pos:,} present)")


def events_from_packets(chunks: list[np.ndarray]) -> tuple[np.ndarray, int]:
    """Concatenate the decoder's event packets (``t`` u8, ``x``, ``y``, ``on``) once.

    Returns the events as EVENTS_DTYPE sorted by time (stable) and the number of late events,
    those earlier than an event before them in the file (0 when the file is in order).
    """
    if not chunks:
        return np.zeros(0, EVENTS_DTYPE), 0
    raw = np.concatenate(chunks)
    events = np.empty(raw.shape[0], EVENTS_DTYPE)
    events["t_us"] = raw["t"].astype(np.int64)
    events["x"] = raw["x"]
    events["y"] = raw["y"]
    events["p"] = np.where(raw["on"], 1, -1)
    t = events["t_us"]
    if t.size > 1 and (t[1:] < t[:-1]).any():
        reordered = int(np.count_nonzero(t[1:] < np.maximum.accumulate(t)[:-1]))
        return events[np.argsort(t, kind="stable")], reordered
    return events, 0


def read_aedat4(path: str | os.PathLike[str], *, sensor: SensorSize | None = None,
                strict: bool = False) -> Recording:
    """Read events and frames of an AEDAT4 file.

    Parameters
    ----------
    path : path
        An ``.aedat4`` file.
    sensor : SensorSize, optional
        Checked against the size the file declares (an error when they differ); the file
        must declare one.
    strict : bool
        Refuse a file cut short (:class:`TruncatedRecordingError`) instead of reading its
        whole packets with a :class:`TruncatedRecordingWarning`.

    Returns
    -------
    Recording
        Times are the camera's µs timestamps (usually µs since the Unix epoch). Frame times
        are the middle of the exposure, ``exposure_us = end - begin``. ``metadata`` holds
        ``format``, ``source``, ``reordered_events``, ``streams``, and ``truncated`` (where
        the file was cut) for a file cut short.

    Raises
    ------
    RecordingError
        For a missing or undecodable file (naming the path and the packet), a file without an
        event or frame stream, or frames of another size than the sensor;
        :class:`EmptyRecordingError` (``truncated``) for an empty file, one cut inside its
        header, one without packets or without a whole one.
    """
    path = Path(path)
    import aedat  # the Rust decoder; imported here so the rest of evcal works without it

    if not path.is_file():
        raise RecordingError(f"{path}: no such file")
    size = refuse_empty_file(path)
    with open(path, "rb") as f:
        head = f.read(len(AEDAT4_MAGIC) + 4)
        magic_ok = head[: len(AEDAT4_MAGIC)] == AEDAT4_MAGIC[: len(head)]
        if magic_ok and len(head) < len(AEDAT4_MAGIC) + 4:
            raise cut_in_header(str(path), size, "the magic and the header's length")
        header_len = struct.unpack_from("<I", head, len(AEDAT4_MAGIC))[0] if magic_ok else 0
        header_end = len(AEDAT4_MAGIC) + 4 + header_len
        if magic_ok and header_end > size:
            raise cut_in_header(str(path), size, f"an IOHeader of {header_len:,} bytes, "
                                f"{size - len(head):,} present")
        compression, table_at = _ioheader(f.read(header_len)) if magic_ok else (0, -1)
    if magic_ok and (header_end == size or header_end == table_at):
        raise header_only(str(path), header_end, "packets")
    try:
        decoder = aedat.Decoder(str(path))
        streams = decoder.id_to_stream()
    except Exception as exc:  # the decoder raises RuntimeError with the OS/format message
        raise RecordingError(f"{path}: cannot open as AEDAT4: {exc}") from None
    event_ids = sorted(i for i, s in streams.items() if s.get("type") == "events")
    frame_ids = sorted(i for i, s in streams.items() if s.get("type") == "frame")
    if not event_ids and not frame_ids:
        kinds = sorted({str(s.get("type")) for s in streams.values()})
        raise RecordingError(f"{path}: no event or frame stream (streams: {kinds})")
    declared = streams[event_ids[0] if event_ids else frame_ids[0]]
    try:
        found = SensorSize(height=int(declared["height"]), width=int(declared["width"]))
    except (KeyError, TypeError, ValueError) as exc:
        raise RecordingError(f"{path}: the stream does not declare a valid sensor size "
                             f"({exc})") from None
    found = check_sensor_arg(found, sensor, str(path))
    ev_id = event_ids[0] if event_ids else None
    fr_id = frame_ids[0] if frame_ids else None

    chunks: list[np.ndarray] = []
    frame_t: list[int] = []
    frame_exp: list[int] = []
    images: list[np.ndarray] = []
    n_packets = 0
    cut: Cut | None = None
    try:
        for packet in decoder:
            n_packets += 1
            sid = packet.get("stream_id")
            if sid == ev_id and "events" in packet:
                if packet["events"].size:
                    chunks.append(packet["events"])
            elif sid == fr_id and "frame" in packet:
                frame = packet["frame"]
                image = _gray(np.asarray(frame["pixels"]))
                if image.shape != found.shape:
                    h, w = image.shape
                    raise RecordingError(
                        f"{path}: frame {len(images)} has shape ({h}, {w}) (a {w}x{h} image), "
                        f"the sensor is {found}"
                    )
                t_us, exp_us = _frame_time(frame)
                frame_t.append(t_us)
                frame_exp.append(exp_us)
                images.append(image)
    except RecordingError:
        raise
    except Exception as exc:
        # the decoder's error for a packet that does not fit in the file ("failed to fill
        # whole buffer") is a cut; for one that does, a corrupt packet
        cut = _packet_cut(path, size, header_end, n_packets, table_at)
        if cut is None:
            raise RecordingError(f"{path}: decoding failed after {n_packets} packets (corrupt "
                                 f"packet {n_packets}?): {exc}", ErrorReason.MALFORMED
                                 ) from None
    if cut is None and table_at > -1:  # the packets are whole; is the index after them?
        whole = False
        if table_at < size:
            with open(path, "rb") as f:
                f.seek(table_at)
                whole = _table_is_whole(f.read(), compression)
        if not whole:
            what = "the file data table (an index of the packets, no events)"
            cut = Cut(str(path), size, min(table_at, size), f"all {n_packets:,} packets",
                      what + (", cut or damaged" if table_at < size else ""))
    truncated = None
    if cut is not None:
        if n_packets == 0:
            raise nothing_whole(cut)
        truncated = report_cut(cut, strict=strict)
    elif n_packets == 0:
        raise header_only(str(path), header_end, "packets")

    events, reordered = events_from_packets(chunks)
    frames = None
    if images:
        try:
            frames = Frames(t_us=np.array(frame_t, np.int64), images=np.stack(images),
                            exposure_us=np.array(frame_exp, np.int64))
        except RecordingError as exc:
            raise RecordingError(f"{path}: {exc}") from None
    metadata = {
        "format": "aedat4",
        "source": str(path),
        "reordered_events": reordered,
        "streams": {str(i): dict(s) for i, s in streams.items()},
    }
    if truncated is not None:
        metadata["truncated"] = truncated
    return file_recording(path, found, events, frames, metadata)
