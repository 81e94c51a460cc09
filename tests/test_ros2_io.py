"""What evcal writes for ROS 2: EventPacket payload encoders against the decoders, the CDR of
Images and EventPackets, and ROS 2 MCAP files read back by rosbags, the bag reader and
``evcal info``."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from evcal.errors import ErrorReason
from evcal.events import EVENTS_DTYPE, SensorSize
from evcal.io import open_recording
from evcal.io._evcodecs import PayloadError, make_decoder
from evcal.io.evencode import ENCODERS, encode_packet, packets
from evcal.io.ros2msg import (
    Ros2McapWriter,
    event_packet_cdr,
    image_cdr,
    message_definition,
    recording_messages,
    ros2_store,
    type_hash,
    write_ros2_bag,
)
from evcal.io.rosbag import EVENT_PACKET, IMAGE, image_to_gray
from evcal.recording import Frames, Recording


def _events(n: int, seed: int, *, t0: int = 1_744_227_144_000_000, span_us: int = 30_000,
            w: int = 346, h: int = 260) -> np.ndarray:
    rng = np.random.default_rng(seed)
    ev = np.empty(n, EVENTS_DTYPE)
    ev["t_us"] = np.sort(rng.integers(t0, t0 + span_us, n))
    ev["x"] = rng.integers(0, w, n)
    ev["y"] = rng.integers(0, h, n)
    ev["p"] = rng.choice(np.array([-1, 1], np.int8), n)
    return ev


def _decode_all(encoding: str, ev: np.ndarray, frame_t: np.ndarray | None = None,
                **kw: int) -> np.ndarray:
    dec = make_decoder(encoding)
    out = []
    for pk in packets(ev, frame_t, encoding=encoding, **kw):
        r = dec.decode(np.frombuffer(pk.payload, np.uint8), time_base=pk.time_base_ns,
                       width=346, height=260, stamp_ns=pk.time_base_ns)
        assert r.dropped == 0
        chunk = np.empty(r.t_us.size, EVENTS_DTYPE)
        chunk["t_us"], chunk["x"], chunk["y"] = r.t_us, r.x, r.y
        chunk["p"] = np.where(r.on, 1, -1)
        out.append(chunk)
    return np.concatenate(out) if out else np.zeros(0, EVENTS_DTYPE)


@pytest.mark.parametrize("encoding", ENCODERS)
def test_encoders_round_trip_through_the_decoders(encoding: str) -> None:
    # stateful decoders over many packets: x and the vector state carry across packets
    ev = _events(50_000, seed=1, span_us=2_000_000)
    frame_t = ev["t_us"][[100, 20_000, 20_001, 40_000]]
    out = _decode_all(encoding, ev, frame_t, packet_us=7_000, max_events=3_000)
    np.testing.assert_array_equal(out, ev)


@settings(max_examples=40, deadline=None)
@given(n=st.integers(0, 400), seed=st.integers(0, 2**32 - 1),
       span=st.integers(1, 40_000_000), encoding=st.sampled_from(ENCODERS))
def test_decode_of_encode_is_identity(n: int, seed: int, span: int, encoding: str) -> None:
    ev = _events(n, seed, span_us=span)
    np.testing.assert_array_equal(_decode_all(encoding, ev, packet_us=1_000_000), ev)


def test_packets_never_span_a_frame_time() -> None:
    ev = _events(5_000, seed=2, span_us=100_000)
    frame_t = np.array([int(ev["t_us"][1000]), int(ev["t_us"][3000]) + 1])
    for pk in packets(ev, frame_t, encoding="mono", packet_us=10_000_000):
        t = ev["t_us"][pk.i0:pk.i1]
        for f in frame_t:
            assert not (t[0] < f <= t[-1]), "an event before and one at/after a frame time"


def test_encoder_refusals_are_specific() -> None:
    ev = _events(10, seed=3)
    with pytest.raises(PayloadError, match="not 'evt2'") as info:
        encode_packet(ev, "evt2")
    assert info.value.reason == ErrorReason.MALFORMED
    long = _events(10, seed=3)
    long["t_us"][-1] = long["t_us"][0] + (1 << 24)  # 16.8 s after the first
    with pytest.raises(PayloadError, match="spans"):
        encode_packet(long, "libcaer_cmp")
    wide = ev.copy()
    wide["x"][0] = 2048
    with pytest.raises(PayloadError, match="below 2048"):
        encode_packet(wide, "libcaer_cmp")
    with pytest.raises(PayloadError, match="sorted"):
        encode_packet(ev[::-1], "mono")


@pytest.mark.parametrize(("encoding", "image"), [
    ("mono8", np.arange(12, dtype=np.uint8).reshape(3, 4)),
    ("mono16", np.arange(12, dtype=np.uint16).reshape(3, 4) * 5000),
    ("32FC1", np.linspace(-1, 1, 12, dtype=np.float32).reshape(3, 4)),
])
def test_image_cdr_reads_back(encoding: str, image: np.ndarray) -> None:
    raw = image_cdr(image, t_ns=1_500_000_123, frame_id="cam", encoding=encoding)
    msg = ros2_store().deserialize_cdr(raw, IMAGE)
    assert (msg.height, msg.width, msg.encoding, msg.step) == (3, 4, encoding,
                                                                 4 * image.itemsize)
    assert (msg.header.stamp.sec, msg.header.stamp.nanosec) == (1, 500_000_123)
    got = np.frombuffer(msg.data.tobytes(), image.dtype.newbyteorder("<")).reshape(3, 4)
    np.testing.assert_array_equal(got, image)
    if encoding != "32FC1":
        gray = image_to_gray(msg)
        expected = image if encoding == "mono8" else image.astype(np.float32) / 257.0
        np.testing.assert_allclose(gray, expected)


def test_event_packet_cdr_and_negative_stamps() -> None:
    ev = _events(100, seed=4)
    payload = encode_packet(ev, "mono")
    raw = event_packet_cdr(payload, encoding="mono", seq=7, time_base_ns=123, t_ns=-1,
                           height=260, width=346, frame_id="f")
    msg = ros2_store().deserialize_cdr(raw, EVENT_PACKET)
    assert (msg.seq, msg.time_base, msg.encoding, msg.width, msg.height) == (7, 123, "mono",
                                                                             346, 260)
    assert (msg.header.stamp.sec, msg.header.stamp.nanosec) == (-1, 999_999_999)
    assert bytes(msg.events) == payload


def test_type_hashes_and_definitions() -> None:
    # RIHS01 hashes as ROS 2 (Jazzy) reports them (`ros2 topic info -v`): rmw_zenoh's keys of
    # these types carry them, so a ROS 2 subscriber of evcal's Images matches exactly
    assert type_hash("std_msgs/msg/String") == (
        "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18")
    assert type_hash("std_msgs/msg/Header") == (
        "RIHS01_f49fb3ae2cf070f793645ff749683ac6b06203e41c891e17701b1cb597ce6a01")
    assert type_hash(IMAGE) == (
        "RIHS01_d31d41a9a4c4bc8eae9be757b0beed306564f7526c88ea6a4588fb9582527d47")
    assert type_hash(EVENT_PACKET).startswith("RIHS01_")  # computed alike (not published)
    text = message_definition(EVENT_PACKET)
    assert text.startswith("std_msgs/Header header\n")
    assert "\n" + "=" * 80 + "\nMSG: std_msgs/Header\n" in text
    assert "MSG: builtin_interfaces/Time" in text
    with pytest.raises(ValueError, match="not known"):
        message_definition("nope_msgs/msg/Nothing")


def _recording(seed: int = 5, float_frames: bool = False) -> Recording:
    rng = np.random.default_rng(seed)
    ev = _events(20_000, seed, t0=0, span_us=200_000, w=40, h=30)
    f_t = np.arange(0, 200_001, 40_000, dtype=np.int64)
    images = rng.integers(0, 256, (f_t.size, 30, 40)).astype(
        np.float32 if float_frames else np.uint8)
    return Recording(sensor=SensorSize(30, 40), events=ev,
                     frames=Frames(t_us=f_t, images=images,
                                   exposure_us=np.zeros(f_t.size, np.int64)))


@pytest.mark.parametrize("float_frames", [False, True])
def test_recording_as_a_ros2_bag_reads_back(tmp_path: Path, float_frames: bool) -> None:
    rec = _recording(float_frames=float_frames)
    path = write_ros2_bag(rec, tmp_path / "sim.mcap", namespace="/lab/cam0",
                          encoding="libcaer_cmp", packet_us=5_000)
    back = open_recording(path)
    assert back.sensor == rec.sensor
    assert back.metadata["events_topic"] == "/lab/cam0/events"
    assert back.metadata["frames_topic"] == "/lab/cam0/image_raw"
    assert back.metadata["frame_encoding"] == ("mono16" if float_frames else "mono8")
    assert back.metadata["lost_messages"] == 0
    np.testing.assert_array_equal(back.events, rec.events)
    np.testing.assert_array_equal(back.frames.t_us, rec.frames.t_us)
    np.testing.assert_allclose(back.frames.images, rec.frames.images, atol=0.5 / 257)
    # messages in time order, each frame after the events before it
    msgs = list(recording_messages(rec, namespace="/lab/cam0", packet_us=5_000))
    t = [m.t_ns for m in msgs]
    assert t == sorted(t)


def test_ros2_mcap_layout_is_what_foxglove_and_rosbag2_read(tmp_path: Path) -> None:
    from mcap.reader import make_reader
    from rosbags.rosbag2 import Reader

    rec = _recording()
    path = write_ros2_bag(rec, tmp_path / "x.mcap")
    with open(path, "rb") as f:
        reader = make_reader(f)
        assert reader.get_header().profile == "ros2"
        summary = reader.get_summary()
        assert summary is not None
        schemas = {s.name: s for s in summary.schemas.values()}
        assert set(schemas) == {EVENT_PACKET, IMAGE}
        assert {s.encoding for s in schemas.values()} == {"ros2msg"}
        assert schemas[IMAGE].data.decode() == message_definition(IMAGE)
        assert {c.message_encoding for c in summary.channels.values()} == {"cdr"}
        assert {c.metadata["topic_type_hash"] for c in summary.channels.values()} == {
            type_hash(EVENT_PACKET), type_hash(IMAGE)}
    with Reader(path) as bag:  # rosbags reads the definitions from the file itself
        n = sum(1 for _ in bag.messages())
        assert n == sum(1 for _ in recording_messages(rec))
    with Ros2McapWriter(tmp_path / "y.mcap") as out:
        out.add("/a", IMAGE, 0, image_cdr(np.zeros((2, 2), np.uint8), t_ns=0, frame_id="",
                                          encoding="mono8"))
        with pytest.raises(ValueError, match="carries"):
            out.add("/a", EVENT_PACKET, 1, b"")
    res = subprocess.run([sys.executable, "-m", "evcal", "info", str(path)],
                         capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr
    assert "40x30" in res.stdout
    assert "20000" in res.stdout


def test_bag_messages_come_out_as_cdr_from_ros1_and_ros2_bags(tmp_path: Path) -> None:
    from rosbags.rosbag1 import Writer as Writer1

    from evcal.io.rosbag import bag_topics, iter_bag_messages, typestore

    ev = _events(300, seed=6)
    cdr = event_packet_cdr(encode_packet(ev, "mono"), encoding="mono", seq=3,
                           time_base_ns=int(ev["t_us"][0]) * 1000, t_ns=5, height=260,
                           width=346, frame_id="cam")
    msg = ros2_store().deserialize_cdr(cdr, EVENT_PACKET)
    store1 = typestore(1)
    t1 = store1.types
    msg1 = t1[EVENT_PACKET](
        header=t1["std_msgs/msg/Header"](seq=0, stamp=t1["builtin_interfaces/msg/Time"](
            sec=0, nanosec=5), frame_id="cam"),
        height=260, width=346, seq=3, time_base=msg.time_base, encoding="mono",
        is_bigendian=False, events=msg.events)
    path1 = tmp_path / "x.bag"
    with Writer1(path1) as w:
        conn = w.add_connection("/cam/events", EVENT_PACKET, typestore=store1)
        w.write(conn, 42, store1.serialize_ros1(msg1, EVENT_PACKET))
    path2 = tmp_path / "x.mcap"
    with Ros2McapWriter(path2) as out:
        out.add("/cam/events", EVENT_PACKET, 42, cdr)
    for path in (path1, path2):
        assert bag_topics(path) == {"/cam/events": EVENT_PACKET}
        (m,) = list(iter_bag_messages(path))
        assert (m.topic, m.msgtype, m.t_ns) == ("/cam/events", EVENT_PACKET, 42)
        back = ros2_store().deserialize_cdr(m.data, EVENT_PACKET)
        assert (back.seq, back.encoding, bytes(back.events)) == (3, "mono", bytes(msg.events))
    assert list(iter_bag_messages(path2, topics={"/other"})) == []
