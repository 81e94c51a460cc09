"""ROS 2 over rmw_zenoh without a network: keys, tokens, attachments, the topic -> camera
map, the per-camera CDR decoder, and a service fed ROS 2 samples in-process (its calibration
also out as Images, its rejections counted and published like the wire's)."""

from __future__ import annotations

import json
import threading

import numpy as np
import pytest

from evcal.errors import ErrorReason, EvcalError
from evcal.events import SensorSize
from evcal.io.evencode import encode_packet
from evcal.io.ros2msg import event_packet_cdr, image_cdr, recording_messages, ros2_store
from evcal.io.rosbag import EVENT_PACKET, IMAGE, RosbagError
from evcal.online import OnEIConfig
from evcal.recording import Frames, Recording
from evcal.service import keys
from evcal.service.core import Service, ServiceConfig
from evcal.service.ros2 import (
    QOS,
    SPECIAL_SCALE,
    RosDecoder,
    RosNode,
    RosRouter,
    RosSample,
    TopicMap,
    dds_type,
    decode_attachment,
    encode_attachment,
    parse_topic_key,
    ros_type,
    subscription_keys,
    topic_key,
)
from evcal.service.ros2out import RosCalibrationPublisher, output_topic, ros_name
from evcal.sim.ideal import SimConfig, simulate_ideal
from evcal.testing import settle as _settle

IMAGE_HASH = "RIHS01_d31d41a9a4c4bc8eae9be757b0beed306564f7526c88ea6a4588fb9582527d47"


# ----------------------------------------------------------------------------- keys, tokens


def test_type_names_and_topic_keys() -> None:
    assert dds_type(EVENT_PACKET) == "event_camera_msgs::msg::dds_::EventPacket_"
    assert ros_type(dds_type(IMAGE)) == IMAGE
    assert ros_type("std_msgs::msg::String") is None
    key = topic_key(3, "/lab/cam0/image_raw/", IMAGE)
    assert key == f"3/lab/cam0/image_raw/sensor_msgs::msg::dds_::Image_/{IMAGE_HASH}"
    parsed = parse_topic_key(key)
    assert parsed is not None
    assert (parsed.domain, parsed.topic, parsed.msgtype, parsed.type_hash) == (
        3, "/lab/cam0/image_raw", IMAGE, IMAGE_HASH)
    assert parse_topic_key("evcal/cam0/events") is None
    assert parse_topic_key("0/x/not_a_dds_type/h") is None


def test_subscription_keys_match_any_topic_and_hash() -> None:
    zenoh = pytest.importorskip("zenoh")
    sub = subscription_keys(0)
    hit = [topic_key(0, "/a/b/c/events", EVENT_PACKET, "TypeHashNotSupported"),
           topic_key(0, "/image_raw", IMAGE)]
    miss = [topic_key(1, "/a/events", EVENT_PACKET), "evcal/a/events",
            topic_key(0, "/a/b", "std_msgs/msg/String")]
    for key in hit:
        assert any(zenoh.KeyExpr(s).intersects(key) for s in sub), key
    for key in miss:
        assert not any(zenoh.KeyExpr(s).intersects(key) for s in sub), key


def test_attachment_is_zenoh_serialization_of_seq_time_gid() -> None:
    ext = pytest.importorskip("zenoh.ext")
    gid = bytes(range(16))
    ours = encode_attachment(41, 1_744_227_144_000_000_123, gid)
    theirs = ext.z_serialize((ext.Int64(41), ext.Int64(1_744_227_144_000_000_123), gid))
    assert ours == theirs.to_bytes()
    assert len(ours) == 33
    att = decode_attachment(ours)
    assert att is not None
    assert (att.seq, att.t_ns, att.gid) == (41, 1_744_227_144_000_000_123, gid)
    for junk in (None, b"", ours[:-1], ours[:16] + b"\x11" + ours[17:]):
        assert decode_attachment(junk) is None
    # the layout of rmw_zenoh's first zenoh-1.0 releases: each field after its name
    named = ext.z_serialize(("sequence_number", ext.Int64(7), "source_timestamp",
                             ext.Int64(-5), "source_gid", gid)).to_bytes()
    att = decode_attachment(named)
    assert att is not None
    assert (att.seq, att.t_ns, att.gid) == (7, -5, gid)
    assert decode_attachment(named.replace(b"source_gid", b"source_gix")) is None


