"""ROS 1 and ROS 2 bags of event cameras, through ``rosbags``: events and intensity frames.

What is read
    - a ROS 2 bag: a folder with ``metadata.yaml`` (MCAP or sqlite3 storage; an empty
      ``storage_identifier`` is told from the files' suffixes), or one ``.mcap`` / ``.db3``
      file of it; a ROS 1 bag (``#ROSBAG V2.0``);
    - events from ``event_camera_msgs/msg/EventPacket`` (encodings ``libcaer_cmp``,
      ``libcaer``, ``evt3``, ``mono``, decoded by :mod:`evcal.io._evcodecs`; its predecessor
      ``event_array_msgs/msg/EventArray`` has the same fields and is read alike),
      ``dvs_msgs/msg/EventArray`` and ``prophesee_event_msgs/msg/EventArray``;
    - frames from ``sensor_msgs/msg/Image`` (``mono8``, ``mono16``, ``rgb8``, ``bgr8``).

The message types are registered in a ``rosbags`` typestore from their ``.msg`` text
(:data:`MSG_DEFINITIONS`); a ROS 1 bag's md5 sums and a ROS 2 bag's type hashes (where the
bag records them) are checked against them, so a bag of another definition is refused instead
of decoded into garbage. The event arrays of ``dvs_msgs`` / ``prophesee_event_msgs`` are read
straight from the serialised bytes with numpy (CDR or ROS 1 layout), not one Python object per
event.

Times (integer µs)
    - EventPacket: ``libcaer_cmp``, ``libcaer`` and ``mono`` give ``time_base`` (ns) plus the
      packet's sensor time, i.e. host-aligned time as the driver set it; ``evt3`` gives the
      camera's own µs since it started (24-bit, unwrapped across packets), ``time_base`` is
      not used;
    - ``dvs_msgs`` / ``prophesee_event_msgs``: each event's ``ts``, floored to µs;
    - frames: ``header.stamp``, floored to µs; the exposure is unknown (0).

The sensor size is the event messages' ``width x height`` (else the frames', else ``sensor``).
Events are sorted by time (stable); how many were out of order is
``metadata["reordered_events"]``. EventPacket ``seq`` gaps are lost messages: counted in
``metadata["lost_messages"]`` with a warning, not an error. Events outside the sensor are
dropped as the reference decoders do, counted in ``metadata["dropped_events"]`` with a
warning.

Frame conversion to gray: ``mono8`` as is (uint8); ``mono16`` to float32 on the 8-bit scale
(value / 257, so 65535 -> 255.0); ``rgb8`` / ``bgr8`` to uint8 ITU-R BT.601 luma
(0.299 R + 0.587 G + 0.114 B, rounded), as for AEDAT4 frames.
"""

from __future__ import annotations

import os
import warnings
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from ..errors import ErrorReason
from ..events import SensorSize
from ..recording import Frames, Recording, RecordingError
from ._bag_partial import PartialBag, PartialBagError, partial_mcap_bag, scan_ros1
from ._evcodecs import PayloadError
from ._mcap_partial import mcap_is_whole, scan_mcap_prefix
from ._partial import Cut, cut_in_header, nothing_whole, refuse_empty_file, report_cut
from ._sqlite_partial import SQLITE_MAGIC, scan_sqlite, sqlite_pages
from ._util import check_sensor_arg, file_head
from .bagdecode import (
    CALIBRATION_IMAGES,
    DVS_EVENT_ARRAY,
    EVENT_ARRAY_LEGACY,
    EVENT_PACKET,
    EVENT_TYPES,
    FRAME_ENCODINGS,
    IMAGE,
    MSG_DEFINITIONS,
    PROPHESEE_EVENT_ARRAY,
    EventStream,
    RosbagError,
    decode_packet,
    deserialize_message,
    event_columns,
    image_to_gray,
    is_calibration_topic,
    packet_decoder,
    packet_events,
    parse_event_array,
    sorted_events,
    stamp_ns,
    typestore,
)

if TYPE_CHECKING:
    from rosbags.interfaces import Connection
    from rosbags.typesys.store import Typestore

