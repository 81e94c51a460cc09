"""ROS 2 interop with a third-party rmw_zenoh client: zenoh-ros2-sdk (PyPI, "ROS 2 without ROS
2") against ``evcal serve --ros2``, in separate processes on loopback.

The SDK's own code does the ROS side: it computes the RIHS01 type hashes from ``.msg`` files,
writes the keys, liveliness tokens and attachments, serializes the CDR, and lists the graph.
Its message registry downloads ``.msg`` files from git; with no network here it is given a
local directory instead, the definitions being evcal's own (``message_definition``, split into
one file per type). Events go in as ``mono`` EventPackets written by this test, not by evcal's
encoder, with the simulated camera's mono8 Images.

- discovery: the SDK's topic list / info show evcal's calibration topics as sensor_msgs/Image
  (node ``evcal``, TRANSIENT_LOCAL depth 1, the hash the SDK computes) and its subscriptions;
- maps out: the SDK's subscribers receive the three maps, bit-identical to what ``evcal query
  --camera C --out FILE`` writes;
- events and frames in: the SDK's publishers feed the camera; evcal counts every event and
  frame, loses none and calibrates it;
- late joiner: a TRANSIENT_LOCAL SDK subscriber created after the last update gets the maps;
- each ``--ros-distro``: the SDK configured for that distribution (Humble: no type hash) feeds
  the service and reads its maps.

SDK 0.1.8 limitations worked around here, in the test only (see :func:`sdk_session` and
:class:`LateSubscriber`):

- one process-wide session (a singleton) and one message registry whose loaded types live in
  that session: both are made afresh for each use;
- ``msg_definition=`` takes one type's text and hashes it without the types it uses (a wrong
  RIHS01 hash for Image and EventPacket): the definitions go in through the registry's
  directory, where the SDK finds the used types too;
- RELIABLE publishers are meant to block, but the SDK looks the enum up as
  ``zenoh.qos.CongestionControl``, absent from zenoh-python 1.x: they drop, and lose messages
  when ``serve --on-full block`` pushes back;
- its TRANSIENT_LOCAL subscriber looks for the topic's publishers with a liveliness pattern in
  which the topic's inner ``/`` are not mangled to ``%``, so it finds none for a topic below
  the root namespace (evcal's all are) and gets no history.

Real zenoh sessions on tcp/127.0.0.1, multicast scouting off, a free port per service.
"""

from __future__ import annotations

import contextlib
import json
import re
import threading
from collections.abc import Callable, Iterator
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

zenoh = pytest.importorskip("zenoh")
pytest.importorskip("xxhash")
sdk = pytest.importorskip("zenoh_ros2_sdk")

from zenoh_ros2_sdk import message_registry  # noqa: E402
from zenoh_ros2_sdk.qos import QosDurability, QosProfile, QosReliability  # noqa: E402

from evcal.io.calibfile import load_calibration  # noqa: E402
from evcal.io.ros2msg import message_definition, type_hash  # noqa: E402
from evcal.io.rosbag import EVENT_PACKET, IMAGE  # noqa: E402
from evcal.io.wire import decode_calibration  # noqa: E402
from evcal.service.ros2 import DISTRO_CHOICES, DISTROS, NO_TYPE_HASH, SPECIAL_SCALE  # noqa: E402
from evcal.service.ros2out import output_topic  # noqa: E402
from evcal.service.transport import Transport, ZenohOptions  # noqa: E402
from evcal.sim.ideal import SimConfig, simulate_ideal  # noqa: E402
from evcal.testing import (  # noqa: E402
    ServiceProcess,
    endpoint,
    free_port,
    run_client,
    wait_for,
)

pytestmark = pytest.mark.timeout(240)

CAMERA = "sdk/cam0"
MAPS = ("contrast", "bias", "special")
SERVE = ["--no-multicast-scouting", "--ros2", "--on-full", "block", "--n-small", "3000",
         "--n-large", "1000000", "--log-offset", "30", "--status-period", "0.2"]
ZARGS = ["--no-multicast-scouting"]
TIME = "builtin_interfaces/msg/Time"
HEADER = "std_msgs/msg/Header"


# ----------------------------------------------------------------------------- the SDK


