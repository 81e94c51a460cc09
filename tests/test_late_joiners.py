"""Late joiners: the last calibration of every camera reaches a subscriber that joins after
the last update -- on evcal's key (an advanced subscriber with history, as ``evcal record``
has), for a ROS 2 TRANSIENT_LOCAL subscription emulated from rmw_zenoh_cpp's sources (an
advanced subscriber with late-publisher detection; and the querying subscriber of the
releases that used a publication cache), and after a restart from the state directory.

Real zenoh sessions on tcp/127.0.0.1, scouting off, a free port each; every wait is for
what the test needs. The delays measured are printed (``pytest -s``).
"""

from __future__ import annotations

import json
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

pytest.importorskip("zenoh")
pytest.importorskip("xxhash")

import zenoh  # noqa: E402
from zenoh import ext  # noqa: E402

from evcal.clients.record import Recorder  # noqa: E402
from evcal.clients.replay import replay  # noqa: E402
from evcal.io.ros2msg import ros2_store  # noqa: E402
from evcal.io.rosbag import IMAGE  # noqa: E402
from evcal.io.wire import decode_calibration  # noqa: E402
from evcal.online import OnEIConfig  # noqa: E402
from evcal.service.camera import CalibrationUpdate  # noqa: E402
from evcal.service.core import ServiceConfig  # noqa: E402
from evcal.service.ros2 import (  # noqa: E402
    DISTROS,
    Ros2Options,
    RosNode,
    topic_key,
)
from evcal.service.ros2out import RosCalibrationPublisher, output_topic  # noqa: E402
from evcal.service.server import run  # noqa: E402
from evcal.service.transport import Transport, ZenohOptions  # noqa: E402
from evcal.sim.ideal import SimConfig, simulate_ideal  # noqa: E402
from evcal.testing import endpoint, free_port, wait_for  # noqa: E402

pytestmark = pytest.mark.timeout(180)

CAMERA = "rig/cam0"
LATE_S = 1.0  # the acceptance: a late joiner has the last calibration within 1 s


class Served:
    """An in-process service on a free port, stopped when the block ends."""

    def __init__(self, state_dir: Path, **kwargs: Any) -> None:
        self.ep = endpoint(free_port())
        self.stop = threading.Event()
        ready = threading.Event()
        cfg = ServiceConfig(on_full="block", status_period_s=0.2,
                            onei=OnEIConfig(n_small=3000, n_large=10**6, log_offset=30.0,
                                            window_frames=5))
        self.thread = threading.Thread(
            target=run, args=(ZenohOptions.loopback(listen=[self.ep]), cfg),
            kwargs={"stop": self.stop, "ready": lambda s: ready.set(),
                    "state_dir": state_dir, **kwargs}, daemon=True)
        self.thread.start()
        assert ready.wait(60), "the service did not start"

    def close(self) -> None:
        self.stop.set()
        self.thread.join(60)


def status_of(t: Transport, camera: str) -> dict[str, Any]:
    replies = t.get(f"evcal/{camera}/status", timeout_s=2.0)
    return json.loads(replies[0].payload) if replies and replies[0].ok else {}


def stream_until_settled(ep: str, camera: str = CAMERA) -> dict[str, Any]:
    """Replay a small simulation into the service; its status once every message is
    processed (no update comes after)."""
    sim = simulate_ideal(SimConfig(height=36, width=48, duration_s=1.5, seed=11))
    with Transport(ZenohOptions.loopback(connect=[ep])) as t:
        replay(t, sim.recording, camera, speed=None)
        return wait_for(lambda: (s := status_of(t, camera)) and s["updates"] >= 1
                        and s["in_flight_messages"] == 0 and s, timeout_s=60,
                        what="the camera's last update")


@pytest.fixture(scope="module")
def service(tmp_path_factory: pytest.TempPathFactory) -> Iterator[dict[str, Any]]:
    served = Served(tmp_path_factory.mktemp("state"), ros2=Ros2Options(distro="auto"))
    try:
        status = stream_until_settled(served.ep)
        with Transport(ZenohOptions.loopback(connect=[served.ep])) as t:
            reply = t.get(f"evcal/{CAMERA}/calibration", timeout_s=5.0)[0]
        assert reply.ok
        yield {"ep": served.ep, "status": status, "payload": reply.payload}
    finally:
        served.close()


def _timed_first(subscribe: Any) -> tuple[float, list[Any]]:
    """Seconds from subscribing to the first sample, and the samples."""
    got: list[Any] = []
    first = threading.Event()

    def on(*args: Any) -> None:
        got.append(args)
        first.set()

    t0 = time.monotonic()
    subscribe(on)
    assert first.wait(10), "the late joiner got nothing"
    return time.monotonic() - t0, got