# what the bag reader offers, and the message names and decoders it uses (evcal.io.bagdecode)
__all__ = ["CALIBRATION_IMAGES", "DVS_EVENT_ARRAY", "EVENT_ARRAY_LEGACY", "EVENT_PACKET",
           "EVENT_TYPES", "FRAME_ENCODINGS", "IMAGE", "MCAP_MAGIC", "MSG_DEFINITIONS",
           "PROPHESEE_EVENT_ARRAY", "ROS1_MAGIC", "SQLITE_MAGIC", "BagMessage", "RosbagError",
           "bag_topics", "decode_packet", "deserialize_message", "event_columns",
           "image_to_gray", "is_calibration_topic", "is_ros2_mcap", "is_rosbag",
           "iter_bag_messages", "packet_decoder", "parse_event_array", "read_rosbag",
           "typestore"]

MCAP_MAGIC = b"\x89MCAP0\r\n"
ROS1_MAGIC = b"#ROSBAG V"

def is_ros2_mcap(path: str | os.PathLike[str]) -> bool:
    """True for an MCAP file of ROS 2 messages: profile ``ros2``, or else ``ros2msg`` /
    ``ros2idl`` schemas or ``cdr`` channels (evcal's own MCAP has msgpack channels; for a
    file cut short, those of its whole records)."""
    try:
        with open(path, "rb") as f:
            head = f.read(8 + 1 + 8 + 4 + 16)
            if not head.startswith(MCAP_MAGIC) or len(head) < 21 or head[8] != 0x01:
                return False
            n = int.from_bytes(head[17:21], "little")
            if head[21:21 + n] == b"ros2":
                return True
            from mcap.reader import make_reader

            if mcap_is_whole(Path(path)):
                f.seek(0)
                summary = make_reader(f).get_summary()
                if summary is None:
                    return False
                schemas, channels = summary.schemas.values(), summary.channels.values()
            else:
                prefix = scan_mcap_prefix(Path(path))
                schemas, channels = prefix.schemas.values(), prefix.channels.values()
    except Exception:  # unreadable: the MCAP reader reports what is wrong
        return False
    return (any(s.encoding in ("ros2msg", "ros2idl") for s in schemas)
            or any(c.message_encoding == "cdr" for c in channels))


def is_rosbag(path: str | os.PathLike[str]) -> str | None:
    """``"rosbag1"``, ``"rosbag2"`` or None, from the content (a folder's metadata.yaml)."""
    path = Path(path)
    if path.is_dir():
        return "rosbag2" if (path / "metadata.yaml").is_file() else None
    if path.name == "metadata.yaml":
        return "rosbag2"
    head = file_head(path)
    if head is None:
        return None
    if head.startswith(ROS1_MAGIC):
        return "rosbag1"
    if head.startswith(SQLITE_MAGIC):
        return "rosbag2"
    if head.startswith(MCAP_MAGIC) and is_ros2_mcap(path):
        return "rosbag2"
    return None


# ------------------------------------------------------------------------------- opening


@dataclass
class _Bag:
    path: Path
    ros_version: int
    storage: str
    readers: list[Any] = field(default_factory=list)  # rosbags Readers, opened
    cuts: list[Cut] = field(default_factory=list)  # of the files read up to a cut


def _open_reader(reader: Any, where: Path) -> Any:
    try:
        reader.open()
    except Exception as exc:  # rosbags ReaderError, sqlite3 and OS errors
        raise RosbagError(f"{where}: cannot open as a ROS bag: {type(exc).__name__}: {exc}"
                          ) from None
    return reader


def _ros2_folder(folder: Path) -> tuple[str, list[Path]]:
    """A ROS 2 bag folder's storage (``mcap``/``sqlite3``, or ``""`` when metadata.yaml names
    none) and its files, from metadata.yaml."""
    from ruamel.yaml import YAML

    try:
        meta = YAML(typ="safe").load((folder / "metadata.yaml").read_text())
        info = meta["rosbag2_bagfile_information"]
        names = [str(n) for n in info["relative_file_paths"]]
        storage = str(info.get("storage_identifier") or "")
        compressed = str(info.get("compression_mode") or "").lower() not in ("", "none")
    except Exception as exc:
        raise RosbagError(f"{folder}: metadata.yaml is not a rosbag2 description "
                          f"({type(exc).__name__}: {exc})") from None
    files = [folder / Path(n).name for n in names]
    missing = [str(f) for f in files if not f.is_file()]
    if missing:
        raise RosbagError(f"{folder}: files named in metadata.yaml are missing: {missing}")
    if storage in ("mcap", "sqlite3"):
        return storage, files
    suffixes = {f.suffix for f in files}
    if compressed or len(suffixes) != 1 or not suffixes <= {".mcap", ".db3"}:
        raise RosbagError(f"{folder}: metadata.yaml names the storage {storage!r}, which evcal "
                          f"cannot read, and files {names}")
    return "", files