@pytest.fixture(scope="session")
def msg_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The SDK's local message directory (``<pkg>/msg/<Name>.msg``): evcal's definitions of
    Image and EventPacket, each type it uses in a file of its own (Header, Time)."""
    root = tmp_path_factory.mktemp("sdk_msgs")
    for msgtype in (IMAGE, EVENT_PACKET):
        first, *used = re.split(r"^=+\n", message_definition(msgtype), flags=re.MULTILINE)
        files = {msgtype: first}
        for section in used:
            head, _, body = section.partition("\n")
            pkg, _, name = head.removeprefix("MSG: ").strip().partition("/")
            files[f"{pkg}/msg/{name}"] = body
        for name, body in files.items():
            path = root / f"{name}.msg"
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_text(body.strip() + "\n")
    assert {p.relative_to(root).as_posix() for p in root.rglob("*.msg")} == {
        f"{t}.msg" for t in (IMAGE, EVENT_PACKET, HEADER, TIME)}
    return root


class Sdk:
    """The SDK's session on one evcal endpoint and the entities made through it."""

    def __init__(self, port: int) -> None:
        self.port = port
        self.session = sdk.ZenohSession.get_instance("127.0.0.1", port)
        self._entities: list[Any] = []

    def _where(self) -> dict[str, Any]:
        return {"router_ip": "127.0.0.1", "router_port": self.port}

    def publisher(self, topic: str, msgtype: str, **kwargs: Any) -> Any:
        pub = sdk.ROS2Publisher(topic, msgtype, **self._where(), **kwargs)
        self._entities.append(pub)
        return pub

    def subscriber(self, topic: str, msgtype: str, callback: Callable[[Any], None], *,
                   cls: type = sdk.ROS2Subscriber, **kwargs: Any) -> Any:
        sub = cls(topic, msgtype, callback, **self._where(), **kwargs)
        self._entities.append(sub)
        return sub

    def topics(self) -> dict[str, list[str]]:
        return dict(sdk.get_topic_names_and_types(**self._where(), timeout=1.0))

    def info(self, topic: str) -> Any:
        return sdk.get_topic_info(topic, **self._where(), timeout=1.0, verbose=True)

    def message_class(self, msgtype: str) -> Any:
        return self.session.store.types[msgtype]

    def close(self) -> None:
        for e in reversed(self._entities):
            e.close()
        self.session.close()  # also drops the singleton


@contextlib.contextmanager
def sdk_session(port: int, msg_dir: Path, cache: Path) -> Iterator[Sdk]:
    """The SDK on ``tcp/127.0.0.1:port``: its process-wide session and message registry made
    afresh (the registry's loaded types live in the session: a registry that outlived its
    session would refuse every type), reading ``msg_dir``. ``ZENOH_CONFIG_OVERRIDE`` keeps
    its session on loopback with scouting off (its default config listens on
    ``tcp/localhost:0`` and gossips); its git cache and config are temporary files.

    SDK 0.1.8 maps a RELIABLE publisher to congestion control BLOCK by looking up
    ``zenoh.qos.CongestionControl``, which zenoh-python 1.x does not have (the enum is
    ``zenoh.CongestionControl``): its publishers are DROP, and with ``serve --on-full block``
    pushing back, a share of the messages vanishes at the SDK's side (the camera's tail
    missing, or gaps counted as lost). The enum is put where the SDK looks, so that its
    intended mapping applies and the stream is lossless.
    """
    assert sdk.ZenohSession._instance is None, "an SDK session was left open"
    with pytest.MonkeyPatch.context() as mp:
        mp.delenv("ZENOH_SESSION_CONFIG_URI", raising=False)
        mp.setenv("ZENOH_CONFIG_OVERRIDE", 'listen/endpoints=["tcp/127.0.0.1:0"];'
                  "scouting/multicast/enabled=false;scouting/gossip/enabled=false")
        mp.setenv("ZENOH_ROS2_SDK_CACHE", str(cache))
        mp.setenv("GIT_TERMINAL_PROMPT", "0")
        # were a definition missing, the SDK would clone into its cache and add that
        # directory to git's global safe.directory list: keep that out of the user's config
        mp.setenv("GIT_CONFIG_GLOBAL", str(cache.parent / "sdk.gitconfig"))
        mp.setattr(message_registry, "_registry", message_registry.MessageRegistry(str(msg_dir)))
        if getattr(zenoh, "qos", None) is None:
            mp.setattr(zenoh, "qos", SimpleNamespace(CongestionControl=zenoh.CongestionControl),
                       raising=False)
        s = Sdk(port)
        try:
            yield s
        finally:
            s.close()


