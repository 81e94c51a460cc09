"""rmw_zenoh across ROS 2 distributions, byte for byte, in both directions.

The fixtures are written out from rmw_zenoh_cpp's sources at the release tags of
github ros2-gbp/rmw_zenoh-release (``release/<distro>/rmw_zenoh_cpp/<version>-1``):

- data key (``TopicInfo``, ``liveliness_utils.cpp``): ``<domain>/<topic without its
  slashes>/<dds type>/<hash>``; Humble's ``rmw_publisher_data.cpp`` passes the hash string
  ``"TypeHashNotSupported"``, Jazzy and later ``rosidl_stringify_type_hash`` (RIHS01_...);
- liveliness token (``Entity``): ``@ros2_lv/<domain>/<zid>/<nid>/<id>/<MP|MS|NN>/<enclave>/
  <namespace>/<node>/<topic>/<type>/<hash>/<qos>``, names with ``/`` as ``%``; the QoS as
  ``qos_to_keyexpr`` writes it: a field only when it differs from ``QoS::default_qos()``
  (reliable, keep last 42, infinite durations, automatic liveliness, and TRANSIENT_LOCAL in
  0.1.0-0.1.1 and 0.2.0-0.2.2, VOLATILE from 0.1.2 and 0.2.3 on);
- GID: ``simplified_XXH3_128bits`` of the token, low then high 64-bit half;
- attachment (``attachment_helpers.cpp``, zenoh-cpp's ``ext::Serializer``): 0.1.2+, 0.2.4+,
  Kilted, Rolling 0.6+: int64 sequence number, int64 source timestamp, ``std::array<uint8_t,
  16>`` (a sequence: LEB128 length 16, then the bytes); 0.1.0-0.1.1 and 0.2.0-0.2.3: each of
  the three after its name as a string (LEB128 length, UTF-8). Each ``AttachmentData``
  constructor throws on the other layout.

"Out": what ``evcal serve --ros2`` publishes, read by an emulation of that distribution's
subscriber. "In": what that distribution's driver publishes, taken by evcal's router and
recognised by ``--ros-distro auto``. Last, the acceptance end to end: a live service
publishes images that a Humble-style and a Jazzy-0.2.3-style subscriber decode.
"""

from __future__ import annotations

import json
import struct
from dataclasses import dataclass
from typing import Any

import numpy as np
import pytest

xxhash = pytest.importorskip("xxhash")

from evcal.io.ros2msg import recording_messages, ros2_store  # noqa: E402
from evcal.io.rosbag import EVENT_PACKET, IMAGE  # noqa: E402
from evcal.service.ros2 import (  # noqa: E402
    DISTROS,
    OUTPUT_QOS,
    DistroDetector,
    RosNode,
    RosPublication,
    RosRouter,
    RosSample,
    TopicMap,
    encode_attachment,
)
from evcal.service.ros2out import output_topic  # noqa: E402

IMAGE_HASH = "RIHS01_d31d41a9a4c4bc8eae9be757b0beed306564f7526c88ea6a4588fb9582527d47"
IMAGE_DDS = "sensor_msgs::msg::dds_::Image_"
PACKET_DDS = "event_camera_msgs::msg::dds_::EventPacket_"
ZID = "a1b2c3d4e5f60718293a4b5c6d7e8f90"


@dataclass(frozen=True)
class Wire:
    """One distribution as its rmw_zenoh writes it (the fixture)."""

    tag: str  # the release tag the facts are read at
    hash: str  # the data key's and token's hash chunk of sensor_msgs/msg/Image
    named: bool  # the named attachment layout
    tl_default: bool  # QoS::default_qos() durability is TRANSIENT_LOCAL
    # evcal's /lab/cam0/calibration/contrast publisher (node /evcal, entity 1, TRANSIENT_LOCAL
    # depth 1) as that rmw_zenoh writes its token
    token: str


def _token(hash_: str, qos: str) -> str:
    return (f"@ros2_lv/0/{ZID}/0/1/MP/%/%/evcal/%lab%cam0%calibration%contrast/"
            f"{IMAGE_DDS}/{hash_}/{qos}")