def _partial(reader: PartialBag, bag: _Bag, strict: bool, report: bool) -> PartialBag:
    """A file read up to its cut: none of it whole is an error, else warn (or refuse)."""
    if not reader.message_count:
        raise nothing_whole(reader.cut)
    if report:
        report_cut(reader.cut, strict=strict)
    bag.cuts.append(reader.cut)
    return reader


def _open_mcap_file(file: Path, bag: _Bag, strict: bool, report: bool) -> Any:
    """One ROS 2 MCAP file: by ``rosbags`` when whole, else up to its cut."""
    from rosbags.rosbag2 import Reader as Reader2

    if mcap_is_whole(file):
        return _open_reader(Reader2(file), file)
    try:
        prefix = scan_mcap_prefix(file)
    except RecordingError as exc:
        raise RosbagError(str(exc), exc.reason) from None
    except Exception as exc:  # mcap and OS errors of a damaged file
        raise RosbagError(f"{file}: cannot read as MCAP (corrupt file?): "
                          f"{type(exc).__name__}: {exc}") from None
    return _partial(partial_mcap_bag(prefix), bag, strict, report)


def _open_sqlite_file(file: Path, bag: _Bag, strict: bool, report: bool) -> Any:
    """One ROS 2 sqlite3 file: by ``rosbags`` when whole, else up to its cut."""
    from rosbags.rosbag2 import Reader as Reader2

    pages = sqlite_pages(file)
    if pages is None:
        return _open_reader(Reader2(file), file)
    scanned = scan_sqlite(file, *pages)
    try:
        return _partial(scanned, bag, strict, report)
    except BaseException:
        scanned.close()
        raise


def _open_ros1(path: Path, bag: _Bag, strict: bool, report: bool) -> Any:
    """A ROS 1 bag: by ``rosbags`` when whole (indexed), else up to its cut."""
    from rosbags.rosbag1 import Reader as Reader1

    try:
        return _open_reader(Reader1(path), path)
    except RosbagError as exc:
        whole_error = exc  # no index where the header says: cut short, or corrupt
    try:
        scanned = scan_ros1(path)
    except PartialBagError as exc:  # corrupt, not cut: both errors say so
        raise RosbagError(f"{whole_error}; walking its records: {exc}") from None
    if scanned is None:
        raise whole_error
    return _partial(scanned, bag, strict, report)


