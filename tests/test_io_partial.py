"""Files cut short (issue 24, item 5): every reader, on a file cut at 10 random places, reads
the whole records before the cut (equal to the full file's first events and frames), warns
with :class:`TruncatedRecordingWarning`, refuses with ``strict=True``, and never raises
anything but an :class:`EvcalError`. Empty and header-only files are
:class:`EmptyRecordingError` s.

What "the records before the cut" are is computed here from each format's framing, apart
from the readers: fixed-size words and records (RAW, DAT, AEDAT 2.0), AEDAT 3.1 packet
headers, AEDAT4 packet lengths with the ``aedat`` decoder's packets, MCAP chunk indexes and
the ROS 1 index that ``rosbags`` reads. A compressed chunk cut short may still give the
messages of its first blocks, so for MCAP and bags the test asks for a count between the
messages of the whole chunks and those of the chunks the cut reaches, at a message boundary.

Files: the real recordings of ``../shared/data`` where present (else those tests skip),
the small files of ``tests/data/formats``, and files written here by evcal's own writers
(evcal MCAP, ROS 2 MCAP) or, for ROS 1 bags, which evcal does not write, by ``rosbags``.
"""

from __future__ import annotations

import struct
import warnings
from collections.abc import Callable
from io import BytesIO
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from evcal.errors import ErrorReason, EvcalError
from evcal.events import SensorSize, make_events
from evcal.io import (
    EmptyRecordingError,
    TruncatedRecordingError,
    TruncatedRecordingWarning,
    open_recording,
    read_aedat2,
    read_aedat4,
    read_mcap,
    read_prophesee,
    read_rosbag,
    write_mcap,
)
from evcal.io.evencode import packets
from evcal.io.ros2msg import write_ros2_bag
from evcal.io.rosbag import EVENT_PACKET, IMAGE, decode_packet, packet_decoder, typestore
from evcal.io.wire import decode_events
from evcal.recording import Frames, Recording

FORMATS = Path(__file__).parent / "data" / "formats"
VGA = SensorSize(height=480, width=640)
DAVIS240 = SensorSize(height=180, width=240)
DAVIS346 = SensorSize(height=260, width=346)
N_CUTS = 10


def _cuts(lo: int, hi: int, seed: int, *, avoid: Callable[[int], bool] = lambda c: False
          ) -> list[int]:
    """``N_CUTS`` distinct random cut sizes in ``[lo, hi)``, moved off the places ``avoid``
    names (a record boundary where a format cannot tell a cut)."""
    rng = np.random.default_rng(seed)
    out: set[int] = set()
    while len(out) < N_CUTS:
        c = int(rng.integers(lo, hi))
        while avoid(c):
            c += 1
        if c < hi:
            out.add(c)
    return sorted(out)


def _write_cut(src: bytes, tmp: Path, name: str, size: int) -> Path:
    path = tmp / name
    path.write_bytes(src[:size])
    return path


def _read_cut(read: Callable[..., Recording], path: Path, **kw: Any) -> Recording | None:
    """The read of a cut file (None when it is an :class:`EmptyRecordingError`): it warns
    once; with ``strict`` it raises :class:`TruncatedRecordingError` (reason
    ``truncated``); anything else than an EvcalError fails the test."""
    empty: EmptyRecordingError | None = None
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            rec = read(path, **kw)
    except EmptyRecordingError as exc:
        empty = exc
    except EvcalError as exc:  # pragma: no cover - the failure names the error
        pytest.fail(f"{path.name}: {type(exc).__name__}: {exc}")
    if empty is not None:  # nothing whole before the cut
        assert empty.reason == ErrorReason.TRUNCATED
        assert "truncated" in str(empty)
        with pytest.raises(EmptyRecordingError):
            read(path, strict=True, **kw)
        return None
    ours = [w for w in caught if issubclass(w.category, TruncatedRecordingWarning)]
    assert len(ours) == 1, [str(w.message) for w in caught]
    assert str(path) in str(ours[0].message)
    assert "truncated file" in str(ours[0].message)
    assert not [w for w in caught if w not in ours], [str(w.message) for w in caught]
    assert rec.metadata["truncated"]["file_bytes"] == path.stat().st_size
    with pytest.raises(TruncatedRecordingError, match="truncated file") as info:
        read(path, strict=True, **kw)
    assert info.value.reason == ErrorReason.TRUNCATED
    return rec