WIRES = {
    "humble": Wire("release/humble/rmw_zenoh_cpp/0.1.9-1", "TypeHashNotSupported", False,
                   False, _token("TypeHashNotSupported", ":1:,1:,:,:,,")),
    "humble-0.1.1": Wire("release/humble/rmw_zenoh_cpp/0.1.1-1", "TypeHashNotSupported",
                         True, True, _token("TypeHashNotSupported", "::,1:,:,:,,")),
    "jazzy-0.2.3": Wire("release/jazzy/rmw_zenoh_cpp/0.2.3-1", IMAGE_HASH, True, False,
                        _token(IMAGE_HASH, ":1:,1:,:,:,,")),
    "jazzy": Wire("release/jazzy/rmw_zenoh_cpp/0.2.5-1", IMAGE_HASH, False, False,
                  _token(IMAGE_HASH, ":1:,1:,:,:,,")),
    "kilted": Wire("release/kilted/rmw_zenoh_cpp/0.6.7-1", IMAGE_HASH, False, False,
                   _token(IMAGE_HASH, ":1:,1:,:,:,,")),
    "rolling": Wire("release/rolling/rmw_zenoh_cpp/0.12.0-1", IMAGE_HASH, False, False,
                    _token(IMAGE_HASH, ":1:,1:,:,:,,")),
}

GID = bytes(range(0xA0, 0xB0))
T_NS = 0x0102030405060708
# sequence number 7, T_NS, GID as each layout serializes them
COMPACT = bytes.fromhex("0700000000000000" "0807060504030201" "10") + GID
NAMED = (b"\x0fsequence_number" + bytes.fromhex("0700000000000000")
         + b"\x10source_timestamp" + bytes.fromhex("0807060504030201")
         + b"\x0asource_gid" + b"\x10" + GID)


def test_the_wire_table_names_every_distribution() -> None:
    assert set(WIRES) == set(DISTROS)
    assert len(COMPACT) == 33
    assert len(NAMED) == 77


# ----------------------------------------------------------------------------- emulations


class Reader:
    """zenoh-cpp's ``ext::Deserializer`` over bytes: int64, string, byte sequence."""

    def __init__(self, raw: bytes) -> None:
        self.raw, self.i = raw, 0

    def _leb128(self) -> int:
        n = shift = 0
        while True:
            if self.i >= len(self.raw):
                raise RuntimeError("Deserialization failure")
            b = self.raw[self.i]
            self.i += 1
            n |= (b & 0x7F) << shift
            shift += 7
            if not b & 0x80:
                return n

    def int64(self) -> int:
        if self.i + 8 > len(self.raw):
            raise RuntimeError("Deserialization failure")
        self.i += 8
        return int(struct.unpack_from("<q", self.raw, self.i - 8)[0])

    def string(self) -> str:
        n = self._leb128()
        if self.i + n > len(self.raw):
            raise RuntimeError("Deserialization failure")
        self.i += n
        return self.raw[self.i - n:self.i].decode("utf-8", "replace")

    def array16(self) -> bytes:
        if self._leb128() != 16:
            raise RuntimeError("Incorrect sequence size")
        if self.i + 16 > len(self.raw):
            raise RuntimeError("Deserialization failure")
        self.i += 16
        return self.raw[self.i - 16:self.i]


def rmw_attachment(raw: bytes, *, named: bool) -> tuple[int, int, bytes]:
    """``AttachmentData(const zenoh::Bytes &)`` of the named (0.1.0-0.1.1, 0.2.0-0.2.3) or
    the compact layout: (sequence number, source timestamp, GID), or RuntimeError."""
    r = Reader(raw)
    if not named:
        return r.int64(), r.int64(), r.array16()
    if r.string() != "sequence_number":
        raise RuntimeError("sequence_number is not found in the attachment.")
    seq = r.int64()
    if r.string() != "source_timestamp":
        raise RuntimeError("source_timestamp is not found in the attachment.")
    t_ns = r.int64()
    if r.string() != "source_gid":
        raise RuntimeError("source_gid is not found in the attachment.")
    return seq, t_ns, r.array16()


INFINITE = (9223372036, 854775807)  # RMW_DURATION_INFINITE