class LateSubscriber(sdk.ROS2Subscriber):
    """SDK 0.1.8's TRANSIENT_LOCAL subscriber asks the topic's publishers for their cache
    after finding them with the liveliness pattern ``@ros2_lv/<d>/*/*/*/MP/*/*/*/%<topic
    without its leading '/'>/<type>/<hash>/*``: the inner ``/`` of the topic stay, so for
    ``/sdk/cam0/calibration/contrast`` it asks for ``%sdk/cam0/calibration/contrast`` where
    rmw_zenoh (and the SDK's own tokens) write ``%sdk%cam0%calibration%contrast``, finds no
    publisher and gets no history. The workaround: the same lookup with the name mangled."""

    def _discover_publishers(self) -> list[str]:
        topic = self.topic
        self.topic = topic.strip("/").replace("/", "%")  # the SDK prepends the first "%"
        try:
            return list(super()._discover_publishers())
        finally:
            self.topic = topic


class Images:
    """What SDK subscribers of a camera's maps received: ``{map: [(stamp ns, msg)]}``."""

    def __init__(self) -> None:
        self.got: dict[str, list[tuple[int, Any]]] = {m: [] for m in MAPS}
        self.lock = threading.Lock()

    def callback(self, name: str) -> Callable[[Any], None]:
        def on(msg: Any) -> None:
            with self.lock:
                self.got[name].append((msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec,
                                       msg))
        return on

    def at(self, t_ns: int) -> dict[str, Any] | None:
        """Each map's image stamped ``t_ns``, None until all three came."""
        with self.lock:
            found = {m: msg for m, got in self.got.items() for t, msg in got if t == t_ns}
        return found if len(found) == len(MAPS) else None

    def count(self) -> int:
        with self.lock:
            return sum(len(g) for g in self.got.values())


def subscribe_maps(s: Sdk, camera: str, images: Images, **kwargs: Any) -> None:
    for m in MAPS:
        s.subscriber(output_topic(camera, m), IMAGE, images.callback(m), **kwargs)


# ----------------------------------------------------------------------------- the camera


@pytest.fixture(scope="module")
def sim() -> Any:
    return simulate_ideal(SimConfig(height=36, width=48, duration_s=1.5, seed=4)).recording


def mono_payload(ev: np.ndarray) -> tuple[bytes, int]:
    """``mono`` EventPacket payload of sorted events (8-byte words: ns after ``time_base``
    in bits 0-31, x 32-47, y 48-62, ON in bit 63) and its ``time_base`` (ns)."""
    t_ns = ev["t_us"].astype(np.uint64) * np.uint64(1000)
    base = t_ns[0]
    words = ((t_ns - base) | (ev["x"].astype(np.uint64) << np.uint64(32))
             | (ev["y"].astype(np.uint64) << np.uint64(48))
             | ((ev["p"] > 0).astype(np.uint64) << np.uint64(63)))
    return words.astype("<u8").tobytes(), int(base)