def _open_bag(path: Path, strict: bool = False, report: bool = True) -> _Bag:
    """The bag at ``path``, its files opened; a file cut short (a ROS 1 bag, a ROS 2 MCAP
    file) is read up to its cut: warned about when ``report``, refused when ``strict``."""
    from rosbags.rosbag2 import Reader as Reader2

    if path.is_file() and path.name == "metadata.yaml":
        path = path.parent
    if path.is_dir():
        if not (path / "metadata.yaml").is_file():
            raise RosbagError(f"{path}: a folder without metadata.yaml is not a ROS 2 bag")
        storage, files = _ros2_folder(path)
        if ((storage == "sqlite3" and not any(sqlite_pages(f) for f in files))
                or (storage == "mcap" and all(mcap_is_whole(f) for f in files))):
            return _Bag(path, 2, storage, [_open_reader(Reader2(path), path)])
        # an empty storage_identifier (the shared EventPacket bag): told by the files' suffix,
        # which the single-file reader goes by; files are read in metadata.yaml's order
        # (so are the files of an MCAP bag with a file cut short)
        bag = _Bag(path, 2, storage or ("mcap" if files[0].suffix == ".mcap" else "sqlite3"))
        try:
            for file in files:
                bag.readers.append(_open_mcap_file(file, bag, strict, report)
                                   if bag.storage == "mcap" else
                                   _open_sqlite_file(file, bag, strict, report))
        except BaseException:
            _close(bag)
            raise
        return bag
    refuse_empty_file(path)
    try:
        with open(path, "rb") as f:
            head = f.read(16)
    except OSError as exc:
        raise RosbagError(f"{path}: cannot read: {exc}") from None
    if 0 < len(head) < 13 and b"#ROSBAG V2.0\n".startswith(head):
        raise cut_in_header(str(path), len(head), "the '#ROSBAG V2.0' line, cut")
    if head.startswith(ROS1_MAGIC):
        bag = _Bag(path, 1, "rosbag1")
        bag.readers.append(_open_ros1(path, bag, strict, report))
        return bag
    for magic, suffix, storage in ((MCAP_MAGIC, ".mcap", "mcap"),
                                   (SQLITE_MAGIC, ".db3", "sqlite3")):
        if head.startswith(magic):
            if path.suffix != suffix:
                raise RosbagError(f"{path}: a ROS 2 {storage} file must be named *{suffix} "
                                  "for the bag reader; rename it")
            bag = _Bag(path, 2, storage)
            bag.readers.append(_open_mcap_file(path, bag, strict, report) if storage == "mcap"
                               else _open_sqlite_file(path, bag, strict, report))
            return bag
    raise RosbagError(f"{path}: not a ROS bag (neither #ROSBAG, the MCAP magic, an SQLite "
                      "database nor a folder with metadata.yaml)")


def _close(bag: _Bag) -> None:
    for reader in bag.readers:
        try:
            reader.close()
        except Exception:  # closing after a failure: the first error is the one reported
            pass


# ------------------------------------------------------------------------------- topics


def _topics(bag: _Bag) -> dict[str, set[str]]:
    topics: dict[str, set[str]] = {}
    for reader in bag.readers:
        for conn in reader.connections:
            topics.setdefault(conn.topic, set()).add(conn.msgtype)
    return topics


def _describe(topics: dict[str, set[str]]) -> str:
    return ", ".join(f"{t} ({'/'.join(sorted(ty))})" for t, ty in sorted(topics.items())) \
        or "none"


def _choose(bag: _Bag, topics: dict[str, set[str]], given: str | None, accepted: tuple[str, ...],
            option: str, kind: str) -> str | None:
    matching = sorted(t for t, types in topics.items() if types & set(accepted))
    # by default, never evcal's own calibration Images (named, they are read)
    candidates = [t for t in matching if not (accepted == (IMAGE,) and is_calibration_topic(t))]
    if given is not None:
        if given not in topics:
            raise RosbagError(f"{bag.path}: no topic {given!r} ({option}); the bag's topics: "
                              f"{_describe(topics)}")
        if given not in matching:
            raise RosbagError(f"{bag.path}: topic {given!r} ({option}) holds "
                              f"{'/'.join(sorted(topics[given]))}, not {kind} "
                              f"({', '.join(accepted)})")
        return given
    if len(candidates) > 1:
        raise RosbagError(f"{bag.path}: {len(candidates)} {kind} topics "
                          f"({', '.join(candidates)}); choose one with {option}=")
    return candidates[0] if candidates else None


def _check_definition(bag: _Bag, conn: Connection, store: Typestore) -> None:
    """Refuse a bag whose recorded definition hash differs from the registered one."""
    digest = conn.digest
    if not digest or digest == "*":
        return
    if bag.ros_version == 1:
        ours = store.generate_msgdef(conn.msgtype)[1]
    else:
        ours = store.hash_rihs01(conn.msgtype)
    if digest != ours:
        raise RosbagError(
            f"{bag.path}: topic {conn.topic}: the bag's {conn.msgtype} has hash {digest}, the "
            f"definition evcal decodes has {ours}: another message definition (fork or "
            "version), refused rather than decoded wrongly", ErrorReason.MALFORMED)


@dataclass(frozen=True)
class BagMessage:
    """One message of a bag as ROS 2 sends it: topic, type, log time (ns) and CDR bytes
    (a ROS 1 bag's message converted to CDR)."""

    topic: str
    msgtype: str
    t_ns: int
    data: bytes