def rmw_qos(text: str, *, tl_default: bool) -> dict[str, Any]:
    """``keyexpr_to_qos``: the fields of a token's QoS chunk, defaults for empty ones."""
    parts = text.split(":")
    assert len(parts) >= 6, text
    hist, dl, ls, lv = (parts[2].split(","), parts[3].split(","), parts[4].split(","),
                        parts[5].split(","))
    assert min(len(hist), len(dl), len(ls)) >= 2, text
    assert len(lv) >= 3, text

    def num(s: str, default: int) -> int:
        assert not s.startswith("-")
        return int(s) if s else default

    return {"reliability": num(parts[0], 1), "durability": num(parts[1], 1 if tl_default else 2),
            "history": num(hist[0], 1), "depth": num(hist[1], 42),
            "deadline": (num(dl[0], INFINITE[0]), num(dl[1], INFINITE[1])),
            "lifespan": (num(ls[0], INFINITE[0]), num(ls[1], INFINITE[1])),
            "liveliness": num(lv[0], 1), "lease": (num(lv[1], INFINITE[0]),
                                                   num(lv[2], INFINITE[1]))}


def rmw_gid(token: str) -> bytes:
    """``Entity``: the XXH3-128 of the token, its low then its high 64-bit half."""
    v = xxhash.xxh3_128(token.encode()).intdigest()
    return struct.pack("<QQ", v & (2**64 - 1), v >> 64)


# ----------------------------------------------------------------------------- out


@pytest.mark.parametrize("name", list(WIRES))
def test_out_evcal_images_as_each_distribution_reads_them(name: str) -> None:
    wire = WIRES[name]
    node = RosNode(zid=ZID, domain=0)
    pub = RosPublication(node, output_topic("lab/cam0", "contrast"), IMAGE, qos=OUTPUT_QOS,
                         distro=DISTROS[name])
    # the key that distribution's subscriber of /lab/cam0/calibration/contrast declares
    assert pub.key == f"0/lab/cam0/calibration/contrast/{IMAGE_DDS}/{wire.hash}"
    assert pub.token == wire.token
    assert pub.gid == rmw_gid(wire.token)
    qos = rmw_qos(wire.token.rsplit("/", 1)[1], tl_default=wire.tl_default)
    assert qos == {"reliability": 1, "durability": 1, "history": 1, "depth": 1,
                   "deadline": INFINITE, "lifespan": INFINITE, "liveliness": 1,
                   "lease": INFINITE}  # RELIABLE, TRANSIENT_LOCAL, KEEP_LAST 1, no limits
    # the attachment, byte for byte, read by that distribution's AttachmentData
    raw = DISTROS[name].attachment(7, T_NS, GID)
    assert raw == (NAMED if wire.named else COMPACT)
    assert rmw_attachment(raw, named=wire.named) == (7, T_NS, GID)
    with pytest.raises(RuntimeError):  # the other releases' constructor throws on it
        rmw_attachment(raw, named=not wire.named)
    seq, _, gid = rmw_attachment(pub.attachment(), named=wire.named)
    assert (seq, gid) == (1, pub.gid)


def test_out_old_releases_read_the_durability_written_out() -> None:
    """The jazzy-0.2.3 profile serves 0.2.0-0.2.2 too, whose default durability was
    TRANSIENT_LOCAL: the durability written out reads alike under both defaults."""
    qos = WIRES["jazzy-0.2.3"].token.rsplit("/", 1)[1]
    assert (rmw_qos(qos, tl_default=True)["durability"]
            == rmw_qos(qos, tl_default=False)["durability"] == 1)


# ----------------------------------------------------------------------------- in


@dataclass
class Delivered:
    items: list[tuple[str, str, RosSample]]

    def __call__(self, camera: str, kind: str, sample: RosSample, t: float) -> None:
        self.items.append((camera, kind, sample))


@pytest.mark.parametrize("name", list(WIRES))
def test_in_a_drivers_topic_of_each_distribution(name: str) -> None:
    wire = WIRES[name]
    packet_hash = (wire.hash if wire.hash == "TypeHashNotSupported"
                   else "RIHS01_" + "ab" * 32)  # any hash: evcal subscribes with *
    key = f"0/event_camera/events/{PACKET_DDS}/{packet_hash}"
    # the driver's publisher token: best effort, keep last 10, volatile (the release's
    # default left empty)
    durability = "2" if wire.tl_default else ""
    token = (f"@ros2_lv/0/0123456789abcdef/0/12/MP/%/%/event_camera/%event_camera%events/"
             f"{PACKET_DDS}/{packet_hash}/2:{durability}:,10:,:,:,,")
    detector = DistroDetector(own_zid=ZID)
    detector.seen_token(token)
    delivered = Delivered([])
    router = RosRouter(RosNode(zid=ZID), delivered, TopicMap(), detector=detector)
    router.on_sample(key, b"cdr", "", NAMED if wire.named else COMPACT)
    assert [(c, k, s.topic, s.msgtype, s.seq) for c, k, s in delivered.items] == [
        ("event_camera", "events", "/event_camera/events", EVENT_PACKET, 7)]
    # auto: evcal now publishes as this distribution's subscribers read
    (profile,) = detector.active()
    assert (profile.type_hash, profile.named_attachment) == (
        DISTROS[name].type_hash, DISTROS[name].named_attachment)
    # the subscription token evcal declares for the topic carries the topic's own hash
    tokens: list[str] = []
    router.declare_pending(tokens.append)
    assert len(tokens) == 1
    chunks = tokens[0].split("/")
    assert chunks[5] == "MS"
    assert chunks[9:12] == ["%event_camera%events", PACKET_DDS,
                                                  packet_hash]