def test_a_late_client_gets_the_last_calibration(service: dict[str, Any]) -> None:
    last_seq = service["status"]["calibration_seq"]
    with Transport(ZenohOptions.loopback(connect=[service["ep"]])) as t:
        plain: list[Any] = []
        t.subscribe(f"evcal/{CAMERA}/calibration", lambda *a: plain.append(a))
        delay, got = _timed_first(lambda on: t.subscribe(
            "evcal/**/calibration", on, history=True))
    print(f"evcal key: late joiner got the last calibration in {delay * 1e3:.1f} ms")
    assert delay < LATE_S
    key, payload, _ = got[0]
    assert key == f"evcal/{CAMERA}/calibration"
    cal, header = decode_calibration(payload)
    assert header["seq"] == last_seq
    assert payload == service["payload"]  # the very message a query returns
    assert cal.shape == (36, 48)
    assert plain == []  # a plain subscriber that joined late has nothing


def test_evcal_record_started_late_records_the_last_calibration(
        service: dict[str, Any], tmp_path: Path) -> None:
    recorder = Recorder(str(tmp_path / "late.mcap"), [CAMERA])
    with Transport(ZenohOptions.loopback(connect=[service["ep"]])) as t:
        t0 = time.monotonic()
        recorder.subscribe(t)
        wait_for(lambda: CAMERA in recorder.writers
                 and recorder.writers[CAMERA].counts["calibrations"] >= 1,
                 timeout_s=10, interval_s=0.01, what="the recorded calibration")
        delay = time.monotonic() - t0
    counts = recorder.close()
    print(f"evcal record: late start recorded the last calibration in {delay * 1e3:.1f} ms")
    assert delay < LATE_S
    assert counts[CAMERA]["calibrations"] == 1


def _rmw_compact_attachment(raw: bytes) -> tuple[int, int, bytes]:
    """rmw_zenoh 0.1.2+/0.2.4+ ``AttachmentData(const zenoh::Bytes &)``: int64 sequence
    number, int64 source timestamp, std::array<uint8_t, 16> (a sequence: its length must be
    16); anything else throws."""
    seq = int.from_bytes(raw[0:8], "little", signed=True)
    t_ns = int.from_bytes(raw[8:16], "little", signed=True)
    if len(raw) < 33 or raw[16] != 16:
        raise RuntimeError("Incorrect sequence size")
    return seq, t_ns, raw[17:33]


def test_a_late_ros2_transient_local_subscriber_gets_the_last_images(
        service: dict[str, Any]) -> None:
    """rmw_zenoh 0.2.4+ (Jazzy, Kilted, Rolling): a TRANSIENT_LOCAL, RELIABLE subscription
    is an advanced subscriber with history (late publishers detected, depth samples per
    publisher) and heartbeat recovery, on its own exact key."""
    cal, _ = decode_calibration(service["payload"])
    key = topic_key(0, output_topic(CAMERA, "contrast"), IMAGE)
    with Transport(ZenohOptions.loopback(connect=[service["ep"]])) as t:
        got: list[tuple[bytes, bytes]] = []
        first = threading.Event()

        def on_sample(sample: Any) -> None:
            got.append((sample.payload.to_bytes(), sample.attachment.to_bytes()))
            first.set()

        t0 = time.monotonic()
        sub = ext.declare_advanced_subscriber(
            t.session, key, on_sample,
            history=ext.HistoryConfig(detect_late_publishers=True, max_samples=10),
            recovery=ext.RecoveryConfig(periodic_queries=None, heartbeat=True),
            subscriber_detection=True)
        try:
            assert first.wait(10), "the TRANSIENT_LOCAL subscriber got nothing"
            delay = time.monotonic() - t0
        finally:
            sub.undeclare()
    print(f"ROS 2 TRANSIENT_LOCAL: late subscriber got the last image in {delay * 1e3:.1f} ms")
    assert delay < LATE_S
    assert len(got) == 1  # the publisher keeps one (depth 1)
    data, att = got[0]
    seq, _, gid = _rmw_compact_attachment(att)
    assert seq >= 1
    msg = ros2_store().deserialize_cdr(data, IMAGE)
    img = np.frombuffer(msg.data.tobytes(), "<f4").reshape(msg.height, msg.width)
    np.testing.assert_array_equal(img, cal.contrast.astype(np.float32))


def _update(h: int = 6, w: int = 8) -> CalibrationUpdate:
    """An update of a small made-up calibration (contrast a ramp)."""
    from evcal.calibration import Calibration

    contrast = np.linspace(0.1, 0.3, h * w, dtype=np.float32).reshape(h, w)
    zeros = np.zeros((h, w), np.float32)
    cal = Calibration(contrast=contrast, bias=zeros, valid=np.ones((h, w), np.uint8),
                      reason=np.zeros((h, w), np.uint8), stderr_contrast=zeros,
                      stderr_bias=zeros, special=np.ones((h, w), np.uint8), log_offset=30.0,
                      method="onei", n_events=np.zeros((h, w), np.int64))
    return CalibrationUpdate(camera="c", t_us=5_000_000, seq=0, calibration=cal, message=b"",
                             t_recv_s=0.0, t_start_s=0.0, t_fed_s=0.0, t_cal_s=0.0,
                             t_enc_s=0.0)


