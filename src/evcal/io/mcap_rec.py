"""evcal's own recording file: MCAP (zstd chunks) with msgpack messages.

Channels (message encoding ``msgpack``; the schemas are JSON Schemas that document the
envelopes, see :mod:`evcal.io.wire`):

``/events``       schema ``evcal.EventChunk``: one chunk of at most ``chunk_events`` events
``/frames``       schema ``evcal.Frame``: one intensity frame
``/calibration``  optional, written by the service; ignored by :func:`read_mcap`

A metadata record named ``evcal`` holds ``sensor`` (``WxH``), ``height``, ``width``,
``format_version`` and ``metadata_json`` (the recording's metadata). Message ``log_time`` and
``publish_time`` are the time of the chunk's first event (or of the frame) in ns, clamped at 0;
``sequence`` is the per-channel message counter, the same as the envelope's ``seq``.

A file without its end (a writer stopped before :meth:`McapFileWriter.close`, a copy cut
short) is read up to its last whole message (:mod:`evcal.io._mcap_partial`), with a
:class:`~evcal.io.TruncatedRecordingWarning`; ``strict=True`` refuses it. A finished file
with the ``evcal`` record and no message is a legitimate empty recording; a cut file with no
whole message is an :class:`~evcal.io.EmptyRecordingError`.
"""

from __future__ import annotations

import json
import os
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np

from ..events import SensorSize
from ..recording import Frames, Recording, RecordingError, concat_events
from ._mcap_partial import McapPrefix, mcap_is_whole, scan_mcap_prefix
from ._partial import nothing_whole, report_cut
from ._util import check_sensor_arg, file_recording, metadata_from_json, metadata_to_json
from .wire import WireError, decode_events, decode_frame, encode_events, encode_frame

EVENTS_TOPIC = "/events"
FRAMES_TOPIC = "/frames"
CALIBRATION_TOPIC = "/calibration"
METADATA_NAME = "evcal"
FORMAT_VERSION = 1
EVENTS_SCHEMA_NAME = "evcal.EventChunk"
FRAME_SCHEMA_NAME = "evcal.Frame"

_BIN = {"type": "string", "contentEncoding": "binary"}  # msgpack bin
# the fields every message's envelope starts with (io.wire)
_ENVELOPE: dict[str, Any] = {
    "version": {"type": "integer", "const": 1},
    "height": {"type": "integer", "minimum": 1, "maximum": 65535},
    "width": {"type": "integer", "minimum": 1, "maximum": 65535},
    "seq": {"type": "integer", "minimum": 0},
}
EVENTS_SCHEMA: dict[str, Any] = {
    "title": EVENTS_SCHEMA_NAME,
    "description": "msgpack map; t_us/x/y/p are raw little-endian arrays of n values "
                   "(<i8, <u2, <u2, i1 with p in {-1, +1}), sorted by t_us",
    "type": "object",
    "properties": {
        **_ENVELOPE,
        "n": {"type": "integer", "minimum": 0},
        "t_us": _BIN, "x": _BIN, "y": _BIN, "p": _BIN,
    },
    "required": ["version", "height", "width", "seq", "n", "t_us", "x", "y", "p"],
}
FRAME_SCHEMA: dict[str, Any] = {
    "title": FRAME_SCHEMA_NAME,
    "description": "msgpack map; data is the raw row-major [y, x] image, height*width values "
                   "of dtype (little-endian); t_us is the middle of the exposure",
    "type": "object",
    "properties": {
        **_ENVELOPE,
        "t_us": {"type": "integer"},
        "exposure_us": {"type": "integer", "minimum": 0},
        "dtype": {"enum": ["uint8", "float32"]},
        "data": _BIN,
    },
    "required": ["version", "height", "width", "seq", "t_us", "exposure_us", "dtype", "data"],
}


def _log_time_ns(t_us: int) -> int:
    # MCAP times are unsigned ns; the exact time is in the message itself.
    return max(int(t_us), 0) * 1000