def publish_camera(s: Sdk, rec: Any, camera: str, *, type_hash_: str | None = None,
                   packet_us: int = 10_000) -> dict[str, int]:
    """Publish ``rec`` as a driver would, through the SDK: ``/<camera>/events`` (mono
    EventPackets of at most ``packet_us``, cut at frame times) and ``/<camera>/image_raw``
    (mono8), in time order, each frame before the events at or after its time. RELIABLE
    publishers block rather than drop. ``type_hash_``: the hash chunk (None: the SDK's)."""
    ns = "/" + camera
    events = s.publisher(f"{ns}/events", EVENT_PACKET, type_hash=type_hash_)
    frames = s.publisher(f"{ns}/image_raw", IMAGE, type_hash=type_hash_)
    for pub in (events, frames):  # lossless (see sdk_session)
        assert pub.pub.congestion_control == zenoh.CongestionControl.BLOCK
    time_cls, header_cls = s.message_class(TIME), s.message_class(HEADER)
    h, w = rec.sensor.shape

    def header(t_ns: int) -> Any:
        sec, nanosec = divmod(t_ns, 10**9)
        return header_cls(stamp=time_cls(sec=sec, nanosec=nanosec), frame_id=camera)

    ev, f_t, images = rec.events, rec.frames.t_us, rec.frames.images
    assert images.dtype == np.uint8
    t = ev["t_us"]
    cuts = np.union1d(f_t, np.arange(int(t[0]), int(t[-1]) + 1, packet_us))
    bounds = np.searchsorted(t, cuts)
    k = seq = 0
    for i, cut in enumerate(cuts):
        while k < len(f_t) and f_t[k] <= cut:
            frames.publish(header=header(int(f_t[k]) * 1000), height=h, width=w,
                           encoding="mono8", is_bigendian=0, step=w,
                           data=np.ascontiguousarray(images[k]).reshape(-1))
            k += 1
        i1 = bounds[i + 1] if i + 1 < len(cuts) else len(t)
        if i1 > bounds[i]:
            chunk = ev[bounds[i]:i1]
            payload, base = mono_payload(chunk)
            events.publish(header=header(int(chunk["t_us"][-1]) * 1000), height=h, width=w,
                           seq=seq, time_base=base, encoding="mono", is_bigendian=False,
                           events=np.frombuffer(payload, np.uint8))
            seq += 1
    for j in range(k, len(f_t)):
        frames.publish(header=header(int(f_t[j]) * 1000), height=h, width=w,
                       encoding="mono8", is_bigendian=0, step=w,
                       data=np.ascontiguousarray(images[j]).reshape(-1))
    return {"event_messages": seq, "frames": len(f_t)}


def status_of(t: Transport, camera: str) -> dict[str, Any]:
    replies = t.get(f"evcal/{camera}/status", timeout_s=2.0)
    return json.loads(replies[0].payload) if replies and replies[0].ok else {}


def settled(t: Transport, camera: str, rec: Any) -> dict[str, Any]:
    """The camera's status once every event and frame of ``rec`` was processed."""
    last: dict[str, Any] = {}

    def done() -> dict[str, Any] | None:
        last.update(status_of(t, camera))
        if (last.get("events"), last.get("frames"), last.get("in_flight_messages")) != (
                rec.n_events, len(rec.frames), 0) or not last.get("updates"):
            return None
        return dict(last)

    try:
        return wait_for(done, timeout_s=60, what=f"{camera}: every event and frame processed")
    except TimeoutError as exc:
        raise AssertionError(f"{exc}; its last status: {json.dumps(last)}") from None


def calibration_now(t: Transport, camera: str) -> tuple[Any, dict[str, Any]]:
    replies = t.get(f"evcal/{camera}/calibration", timeout_s=5.0)
    assert replies, "no calibration"
    assert replies[0].ok, replies[0].payload
    return decode_calibration(replies[0].payload)


def assert_images_are(images: dict[str, Any], cal: Any) -> None:
    """The three Images carry the calibration's maps, bit for bit."""
    h, w = cal.shape
    for name in ("contrast", "bias"):
        msg = images[name]
        assert (msg.encoding, msg.height, msg.width, msg.step) == ("32FC1", h, w, 4 * w)
        got = np.frombuffer(msg.data.tobytes(), "<u4").reshape(h, w)
        want = np.ascontiguousarray(getattr(cal, name), "<f4").view("<u4")
        np.testing.assert_array_equal(got, want, err_msg=name)
    msg = images["special"]
    assert (msg.encoding, msg.height, msg.width, msg.step) == ("mono8", h, w, w)
    np.testing.assert_array_equal(
        msg.data.reshape(h, w), (cal.special.astype(np.uint16) * SPECIAL_SCALE).astype(np.uint8))


# ----------------------------------------------------------------------------- one service


