"""ROS bags through ``evcal.open_recording``: the shared EventPacket bag against its published
decoded truth, small bags written here with rosbags' writers (ROS 2 MCAP and sqlite3, ROS 1),
the payload decoders on hand-made words, and the errors of malformed input."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from evcal.errors import ErrorReason
from evcal.events import SensorSize, make_events
from evcal.io import RosbagError, open_recording, read_rosbag, sniff
from evcal.io._evcodecs import (
    Evt3Decoder,
    LibcaerCmpDecoder,
    LibcaerDecoder,
    MonoDecoder,
    PayloadError,
    make_decoder,
)
from evcal.io.rosbag import (
    DVS_EVENT_ARRAY,
    EVENT_PACKET,
    IMAGE,
    PROPHESEE_EVENT_ARRAY,
    image_to_gray,
    parse_event_array,
    typestore,
)
from evcal.recording import RecordingError

H, W = 20, 30  # the synthetic sensor

# ------------------------------------------------------------------ the shared bag (real data)

# Published with the bag (github ros-event-camera/event_camera_py, tests/test_2.py): the
# counts, the first sensor time, sum_time = the sum of (t - first event's t) in µs, and
# decode_until's final frame time (first + 1 s: every event is earlier).
SHARED_N, SHARED_ON, SHARED_OFF = 571_266, 211_043, 360_223
SHARED_FIRST_US = 1744227144732712
SHARED_SUM_REL_US = 335555680277
SHARED_END_US = 1744227145732712


@pytest.fixture(scope="module")
def shared_bag(shared_data: Path) -> Path:
    bag = shared_data / "ros2_event_packet_mcap"
    if not (bag / "metadata.yaml").is_file():
        pytest.skip(f"the shared ROS 2 bag is not at {bag}")
    return bag


@pytest.mark.parametrize("which", ["folder", "mcap", "metadata.yaml"])
def test_shared_bag_decodes_to_the_published_truth(shared_bag: Path, which: str) -> None:
    path = {"folder": shared_bag, "mcap": shared_bag / "test_events_2_0.mcap",
            "metadata.yaml": shared_bag / "metadata.yaml"}[which]
    assert sniff(path) == "rosbag2"
    rec = open_recording(path)
    ev = rec.events
    t = ev["t_us"]
    assert rec.sensor == SensorSize(height=260, width=346)
    assert rec.n_events == SHARED_N
    assert int(np.count_nonzero(ev["p"] == 1)) == SHARED_ON
    assert int(np.count_nonzero(ev["p"] == -1)) == SHARED_OFF
    assert int(t[0]) == SHARED_FIRST_US
    assert int((t - t[0]).sum()) == SHARED_SUM_REL_US
    assert SHARED_END_US - 100_000 <= int(t[-1]) < SHARED_END_US
    assert len(rec.frames) == 0
    meta = rec.metadata
    assert meta["encoding"] == "libcaer_cmp"
    assert meta["events_topic"] == "/event_camera/events"
    assert meta["messages"] == {"events": 100, "frames": 0}
    assert meta["lost_messages"] == 0
    assert meta["dropped_events"] == 0
    assert meta["reordered_events"] == 0
    assert meta["time_base_unit"] == "ns"


def test_shared_bag_through_evcal_info(shared_bag: Path, capsys: pytest.CaptureFixture[str]
                                       ) -> None:
    from evcal.cli import main

    assert main(["info", str(shared_bag), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["sensor"] == "346x260"
    assert info["n_events"] == SHARED_N
    assert info["t_first_us"] == SHARED_FIRST_US
    assert info["n_frames"] == 0
    assert main(["info", str(shared_bag), "--json", "--events-topic",
                 "/event_camera/events"]) == 0
    assert json.loads(capsys.readouterr().out)["n_events"] == SHARED_N
    assert main(["info", str(shared_bag), "--events-topic", "/nope"]) == 1
    err = capsys.readouterr().err
    assert "no topic '/nope'" in err
    assert "/event_camera/events" in err


def test_shared_bag_topic_option(shared_bag: Path) -> None:
    rec = read_rosbag(shared_bag, events_topic="/event_camera/events")
    assert rec.n_events == SHARED_N
    with pytest.raises(RosbagError, match=r"no topic '/nope' \(events_topic\); the bag's "
                                          r"topics: /event_camera/events \(event_camera_msgs"):
        read_rosbag(shared_bag, events_topic="/nope")
    with pytest.raises(RosbagError, match="declares a 346x260 sensor, but sensor=240x180"):
        read_rosbag(shared_bag, sensor=SensorSize(height=180, width=240))


# ------------------------------------------------------------------ writing small bags


def _events(n: int, seed: int, t0_us: int = 1_700_000_000_000_000) -> np.ndarray:
    rng = np.random.default_rng(seed)
    t = t0_us + np.sort(rng.integers(0, 2_000_000, n))
    return make_events(t, rng.integers(0, W, n), rng.integers(0, H, n), rng.integers(0, 2, n))


def _frames(n: int, seed: int, t0_us: int = 1_700_000_000_000_000) -> tuple[np.ndarray,
                                                                                np.ndarray]:
    rng = np.random.default_rng(seed)
    t = t0_us + 1000 + 250_000 * np.arange(n)
    return t, rng.integers(0, 256, (n, H, W)).astype(np.uint8)


def _split(events: np.ndarray) -> list[np.ndarray]:
    """Uneven messages, with an empty and a one-event message (the CDR layout's edge)."""
    n = events.shape[0]
    cuts = [0, 0, 1, n // 3, n // 2, n]
    return [events[a:b] for a, b in zip(cuts[:-1], cuts[1:], strict=True)]


class _Msgs:
    """Messages of the synthetic camera for ROS 1 or ROS 2."""

    def __init__(self, ros: int) -> None:
        self.ros = ros
        self.store = typestore(ros)

    def serialize(self, msg: Any, msgtype: str) -> bytes:
        if self.ros == 1:
            return bytes(self.store.serialize_ros1(msg, msgtype))
        return bytes(self.store.serialize_cdr(msg, msgtype))

    def time(self, t_ns: int) -> Any:
        return self.store.types["builtin_interfaces/msg/Time"](
            sec=t_ns // 1_000_000_000, nanosec=t_ns % 1_000_000_000)

    def header(self, t_ns: int) -> Any:
        cls = self.store.types["std_msgs/msg/Header"]
        if self.ros == 1:
            return cls(seq=0, stamp=self.time(t_ns), frame_id="cam")
        return cls(stamp=self.time(t_ns), frame_id="cam")

    def event_array(self, msgtype: str, ev: np.ndarray, height: int = H, width: int = W) -> Any:
        pkg = msgtype.split("/")[0]
        event = self.store.types[f"{pkg}/msg/Event"]
        # 999 ns below the µs: times are floored to µs
        items = [event(x=int(e["x"]), y=int(e["y"]), ts=self.time(int(e["t_us"]) * 1000 + 999),
                       polarity=bool(e["p"] > 0)) for e in ev]
        t = int(ev["t_us"][0]) * 1000 if ev.size else 0
        return self.store.types[msgtype](header=self.header(t), height=height, width=width,
                                         events=items)

    def packet(self, ev: np.ndarray, seq: int, encoding: str = "libcaer",
               payload: np.ndarray | None = None, height: int = H, width: int = W) -> Any:
        t0_us = int(ev["t_us"][0]) if ev.size else 1_700_000_000_000_000
        time_base = t0_us * 1000 + 123  # ns; not a whole µs: event times are floored
        if payload is None:
            payload = libcaer_payload(ev, t0_us)
        return self.store.types[EVENT_PACKET](
            header=self.header(t0_us * 1000), height=height, width=width, seq=seq,
            time_base=time_base, encoding=encoding, is_bigendian=False, events=payload)

    def image(self, t_us: int, image: np.ndarray, encoding: str = "mono8") -> Any:
        h = image.shape[0]
        data = np.ascontiguousarray(image).view(np.uint8).reshape(-1)
        return self.store.types[IMAGE](
            header=self.header(t_us * 1000), height=h, width=image.shape[1],
            encoding=encoding, is_bigendian=0, step=data.size // h, data=data)


class _Bag(_Msgs):
    """One bag being written, whatever the format: ``add(topic, type)``, ``write(...)``."""

    def __init__(self, kind: str, path: Path) -> None:
        super().__init__(1 if kind == "ros1" else 2)
        self.kind = kind
        if kind == "ros1":
            from rosbags.rosbag1 import Writer as Writer1

            self.writer: Any = Writer1(path)
        else:
            from rosbags.rosbag2 import StoragePlugin, Writer

            plugin = StoragePlugin.MCAP if kind == "ros2-mcap" else StoragePlugin.SQLITE3
            self.writer = Writer(path, version=9, storage_plugin=plugin)
        self.writer.open()
        self.conns: dict[str, Any] = {}

    def add(self, topic: str, msgtype: str, **kwargs: Any) -> None:
        self.conns[topic] = self.writer.add_connection(topic, msgtype, typestore=self.store,
                                                       **kwargs)

    def write(self, topic: str, msg: Any, t_ns: int, raw: bytes | None = None) -> None:
        conn = self.conns[topic]
        self.writer.write(conn, t_ns, raw if raw is not None
                          else self.serialize(msg, conn.msgtype))

    def close(self) -> None:
        self.writer.close()


def libcaer_payload(ev: np.ndarray, t0_us: int) -> np.ndarray:
    """Uncompressed libcaer polarity events: data (x << 17 | y << 2 | p << 1 | valid), ts."""
    rec = np.empty(ev.shape[0], [("data", "<u4"), ("ts", "<i4")])
    on = (ev["p"] > 0).astype(np.uint32)
    rec["data"] = (ev["x"].astype(np.uint32) << 17) | (ev["y"].astype(np.uint32) << 2) \
        | (on << 1) | 1
    rec["ts"] = ev["t_us"] - t0_us
    return rec.view(np.uint8)


KINDS = ["ros2-mcap", "ros2-sqlite3", "ros1"]
EVENT_KINDS = [DVS_EVENT_ARRAY, PROPHESEE_EVENT_ARRAY, EVENT_PACKET]


def _write(tmp_path: Path, kind: str, fill: Callable[[_Bag], None], name: str = "bag") -> Path:
    path = tmp_path / (name + (".bag" if kind == "ros1" else ""))
    bag = _Bag(kind, path)
    try:
        fill(bag)
    finally:
        bag.close()
    return path


def _write_events(bag: _Bag, msgtype: str, events: np.ndarray, topic: str = "/events",
                  seqs: list[int] | None = None) -> None:
    bag.add(topic, msgtype)
    for k, chunk in enumerate(_split(events)):
        t_ns = (int(chunk["t_us"][0]) if chunk.size else 1_700_000_000_000_000) * 1000 + k
        if msgtype == EVENT_PACKET:
            msg = bag.packet(chunk, seq=seqs[k] if seqs else 10 + k)
        else:
            msg = bag.event_array(msgtype, chunk)
        bag.write(topic, msg, t_ns)


def _write_frames(bag: _Bag, t: np.ndarray, images: np.ndarray, topic: str = "/image") -> None:
    bag.add(topic, IMAGE)
    for ti, image in zip(t, images, strict=True):
        bag.write(topic, bag.image(int(ti), image), int(ti) * 1000)


def _single_file(path: Path, kind: str) -> Path:
    suffix = ".mcap" if kind == "ros2-mcap" else ".db3"
    (file,) = path.glob("*" + suffix)
    return file


@pytest.mark.parametrize("msgtype", EVENT_KINDS)
@pytest.mark.parametrize("kind", KINDS)
def test_synthetic_bag_round_trips_exactly(tmp_path: Path, kind: str, msgtype: str) -> None:
    events = _events(500, seed=1)
    ft, images = _frames(6, seed=2)

    def fill(bag: _Bag) -> None:
        _write_events(bag, msgtype, events)
        _write_frames(bag, ft, images)

    path = _write(tmp_path, kind, fill)
    paths = [path] if kind == "ros1" else [path, _single_file(path, kind)]
    for p in paths:
        assert sniff(p) == ("rosbag1" if kind == "ros1" else "rosbag2")
        rec = open_recording(p)
        assert rec.sensor == SensorSize(height=H, width=W)
        np.testing.assert_array_equal(rec.events, events)
        np.testing.assert_array_equal(rec.frames.t_us, ft)
        np.testing.assert_array_equal(rec.frames.images, images)
        assert rec.frames.images.dtype == np.uint8
        meta = rec.metadata
        assert meta["format"] == ("rosbag1" if kind == "ros1" else "rosbag2")
        assert meta["events_type"] == msgtype
        assert meta["frames_topic"] == "/image"
        assert meta["messages"] == {"events": 5, "frames": 6}
        assert meta["lost_messages"] == 0
        assert meta["reordered_events"] == 0
        assert meta["encoding"] == ("libcaer" if msgtype == EVENT_PACKET else None)


@pytest.mark.parametrize("kind", KINDS)
def test_frames_only_and_events_only(tmp_path: Path, kind: str) -> None:
    ft, images = _frames(3, seed=4)
    rec = open_recording(_write(tmp_path, kind, lambda b: _write_frames(b, ft, images), "fr"))
    assert rec.n_events == 0
    assert len(rec.frames) == 3
    assert rec.sensor.shape == (H, W)
    events = _events(50, seed=5)
    rec = open_recording(_write(tmp_path, kind,
                                lambda b: _write_events(b, DVS_EVENT_ARRAY, events), "ev"))
    np.testing.assert_array_equal(rec.events, events)
    assert len(rec.frames) == 0


@settings(max_examples=40, deadline=None)
@given(n=st.integers(0, 40), frame_id=st.text(max_size=7), seed=st.integers(0, 2**16),
       big=st.booleans(), ros=st.sampled_from([1, 2]))
def test_event_array_bytes_parse_like_rosbags(n: int, frame_id: str, seed: int, big: bool,
                                              ros: int) -> None:
    """The numpy reading of the serialised arrays equals rosbags' own deserialisation, for
    any frame_id length (alignment) and either CDR byte order."""
    msgs = _Msgs(ros)
    store = msgs.store
    ev = _events(n, seed)
    msg = msgs.event_array(DVS_EVENT_ARRAY, ev)
    msg.header.frame_id = frame_id
    raw = bytes(store.serialize_ros1(msg, DVS_EVENT_ARRAY) if ros == 1
                else store.serialize_cdr(msg, DVS_EVENT_ARRAY, little_endian=not big))
    h, w, stamp, t_us, x, y, on = parse_event_array(raw, ros)
    assert (h, w) == (H, W)
    assert stamp == (int(ev["t_us"][0]) * 1000 if n else 0)
    np.testing.assert_array_equal(t_us, ev["t_us"])
    np.testing.assert_array_equal(x, ev["x"])
    np.testing.assert_array_equal(y, ev["y"])
    np.testing.assert_array_equal(on, ev["p"] > 0)


def test_seq_gaps_are_counted_and_warned(tmp_path: Path) -> None:
    events = _events(300, seed=6)
    path = _write(tmp_path, "ros2-mcap", lambda b: _write_events(
        b, EVENT_PACKET, events, seqs=[7, 8, 11, 12, 20]))
    with pytest.warns(RuntimeWarning, match=r"9 EventPacket messages lost on /events \(2 seq "
                                            r"gaps, first \(8, 11\)\)"):
        rec = open_recording(path)
    assert rec.metadata["lost_messages"] == 2 + 7
    assert rec.metadata["seq_gaps"] == [(8, 11), (12, 20)]
    np.testing.assert_array_equal(rec.events, events)


def test_events_outside_the_sensor_are_dropped_and_counted(tmp_path: Path) -> None:
    events = _events(100, seed=7)

    def fill(bag: _Bag) -> None:
        bag.add("/events", EVENT_PACKET)
        bag.write("/events", bag.packet(events, seq=0, height=H, width=W - 5), 1)

    with pytest.warns(RuntimeWarning, match="events outside the 25x20 sensor dropped"):
        rec = open_recording(_write(tmp_path, "ros2-sqlite3", fill))
    inside = events[events["x"] < W - 5]
    np.testing.assert_array_equal(rec.events, inside)
    assert rec.metadata["dropped_events"] == events.size - inside.size


def test_unsorted_messages_are_sorted_stably(tmp_path: Path) -> None:
    events = _events(200, seed=8)
    late, early = events[100:], events[:100]

    def fill(bag: _Bag) -> None:
        bag.add("/events", DVS_EVENT_ARRAY)
        bag.write("/events", bag.event_array(DVS_EVENT_ARRAY, late), 1)
        bag.write("/events", bag.event_array(DVS_EVENT_ARRAY, early), 2)

    rec = open_recording(_write(tmp_path, "ros1", fill))
    np.testing.assert_array_equal(rec.events, events)
    assert rec.metadata["reordered_events"] == 100


# ------------------------------------------------------------------ malformed input


def _one_packet(payload: np.ndarray, encoding: str = "libcaer") -> Callable[[_Bag], None]:
    def fill(bag: _Bag) -> None:
        bag.add("/events", EVENT_PACKET)
        ev = _events(4, seed=9)
        bag.write("/events", bag.packet(ev, seq=0), 1)
        bag.write("/events", bag.packet(ev, seq=1, encoding=encoding, payload=payload), 2)
    return fill


def test_truncated_payload_names_topic_message_and_size(tmp_path: Path) -> None:
    ev = _events(4, seed=9)
    cut = libcaer_payload(ev, int(ev["t_us"][0]))[:-5]
    path = _write(tmp_path, "ros2-mcap", _one_packet(cut))
    with pytest.raises(RosbagError, match=r"topic /events message 1 \(seq 1\): libcaer payload "
                                          r"of 27 bytes is not a whole number of 8-byte words"
                       ) as info:
        open_recording(path)
    assert info.value.reason == ErrorReason.TRUNCATED
    assert isinstance(info.value, RecordingError)


def test_unknown_encoding_is_named(tmp_path: Path) -> None:
    def fill(bag: _Bag) -> None:
        bag.add("/events", EVENT_PACKET)
        bag.write("/events", bag.packet(_events(4, seed=9), seq=0, encoding="evt2"), 1)

    path = _write(tmp_path, "ros2-sqlite3", fill)
    with pytest.raises(RosbagError, match=r"topic /events message 0: EventPacket encoding "
                                          r"'evt2' is not one evcal decodes \(it reads "
                                          r"libcaer_cmp, libcaer, evt3, mono\)"):
        open_recording(path)


def test_encoding_change_and_sensor_change_are_refused(tmp_path: Path) -> None:
    ev = _events(8, seed=10)
    path = _write(tmp_path, "ros1", _one_packet(np.zeros(8, np.uint8), "mono"))
    with pytest.raises(RosbagError, match=r"message 1: encoding 'mono', the topic's earlier "
                                          r"messages are 'libcaer'"):
        open_recording(path)

    def fill(bag: _Bag) -> None:
        bag.add("/events", EVENT_PACKET)
        bag.write("/events", bag.packet(ev, seq=0), 1)
        bag.write("/events", bag.packet(ev, seq=1, height=H + 1), 2)

    with pytest.raises(RosbagError, match=r"message 1: declares a 30x21 sensor, the topic's "
                                          r"earlier messages 30x20") as info:
        open_recording(_write(tmp_path, "ros2-mcap", fill, "size"))
    assert info.value.reason == ErrorReason.SENSOR_CHANGED


@pytest.mark.parametrize("kind", KINDS)
def test_truncated_event_array_message(tmp_path: Path, kind: str) -> None:
    ev = _events(10, seed=11)

    def fill(bag: _Bag) -> None:
        bag.add("/dvs", DVS_EVENT_ARRAY)
        raw = bag.serialize(bag.event_array(DVS_EVENT_ARRAY, ev), DVS_EVENT_ARRAY)
        bag.write("/dvs", None, 1, raw=raw[:-20])

    with pytest.raises(RosbagError, match=r"topic /dvs message 0: dvs_msgs/msg/EventArray: the "
                                          r"message ends \(\d+ bytes\) inside event 8 of 10"
                       ) as info:
        open_recording(_write(tmp_path, kind, fill))
    assert info.value.reason == ErrorReason.TRUNCATED


def test_truncated_packet_message_fails_deserialisation(tmp_path: Path) -> None:
    def fill(bag: _Bag) -> None:
        bag.add("/events", EVENT_PACKET)
        raw = bag.serialize(bag.packet(_events(10, seed=12), seq=0), EVENT_PACKET)
        bag.write("/events", None, 1, raw=raw[:40])

    with pytest.raises(RosbagError, match=r"topic /events message 0: cannot deserialise 40 "
                                          r"bytes as event_camera_msgs/msg/EventPacket"):
        open_recording(_write(tmp_path, "ros2-mcap", fill))


def test_ambiguous_topics_are_refused_with_their_names(tmp_path: Path) -> None:
    a, b = _events(40, seed=13), _events(60, seed=14)
    ft, images = _frames(2, seed=15)

    def fill(bag: _Bag) -> None:
        _write_events(bag, DVS_EVENT_ARRAY, a, topic="/left/events")
        _write_events(bag, PROPHESEE_EVENT_ARRAY, b, topic="/right/events")
        _write_frames(bag, ft, images, topic="/left/image")
        _write_frames(bag, ft, images, topic="/right/image")

    path = _write(tmp_path, "ros2-mcap", fill)
    with pytest.raises(RosbagError, match=r"2 event topics \(/left/events, /right/events\); "
                                          r"choose one with events_topic="):
        open_recording(path)
    with pytest.raises(RosbagError, match=r"2 image topics \(/left/image, /right/image\); "
                                          r"choose one with frames_topic="):
        open_recording(path, events_topic="/left/events")
    rec = open_recording(path, events_topic="/right/events", frames_topic="/left/image")
    np.testing.assert_array_equal(rec.events, b)
    assert len(rec.frames) == 2
    with pytest.raises(RosbagError, match=r"topic '/left/image' \(events_topic\) holds "
                                          r"sensor_msgs/msg/Image, not event"):
        open_recording(path, events_topic="/left/image", frames_topic="/left/image")


def test_bag_without_camera_topics(tmp_path: Path) -> None:
    def fill(bag: _Bag) -> None:
        bag.add("/chatter", "std_msgs/msg/String")
        bag.write("/chatter", bag.store.types["std_msgs/msg/String"](data="hi"), 1)

    with pytest.raises(RosbagError, match=r"no event topic .* and no sensor_msgs/msg/Image "
                                          r"topic; the bag's topics: /chatter "
                                          r"\(std_msgs/msg/String\)"):
        open_recording(_write(tmp_path, "ros2-sqlite3", fill))


def test_other_message_definition_is_refused(tmp_path: Path) -> None:
    other = "int32 x\nint32 y\nbool polarity\ntime ts\n"

    def fill(bag: _Bag) -> None:
        bag.add("/dvs", DVS_EVENT_ARRAY, msgdef=other, md5sum="0" * 32)
        bag.write("/dvs", None, 1, raw=b"\x00" * 40)

    with pytest.raises(RosbagError, match=r"topic /dvs: the bag's dvs_msgs/msg/EventArray has "
                                          r"hash 0{32}, the definition evcal decodes has"):
        open_recording(_write(tmp_path, "ros1", fill))


def test_unsupported_image_encoding(tmp_path: Path) -> None:
    def fill(bag: _Bag) -> None:
        bag.add("/image", IMAGE)
        img = np.zeros((H, W, 2), np.uint8)
        bag.write("/image", bag.image(1000, img, encoding="yuv422"), 1)

    with pytest.raises(RosbagError, match=r"topic /image message 0: image encoding 'yuv422' is "
                                          r"not one evcal reads \(mono8, mono16, rgb8, bgr8\)"):
        open_recording(_write(tmp_path, "ros2-mcap", fill))


def test_topic_options_are_for_bags_only(tmp_path: Path) -> None:
    from evcal.io import write_recording
    from evcal.recording import Recording

    path = write_recording(Recording(SensorSize(height=H, width=W), _events(5, seed=1)),
                           tmp_path / "r.npz")
    with pytest.raises(RecordingError, match="events_topic/frames_topic choose topics of ROS "
                                             "bags; this is a recording of kind 'npz'"):
        open_recording(path, events_topic="/events")


def test_evcal_mcap_is_still_evcal_mcap(tmp_path: Path) -> None:
    from evcal.io import write_recording
    from evcal.recording import Recording

    rec = Recording(SensorSize(height=H, width=W), _events(5, seed=1))
    path = write_recording(rec, tmp_path / "r.mcap")
    assert sniff(path) == "mcap"
    (tmp_path / "db.db3").write_bytes(b"SQLite format 3\x00" + b"\x00" * 100)
    assert sniff(tmp_path / "db.db3") == "rosbag2"
    with pytest.raises(RosbagError, match=r"db\.db3: cannot open as a ROS bag"):
        open_recording(tmp_path / "db.db3")
    (tmp_path / "x.bag").write_bytes(b"#ROSBAG V2.0\n" + b"\x00" * 10)
    assert sniff(tmp_path / "x.bag") == "rosbag1"
    with pytest.raises(RosbagError, match=r"x\.bag: cannot open as a ROS bag"):
        open_recording(tmp_path / "x.bag")


# ------------------------------------------------------------------ frames


def _image_msg(data: np.ndarray, encoding: str, h: int, w: int, step: int,
               big: bool = False) -> SimpleNamespace:
    return SimpleNamespace(height=h, width=w, step=step, encoding=encoding, is_bigendian=big,
                           data=data.view(np.uint8).reshape(-1))


def test_image_conversions_to_gray() -> None:
    rgb = np.array([[[255, 0, 0], [0, 255, 0], [0, 0, 255], [10, 20, 30]]], np.uint8)
    luma = np.rint(rgb.astype(float) @ [0.299, 0.587, 0.114]).astype(np.uint8)
    np.testing.assert_array_equal(image_to_gray(_image_msg(rgb, "rgb8", 1, 4, 12)), luma)
    np.testing.assert_array_equal(
        image_to_gray(_image_msg(np.ascontiguousarray(rgb[:, :, ::-1]), "bgr8", 1, 4, 12)), luma)
    mono16 = np.array([[0, 257, 65535]], "<u2")
    out = image_to_gray(_image_msg(mono16, "mono16", 1, 3, 6))
    assert out.dtype == np.float32
    np.testing.assert_array_equal(out, [[0.0, 1.0, 255.0]])
    out = image_to_gray(_image_msg(mono16.astype(">u2"), "mono16", 1, 3, 6, big=True))
    np.testing.assert_array_equal(out, [[0.0, 1.0, 255.0]])
    # rows padded to a longer step
    padded = np.array([[1, 2, 3, 99], [4, 5, 6, 99]], np.uint8)
    np.testing.assert_array_equal(image_to_gray(_image_msg(padded, "mono8", 2, 3, 4)),
                                  [[1, 2, 3], [4, 5, 6]])
    with pytest.raises(PayloadError, match="image data has 7 bytes, 2 rows of step 4 need 8"):
        image_to_gray(_image_msg(padded.reshape(-1)[:7], "mono8", 2, 3, 4))


# ------------------------------------------------------------------ payload decoders


def _words16(*pairs: tuple[int, int]) -> np.ndarray:
    return np.array([(code << 12) | value for code, value in pairs], "<u2").view(np.uint8)


def test_libcaer_cmp_decoder_on_handmade_words() -> None:
    """Codes (event_camera_codecs libcaer_cmp_types.h): TIME_HIGH 0, TIME_LOW 1, ADDR_X 2,
    ADDR_Y 3 (bit 11 polarity), VECT_BASE_Y 4, VECT_8 5."""
    dec = LibcaerCmpDecoder()
    base_us = 1_000_000_000
    first = _words16((0, 1), (1, 5), (2, 100), (3, 7 | 1 << 11),   # (100, 7, ON)
                     (4, 20), (5, 0b11),                          # (100, 20/21, OFF)
                     (5, 0b1000_0000),                             # (100, 28 + 7, OFF)
                     (2, 400), (3, 1 | 1 << 11),                   # x = 400: outside
                     (2, 200))
    pk = dec.decode(first, time_base=base_us * 1000, width=346, height=260, stamp_ns=0)
    assert pk.x.tolist() == [100, 100, 100, 100]
    assert pk.y.tolist() == [7, 20, 21, 35]
    assert pk.on.tolist() == [True, False, False, False]
    assert (pk.t_us - base_us).tolist() == [4096 + 5] * 4
    assert pk.dropped == 1
    # the next packet: time starts from 0 again, x, the vector base and polarity carry over
    pk = dec.decode(_words16((1, 9), (5, 0b1)), time_base=base_us * 1000, width=346,
                    height=260, stamp_ns=0)
    assert (pk.x.tolist(), pk.y.tolist(), pk.on.tolist()) == ([200], [36], [False])
    assert (pk.t_us - base_us).tolist() == [9]
    with pytest.raises(PayloadError, match=r"word 1 has code 6 \(VECT_12"):
        dec.decode(_words16((1, 0), (6, 1)), time_base=0, width=346, height=260, stamp_ns=0)
    with pytest.raises(PayloadError, match="payload of 3 bytes is not a whole number of 2-byte"
                       ) as info:
        dec.decode(np.zeros(3, np.uint8), time_base=0, width=346, height=260, stamp_ns=0)
    assert info.value.reason == ErrorReason.TRUNCATED


def test_libcaer_cmp_time_base_in_us_is_recognised() -> None:
    # event_camera_codecs' 2023 test data: time_base in µs; the 2025 data (shared bag): ns
    stamp_ns = 1_702_669_729_864_452_000
    dec = LibcaerCmpDecoder()
    pk = dec.decode(_words16((1, 3), (2, 1), (3, 1)), time_base=stamp_ns // 1000,
                    width=4, height=4, stamp_ns=stamp_ns)
    assert dec.time_base_unit == "us"
    assert pk.t_us.tolist() == [stamp_ns // 1000 + 3]
    dec = LibcaerCmpDecoder()
    pk = dec.decode(_words16((1, 3), (2, 1), (3, 1)), time_base=stamp_ns, width=4, height=4,
                    stamp_ns=stamp_ns)
    assert dec.time_base_unit == "ns"
    assert pk.t_us.tolist() == [stamp_ns // 1000 + 3]


def test_libcaer_decoder_overflow_inside_a_packet() -> None:
    rec = np.array([((5 << 17) | (6 << 2) | (1 << 1) | 1, 2**31 - 2),
                    ((7 << 17) | (8 << 2) | 1, 3)], [("data", "<u4"), ("ts", "<i4")])
    pk = LibcaerDecoder().decode(rec.view(np.uint8), time_base=10_999, width=10, height=10,
                                 stamp_ns=0)
    assert pk.t_us.tolist() == [10 + 2**31 - 2, 10 + 2**31 + 3]
    assert (pk.x.tolist(), pk.y.tolist(), pk.on.tolist()) == ([5, 7], [6, 8], [True, False])
    rec["ts"][1] = -1
    with pytest.raises(PayloadError, match="libcaer event 1 has a negative timestamp -1"):
        LibcaerDecoder().decode(rec.view(np.uint8), time_base=0, width=10, height=10,
                                stamp_ns=0)


def test_mono_decoder() -> None:
    words = np.array([(1 << 63) | (3 << 48) | (2 << 32) | 1500, (4 << 48) | (5 << 32) | 2600],
                     "<u8")
    pk = MonoDecoder().decode(words.view(np.uint8), time_base=999_700, width=10, height=10,
                              stamp_ns=0)
    assert pk.t_us.tolist() == [(999_700 + 1500) // 1000, (999_700 + 2600) // 1000]
    assert (pk.x.tolist(), pk.y.tolist(), pk.on.tolist()) == ([2, 5], [3, 4], [True, False])


def test_evt3_decoder_state_and_wrap_carry_across_packets() -> None:
    """Codes (event_camera_codecs evt3_types.h): ADDR_Y 0, ADDR_X 2 (bit 11 polarity),
    VECT_BASE_X 3, VECT_12 4, VECT_8 5, TIME_LOW 6, TIME_HIGH 8, EXT_TRIGGER 10."""
    dec = Evt3Decoder()
    kw: dict[str, int] = {"time_base": 0, "width": 640, "height": 480, "stamp_ns": 0}
    first = _words16((0, 9), (2, 1),                   # before a valid time: ignored
                     (8, 0xFFE), (6, 0x010),            # time = 0xFFE << 12 | 0x10
                     (0, 7), (2, 3 | 1 << 11),          # (3, 7, ON)
                     (3, 10), (4, 0b1000_0000_0101),    # x = 10, 12, 21 (OFF)
                     (5, 0b1000_0001),                  # x = 22, 29 (OFF)
                     (10, 1))                           # a trigger edge
    pk = dec.decode(first, **kw)
    t1 = 0xFFE << 12 | 0x010
    assert pk.x.tolist() == [3, 10, 12, 21, 22, 29]
    assert pk.y.tolist() == [7] * 6
    assert pk.on.tolist() == [True] + [False] * 5
    assert pk.t_us.tolist() == [t1] * 6
    assert pk.trigger_t_us.tolist() == [t1]
    # next packet: TIME_HIGH 0x001 after 0xFFE is the 24-bit wrap (+2^24 µs); a step back of
    # at most 10 (0x001 -> 0x000) is a sensor bit error, not a wrap; y, the vector base (30)
    # and its polarity carry over
    second = _words16((8, 0x001), (6, 0x002), (2, 4),
                      (8, 0x000), (5, 0b1))
    pk = dec.decode(second, **kw)
    assert pk.t_us.tolist() == [2**24 + (1 << 12 | 2), 2**24 + 2]
    assert (pk.x.tolist(), pk.y.tolist(), pk.on.tolist()) == ([4, 30], [7, 7], [False, False])
    with pytest.raises(PayloadError, match=r"evt3 word 1 has code 1 \(no EVT3 meaning\)"):
        dec.decode(_words16((6, 0), (1, 0)), **kw)


def test_evt3_needs_time_high_then_low_in_one_packet() -> None:
    dec = Evt3Decoder()
    kw: dict[str, int] = {"time_base": 0, "width": 640, "height": 480, "stamp_ns": 0}
    assert dec.decode(_words16((6, 1), (2, 1), (8, 2)), **kw).t_us.size == 0
    pk = dec.decode(_words16((2, 1), (8, 2), (6, 3), (2, 5)), **kw)
    assert pk.x.tolist() == [5]
    assert pk.t_us.tolist() == [2 << 12 | 3]


def test_make_decoder_names_the_encodings() -> None:
    for enc in ("libcaer_cmp", "libcaer", "evt3", "mono"):
        assert make_decoder(enc).encoding == enc
    with pytest.raises(PayloadError, match="'trigger' is not one evcal decodes"):
        make_decoder("trigger")