def test_auto_serves_humble_and_jazzy_side_by_side() -> None:
    det = DistroDetector(own_zid=ZID)
    assert [d.name for d in det.active()] == ["jazzy"]  # nothing seen yet
    det.seen_token(f"@ros2_lv/0/{ZID}/0/3/MS/%/%/evcal/%x/{IMAGE_DDS}/TypeHashNotSupported/"
                   "::,10:,:,:,,")
    assert [d.name for d in det.active()] == ["jazzy"]  # evcal's own tokens do not count
    det.seen_token(f"@ros2_lv/0/ffee/0/3/MS/%/%/rviz2/%lab%cam0%calibration%contrast/"
                   f"{IMAGE_DDS}/TypeHashNotSupported/::,10:,:,:,,")
    assert [d.name for d in det.active()] == ["humble"]
    det.seen_token(f"@ros2_lv/0/ffef/0/3/MP/%/%/drv/%a/{IMAGE_DDS}/{IMAGE_HASH}/::,10:,:,:,,")
    assert [d.name for d in det.active()] == ["jazzy", "humble"]
    det.seen_sample(f"0/a/{IMAGE_DDS}/{IMAGE_HASH}", NAMED)
    assert [d.name for d in det.active()] == ["jazzy-0.2.3", "humble"]
    det.seen_sample(f"0/a/{IMAGE_DDS}/{IMAGE_HASH}", COMPACT)  # the newest sample says
    assert [d.name for d in det.active()] == ["jazzy", "humble"]
    det.seen_sample(f"0/a/{IMAGE_DDS}/{IMAGE_HASH}", b"junk")  # unreadable: no change
    assert [d.name for d in det.active()] == ["jazzy", "humble"]
    assert encode_attachment(7, T_NS, GID) == COMPACT


def test_an_explicit_distro_that_the_domain_contradicts_is_warned_of(caplog) -> None:
    """Issue 40: ``--ros-distro humble`` with Jazzy-style subscribers on the domain published
    on keys nobody heard, silently. Once, and not while a node of its own style is there."""
    from evcal.service.ros2 import DISTROS, DistroMismatch

    jazzy_sub = (f"@ros2_lv/0/ffee/0/3/MS/%/%/rviz2/%lab%cam0%calibration%contrast/"
                 f"{IMAGE_DDS}/{IMAGE_HASH}/::,10:,:,:,,")
    humble_sub = (f"@ros2_lv/0/ffef/0/3/MS/%/%/rviz2/%a/{IMAGE_DDS}/TypeHashNotSupported/"
                  "::,10:,:,:,,")
    w = DistroMismatch(DISTROS["humble"], own_zid=ZID)
    with caplog.at_level("WARNING", logger="evcal.service"):
        # evcal's own token (its style) does not count either way
        assert w.seen_token(humble_sub.replace("ffef", ZID)) is None
        text = w.seen_token(jazzy_sub)
        assert text is not None
        assert "--ros-distro humble" in text
        assert "RIHS01" in text
        assert w.seen_token(jazzy_sub.replace("ffee", "ffe0")) is None  # once
    assert sum("--ros-distro humble" in r.message for r in caplog.records) == 1
    # a Humble node on the domain: evcal's choice fits someone, no warning
    w2 = DistroMismatch(DISTROS["humble"], own_zid=ZID)
    assert w2.seen_token(humble_sub) is None
    assert w2.seen_token(jazzy_sub) is None
    # and the other way round
    w3 = DistroMismatch(DISTROS["jazzy"], own_zid=ZID)
    assert "no type hashes (Humble)" in (w3.seen_token(humble_sub) or "")