def test_liveliness_tokens_have_rmw_zenohs_layout() -> None:
    node = RosNode(zid="a1b2", domain=7)
    assert node.node_token() == "@ros2_lv/7/a1b2/0/0/NN/%/%/evcal"
    token, gid = node.entity("MP", "/lab/cam0/calibration/contrast", IMAGE)
    chunks = token.split("/")
    assert len(chunks) == 13
    assert chunks[:9] == ["@ros2_lv", "7", "a1b2", "0", "1", "MP", "%", "%", "evcal"]
    assert chunks[9:] == ["%lab%cam0%calibration%contrast", dds_type(IMAGE), IMAGE_HASH, QOS]
    assert len(gid) == 16
    token2, gid2 = node.entity("MS", "/x/events", EVENT_PACKET)
    assert token2.split("/")[4:6] == ["2", "MS"]
    assert gid2 != gid
    with pytest.raises(ValueError, match="MP or MS"):
        node.entity("XX", "/a", IMAGE)


def test_topic_map_default_explicit_and_namespace_rules() -> None:
    m = TopicMap()
    assert m.camera("/event_camera/events", "events") == "event_camera"
    assert m.camera("/lab/rig1/cam0/image_raw", "frames") == "lab/rig1/cam0"
    assert m.camera("/lab/rig1/cam0/depth", "frames") is None  # not an image* name
    assert m.camera("/lab/cam0/calibration/contrast", "frames") is None  # evcal's own output
    assert m.camera("/events", "events") is None  # no namespace: needs a map entry
    m = TopicMap.parse(["/dvs=lab/cam0", "/dvs/left/events=stereo/left",
                        "/events=solo", "/cam/aps=solo"])
    assert m.camera("/dvs/events", "events") == "lab/cam0"
    assert m.camera("/dvs/image_raw", "frames") == "lab/cam0"
    assert m.camera("/dvs/left/events", "events") == "stereo/left"  # the longest entry wins
    assert m.camera("/events", "events") == "solo"
    assert m.camera("/cam/aps", "frames") == "solo"  # an exact topic needs no image* name
    assert m.camera("/dvs/depth", "frames") is None
    for bad in ("/a", "=cam", "/a=", "/a=bad*id"):
        with pytest.raises(ValueError, match="ros-topic-map"):
            TopicMap.parse([bad])


def test_ros_names_of_camera_ids() -> None:
    assert ros_name("lab/rig1/cam0") == "/lab/rig1/cam0"
    assert ros_name("lab-1/0cam.x") == "/lab_1/_0cam_x"
    assert output_topic("cam0", "bias") == "/cam0/calibration/bias"


# ----------------------------------------------------------------------------- decoding

H, W = 30, 40


def _packet(seq: int, n: int = 500, t0: int = 10**15, encoding: str = "libcaer_cmp",
            h: int = H, w: int = W) -> tuple[bytes, np.ndarray]:
    rng = np.random.default_rng(seq)
    ev = np.zeros(n, dtype=[("t_us", "<i8"), ("x", "<u2"), ("y", "<u2"), ("p", "i1")])
    ev["t_us"] = np.sort(rng.integers(t0, t0 + 5_000, n))
    ev["x"] = rng.integers(0, W, n)
    ev["y"] = rng.integers(0, H, n)
    ev["p"] = rng.choice(np.array([-1, 1], np.int8), n)
    cdr = event_packet_cdr(encode_packet(ev, encoding), encoding=encoding, seq=seq,
                           time_base_ns=int(ev["t_us"][0]) * 1000, t_ns=t0 * 1000, height=h,
                           width=w, frame_id="cam")
    return cdr, ev