@pytest.fixture(scope="module")
def served(tmp_path_factory: pytest.TempPathFactory, msg_dir: Path, sim: Any
           ) -> Iterator[dict[str, Any]]:
    """``evcal serve --ros2`` (``--ros-distro`` left at auto), fed the simulated camera by
    the SDK's publishers while the SDK's subscribers take its maps."""
    d = tmp_path_factory.mktemp("sdk_service")
    port = free_port()
    ep = endpoint(port)
    with ServiceProcess(["--listen", ep, *SERVE], log_path=d / "service.log") as sp, \
            Transport(ZenohOptions.loopback(connect=[ep])) as t:
        wait_for(lambda: t.alive("@ros2_lv/0/*/0/0/NN/%/%/evcal", timeout_s=1.0),
                 timeout_s=60, what="the service's ROS 2 node")
        images = Images()
        with sdk_session(port, msg_dir, d / "cache") as s:
            subscribe_maps(s, CAMERA, images)
            sent = publish_camera(s, sim, CAMERA)
            status = settled(t, CAMERA, sim)
            cal, header = calibration_now(t, CAMERA)
            wait_for(lambda: images.at(header["t_us"] * 1000), timeout_s=30,
                     what="the SDK's images of the last update")
        yield {"port": port, "ep": ep, "t": t, "dir": d, "images": images, "sent": sent,
               "status": status, "cal": cal, "header": header, "proc": sp}
        assert sp.stop() == 0, sp.log_text()


def test_sdk_discovers_evcals_topics(served: dict[str, Any], msg_dir: Path) -> None:
    """The SDK's ``ros2 topic list -t`` / ``ros2 topic info -v``: evcal's three calibration
    topics are sensor_msgs/Image published by node /evcal, RELIABLE, TRANSIENT_LOCAL, keep
    last 1, with the RIHS01 hash the SDK computes; its subscriptions to the camera's
    topics are listed too."""
    with sdk_session(served["port"], msg_dir, served["dir"] / "cache") as s:
        ns = "/" + CAMERA
        want = {output_topic(CAMERA, m): [IMAGE] for m in MAPS}
        want.update({f"{ns}/events": [EVENT_PACKET], f"{ns}/image_raw": [IMAGE]})
        topics = wait_for(lambda: (got := s.topics()) and all(
            got.get(k) == v for k, v in want.items()) and got, timeout_s=10,
            what="evcal's topics in the SDK's topic list")
        assert {k: topics[k] for k in want} == want

        def counts(topic: str) -> tuple[int, int] | None:
            info = s.info(topic)
            return None if info is None else (info.publisher_count, info.subscriber_count)

        # the earlier SDK sessions' entities are gone once their tokens are
        wait_for(lambda: all(counts(output_topic(CAMERA, m)) == (1, 0) for m in MAPS)
                 and counts(f"{ns}/events") == (0, 1), timeout_s=10,
                 what="evcal's endpoints alone in the graph")
        # the hash the SDK computes from the .msg files: its subscriber's key chunk
        probe = s.subscriber("/sdk_probe", IMAGE, lambda msg: None)
        assert probe.type_hash == type_hash(IMAGE)
        for m in MAPS:
            info = s.info(output_topic(CAMERA, m))
            assert info is not None, m
            assert (info.topic_types, info.publisher_count, info.subscriber_count) == (
                [IMAGE], 1, 0)
            (pub,) = info.publishers
            assert (pub.node_name, pub.node_namespace, pub.topic_type, pub.type_hash) == (
                "evcal", "/", IMAGE, probe.type_hash)
            qos = QosProfile.decode(pub.qos)
            assert (qos.reliability, qos.durability, qos.history_depth) == (
                QosReliability.RELIABLE, QosDurability.TRANSIENT_LOCAL, 1)
        info = s.info(f"{ns}/events")
        assert info is not None
        assert info.publisher_count == 0  # the SDK's publishers are gone
        assert [(e.node_name, e.topic_type) for e in info.subscribers] == [
            ("evcal", EVENT_PACKET)]