def test_serve_ros_distro_flag() -> None:
    from evcal.service.cli import build_parser, ros2_from_args

    args = build_parser().parse_args(["--ros2", "--ros-distro", "humble"])
    opts = ros2_from_args(args)
    assert opts is not None
    assert opts.distro == "humble"
    opts = ros2_from_args(build_parser().parse_args(["--ros2"]))
    assert opts is not None
    assert opts.distro == "auto"
    with pytest.raises(SystemExit):
        build_parser().parse_args(["--ros2", "--ros-distro", "foxy"])


# ----------------------------------------------------------------------------- end to end


def test_serve_ros2_images_decode_for_humble_and_jazzy_023_subscribers() -> None:
    """The acceptance: ``evcal serve --ros2`` (``--ros-distro auto``) fed by a Jazzy 0.2.3 driver
    (named attachments) while a Humble rviz2 subscribes to its images: both a Humble-style
    subscriber (TypeHashNotSupported key, 33-byte attachments) and a Jazzy-0.2.3-style one
    (RIHS01 key, named attachments) decode the calibration images, TRANSIENT_LOCAL."""
    pytest.importorskip("zenoh")
    from zenoh import ext

    from evcal.io.wire import decode_calibration
    from evcal.service.transport import Transport, ZenohOptions
    from evcal.sim.ideal import SimConfig, simulate_ideal
    from evcal.testing import ServiceProcess, endpoint, free_port, wait_for

    sim = simulate_ideal(SimConfig(height=36, width=48, duration_s=1.5, seed=4))
    ep = endpoint(free_port())
    service = ServiceProcess(["--listen", ep, "--no-multicast-scouting", "--ros2",
                              "--on-full", "block", "--n-small", "3000", "--n-large",
                              "1000000", "--log-offset", "30", "--status-period", "0.2"])
    store = ros2_store()
    latest: dict[str, tuple[bytes, bytes]] = {}
    with service, Transport(ZenohOptions.loopback(connect=[ep])) as t:
        wait_for(lambda: t.alive("@ros2_lv/0/*/0/0/NN/%/%/evcal", timeout_s=1.0),
                 timeout_s=60, what="the service's ROS 2 node")
        # a Humble rviz2 showing the contrast map: its subscription's token
        t.token(f"@ros2_lv/0/{t.zid}/0/5/MS/%/%/rviz2/%lab%cam0%calibration%contrast/"
                f"{IMAGE_DDS}/TypeHashNotSupported/::,10:,:,:,,")
        subs = []
        for name in ("humble", "jazzy-0.2.3"):
            key = f"0/lab/cam0/calibration/contrast/{IMAGE_DDS}/{WIRES[name].hash}"

            def on(sample: Any, name: str = name) -> None:
                latest[name] = (sample.payload.to_bytes(), sample.attachment.to_bytes())

            # rmw_zenoh 0.1.2+ and 0.2.2+: a TRANSIENT_LOCAL subscription
            subs.append(ext.declare_advanced_subscriber(
                t.session, key, on,
                history=ext.HistoryConfig(detect_late_publishers=True, max_samples=10),
                subscriber_detection=True))
        # the Jazzy 0.2.3 driver: its topics, named attachments
        dds = {EVENT_PACKET: PACKET_DDS, IMAGE: IMAGE_DDS}
        seqs: dict[str, int] = {}
        for m in recording_messages(sim.recording, namespace="/lab/cam0"):
            seqs[m.topic] = seqs.get(m.topic, 0) + 1
            t.put(f"0{m.topic}/{dds[m.msgtype]}/RIHS01_{'cd' * 32}", m.data, "",
                  block=True, attachment=encode_attachment(seqs[m.topic], 0, GID,
                                                           named=True))

        def settled() -> bytes | None:
            st = t.get("evcal/lab/cam0/status", timeout_s=2.0)
            if not st or not st[0].ok:
                return None
            doc = json.loads(st[0].payload)
            if doc["in_flight_messages"] or not doc["updates"]:
                return None
            cal = t.get("evcal/lab/cam0/calibration", timeout_s=2.0)
            return cal[0].payload if cal and cal[0].ok else None

        payload = wait_for(settled, timeout_s=60, what="the camera's last update")
        contrast = decode_calibration(payload)[0].contrast.astype(np.float32)

        def image(name: str) -> np.ndarray | None:
            if name not in latest:
                return None
            msg = store.deserialize_cdr(latest[name][0], IMAGE)
            return np.frombuffer(msg.data.tobytes(), "<f4").reshape(msg.height, msg.width)

        for name in ("humble", "jazzy-0.2.3"):
            wait_for(lambda name=name: (img := image(name)) is not None
                     and np.array_equal(img, contrast), timeout_s=30,
                     what=f"the {name} subscriber's last image")
        for s in subs:
            s.undeclare()
        assert service.stop() == 0
    for name, (data, att) in latest.items():
        seq, _, gid = rmw_attachment(att, named=WIRES[name].named)
        assert seq >= 1
        assert len(gid) == 16
        with pytest.raises(RuntimeError):
            rmw_attachment(att, named=not WIRES[name].named)
        msg = store.deserialize_cdr(data, IMAGE)
        assert (msg.encoding, msg.height, msg.width) == ("32FC1", 36, 48)