CALIBRATION_SCHEMA_NAME = "evcal.Calibration"
CALIBRATION_SCHEMA: dict[str, Any] = {
    "title": CALIBRATION_SCHEMA_NAME,
    "description": "msgpack map, see docs/WIRE.md: header fields and 'maps' of raw "
                   "little-endian [y, x] arrays",
    "type": "object",
}


class McapFileWriter:
    """An MCAP file being written (zstd chunks): opened and started here, finished by
    :meth:`close` (extra metadata records, summary, footer; until then the file is
    incomplete). A context manager; the base of evcal's and the ROS 2 layouts' writers."""

    def __init__(self, path: str | os.PathLike[str], *, profile: str, library: str) -> None:
        from mcap.writer import CompressionType, Writer

        self.path = Path(path)
        self._f = open(self.path, "wb")
        try:
            self._w = Writer(self._f, compression=CompressionType.ZSTD)
            self._w.start(profile=profile, library=library)
        except BaseException:
            self._f.close()
            raise
        self._closed = False

    def close(self, metadata: dict[str, dict[str, str]] | None = None) -> None:
        """Write extra metadata records (name -> string map) and finish the file."""
        if self._closed:
            return
        self._closed = True
        try:
            for name, record in (metadata or {}).items():
                self._w.add_metadata(name, record)
            self._w.finish()
        finally:
            self._f.close()

    def __enter__(self) -> McapFileWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class McapWriter(McapFileWriter):
    """evcal's MCAP layout, written message by message (a context manager).

    ``add_events``/``add_frame``/``add_calibration`` take encoded wire messages (the
    envelope's own ``seq`` is the caller's business; the MCAP ``sequence`` is the per-channel
    counter). The ``evcal`` metadata record is written with the sensor once it is known
    (:meth:`set_sensor`); :meth:`close` adds any extra metadata records and finishes the
    file (summary and footer): until then the file is incomplete.
    """

    def __init__(self, path: str | os.PathLike[str], *, library: str = "evcal",
                 calibration: bool = False) -> None:
        super().__init__(path, profile="", library=library)
        try:
            schemas = [("events", EVENTS_TOPIC, EVENTS_SCHEMA_NAME, EVENTS_SCHEMA),
                       ("frames", FRAMES_TOPIC, FRAME_SCHEMA_NAME, FRAME_SCHEMA)]
            if calibration:
                schemas.append(("calibration", CALIBRATION_TOPIC, CALIBRATION_SCHEMA_NAME,
                                CALIBRATION_SCHEMA))
            self._channels: dict[str, int] = {}
            for kind, topic, name, schema in schemas:
                sid = self._w.register_schema(name, "jsonschema", json.dumps(schema).encode())
                self._channels[kind] = self._w.register_channel(topic, "msgpack", sid)
        except BaseException:
            self._f.close()
            raise
        self.counts = {kind: 0 for kind in self._channels}
        self.sensor: SensorSize | None = None

    def set_sensor(self, sensor: SensorSize, metadata: dict[str, Any] | None = None) -> None:
        """Write the ``evcal`` metadata record (once)."""
        if self.sensor is not None:
            return
        self.sensor = sensor
        self._w.add_metadata(METADATA_NAME, {
            "format_version": str(FORMAT_VERSION), "sensor": str(sensor),
            "height": str(sensor.height), "width": str(sensor.width),
            "metadata_json": metadata_to_json(metadata or {}),
        })

    def _add(self, kind: str, t_us: int, data: bytes) -> None:
        n = self.counts[kind]
        self._w.add_message(self._channels[kind], log_time=_log_time_ns(t_us),
                            publish_time=_log_time_ns(t_us), sequence=n & 0xFFFFFFFF, data=data)
        self.counts[kind] = n + 1

    def add_events(self, t_us: int, data: bytes) -> None:
        """One events message; ``t_us`` is its first event's time."""
        self._add("events", t_us, data)

    def add_frame(self, t_us: int, data: bytes) -> None:
        self._add("frames", t_us, data)

    def add_calibration(self, t_us: int, data: bytes) -> None:
        self._add("calibration", t_us, data)

    def __enter__(self) -> McapWriter:
        return self