def test_decoder_events_frames_and_restart() -> None:
    dec = RosDecoder()
    cdr, ev = _packet(5)
    out, header = dec.decode("events", RosSample(cdr, EVENT_PACKET, "/c/events"))
    np.testing.assert_array_equal(out, ev)
    assert header == {"seq": 5, "height": H, "width": W, "n": ev.size}
    # a driver restart (seq back) with another encoding starts a fresh payload decoder
    cdr, ev = _packet(0, encoding="mono", t0=10**15 + 10**6)
    out, header = dec.decode("events", RosSample(cdr, EVENT_PACKET, "/c/events"))
    np.testing.assert_array_equal(out, ev)
    image = np.arange(H * W, dtype=np.uint8).reshape(H, W)
    raw = image_cdr(image, t_ns=1_234_567_891, frame_id="c", encoding="mono8")
    t_us, exposure_us, gray, header = dec.decode("frames", RosSample(raw, IMAGE, "/c/image",
                                                                     seq=9))
    assert (t_us, exposure_us) == (1_234_567, 0)
    np.testing.assert_array_equal(gray, image)
    assert header == {"seq": 9, "height": H, "width": W, "dtype": "uint8"}


def test_decoder_refusals_name_topic_and_reason() -> None:
    dec = RosDecoder()
    good, _ = _packet(1)
    cases = {
        ErrorReason.TRUNCATED: RosSample(good[:60], EVENT_PACKET, "/c/events"),
        ErrorReason.OUT_OF_RANGE: RosSample(_packet(2, w=0)[0], EVENT_PACKET, "/c/events"),
    }
    for reason, sample in cases.items():
        with pytest.raises(EvcalError, match="ROS 2 topic /c/events") as info:
            dec.decode("events", sample)
        assert info.value.reason == reason
    store = ros2_store()
    msg = store.deserialize_cdr(good, EVENT_PACKET)
    msg.encoding = "evt2"
    with pytest.raises(EvcalError, match="'evt2' is not one evcal decodes") as info:
        dec.decode("events", RosSample(bytes(store.serialize_cdr(msg, EVENT_PACKET)),
                                       EVENT_PACKET, "/d/events"))
    assert info.value.reason == ErrorReason.MALFORMED
    msg = store.deserialize_cdr(good, EVENT_PACKET)
    msg.events = msg.events[:-1]  # libcaer_cmp is 16-bit words
    with pytest.raises(EvcalError, match="not a whole number") as info:
        dec.decode("events", RosSample(bytes(store.serialize_cdr(msg, EVENT_PACKET)),
                                       EVENT_PACKET, "/e/events"))
    assert info.value.reason == ErrorReason.TRUNCATED
    img = store.deserialize_cdr(image_cdr(np.zeros((2, 2), np.uint8), t_ns=0, frame_id="",
                                          encoding="mono8"), IMAGE)
    img.encoding = "yuv422"
    with pytest.raises(EvcalError, match="yuv422") as info:
        dec.decode("frames", RosSample(bytes(store.serialize_cdr(img, IMAGE)), IMAGE, "/c/i"))
    assert info.value.reason == ErrorReason.MALFORMED
    with pytest.raises(RosbagError):
        dec.decode("frames", RosSample(b"\x00\x01\x00\x00junk", IMAGE, "/c/i"))


# ----------------------------------------------------------------------------- the service


class Puts:
    """A transport's ``put`` and ``token`` for the service and the ROS publisher."""

    def __init__(self) -> None:
        self.items: list[tuple[str, bytes, bytes | None]] = []
        self.tokens: list[str] = []
        self.lock = threading.Lock()

    def put(self, key: str, payload: bytes, enc: str, *, attachment: bytes | None = None
            ) -> None:
        with self.lock:
            self.items.append((key, payload, attachment))

    def on(self, prefix: str) -> list[tuple[str, bytes, bytes | None]]:
        with self.lock:
            return [i for i in self.items if i[0].startswith(prefix)]


def _ros_service() -> tuple[Service, RosRouter, RosCalibrationPublisher, Puts]:
    puts = Puts()
    node = RosNode(zid="feed", domain=0)
    ros_out = RosCalibrationPublisher(node, puts.put, puts.tokens.append)
    cfg = ServiceConfig(onei=OnEIConfig(n_small=4000, n_large=10**7, log_offset=30.0,
                                        window_frames=5), error_rate_hz=1000)
    svc = Service(cfg, puts.put, on_update=ros_out.publish)
    return svc, RosRouter(node, svc.deliver), ros_out, puts