def bag_topics(path: str | os.PathLike[str]) -> dict[str, str]:
    """Every topic of a bag and its type (:class:`RosbagError` for a bag that does not open
    or a topic carrying several types)."""
    bag = _open_bag(Path(path), report=False)
    try:
        topics = _topics(bag)
    finally:
        _close(bag)
    several = sorted(t for t, types in topics.items() if len(types) > 1)
    if several:
        raise RosbagError(f"{path}: topics carry several types: {_describe(topics)}")
    return {t: next(iter(types)) for t, types in topics.items()}


def iter_bag_messages(path: str | os.PathLike[str], *, topics: set[str] | None = None,
                      strict: bool = False) -> Iterator[BagMessage]:
    """The messages of a bag (of ``topics``, else all) in log-time order, each as CDR.

    A ROS 1 bag's messages are converted to their ROS 2 form (``rosbags``' ``ros1_to_cdr``
    with the ROS 2 types: a ``Header`` loses its ``seq``) for the types evcal knows (ROS 2
    Humble's standard types and :data:`MSG_DEFINITIONS`). A bag file cut short gives its
    whole messages in file order, after a :class:`~evcal.io.TruncatedRecordingWarning`
    (``strict``: :class:`~evcal.io.TruncatedRecordingError`). The bag is closed when the
    iterator is exhausted or closed. Raises :class:`RosbagError`.
    """
    bag = _open_bag(Path(path), strict)
    try:
        store = typestore(2) if bag.ros_version == 1 else None
        current = "the first message"
        for reader in bag.readers:
            conns = [c for c in reader.connections if topics is None or c.topic in topics]
            if not conns:
                continue
            try:
                for conn, t_ns, raw in reader.messages(connections=conns):
                    current = f"a {conn.msgtype} message on {conn.topic} at {t_ns} ns"
                    data = (bytes(store.ros1_to_cdr(raw, conn.msgtype)) if store is not None
                            else bytes(raw))
                    yield BagMessage(conn.topic, conn.msgtype, int(t_ns), data)
            except RecordingError:
                raise
            except Exception as exc:  # rosbags/sqlite/zstd errors of a damaged file
                raise RosbagError(f"{bag.path}: reading failed at {current} (truncated or "
                                  f"corrupt bag?): {type(exc).__name__}: {exc}") from None
    finally:
        _close(bag)


def read_rosbag(path: str | os.PathLike[str], *, sensor: SensorSize | None = None,
                events_topic: str | None = None, frames_topic: str | None = None,
                strict: bool = False) -> Recording:
    """Read events and frames of a ROS 1 or ROS 2 bag (see the module docstring).

    Parameters
    ----------
    path : path
        A ROS 2 bag folder (or its ``metadata.yaml``), one ``.mcap`` / ``.db3`` file of a
        ROS 2 bag, or a ROS 1 ``.bag``.
    sensor : SensorSize, optional
        Checked against the size the messages declare; needed only when no message does.
    events_topic, frames_topic : str, optional
        The topic to read when the bag holds several of that kind (else the one there is).
    strict : bool
        Refuse a bag file cut short (:class:`~evcal.io.TruncatedRecordingError`) instead of
        reading its whole messages with a :class:`~evcal.io.TruncatedRecordingWarning`. Cut
        ROS 1 bags and ROS 2 MCAP files are read up to their last whole message (in file
        order; a sqlite3 file in the order its messages were written).

    Returns
    -------
    Recording
        ``metadata`` holds ``format`` ("rosbag1"/"rosbag2"), ``storage``, ``source``,
        ``events_topic``, ``events_type``, ``encoding``, ``frames_topic``,
        ``frame_encoding``, ``messages``, ``lost_messages``, ``seq_gaps``,
        ``dropped_events``, ``reordered_events``, ``trigger_events``, and ``truncated``
        (where the file was cut) for a bag file cut short.

    Raises
    ------
    RosbagError
        (a :class:`~evcal.recording.RecordingError`) for a bag that does not open, ambiguous
        or missing topics, an unknown encoding, a truncated or malformed message (naming the
        topic and the message index), or sizes that disagree;
        :class:`~evcal.io.EmptyRecordingError` for an empty file or one cut before its first
        whole message.
    """
    path = Path(path)
    if not path.exists():
        raise RosbagError(f"{path}: no such file or directory")
    bag = _open_bag(path, strict)
    try:
        return _read(bag, sensor, events_topic, frames_topic)
    finally:
        _close(bag)