def write_mcap(
    recording: Recording,
    path: str | os.PathLike[str],
    *,
    chunk_events: int = 100_000,
) -> Path:
    """Write a recording as an MCAP file (zstd chunks, msgpack messages); return the path.

    Events go to ``/events`` in messages of at most ``chunk_events`` events, frames to
    ``/frames`` one a message; messages of both channels are interleaved in time order.
    Float frames must be float32 or are cast to it; other frame dtypes than uint8 and float32
    are refused.

    Raises
    ------
    RecordingError
        For ``chunk_events < 1`` or frames that cannot be encoded.
    """
    if chunk_events < 1:
        raise RecordingError(f"chunk_events={chunk_events} must be >= 1")
    path = Path(path)
    h, w = recording.sensor.shape
    frames = recording.frames
    images = frames.images
    if images.dtype.kind == "f" and images.dtype != np.float32:
        images = images.astype(np.float32)

    def add_frame(out: McapWriter, k: int) -> None:
        t = int(frames.t_us[k])
        try:
            data = encode_frame(t, images[k], exposure_us=int(frames.exposure_us[k]), seq=k)
        except WireError as exc:
            raise RecordingError(f"frame {k}: {exc}", exc.reason) from None
        out.add_frame(t, data)

    with McapWriter(path) as out:
        out.set_sensor(recording.sensor, recording.metadata)
        # Merge the two channels in time order: frame k goes before the first chunk that
        # starts after it. One iteration per message, not per event.
        k = 0
        for seq_ev, chunk in enumerate(recording.iter_events(chunk_events)):
            t0 = int(chunk["t_us"][0])
            while k < len(frames) and frames.t_us[k] <= t0:
                add_frame(out, k)
                k += 1
            out.add_events(t0, encode_events(chunk, height=h, width=w, seq=seq_ev))
        while k < len(frames):
            add_frame(out, k)
            k += 1
    return path


MCAP_MAGIC = b"\x89MCAP0\r\n"


def _prefix(path: Path, strict: bool) -> tuple[McapPrefix | None, dict[str, Any] | None]:
    """Clear errors for a missing, foreign or empty MCAP file; for one without its end (never
    finished, or cut), its whole records and the ``truncated`` metadata (a warning, or
    :class:`~evcal.io.TruncatedRecordingError` when ``strict``)."""
    if not path.is_file():
        raise RecordingError(f"{path}: no such file")
    if mcap_is_whole(path):
        return None, None
    with _mcap_errors(path):
        prefix = scan_mcap_prefix(path)
    if not prefix.n_messages:
        raise nothing_whole(prefix.cut)
    # outside _mcap_errors: a warning made an error by a filter stays what it is
    return prefix, report_cut(prefix.cut, strict=strict)


def _read_metadata(reader: Any, path: Path) -> dict[str, str] | None:
    for record in reader.iter_metadata():
        if record.name == METADATA_NAME:
            return dict(record.metadata)
    return None


def _metadata_sensor(meta: dict[str, str], path: Path) -> SensorSize:
    """The sensor the 'evcal' metadata record declares."""
    try:
        return SensorSize.parse(meta["sensor"])
    except (KeyError, ValueError) as exc:
        raise RecordingError(f"{path}: the 'evcal' metadata record has no valid sensor "
                             f"({exc})") from None


def is_ros2_event_mcap(path: str | os.PathLike[str]) -> bool:
    """True when an MCAP file holds ``event_camera_msgs/msg/EventPacket`` messages."""
    from mcap.reader import make_reader

    try:
        with open(path, "rb") as f:
            summary = make_reader(f).get_summary()
    except Exception:  # not readable: let the reader report it
        return False
    if summary is None:
        return False
    return any(s.name == "event_camera_msgs/msg/EventPacket" for s in summary.schemas.values())


@contextmanager
def _mcap_errors(path: Path) -> Iterator[None]:
    """Errors while reading ``path`` as RecordingError naming the file: a malformed message
    (WireError), or what mcap, zstd and the OS raise for a truncated or corrupt file."""
    try:
        yield
    except WireError as exc:
        raise RecordingError(f"{path}: {exc}") from None
    except RecordingError:
        raise
    except Exception as exc:  # mcap, zstd and OS errors of a corrupt file
        raise RecordingError(f"{path}: cannot read as MCAP (truncated or corrupt file?): "
                             f"{type(exc).__name__}: {exc}") from None