def _is_prefix(rec: Recording, full: Recording, n_events: int, n_frames: int) -> None:
    assert full.metadata.get("reordered_events", 0) == 0  # else a prefix is not the file's
    assert rec.n_events == n_events
    np.testing.assert_array_equal(rec.events, full.events[:n_events])
    assert len(rec.frames) == n_frames
    np.testing.assert_array_equal(rec.frames.t_us, full.frames.t_us[:n_frames])
    if n_frames:
        np.testing.assert_array_equal(rec.frames.images, full.frames.images[:n_frames])


# ------------------------------------------------------------------ fixed-size words


def _data_start(data: bytes, comment: bytes) -> int:
    """Where the binary part starts after header lines starting with ``comment``."""
    pos = 0
    while data[pos : pos + 1] == comment:
        pos = data.index(b"\n", pos) + 1
    return pos


@pytest.mark.parametrize(("name", "word", "sensor"), [
    ("evt2_real.raw", 4, VGA), ("evt21.raw", 8, None), ("evt21_legacy.raw", 8, None),
    ("evt3_faery.raw", 2, None), ("cd_faery.dat", 8, None),
])
def test_prophesee_cut_at_random_places(tmp_path: Path, name: str, word: int,
                                        sensor: SensorSize | None) -> None:
    src = (FORMATS / name).read_bytes()
    start = _data_start(src, b"%") + (2 if name.endswith(".dat") else 0)
    full = read_prophesee(FORMATS / name, sensor=sensor)
    for c in _cuts(start + 1, len(src), seed=len(name),
                   avoid=lambda c: (c - start) % word == 0):
        whole_end = start + (c - start) // word * word
        rec = _read_cut(read_prophesee, _write_cut(src, tmp_path, name, c), sensor=sensor)
        if whole_end == start:
            assert rec is None
            continue
        assert rec is not None
        # the oracle: the same reader on the whole words alone (a whole file: no warning)
        oracle = read_prophesee(_write_cut(src, tmp_path, "whole_" + name, whole_end),
                                sensor=sensor)
        _is_prefix(rec, full, oracle.n_events, 0)
        np.testing.assert_array_equal(rec.events, oracle.events)
        assert rec.metadata["truncated"]["whole_end_byte"] == whole_end


def test_aedat2_cut_at_random_places(tmp_path: Path) -> None:
    src = (FORMATS / "v2e_davis240.aedat").read_bytes()
    start = _data_start(src, b"#")
    full = read_aedat2(FORMATS / "v2e_davis240.aedat", sensor=DAVIS240)
    assert full.n_events == (len(src) - start) // 8  # every record of v2e's file is an event
    for c in _cuts(start + 1, len(src), seed=2, avoid=lambda c: (c - start) % 8 == 0):
        rec = _read_cut(read_aedat2, _write_cut(src, tmp_path, "cut.aedat", c),
                        sensor=DAVIS240)
        n = (c - start) // 8
        if n == 0:
            assert rec is None
            continue
        assert rec is not None
        _is_prefix(rec, full, n, 0)
        assert rec.metadata["truncated"]["cut_bytes"] == (c - start) % 8


# ------------------------------------------------------------------ packets


def test_aedat31_cut_at_random_places(tmp_path: Path) -> None:
    src = (FORMATS / "davis240_v31.aedat").read_bytes()
    start = src.index(b"#!END-HEADER\r\n") + 14
    full = read_aedat2(FORMATS / "davis240_v31.aedat")
    # the packets (libcaer common.h): 28-byte header, capacity * size bytes; what each adds
    ends, events, frames = [start], [0], [0]
    pos = start
    while pos < len(src):
        ev_type, _src, size, _o, _ov, capacity, _number, valid = struct.unpack_from(
            "<hhiiiiii", src, pos)
        pos += 28 + capacity * size
        ends.append(pos)
        events.append(events[-1] + (valid if ev_type == 1 else 0))
        frames.append(frames[-1] + (valid if ev_type == 2 else 0))
    assert events[-1] == full.n_events + full.metadata["invalid_events"]
    for c in _cuts(start + 1, len(src), seed=3, avoid=lambda c: c in ends):
        rec = _read_cut(read_aedat2, _write_cut(src, tmp_path, "cut.aedat", c))
        k = int(np.searchsorted(ends, c, side="right")) - 1  # whole packets before the cut
        if k == 0:
            assert rec is None
            continue
        assert rec is not None
        invalid = rec.metadata["invalid_events"]  # the file's one invalid event, if whole
        _is_prefix(rec, full, events[k] - invalid, frames[k])