def test_sdk_subscribers_get_the_maps_query_returns(served: dict[str, Any],
                                                    tmp_path: Path) -> None:
    """The maps the SDK's subscribers received are bit-identical to ``evcal query --camera
    C --out FILE``'s calibration, stamped with its time."""
    out = tmp_path / "cal.npz"
    res = run_client("query", ["--camera", CAMERA, "--connect", served["ep"], *ZARGS,
                               "--out", str(out), "--timeout", "5"])
    assert res.returncode == 0, res.stderr
    said = re.search(r"t_us=(\d+)", res.stderr)
    assert said, res.stderr
    t_us = int(said.group(1))
    assert t_us == served["header"]["t_us"]
    images = served["images"].at(t_us * 1000)
    assert images is not None
    cal = load_calibration(out)
    assert cal.shape == (36, 48)
    assert_images_are(images, cal)
    for msg in images.values():
        assert msg.header.frame_id == CAMERA
    # the updates' images came in order (evcal publishes them congestion control DROP, so
    # that a slow ROS subscriber never stalls a camera: one may miss an intermediate update)
    for m in MAPS:
        stamps = [t for t, _ in served["images"].got[m]]
        assert stamps == sorted(set(stamps)), m
        assert 1 <= len(stamps) <= served["status"]["updates"]


def test_sdk_publishers_feed_the_camera(served: dict[str, Any], sim: Any) -> None:
    """The SDK's EventPackets (mono) and Images reach the camera whole: every event and
    frame counted, none lost or refused, the camera calibrated."""
    st = served["status"]
    assert st["events"] == sim.n_events
    assert st["frames"] == len(sim.frames) == served["sent"]["frames"]
    assert st["event_messages"] == served["sent"]["event_messages"]
    assert st["errors"] == {}
    assert st["lost_messages"] == {"events": 0, "frames": 0}
    assert st["sensor"] == "48x36"
    assert st["updates"] >= 1
    cal = served["cal"]
    assert cal.shape == (36, 48)
    assert cal.valid_fraction > 0.5
    # the ROS side of the status: the messages of each topic, the encoding seen
    ros = st["ros2"]
    assert ros["messages"] == {f"/{CAMERA}/events": served["sent"]["event_messages"],
                               f"/{CAMERA}/image_raw": served["sent"]["frames"]}
    assert ros["encodings"] == {f"/{CAMERA}/events": "mono"}
    assert ros["dropped_events"] == ros["reordered_events"] == 0


def test_a_late_sdk_subscriber_gets_the_last_maps(served: dict[str, Any],
                                                  msg_dir: Path) -> None:
    """An SDK subscriber created after the last update, TRANSIENT_LOCAL (as rmw_zenoh's:
    it queries the publishers' advanced-publisher caches), gets each map's last image."""
    late = Images()
    with sdk_session(served["port"], msg_dir, served["dir"] / "cache") as s:
        subscribe_maps(s, CAMERA, late, cls=LateSubscriber,
                       qos=QosProfile(durability=QosDurability.TRANSIENT_LOCAL,
                                      history_depth=1))
        t_ns = served["header"]["t_us"] * 1000
        images = wait_for(lambda: late.at(t_ns), timeout_s=10, what="the late joiner's maps")
    assert late.count() == 3  # one image per map: the last
    assert_images_are(images, served["cal"])


# ----------------------------------------------------------------------------- distributions


def _sdk_hash(name: str) -> str | None:
    """The hash chunk an SDK node of that distribution uses (None: the RIHS01 hash the SDK
    computes); Humble has no type hashes."""
    return NO_TYPE_HASH if name.startswith("humble") else None


