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
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import numpy as np

from ..events import SensorSize
from ..recording import Frames, Recording, RecordingError, concat_events
from ._util import check_sensor_arg, metadata_from_json, metadata_to_json
from .wire import WireError, decode_events, decode_frame, encode_events, encode_frame

EVENTS_TOPIC = "/events"
FRAMES_TOPIC = "/frames"
CALIBRATION_TOPIC = "/calibration"
METADATA_NAME = "evcal"
FORMAT_VERSION = 1
EVENTS_SCHEMA_NAME = "evcal.EventChunk"
FRAME_SCHEMA_NAME = "evcal.Frame"

_BIN = {"type": "string", "contentEncoding": "binary"}  # msgpack bin
EVENTS_SCHEMA: dict[str, Any] = {
    "title": EVENTS_SCHEMA_NAME,
    "description": "msgpack map; t_us/x/y/p are raw little-endian arrays of n values "
                   "(<i8, <u2, <u2, i1 with p in {-1, +1}), sorted by t_us",
    "type": "object",
    "properties": {
        "version": {"type": "integer", "const": 1},
        "height": {"type": "integer", "minimum": 1, "maximum": 65535},
        "width": {"type": "integer", "minimum": 1, "maximum": 65535},
        "seq": {"type": "integer", "minimum": 0},
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
        "version": {"type": "integer", "const": 1},
        "height": {"type": "integer", "minimum": 1, "maximum": 65535},
        "width": {"type": "integer", "minimum": 1, "maximum": 65535},
        "seq": {"type": "integer", "minimum": 0},
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
    from mcap.writer import CompressionType, Writer

    if chunk_events < 1:
        raise RecordingError(f"chunk_events={chunk_events} must be >= 1")
    path = Path(path)
    h, w = recording.sensor.shape
    frames = recording.frames
    assert frames is not None  # Recording fills in empty frames
    images = frames.images
    if images.dtype.kind == "f" and images.dtype != np.float32:
        images = images.astype(np.float32)
    with open(path, "wb") as f:
        writer = Writer(f, compression=CompressionType.ZSTD)
        writer.start(profile="", library="evcal")
        ev_schema = writer.register_schema(EVENTS_SCHEMA_NAME, "jsonschema",
                                           json.dumps(EVENTS_SCHEMA).encode())
        fr_schema = writer.register_schema(FRAME_SCHEMA_NAME, "jsonschema",
                                           json.dumps(FRAME_SCHEMA).encode())
        ev_channel = writer.register_channel(EVENTS_TOPIC, "msgpack", ev_schema)
        fr_channel = writer.register_channel(FRAMES_TOPIC, "msgpack", fr_schema)
        writer.add_metadata(METADATA_NAME, {
            "format_version": str(FORMAT_VERSION),
            "sensor": str(recording.sensor),
            "height": str(h),
            "width": str(w),
            "metadata_json": metadata_to_json(recording.metadata),
        })
        # Merge the two channels in time order: frame k goes before the first chunk that
        # starts after it. One iteration per message, not per event.
        starts = [int(c["t_us"][0]) for c in recording.iter_events(chunk_events)]
        k = 0
        seq_ev = 0
        for seq_ev, chunk in enumerate(recording.iter_events(chunk_events)):
            while k < len(frames) and frames.t_us[k] <= starts[seq_ev]:
                _add_frame(writer, fr_channel, frames, images, k)
                k += 1
            t0 = int(chunk["t_us"][0])
            writer.add_message(ev_channel, log_time=_log_time_ns(t0),
                               publish_time=_log_time_ns(t0), sequence=seq_ev & 0xFFFFFFFF,
                               data=encode_events(chunk, height=h, width=w, seq=seq_ev))
        while k < len(frames):
            _add_frame(writer, fr_channel, frames, images, k)
            k += 1
        writer.finish()
    return path


def _add_frame(writer: Any, channel: int, frames: Frames, images: np.ndarray, k: int) -> None:
    t = int(frames.t_us[k])
    try:
        data = encode_frame(t, images[k], exposure_us=int(frames.exposure_us[k]), seq=k)
    except WireError as exc:
        raise RecordingError(f"frame {k}: {exc}") from None
    writer.add_message(channel, log_time=_log_time_ns(t), publish_time=_log_time_ns(t),
                       sequence=k & 0xFFFFFFFF, data=data)


MCAP_MAGIC = b"\x89MCAP0\r\n"


def _check_magic(path: Path) -> None:
    """Clear errors for a missing, foreign or truncated (never finished) MCAP file."""
    if not path.is_file():
        raise RecordingError(f"{path}: no such file")
    size = path.stat().st_size
    with open(path, "rb") as f:
        head = f.read(len(MCAP_MAGIC))
        if size >= 2 * len(MCAP_MAGIC):
            f.seek(size - len(MCAP_MAGIC))
        tail = f.read(len(MCAP_MAGIC))
    if head != MCAP_MAGIC:
        raise RecordingError(f"{path}: not an MCAP file (it does not start with the MCAP magic)")
    if tail != MCAP_MAGIC:
        raise RecordingError(f"{path}: the MCAP file is truncated: it does not end with the MCAP "
                             f"magic ({size} bytes; was the writer stopped before finishing?)")


def _read_metadata(reader: Any, path: Path) -> dict[str, str] | None:
    for record in reader.iter_metadata():
        if record.name == METADATA_NAME:
            return dict(record.metadata)
    return None


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


def read_mcap(path: str | os.PathLike[str], *, sensor: SensorSize | None = None) -> Recording:
    """Read an evcal MCAP recording.

    Parameters
    ----------
    path : path
        A file written by :func:`write_mcap` (or by the service with the same channels).
    sensor : SensorSize, optional
        Checked against the file's ``evcal`` metadata; needed only when the file has
        neither that record nor messages telling the size.

    Returns
    -------
    Recording
        ``metadata`` is the stored metadata with ``format`` = "mcap" and ``source`` set.

    Raises
    ------
    RecordingError
        For an unreadable or truncated file, a malformed message (naming channel and seq),
        missing or repeated event chunks, or messages that disagree on the sensor size.
    """
    from mcap.reader import make_reader

    path = Path(path)
    _check_magic(path)
    events: dict[int, np.ndarray] = {}
    frames: dict[int, tuple[int, int, np.ndarray]] = {}
    sizes: set[tuple[int, int]] = set()
    meta_record: dict[str, str] | None = None
    topics: set[str] = set()
    try:
        with open(path, "rb") as f:
            reader = make_reader(f, validate_crcs=True)
            meta_record = _read_metadata(reader, path)
            for _schema, channel, message in reader.iter_messages(log_time_order=False):
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
    except WireError as exc:
        raise RecordingError(f"{path}: {exc}") from None
    except RecordingError:
        raise
    except Exception as exc:  # mcap, zstd and OS errors of a corrupt file
        raise RecordingError(f"{path}: cannot read as MCAP (truncated or corrupt file?): "
                             f"{type(exc).__name__}: {exc}") from None

    found: SensorSize | None = None
    metadata: dict[str, Any] = {}
    if meta_record is not None:
        try:
            found = SensorSize.parse(meta_record["sensor"])
        except (KeyError, ValueError) as exc:
            raise RecordingError(f"{path}: the 'evcal' metadata record has no valid sensor "
                                 f"({exc})") from None
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
    try:
        return Recording(sensor=found, events=concat_events([events[s] for s in seqs]),
                         frames=fr, metadata=metadata)
    except RecordingError as exc:
        raise RecordingError(f"{path}: {exc}") from None