def test_a_late_querying_subscriber_of_the_publication_cache_releases() -> None:
    """rmw_zenoh 0.1.0-0.1.1 (Humble) and 0.2.0-0.2.1 (Jazzy): a TRANSIENT_LOCAL
    subscription is a querying subscriber that asks ``*/<its key>`` (any reply key, every
    queryable, no consolidation); the publisher's publication cache answers from
    ``<zid>/<key>`` with the cached samples, named attachments included."""
    ep = endpoint(free_port())
    profile = DISTROS["jazzy-0.2.3"]
    with Transport(ZenohOptions.loopback(listen=[ep])) as pub_t:
        node = RosNode(zid=pub_t.zid, domain=0)
        out = RosCalibrationPublisher(node, pub_t.put, pub_t.token, session=pub_t,
                                      distros=lambda: (profile,))
        upd = _update()
        out.publish("lab/cam9", upd)
        key = topic_key(0, output_topic("lab/cam9", "contrast"), IMAGE)
        with Transport(ZenohOptions.loopback(connect=[ep])) as t:
            def ask() -> list[Any]:
                return [r for r in t.session.get(
                    f"*/{key}", accept_replies=zenoh.ReplyKeyExpr.ANY,
                    target=zenoh.QueryTarget.ALL,
                    consolidation=zenoh.ConsolidationMode.NONE, timeout=2.0) if r.ok]

            t0 = time.monotonic()
            replies = wait_for(ask, timeout_s=10, interval_s=0.01, what="a cached reply")
            delay = time.monotonic() - t0
    print(f"publication cache: late querying subscriber answered in {delay * 1e3:.1f} ms")
    assert delay < LATE_S
    assert len(replies) == 1
    sample = replies[0].ok
    assert str(sample.key_expr) == key
    att = sample.attachment.to_bytes()
    assert att.startswith(b"\x0fsequence_number")  # the layout those releases read
    msg = ros2_store().deserialize_cdr(sample.payload.to_bytes(), IMAGE)
    img = np.frombuffer(msg.data.tobytes(), "<f4").reshape(msg.height, msg.width)
    np.testing.assert_array_equal(img, upd.calibration.contrast)


def test_a_restarted_service_serves_its_restored_calibration_to_late_joiners(
        tmp_path: Path) -> None:
    state = tmp_path / "state"
    first = Served(state)
    try:
        status = stream_until_settled(first.ep)
    finally:
        first.close()  # snapshots written at shutdown
    second = Served(state, ros2=Ros2Options(distro="humble"))
    ros_key = topic_key(0, output_topic(CAMERA, "contrast"), IMAGE, "TypeHashNotSupported")
    try:
        with Transport(ZenohOptions.loopback(connect=[second.ep])) as t:
            delay, got = _timed_first(lambda on: t.subscribe(
                f"evcal/{CAMERA}/calibration", on, history=True))
            # and as a TRANSIENT_LOCAL image, to a Humble subscriber (rmw_zenoh 0.1.2+)
            ros_delay, ros_got = _timed_first(lambda on: t.subscribe(
                ros_key, on, attachment=True, history=True))
            # the latched publisher announces itself (zenoh's publisher detection) ...
            cache = f"evcal/{CAMERA}/calibration/@adv/**"
            assert t.alive(cache)
            # ... until the camera is forgotten: late joiners then get nothing
            forgot = t.get(f"evcal/{CAMERA}/forget", timeout_s=5.0)
            assert json.loads(forgot[0].payload)["forgotten"] is True
            for gone in (cache, f"{ros_key}/@adv/**"):
                wait_for(lambda gone=gone: not t.alive(gone, timeout_s=0.5), timeout_s=10,
                         what=f"the forgotten camera's cache {gone} undeclared")
    finally:
        second.close()
    print(f"restart: late joiner got the restored calibration in {delay * 1e3:.1f} ms, "
          f"a late Humble TRANSIENT_LOCAL subscriber its image in {ros_delay * 1e3:.1f} ms")
    assert delay < LATE_S
    assert ros_delay < LATE_S
    cal, header = decode_calibration(got[0][1])
    assert header["seq"] == status["calibration_seq"]
    _, data, _, att = ros_got[0]
    assert _rmw_compact_attachment(att)[0] == 1
    msg = ros2_store().deserialize_cdr(data, IMAGE)
    img = np.frombuffer(msg.data.tobytes(), "<f4").reshape(msg.height, msg.width)
    np.testing.assert_array_equal(img, cal.contrast.astype(np.float32))