def test_aedat4_cut_at_random_places(shared_data: Path, tmp_path: Path) -> None:
    import aedat

    path = shared_data / "davis346_road" / "road.aedat4"
    src = path.read_bytes()
    full = read_aedat4(path)
    # packets (DV's AEDAT 4.0 layout): 14-byte magic, uint32 header length, the header,
    # then int32 stream id, uint32 length, data; the aedat decoder gives their content
    header_end = 18 + struct.unpack_from("<I", src, 14)[0]
    ends, events, frames = [header_end], [0], [0]
    for packet in aedat.Decoder(str(path)):
        ends.append(ends[-1] + 8 + struct.unpack_from("<I", src, ends[-1] + 4)[0])
        is_ev = packet["stream_id"] == 0 and "events" in packet
        events.append(events[-1] + (packet["events"].size if is_ev else 0))
        frames.append(frames[-1] + ("frame" in packet))
    assert (events[-1], frames[-1]) == (full.n_events, len(full.frames))
    for c in _cuts(header_end + 1, len(src), seed=4):
        rec = _read_cut(read_aedat4, _write_cut(src, tmp_path, "cut.aedat4", c))
        k = int(np.searchsorted(ends, c, side="right")) - 1
        if k == 0:
            assert rec is None
            continue
        assert rec is not None
        _is_prefix(rec, full, events[k], frames[k])


# ------------------------------------------------------------------ MCAP and bags


def _mcap_chunks(path: Path) -> list[tuple[int, int, list[tuple[str, bytes]]]]:
    """Every chunk of a finished MCAP file from its chunk indexes: ``(start, end, [(topic,
    message data)])`` in file order."""
    from mcap.data_stream import ReadDataStream
    from mcap.reader import make_reader
    from mcap.records import Chunk, Message
    from mcap.stream_reader import breakup_chunk

    data = path.read_bytes()
    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None
    out = []
    for ci in sorted(summary.chunk_indexes, key=lambda c: c.chunk_start_offset):
        a, b = ci.chunk_start_offset, ci.chunk_start_offset + ci.chunk_length
        chunk = Chunk.read(ReadDataStream(BytesIO(data[a + 9 : b])))
        msgs = [(summary.channels[r.channel_id].topic, bytes(r.data))
                for r in breakup_chunk(chunk) if isinstance(r, Message)]
        out.append((a, b, msgs))
    return out


def _bounds(chunks: list[tuple[int, int, list[int]]], cut: int) -> tuple[int, int]:
    """Messages (of one topic) in the chunks whole before ``cut``, and in those it reaches."""
    lo = sum(len(m) for a, b, m in chunks if b <= cut)
    hi = sum(len(m) for a, b, m in chunks if a < cut)
    return lo, hi


def _check_messages(rec: Recording | None, full: Recording, cut: int,
                    ev_chunks: list[tuple[int, int, list[int]]],
                    fr_chunks: list[tuple[int, int, list[int]]]) -> None:
    """A cut read of chunked messages: a count of whole messages between the bounds, at a
    message boundary, equal to the full file's first events and frames."""
    ev_lo, ev_hi = _bounds(ev_chunks, cut)
    fr_lo, fr_hi = _bounds(fr_chunks, cut)
    if rec is None:
        assert ev_lo == fr_lo == 0
        return
    cum = np.cumsum([0] + [n for _a, _b, m in ev_chunks for n in m])
    assert rec.n_events in cum[ev_lo : ev_hi + 1].tolist()
    assert fr_lo <= len(rec.frames) <= fr_hi
    _is_prefix(rec, full, rec.n_events, len(rec.frames))