@pytest.mark.timeout(240)
@pytest.mark.parametrize(("flag", "subscriber_hash", "name"), [
    ("humble", None, "humble"), ("jazzy-0.2.3", None, "jazzy-0.2.3"),
    ("auto", "TypeHashNotSupported", "humble"), ("auto", None, "jazzy"),
])
def test_replay_ros2_in_each_distributions_wire(tmp_path, flag: str,
                                                 subscriber_hash: str | None,
                                                 name: str) -> None:
    """``evcal replay BAG --ros2 --ros-distro``: the bag's topics on the keys, tokens and
    attachments of that rmw_zenoh, as its subscribers read them (emulated from their
    sources); ``auto`` takes Humble's wire from a domain whose tokens are Humble's."""
    pytest.importorskip("zenoh")
    from evcal.io.ros2msg import write_ros2_bag
    from evcal.service.transport import Transport, ZenohOptions
    from evcal.sim.ideal import SimConfig, simulate_ideal
    from evcal.testing import endpoint, free_port, run_client, wait_for

    sim = simulate_ideal(SimConfig(height=24, width=32, duration_s=0.5, seed=3))
    bag = write_ros2_bag(sim.recording, tmp_path / "sim.mcap", namespace="/lab/cam9",
                         encoding="libcaer_cmp")
    wire = WIRES[name]
    ep = endpoint(free_port())
    samples: list[tuple[str, bytes | None]] = []
    with Transport(ZenohOptions.loopback(listen=[ep])) as t:
        t.subscribe("0/**", lambda key, payload, enc, attachment:
                    samples.append((key, attachment)), attachment=True)
        if subscriber_hash is not None:  # a subscriber of that distribution is on the domain
            t.token(f"@ros2_lv/0/{ZID}/0/5/MS/%/%/listener/%lab%cam9%events/{PACKET_DDS}/"
                    f"{subscriber_hash}/:1:,1:,:,:,,")
        res = run_client("replay", [str(bag), "--ros2", "--connect", ep,
                                    "--no-multicast-scouting", "--max-rate",
                                    "--ros-distro", flag, "--wait-subscriber", "10",
                                    "--confirm-timeout", "1"])
        assert res.returncode == 7, res.stderr  # no evcal service: unconfirmed
        assert f"({name}'s rmw_zenoh wire)" in res.stderr, res.stderr
        sent = int(res.stderr.split("sent ")[1].split()[0])
        wait_for(lambda: len(samples) >= sent, timeout_s=30, what=f"{sent} samples")
    assert len(samples) == sent
    seqs: dict[str, list[int]] = {}
    for key, attachment in samples:
        head, dds, hash_ = key.rsplit("/", 2)
        if wire.hash == "TypeHashNotSupported":
            assert hash_ == wire.hash, key
        else:
            assert hash_.startswith("RIHS01_"), key
            assert dds != IMAGE_DDS or hash_ == IMAGE_HASH, key
        assert attachment is not None
        seq, _t_ns, _gid = rmw_attachment(attachment, named=wire.named)
        if wire.named:
            assert len(attachment) == 77  # each field after its name
        else:
            with pytest.raises(RuntimeError):  # 0.2.0-0.2.3's constructor throws on it
                rmw_attachment(attachment, named=True)
        seqs.setdefault(head, []).append(seq)
    for head, s in seqs.items():
        assert s == list(range(1, len(s) + 1)), head