@pytest.mark.parametrize("flag", DISTRO_CHOICES)
def test_each_ros_distro_interoperates_with_the_sdk(flag: str, msg_dir: Path, sim: Any,
                                                    tmp_path: Path) -> None:
    """``evcal serve --ros2 --ros-distro FLAG`` with SDK nodes of the matching distribution
    (``auto``: Humble's, which evcal has to detect): the SDK's publishers feed the camera,
    its subscribers get the maps (and a late TRANSIENT_LOCAL one the last maps), its topic
    info shows evcal's publishers with that distribution's hash.

    The SDK's subscriber of the other hash style (RIHS01 against Humble's none) lists the
    same topics but gets data only when evcal speaks its style too: ``auto`` serves both
    styles it sees; a fixed ``--ros-distro`` serves that one only (real rmw_zenoh Humble and
    Jazzy nodes do not talk to each other either). The attachment layout of the older
    releases (``humble-0.1.1``, ``jazzy-0.2.3``) does not matter to the SDK, which does not
    read attachments."""
    mine = "humble" if flag == "auto" else flag
    my_hash = _sdk_hash(mine)
    other_hash = None if my_hash else NO_TYPE_HASH
    port = free_port()
    ep = endpoint(port)
    ours, theirs, late = Images(), Images(), Images()
    with ServiceProcess(["--listen", ep, *SERVE, "--ros-distro", flag],
                        log_path=tmp_path / "service.log") as sp, \
            Transport(ZenohOptions.loopback(connect=[ep])) as t:
        wait_for(lambda: t.alive("@ros2_lv/0/*/0/0/NN/%/%/evcal", timeout_s=1.0),
                 timeout_s=60, what="the service's ROS 2 node")
        with sdk_session(port, msg_dir, tmp_path / "cache") as s:
            subscribe_maps(s, CAMERA, ours, type_hash=my_hash)
            subscribe_maps(s, CAMERA, theirs, type_hash=other_hash)
            publish_camera(s, sim, CAMERA, type_hash_=my_hash)
            st = settled(t, CAMERA, sim)
            assert st["errors"] == {}
            assert st["lost_messages"] == {"events": 0, "frames": 0}
            cal, header = calibration_now(t, CAMERA)
            t_ns = header["t_us"] * 1000
            images = wait_for(lambda: ours.at(t_ns), timeout_s=30,
                              what=f"the {mine} SDK subscriber's maps")
            assert_images_are(images, cal)
            subscribe_maps(s, CAMERA, late, type_hash=my_hash, cls=LateSubscriber,
                           qos=QosProfile(durability=QosDurability.TRANSIENT_LOCAL,
                                          history_depth=1))
            assert_images_are(wait_for(lambda: late.at(t_ns), timeout_s=10,
                                       what="the late joiner's maps"), cal)
            topic = output_topic(CAMERA, "contrast")
            assert s.topics()[topic] == [IMAGE]  # whatever the hash
            info = s.info(topic)
            assert info is not None
            hashes = sorted(p.type_hash for p in info.publishers if p.node_name == "evcal")
            if flag == "auto":  # both styles subscribe: evcal serves both
                assert hashes == sorted([type_hash(IMAGE), NO_TYPE_HASH])
                assert_images_are(wait_for(lambda: theirs.at(t_ns), timeout_s=30,
                                           what="the other style's SDK subscriber's maps"), cal)
            else:
                assert hashes == [DISTROS[flag].hash_of(IMAGE)]
                assert hashes == [my_hash or type_hash(IMAGE)]
                assert theirs.count() == 0  # its key never matches
        assert sp.stop() == 0, sp.log_text()


def test_an_explicit_distro_the_domain_contradicts_is_warned_of(msg_dir: Path,
                                                                tmp_path: Path) -> None:
    """Issue 40: ``--ros-distro humble`` with only Jazzy-style subscribers (the SDK's, RIHS01
    hashes) on the domain: nobody hears evcal's images, and the service says why."""
    port = free_port()
    ep = endpoint(port)
    theirs = Images()
    with ServiceProcess(["--listen", ep, *SERVE, "--ros-distro", "humble"],
                        log_path=tmp_path / "service.log") as sp, \
            Transport(ZenohOptions.loopback(connect=[ep])) as t:
        wait_for(lambda: t.alive("@ros2_lv/0/*/0/0/NN/%/%/evcal", timeout_s=1.0),
                 timeout_s=60, what="the service's ROS 2 node")
        with sdk_session(port, msg_dir, tmp_path / "cache") as s:
            subscribe_maps(s, CAMERA, theirs, type_hash=None)  # the SDK's RIHS01 hash
            wait_for(lambda: "the domain's other nodes use RIHS01" in sp.log_text(),
                     timeout_s=20, what="the warning in the service's log")
        assert sp.stop() == 0, sp.log_text()
    assert sp.log_text().count("--ros-distro humble: the domain's other nodes") == 1