def _recording(n: int = 150_000, n_frames: int = 12, seed: int = 5) -> Recording:
    rng = np.random.default_rng(seed)
    t0 = 1_700_000_000_000_000
    t = t0 + np.sort(rng.integers(0, 3_000_000, n))
    ev = make_events(t, rng.integers(0, 346, n), rng.integers(0, 260, n), rng.integers(0, 2, n))
    images = rng.integers(0, 256, (n_frames, 260, 346)).astype(np.uint8)
    return Recording(DAVIS346, ev, Frames(t_us=t0 + 1000 + 250_000 * np.arange(n_frames),
                                          images=images,
                                          exposure_us=np.full(n_frames, 500)))


def test_evcal_mcap_cut_at_random_places(tmp_path: Path) -> None:
    path = write_mcap(_recording(), tmp_path / "rec.mcap", chunk_events=2000)
    src = path.read_bytes()
    full = read_mcap(path)
    chunks = _mcap_chunks(path)
    assert len(chunks) >= 3
    ev = [(a, b, [decode_events(d)[0].size for t, d in m if t == "/events"])
          for a, b, m in chunks]
    fr = [(a, b, [1 for t, _d in m if t == "/frames"]) for a, b, m in chunks]
    for c in _cuts(chunks[0][0], len(src), seed=6):
        rec = _read_cut(read_mcap, _write_cut(src, tmp_path, "cut.mcap", c))
        _check_messages(rec, full, c, ev, fr)


def _ros2_counts(path: Path, events_topic: str, frames_topic: str
                 ) -> tuple[list[tuple[int, int, list[int]]], list[tuple[int, int, list[int]]]]:
    """Per chunk, the events of each EventPacket (decoded in file order, as the decoders
    carry state from packet to packet) and the Images."""
    store = typestore(2)
    decoder = None
    ev, fr = [], []
    for a, b, msgs in _mcap_chunks(path):
        counts = []
        for topic, data in msgs:
            if topic == events_topic:
                msg = store.deserialize_cdr(data, EVENT_PACKET)
                decoder = packet_decoder(decoder, msg)
                counts.append(decode_packet(decoder, msg).t_us.size)
        ev.append((a, b, counts))
        fr.append((a, b, [1 for topic, _d in msgs if topic == frames_topic]))
    return ev, fr


def test_ros2_mcap_by_evcal_cut_at_random_places(tmp_path: Path) -> None:
    path = write_ros2_bag(_recording(n_frames=24, seed=7), tmp_path / "rec.mcap")
    src = path.read_bytes()
    full = read_rosbag(path)
    ev, fr = _ros2_counts(path, "/camera/events", "/camera/image_raw")
    assert len(ev) >= 2
    assert sum(sum(m) for _a, _b, m in ev) == full.n_events
    for c in _cuts(ev[0][0], len(src), seed=8):
        rec = _read_cut(read_rosbag, _write_cut(src, tmp_path, "cut.mcap", c))
        _check_messages(rec, full, c, ev, fr)