def test_service_calibrates_from_ros_samples_and_publishes_images() -> None:
    sim = simulate_ideal(SimConfig(height=H, width=W, duration_s=1.5, seed=3))
    svc, router, ros_out, puts = _ros_service()
    try:
        seqs: dict[str, int] = {}
        for m in recording_messages(sim.recording, namespace="/lab/cam0"):
            seqs[m.topic] = seqs.get(m.topic, 0) + 1
            router.on_sample(topic_key(0, m.topic, m.msgtype), m.data, "",
                             encode_attachment(seqs[m.topic], 0, bytes(16)))
        _settle(svc)
        cam = svc.cameras["lab/cam0"]
        assert cam.counters.events == sim.recording.n_events
        assert cam.counters.frames == len(sim.recording.frames)
        assert cam.counters.errors == {}
        assert cam.counters.updates >= 1
        assert cam.counters.lost == {"events": 0, "frames": 0}
        # the same update on evcal's key and as three ROS 2 Images
        assert ros_out.published == cam.counters.updates
        cal = cam.state.calibration
        store = ros2_store()
        latest = {}
        for key, data, att in puts.on("0/lab/cam0/calibration/"):
            parsed = parse_topic_key(key)
            assert parsed is not None
            assert parsed.msgtype == IMAGE
            assert decode_attachment(att) is not None
            latest[parsed.topic.rpartition("/")[2]] = store.deserialize_cdr(data, IMAGE)
        assert set(latest) == {"contrast", "bias", "special"}
        for name in ("contrast", "bias"):
            msg = latest[name]
            assert (msg.encoding, msg.height, msg.width) == ("32FC1", H, W)
            got = np.frombuffer(msg.data.tobytes(), "<f4").reshape(H, W)
            np.testing.assert_array_equal(got, getattr(cal, name).astype(np.float32))
        special = latest["special"]
        assert special.encoding == "mono8"
        np.testing.assert_array_equal(special.data.reshape(H, W) // SPECIAL_SCALE, cal.special)
        t_ns = special.header.stamp.sec * 10**9 + special.header.stamp.nanosec
        assert t_ns == cam.state.calibration_t_us * 1000
        svc.tick(force=True)
        status = json.loads([p for k, p, _ in puts.on("evcal/lab/cam0/status")][-1])
        assert status["ros2"]["messages"] == {"/lab/cam0/events": seqs["/lab/cam0/events"],
                                              "/lab/cam0/image_raw": len(sim.recording.frames)}
        assert status["ros2"]["encodings"] == {"/lab/cam0/events": "libcaer_cmp"}
        assert status["ros2"]["dropped_events"] == 0
        assert len(puts.tokens) == 3  # the three publications' liveliness tokens
        assert router.declare_pending(puts.tokens.append) == 2  # events and image_raw: MS
        assert all("/MS/" in t for t in puts.tokens[3:])
    finally:
        svc.close()


def test_bad_ros_input_is_counted_and_published_per_camera() -> None:
    svc, router, _, puts = _ros_service()
    try:
        key = topic_key(0, "/bad/cam/events", EVENT_PACKET)
        good, _ = _packet(0)
        router.on_sample(key, good, "", None)
        router.on_sample(key, good[:50], "", None)  # cut CDR
        router.on_sample(key, _packet(1, h=H + 1, t0=10**15 + 10**4)[0], "", None)  # size
        router.on_sample(topic_key(0, "/events", EVENT_PACKET), good, "", None)  # no camera
        _settle(svc)
        cam = svc.cameras["bad/cam"]
        assert cam.counters.errors == {"truncated": 1, "sensor_changed": 1}
        assert cam.counters.events == 500
        errors = [json.loads(p) for k, p, _ in puts.on(keys.camera_key("evcal", "bad/cam",
                                                                         "errors"))]
        assert {e["reason"] for e in errors} == {"truncated", "sensor_changed"}
        assert any("ROS 2 topic /bad/cam/events" in e["message"] for e in errors)
        assert set(svc.cameras) == {"bad/cam"}
        assert sum(router.ignored.values()) == 1
    finally:
        svc.close()


def test_frames_lost_from_the_attachment_sequence() -> None:
    svc, router, _, _ = _ros_service()
    try:
        key = topic_key(0, "/c/image_raw", IMAGE)
        for i, seq in enumerate((1, 2, 5, 6)):
            raw = image_cdr(np.full((H, W), 100, np.uint8), t_ns=(i + 1) * 40_000_000,
                            frame_id="c", encoding="mono8")
            router.on_sample(key, raw, "", encode_attachment(seq, 0, bytes(16)))
        _settle(svc)
        cam = svc.cameras["c"]
        assert cam.counters.frames == 4
        assert cam.counters.lost["frames"] == 2
        assert cam.sensor == SensorSize(H, W)
    finally:
        svc.close()


def test_event_packet_seq_gaps_are_lost_messages() -> None:
    svc, router, _, _ = _ros_service()
    try:
        key = topic_key(0, "/g/events", EVENT_PACKET)
        for seq in (10, 11, 14):
            router.on_sample(key, _packet(seq, t0=10**15 + seq * 10_000)[0], "", None)
        _settle(svc)
        cam = svc.cameras["g"]
        assert cam.counters.lost["events"] == 2
        assert cam.counters.errors == {}
    finally:
        svc.close()


def test_a_recording_with_float_frames_still_feeds_the_service() -> None:
    # mono16 frames (float frames written at 257 x the 8-bit scale) come back as float32
    rng = np.random.default_rng(0)
    f_t = np.arange(0, 400_001, 40_000, dtype=np.int64)
    ev = np.zeros(2000, dtype=[("t_us", "<i8"), ("x", "<u2"), ("y", "<u2"), ("p", "i1")])
    ev["t_us"] = np.sort(rng.integers(0, 400_000, ev.size))
    ev["x"], ev["y"] = rng.integers(0, W, ev.size), rng.integers(0, H, ev.size)
    ev["p"] = 1
    rec = Recording(sensor=SensorSize(H, W), events=ev,
                    frames=Frames(t_us=f_t, images=rng.uniform(0, 255, (f_t.size, H, W)),
                                  exposure_us=np.zeros(f_t.size, np.int64)))
    svc, router, _, _ = _ros_service()
    try:
        for m in recording_messages(rec, namespace="/f"):
            router.on_sample(topic_key(0, m.topic, m.msgtype), m.data, "", None)
        _settle(svc)
        cam = svc.cameras["f"]
        assert cam.counters.errors == {}
        assert cam.counters.frames == f_t.size
        assert cam.state.frame_dtype == np.float32
    finally:
        svc.close()


def test_serve_ros2_flags(monkeypatch: pytest.MonkeyPatch) -> None:
    from evcal.service.cli import build_parser, ros2_from_args

    p = build_parser()
    monkeypatch.delenv("ROS_DOMAIN_ID", raising=False)
    assert ros2_from_args(p.parse_args([])) is None
    with pytest.raises(ValueError, match="go with --ros2"):
        ros2_from_args(p.parse_args(["--ros-domain", "3"]))
    opts = ros2_from_args(p.parse_args(["--ros2"]))
    assert opts is not None
    assert opts.domain == 0
    monkeypatch.setenv("ROS_DOMAIN_ID", "5")
    opts = ros2_from_args(p.parse_args(["--ros2", "--ros-topic-map", "/dvs=lab/cam0"]))
    assert opts is not None
    assert opts.domain == 5
    assert opts.topic_map.camera("/dvs/events", "events") == "lab/cam0"
    opts = ros2_from_args(p.parse_args(["--ros2", "--ros-domain", "2"]))
    assert opts is not None
    assert opts.domain == 2
    with pytest.raises(ValueError, match="0..232"):
        ros2_from_args(p.parse_args(["--ros2", "--ros-domain", "999"]))
    monkeypatch.setenv("ROS_DOMAIN_ID", "x")
    with pytest.raises(ValueError, match="ROS_DOMAIN_ID"):
        ros2_from_args(p.parse_args(["--ros2"]))