def iter_mcap(path: str | os.PathLike[str], *, sensor: SensorSize | None = None,
              strict: bool = True) -> tuple[SensorSize, Iterator[tuple[str, int, Any]], int]:
    """An evcal MCAP recording as a stream, for files larger than memory: ``(sensor,
    messages, n_messages)``, ``messages`` yielding ``("events", t_us of the first event,
    events)`` and ``("frames", t_us, image)`` in the file's time order (log time), each
    message decoded and checked as :func:`read_mcap` does. The sensor comes from the
    ``evcal`` metadata record (or ``sensor=``); a message for another size is refused when
    it is reached. A file without its end is refused (:class:`~evcal.io.
    TruncatedRecordingError`) unless ``strict=False``, which streams its whole messages in
    file order (``n_messages`` counts them) after a warning."""
    from mcap.reader import make_reader

    path = Path(path)
    prefix, _truncated = _prefix(path, strict)
    if prefix is not None:
        meta = prefix.metadata.get(METADATA_NAME)
        summary = None
    else:
        try:
            with open(path, "rb") as f:
                reader = make_reader(f, validate_crcs=True)
                meta = _read_metadata(reader, path)
                summary = reader.get_summary()
        except Exception as exc:  # mcap and OS errors of a corrupt file
            raise RecordingError(f"{path}: cannot read as MCAP (corrupt file?): "
                                 f"{type(exc).__name__}: {exc}") from None
    if meta is not None:
        found = _metadata_sensor(meta, path)
        found = check_sensor_arg(found, sensor, str(path))
    elif sensor is not None:
        found = sensor
    else:
        raise RecordingError(f"{path}: no 'evcal' metadata record: give the sensor size "
                             "(sensor=) to stream it")
    total = int(sum(summary.statistics.channel_message_counts.values())) if (
        summary is not None and summary.statistics is not None) else (
        prefix.n_messages if prefix is not None else 0)

    def in_order() -> Iterator[tuple[Any, Any]]:
        if prefix is not None:
            yield from prefix.messages()
            return
        with open(path, "rb") as f:
            reader = make_reader(f, validate_crcs=True)
            for _schema, channel, message in reader.iter_messages(log_time_order=True):
                yield channel, message

    def messages() -> Iterator[tuple[str, int, Any]]:
        with _mcap_errors(path):
            for channel, message in in_order():
                if channel.topic == EVENTS_TOPIC:
                    ev, header = decode_events(message.data)
                    kind, t_us, payload = "events", (int(ev["t_us"][0]) if ev.size else 0), ev
                elif channel.topic == FRAMES_TOPIC:
                    t_us, _exp, payload, header = decode_frame(message.data)
                    kind = "frames"
                else:
                    continue
                if (header["height"], header["width"]) != found.shape:
                    raise RecordingError(
                        f"{path}: a {channel.topic} message is for a "
                        f"{header['width']}x{header['height']} sensor, the recording is "
                        f"{found}")
                yield kind, int(t_us), payload

    return found, messages(), total