def test_shared_ros2_mcap_cut_at_random_places(shared_data: Path, tmp_path: Path) -> None:
    path = shared_data / "ros2_event_packet_mcap" / "test_events_2_0.mcap"
    src = path.read_bytes()
    full = read_rosbag(path)
    ev, fr = _ros2_counts(path, "/event_camera/events", "")
    assert sum(sum(m) for _a, _b, m in ev) == full.n_events == 571_266
    for c in _cuts(ev[0][0], len(src), seed=9):
        rec = _read_cut(read_rosbag, _write_cut(src, tmp_path, "cut.mcap", c))
        _check_messages(rec, full, c, ev, fr)
    # the bag folder (metadata.yaml and its cut file) reads the same
    folder = tmp_path / "bag"
    folder.mkdir()
    (folder / "metadata.yaml").write_bytes((path.parent / "metadata.yaml").read_bytes())
    (folder / path.name).write_bytes(src[: len(src) // 2])
    with pytest.warns(TruncatedRecordingWarning, match=path.name):
        rec = open_recording(folder)
    np.testing.assert_array_equal(rec.events, full.events[: rec.n_events])


def _ros1_bag(path: Path, rec: Recording, compression: str) -> Path:
    """``rec`` as a ROS 1 bag of libcaer_cmp EventPackets and mono8 Images (rosbags' writer,
    100 kB chunks), messages in time order."""
    from rosbags.rosbag1 import Writer

    store = typestore(1)

    def header(t_ns: int) -> Any:
        stamp = store.types["builtin_interfaces/msg/Time"](sec=t_ns // 10**9,
                                                           nanosec=t_ns % 10**9)
        return store.types["std_msgs/msg/Header"](seq=0, stamp=stamp, frame_id="cam")

    writer = Writer(path)
    if compression != "none":
        writer.set_compression(getattr(Writer.CompressionFormat, compression.upper()))
    writer.chunk_threshold = 100_000
    writer.open()
    ce = writer.add_connection("/ev", EVENT_PACKET, typestore=store)
    ci = writer.add_connection("/img", IMAGE, typestore=store)
    h, w = rec.sensor.shape
    msgs: list[tuple[int, Any, bytes]] = []
    for i, pk in enumerate(packets(rec.events, rec.frames.t_us, packet_us=20_000)):
        msg = store.types[EVENT_PACKET](
            header=header(pk.time_base_ns), height=h, width=w, seq=i, time_base=pk.time_base_ns,
            encoding="libcaer_cmp", is_bigendian=False,
            events=np.frombuffer(pk.payload, np.uint8))
        msgs.append((pk.time_base_ns, ce, bytes(store.serialize_ros1(msg, EVENT_PACKET))))
    for t, image in zip(rec.frames.t_us, rec.frames.images, strict=True):
        msg = store.types[IMAGE](header=header(int(t) * 1000), height=h, width=w,
                                 encoding="mono8", is_bigendian=0, step=w,
                                 data=image.reshape(-1))
        msgs.append((int(t) * 1000, ci, bytes(store.serialize_ros1(msg, IMAGE))))
    for t_ns, conn, raw in sorted(msgs, key=lambda m: m[0]):
        writer.write(conn, t_ns, raw)
    writer.close()
    return path


def _ros1_counts(path: Path) -> tuple[list[tuple[int, int, list[int]]],
                                      list[tuple[int, int, list[int]]]]:
    """Per chunk (from the bag's index, as rosbags reads it), the events of each EventPacket
    and the Images."""
    from rosbags.rosbag1 import Reader

    store = typestore(1)
    with Reader(path) as reader:
        topic = {c.id: c.topic for c in reader.connections}
        spans = [(ci.pos, reader.chunks[ci.pos].datapos + reader.chunks[ci.pos].datasize,
                  {topic[k]: v for k, v in ci.connection_counts.items()})
                 for ci in sorted(reader.chunk_infos, key=lambda ci: ci.pos)]
        decoder = None
        counts = []
        for conn, _t, raw in reader.messages([c for c in reader.connections
                                              if c.topic == "/ev"]):
            msg = store.deserialize_ros1(raw, conn.msgtype)
            decoder = packet_decoder(decoder, msg)
            counts.append(decode_packet(decoder, msg).t_us.size)
    ev, fr, i = [], [], 0
    for a, b, n in spans:
        ev.append((a, b, counts[i : i + n.get("/ev", 0)]))
        i += n.get("/ev", 0)
        fr.append((a, b, [1] * n.get("/img", 0)))
    return ev, fr


@pytest.mark.parametrize("compression", ["none", "lz4", "bz2"])
def test_ros1_bag_cut_at_random_places(tmp_path: Path, compression: str) -> None:
    path = _ros1_bag(tmp_path / "rec.bag", _recording(n=60_000, seed=10), compression)
    src = path.read_bytes()
    full = read_rosbag(path)
    ev, fr = _ros1_counts(path)
    assert len(ev) >= 4
    assert sum(sum(m) for _a, _b, m in ev) == full.n_events
    for c in _cuts(ev[0][0], len(src), seed=11):
        rec = _read_cut(read_rosbag, _write_cut(src, tmp_path, "cut.bag", c))
        _check_messages(rec, full, c, ev, fr)


def _ros2_sqlite_bag(folder: Path, rec: Recording) -> Path:
    """``rec`` as a ROS 2 sqlite3 bag (rosbags' writer) of libcaer_cmp EventPackets and mono8
    Images, in time order; returns its ``.db3`` file."""
    from rosbags.rosbag2 import StoragePlugin, Writer

    store = typestore(2)

    def header(t_ns: int) -> Any:
        stamp = store.types["builtin_interfaces/msg/Time"](sec=t_ns // 10**9,
                                                           nanosec=t_ns % 10**9)
        return store.types["std_msgs/msg/Header"](stamp=stamp, frame_id="cam")

    h, w = rec.sensor.shape
    msgs: list[tuple[int, str, Any]] = []
    for i, pk in enumerate(packets(rec.events, rec.frames.t_us, packet_us=20_000)):
        msgs.append((pk.time_base_ns, EVENT_PACKET, store.types[EVENT_PACKET](
            header=header(pk.time_base_ns), height=h, width=w, seq=i, time_base=pk.time_base_ns,
            encoding="libcaer_cmp", is_bigendian=False,
            events=np.frombuffer(pk.payload, np.uint8))))
    for t, image in zip(rec.frames.t_us, rec.frames.images, strict=True):
        msgs.append((int(t) * 1000, IMAGE, store.types[IMAGE](
            header=header(int(t) * 1000), height=h, width=w, encoding="mono8", is_bigendian=0,
            step=w, data=image.reshape(-1))))
    with Writer(folder, version=8, storage_plugin=StoragePlugin.SQLITE3) as writer:
        conns = {EVENT_PACKET: writer.add_connection("/ev", EVENT_PACKET, typestore=store),
                 IMAGE: writer.add_connection("/img", IMAGE, typestore=store)}
        for t_ns, kind, msg in sorted(msgs, key=lambda m: m[0]):
            writer.write(conns[kind], t_ns, bytes(store.serialize_cdr(msg, kind)))
    (db3,) = folder.glob("*.db3")
    return db3


def test_ros2_sqlite3_bag_cut_at_random_places(tmp_path: Path) -> None:
    """A cut ``.db3``: the messages read are the full bag's first ones, none of them with
    bytes past the cut (SQLite would give zeros for missing pages), more as the cut moves
    on, and nearly all of them when only the last page is cut."""
    db3 = _ros2_sqlite_bag(tmp_path / "bag", _recording(n=60_000, seed=12))
    src = db3.read_bytes()
    full = read_rosbag(db3)
    page = int.from_bytes(src[16:18], "big")
    # where each message's data ends in the file (its last 16 bytes, random content)
    import sqlite3

    with sqlite3.connect(f"file:{db3}?mode=ro", uri=True) as db:
        rows = db.execute("SELECT topic_id, data FROM messages ORDER BY id").fetchall()
    tails = [src.find(bytes(d[-16:])) + 16 for _t, d in rows]
    assert min(tails) > 16
    events_topic = min(t for t, _d in rows)  # /ev was added first
    counts, last = [], (0, 0)
    for c in [*_cuts(2 * page, len(src), seed=12, avoid=lambda c: c % page == 0),
              len(src) - 5]:
        rec = _read_cut(read_rosbag, _write_cut(src, tmp_path, "cut.db3", c))
        if rec is None:
            counts.append(0)
            continue
        _is_prefix(rec, full, rec.n_events, len(rec.frames))
        n = rec.metadata["truncated"]["read"]
        k = int(n.split()[0].replace(",", ""))
        assert max(tails[:k]) <= c  # no message read has bytes past the cut
        assert (rec.n_events, len(rec.frames)) >= last
        last = (rec.n_events, len(rec.frames))
        counts.append(k)
        assert k == sum(1 for t, _d in rows[:k] if t == events_topic) + len(rec.frames)
    assert counts == sorted(counts)
    assert counts[-1] >= len(rows) - 3  # the last page cut: (nearly) every message


def test_ecd_events_cut_at_random_places(tmp_path: Path) -> None:
    from evcal.io import read_ecd, write_ecd

    rec = _recording(n=20_000, n_frames=3)
    folder = write_ecd(rec, tmp_path / "ecd")
    src = (folder / "events.txt").read_bytes()
    full = read_ecd(folder)
    cut_folder = tmp_path / "cut"
    cut_folder.mkdir()
    for name in ("images.txt", "images"):
        (cut_folder / name).symlink_to(folder / name)
    for c in _cuts(1, len(src), seed=13, avoid=lambda c: src[c - 1 : c] == b"\n"):
        (cut_folder / "events.txt").write_bytes(src[:c])
        rec_cut = _read_cut(lambda p, **kw: read_ecd(p.parent, **kw),
                            cut_folder / "events.txt")
        assert rec_cut is not None  # the frames are whole
        _is_prefix(rec_cut, full, src[:c].count(b"\n"), len(full.frames))
        assert rec_cut.metadata["truncated"]["whole_end_byte"] == src[:c].rfind(b"\n") + 1


def test_npz_and_hdf5_are_not_read_in_part(tmp_path: Path) -> None:
    """A zip keeps its directory at its end, HDF5 its index anywhere: a cut ``.npz`` or
    HDF5 file is refused, naming the file, the cut and why, whatever ``strict`` says."""
    from evcal.io import write_npz

    npz = write_npz(_recording(n=20_000, n_frames=2), tmp_path / "rec.npz")
    for path, pattern in ((npz, r"truncated zip archive: it ends at byte [\d,]+ inside "
                                r"(member '[a-z_]+\.npy'|its directory)"),
                          (FORMATS / "dsec_like.h5", r"truncated HDF5 file: it has [\d,]+ "
                                                     r"bytes, its superblock says"),
                          (FORMATS / "mvsec_like.hdf5", "truncated HDF5 file"),
                          (FORMATS / "v2e_dvs.h5", "truncated HDF5 file")):
        src = path.read_bytes()
        for c in _cuts(64, len(src), seed=14):
            cut = _write_cut(src, tmp_path, "cut" + path.suffix, c)
            for strict in (False, True):
                with pytest.raises(EvcalError, match=pattern) as info:
                    open_recording(cut, strict=strict,
                                   sensor=DAVIS346 if "v2e" in path.name else None)
                assert info.value.reason == ErrorReason.TRUNCATED
                assert str(cut) in str(info.value)


# ------------------------------------------------------------------ empty, header only


@pytest.mark.parametrize("name", ["x.raw", "x.dat", "x.aedat", "x.aedat4", "x.mcap", "x.bag"])
def test_empty_files_say_so(tmp_path: Path, name: str) -> None:
    path = tmp_path / name
    path.write_bytes(b"")
    for read in (open_recording, {".raw": read_prophesee, ".dat": read_prophesee,
                                  ".aedat": read_aedat2, ".aedat4": read_aedat4,
                                  ".mcap": read_mcap, ".bag": read_rosbag}[path.suffix]):
        with pytest.raises(EmptyRecordingError, match=r"empty file \(0 bytes\)") as info:
            read(path)
        assert info.value.reason == ErrorReason.TRUNCATED


def _header_of(name: str) -> bytes:
    src = (FORMATS / name).read_bytes()
    if name.endswith(".aedat") and src.startswith(b"#!AER-DAT3.1"):
        return src[: src.index(b"#!END-HEADER\r\n") + 14]
    return src[: _data_start(src, b"#" if name.endswith(".aedat") else b"%")]


@pytest.mark.parametrize(("name", "sensor"), [
    ("evt2_real.raw", VGA), ("evt3_faery.raw", None), ("cd_faery.dat", None),
    ("v2e_davis240.aedat", DAVIS240), ("davis240_v31.aedat", None),
])
def test_header_only_files_say_so(tmp_path: Path, name: str, sensor: SensorSize | None
                                  ) -> None:
    path = tmp_path / name
    path.write_bytes(_header_of(name))
    with pytest.raises(EmptyRecordingError, match=r"header only: the file ends after its "
                                                  r"[\d,]+-byte header with no") as info:
        open_recording(path, sensor=sensor)
    assert info.value.reason == ErrorReason.TRUNCATED
    path.write_bytes(_header_of(name)[:-3])  # cut inside the header
    with pytest.raises(EmptyRecordingError, match="truncated inside its header|header only"):
        open_recording(path, sensor=sensor)


def test_header_only_aedat4(shared_data: Path, tmp_path: Path) -> None:
    src = (shared_data / "davis346_road" / "road.aedat4").read_bytes()
    header_end = 18 + struct.unpack_from("<I", src, 14)[0]
    path = tmp_path / "head.aedat4"
    path.write_bytes(src[:header_end])
    with pytest.raises(EmptyRecordingError, match="header only: .* with no packets"):
        open_recording(path)
    for cut in (5, 16, header_end - 1):
        path.write_bytes(src[:cut])
        with pytest.raises(EmptyRecordingError, match="truncated inside its header"):
            open_recording(path)
    path.write_bytes(src[: header_end + 20])  # inside the first packet
    with pytest.raises(EmptyRecordingError, match=r"before its first whole record: .* inside "
                                                  r"packet 0 \(stream 0"):
        open_recording(path)


def test_mcap_and_bags_without_a_whole_message(tmp_path: Path) -> None:
    rec = _recording(n=20_000, n_frames=2)
    evcal_mcap = write_mcap(rec, tmp_path / "rec.mcap")
    ros2 = write_ros2_bag(rec, tmp_path / "ros2.mcap")
    ros1 = _ros1_bag(tmp_path / "rec.bag", rec, "none")
    for path in (evcal_mcap, ros2, ros1):
        src = path.read_bytes()
        first = (_ros1_counts(path) if path.suffix == ".bag" else
                 ([(a, b, []) for a, b, _m in _mcap_chunks(path)], []))[0][0][0]
        for cut in (first, first + 30):  # the records before the first chunk, and into it
            cut_path = _write_cut(src, tmp_path, "cut" + path.suffix, cut)
            with pytest.raises(EmptyRecordingError, match="truncated before its first whole "
                                                          "record"):
                open_recording(cut_path)
        for cut in (3, 10):  # inside the magic / the first record
            cut_path = _write_cut(src, tmp_path, "cut" + path.suffix, cut)
            with pytest.raises(EmptyRecordingError):
                open_recording(cut_path)


def test_a_finished_evcal_mcap_without_events_is_a_legitimate_empty_recording(
        tmp_path: Path) -> None:
    """Decided: evcal's own MCAP with its metadata record and no message, finished (summary,
    footer), is an empty recording (a session that saw no event); the same file cut before
    its end is not."""
    empty = Recording(DAVIS346, make_events([], [], [], []))
    back = read_mcap(write_mcap(empty, tmp_path / "empty.mcap"))
    assert back.n_events == 0
    assert back.sensor == DAVIS346
    assert "truncated" not in back.metadata


def test_corrupt_is_not_cut(tmp_path: Path) -> None:
    """A whole record that does not decode is still refused as corrupt, not read around."""
    path = write_mcap(_recording(n=20_000, n_frames=2), tmp_path / "rec.mcap",
                      chunk_events=1000)
    chunks = _mcap_chunks(path)
    bad = bytearray(path.read_bytes())
    a, b, _m = chunks[0]
    bad[(a + b) // 2 : (a + b) // 2 + 16] = bytes(16)  # inside the first chunk
    cut = tmp_path / "bad.mcap"
    cut.write_bytes(bytes(bad[: chunks[-1][0] + 40]))
    with pytest.raises(EvcalError, match="corrupt|CRC|cannot read"):
        read_mcap(cut)


def test_cli_strict_flag(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from evcal.cli import main

    src = (FORMATS / "evt3_faery.raw").read_bytes()
    path = _write_cut(src, tmp_path, "cut.raw", len(src) - 1)
    with pytest.warns(TruncatedRecordingWarning, match=r"cut\.raw: truncated file"):
        assert main(["info", str(path)]) == 0
    capsys.readouterr()
    assert main(["info", str(path), "--strict"]) == 1
    err = capsys.readouterr().err
    assert "TruncatedRecordingError" in err
    assert "truncated file" in err
    assert "refused: strict" in err


def test_iter_mcap_refuses_a_cut_file_unless_told(tmp_path: Path) -> None:
    """The streaming reader (``calibrate --stream``) keeps refusing a cut file by default;
    ``strict=False`` streams its whole messages after the warning."""
    from evcal.io.mcap_rec import iter_mcap

    path = write_mcap(_recording(n=60_000, n_frames=4), tmp_path / "rec.mcap",
                      chunk_events=2000)
    src = path.read_bytes()
    full = read_mcap(path)
    cut = _write_cut(src, tmp_path, "cut.mcap", int(len(src) * 0.8))
    with pytest.raises(TruncatedRecordingError, match="truncated file"):
        iter_mcap(cut)
    with pytest.warns(TruncatedRecordingWarning, match=r"cut\.mcap: truncated file"):
        sensor, messages, total = iter_mcap(cut, strict=False)
    got = [payload for kind, _t, payload in messages if kind == "events"]
    assert sensor == DAVIS346
    assert 0 < total < 34
    n = sum(len(e) for e in got)
    np.testing.assert_array_equal(np.concatenate(got), full.events[:n])