def _read(bag: _Bag, sensor: SensorSize | None, events_topic: str | None,
          frames_topic: str | None) -> Recording:
    store = typestore(bag.ros_version)
    topics = _topics(bag)
    ev_topic = _choose(bag, topics, events_topic, EVENT_TYPES, "events_topic", "event")
    fr_topic = _choose(bag, topics, frames_topic, (IMAGE,), "frames_topic", "image")
    if ev_topic is None and fr_topic is None:
        raise RosbagError(f"{bag.path}: no event topic ({', '.join(EVENT_TYPES)}) and no "
                          f"{IMAGE} topic; the bag's topics: {_describe(topics)}")
    for topic in (ev_topic, fr_topic):
        if topic is not None and len(topics[topic]) > 1:
            raise RosbagError(f"{bag.path}: topic {topic} carries several types "
                              f"({', '.join(sorted(topics[topic]))})")
    ev_type = next(iter(topics[ev_topic])) if ev_topic is not None else None
    stream = EventStream(ev_type or "")
    deser = store.deserialize_ros1 if bag.ros_version == 1 else store.deserialize_cdr
    frame_t: list[int] = []
    images: list[np.ndarray] = []
    frame_size: tuple[int, int] | None = None
    frame_enc: str | None = None
    counts = {"events": 0, "frames": 0}
    current = "the first message"
    for reader in bag.readers:
        conns = [c for c in reader.connections if c.topic in (ev_topic, fr_topic)]
        for conn in conns:
            _check_definition(bag, conn, store)
        if not conns:
            continue
        try:
            for conn, _t, raw in reader.messages(connections=conns):
                if conn.topic == ev_topic:
                    k = counts["events"]
                    current = where = f"{bag.path}: topic {ev_topic} message {k}"
                    counts["events"] += 1
                    stream.chunks.append(_event_message(bag, stream, deser, raw, where))
                else:
                    k = counts["frames"]
                    current = where = f"{bag.path}: topic {fr_topic} message {k}"
                    counts["frames"] += 1
                    msg = deserialize_message(deser, raw, conn.msgtype, where)
                    try:
                        image = image_to_gray(msg)
                    except PayloadError as exc:
                        raise RosbagError(f"{where}: {exc}", exc.reason) from None
                    if frame_size is not None and image.shape != frame_size:
                        raise RosbagError(f"{where}: a {image.shape[1]}x{image.shape[0]} image, "
                                          f"the earlier ones are {frame_size[1]}x"
                                          f"{frame_size[0]}", ErrorReason.SENSOR_CHANGED)
                    if frame_enc is not None and image.dtype != images[0].dtype:
                        raise RosbagError(f"{where}: encoding {msg.encoding!r} after "
                                          f"{frame_enc!r} images (frames of one dtype)")
                    frame_size, frame_enc = image.shape, frame_enc or str(msg.encoding)
                    frame_t.append(stamp_ns(msg) // 1000)
                    images.append(image)
        except RecordingError:
            raise
        except Exception as exc:  # rosbags/sqlite/zstd errors of a damaged file
            raise RosbagError(f"{bag.path}: reading failed after {current} "
                              f"(truncated or corrupt bag?): {type(exc).__name__}: {exc}"
                              ) from None

    found: SensorSize | None = None
    if stream.size is not None:
        found = SensorSize(height=stream.size[0], width=stream.size[1])
    elif frame_size is not None:
        found = SensorSize(height=frame_size[0], width=frame_size[1])
    if found is None:
        if sensor is None:
            raise RosbagError(f"{bag.path}: no message declares the sensor size (topic "
                              f"{ev_topic or fr_topic}); give it with sensor=")
        found = sensor
    try:
        found = check_sensor_arg(found, sensor, str(bag.path))
    except RecordingError as exc:
        raise RosbagError(str(exc), exc.reason) from None
    if frame_size is not None and frame_size != found.shape:
        raise RosbagError(f"{bag.path}: frames on {fr_topic} are {frame_size[1]}x"
                          f"{frame_size[0]}, the sensor is {found}",
                          ErrorReason.SENSOR_CHANGED)
    events, reordered = sorted_events(stream.chunks)
    if stream.size is None and events.size:  # arrays that declared no size: cut to the sensor
        keep = (events["x"] < found.width) & (events["y"] < found.height)
        stream.dropped += int(events.size - np.count_nonzero(keep))
        events = events[keep]
    metadata: dict[str, Any] = {
        "format": f"rosbag{bag.ros_version}", "storage": bag.storage, "source": str(bag.path),
        "events_topic": ev_topic, "events_type": ev_type, "encoding": stream.encoding,
        "frames_topic": fr_topic, "frame_encoding": frame_enc, "messages": counts,
        "lost_messages": stream.lost, "seq_gaps": stream.seq_gaps[:100],
        "seq_backwards": stream.seq_back, "dropped_events": stream.dropped,
        "reordered_events": reordered, "trigger_events": stream.triggers,
    }
    decoder = stream.decoder
    unit = getattr(decoder, "time_base_unit", None)
    if unit is not None:
        metadata["time_base_unit"] = unit
    if bag.cuts:
        cuts = [c.metadata() for c in bag.cuts]
        metadata["truncated"] = cuts[0] if len(cuts) == 1 else cuts
    if stream.lost:
        warnings.warn(f"{bag.path}: {stream.lost} EventPacket messages lost on {ev_topic} "
                      f"({len(stream.seq_gaps)} seq gaps, first {stream.seq_gaps[0]})",
                      RuntimeWarning, stacklevel=3)
    if stream.dropped:
        warnings.warn(f"{bag.path}: {stream.dropped} events outside the {found} sensor "
                      f"dropped on {ev_topic}", RuntimeWarning, stacklevel=3)
    frames = None
    if images:
        try:
            frames = Frames(t_us=np.array(frame_t, np.int64), images=np.stack(images),
                            exposure_us=np.zeros(len(images), np.int64))
        except RecordingError as exc:
            raise RosbagError(f"{bag.path}: topic {fr_topic}: {exc}", exc.reason) from None
    try:
        return Recording(sensor=found, events=events,
                         frames=frames if frames is not None else Frames.empty(0, 0),
                         metadata=metadata)
    except RecordingError as exc:
        raise RosbagError(f"{bag.path}: {exc}", exc.reason) from None


def _event_message(bag: _Bag, stream: EventStream, deser: Any, raw: bytes | memoryview,
                   where: str) -> np.ndarray:
    if stream.msgtype in (EVENT_PACKET, EVENT_ARRAY_LEGACY):
        msg = deserialize_message(deser, raw, stream.msgtype, where)
        size = (int(msg.height), int(msg.width))
        chunk = packet_events(stream, msg, where)
    else:
        try:
            h, w, _stamp, t_us, x, y, on = parse_event_array(raw, bag.ros_version)
        except PayloadError as exc:
            raise RosbagError(f"{where}: {stream.msgtype}: {exc}", exc.reason) from None
        size = (h, w)
        chunk = event_columns(t_us, x, y, on)
        if h and w:
            keep = (x < w) & (y < h)
            stream.dropped += int(keep.size - np.count_nonzero(keep))
            chunk = chunk[keep]
    if size == (0, 0) and stream.msgtype not in (EVENT_PACKET, EVENT_ARRAY_LEGACY):
        return chunk  # an EventArray that does not declare its size
    if not (0 < size[0] <= 65535 and 0 < size[1] <= 65535):
        raise RosbagError(f"{where}: declares a {size[1]}x{size[0]} sensor",
                          ErrorReason.OUT_OF_RANGE)
    if stream.size is None:
        stream.size = size
    elif size != stream.size:
        raise RosbagError(f"{where}: declares a {size[1]}x{size[0]} sensor, the topic's earlier "
                          f"messages {stream.size[1]}x{stream.size[0]}",
                          ErrorReason.SENSOR_CHANGED)
    return chunk