def read_mcap(path: str | os.PathLike[str], *, sensor: SensorSize | None = None,
              strict: bool = False) -> Recording:
    """Read an evcal MCAP recording.

    Parameters
    ----------
    path : path
        A file written by :func:`write_mcap` (or by the service with the same channels).
    sensor : SensorSize, optional
        Checked against the file's ``evcal`` metadata; needed only when the file has
        neither that record nor messages telling the size.
    strict : bool
        Refuse a file without its end (:class:`~evcal.io.TruncatedRecordingError`) instead
        of reading its whole messages with a :class:`~evcal.io.TruncatedRecordingWarning`.

    Returns
    -------
    Recording
        ``metadata`` is the stored metadata with ``format`` = "mcap" and ``source`` set, and
        ``truncated`` (where the file was cut) for a file without its end.

    Raises
    ------
    RecordingError
        For an unreadable file, a malformed message (naming channel and seq), missing or
        repeated event chunks, or messages that disagree on the sensor size;
        :class:`~evcal.io.EmptyRecordingError` for an empty file or a cut one without a
        whole message.
    """
    from mcap.reader import make_reader

    path = Path(path)
    prefix, truncated = _prefix(path, strict)
    events: dict[int, np.ndarray] = {}
    frames: dict[int, tuple[int, int, np.ndarray]] = {}
    sizes: set[tuple[int, int]] = set()
    meta_record: dict[str, str] | None = None
    topics: set[str] = set()

    def all_messages() -> Iterator[tuple[Any, Any]]:
        nonlocal meta_record
        if prefix is not None:
            meta_record = prefix.metadata.get(METADATA_NAME)
            yield from prefix.messages()
            return
        with open(path, "rb") as f:
            reader = make_reader(f, validate_crcs=True)
            meta_record = _read_metadata(reader, path)
            for _schema, channel, message in reader.iter_messages(log_time_order=False):
                yield channel, message

    with _mcap_errors(path):
        for channel, message in all_messages():
            topic = channel.topic
            topics.add(topic)
            if topic == EVENTS_TOPIC:
                ev, header = decode_events(message.data)
                if header["seq"] in events:
                    raise RecordingError(f"{path}: /events message seq {header['seq']} "
                                         "appears twice")
                events[header["seq"]] = ev
                sizes.add((header["height"], header["width"]))
            elif topic == FRAMES_TOPIC:
                t_us, exp_us, image, header = decode_frame(message.data)
                if header["seq"] in frames:
                    raise RecordingError(f"{path}: /frames message seq {header['seq']} "
                                         "appears twice")
                frames[header["seq"]] = (t_us, exp_us, image)
                sizes.add((header["height"], header["width"]))
            # /calibration and unknown channels: not part of a Recording.

    found: SensorSize | None = None
    metadata: dict[str, Any] = {}
    if meta_record is not None:
        found = _metadata_sensor(meta_record, path)
        metadata = metadata_from_json(meta_record.get("metadata_json", ""), str(path))
    if found is None and sizes:
        h, w = next(iter(sizes))
        found = SensorSize(height=h, width=w)
    if found is None:
        if topics:
            raise RecordingError(f"{path}: not an evcal recording: no 'evcal' metadata record "
                                 f"and no {EVENTS_TOPIC} or {FRAMES_TOPIC} messages (channels: "
                                 f"{sorted(topics)})")
        if sensor is None:
            raise RecordingError(f"{path}: no 'evcal' metadata record and no messages: the "
                                 "sensor size is unknown; give it with sensor=")
        found = sensor
    found = check_sensor_arg(found, sensor, str(path))
    wrong = sorted(s for s in sizes if s != found.shape)
    if wrong:
        h, w = wrong[0]
        raise RecordingError(f"{path}: a message is for a {w}x{h} sensor, the recording is "
                             f"{found}")
    seqs = sorted(events)
    if seqs and seqs != list(range(len(seqs))):
        missing = sorted(set(range(seqs[-1] + 1)) - set(seqs))
        raise RecordingError(f"{path}: /events messages are missing: seq {missing[:10]} "
                             f"({len(missing)} in all)")
    frame_seqs = sorted(frames)
    fr = None
    if frame_seqs:
        t = np.array([frames[s][0] for s in frame_seqs], np.int64)
        exp = np.array([frames[s][1] for s in frame_seqs], np.int64)
        dtypes = {frames[s][2].dtype for s in frame_seqs}
        if len(dtypes) > 1:
            raise RecordingError(f"{path}: frames mix dtypes {sorted(map(str, dtypes))}")
        images = np.stack([frames[s][2] for s in frame_seqs])
        try:
            fr = Frames(t_us=t, images=images, exposure_us=exp)
        except RecordingError as exc:
            raise RecordingError(f"{path}: {exc}") from None
    metadata["format"] = "mcap"
    metadata["source"] = str(path)
    if truncated is not None:
        metadata["truncated"] = truncated
    return file_recording(path, found, concat_events([events[s] for s in seqs]), fr, metadata)
