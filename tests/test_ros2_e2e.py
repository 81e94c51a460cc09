"""ROS 2 over rmw_zenoh end to end, in separate processes on loopback: a ROS-2-style
publisher (``evcal replay BAG --ros2``: rmw_zenoh keys, CDR, attachments, liveliness tokens)
streams a simulated camera's EventPackets and Images, and the shared real bag's events, into
``evcal serve --ros2``, which publishes calibrations on evcal's key and as ROS 2 Images that a
CDR decoder reads back; ``evcal record --ros2`` writes the domain to a ROS 2 MCAP meanwhile.

One service process for the module; the simulation is small (64x48, 3 s).
"""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import threading
from pathlib import Path
from typing import Any

import numpy as np
import pytest

pytest.importorskip("zenoh")

from evcal.io import open_recording  # noqa: E402
from evcal.io.ros2msg import ros2_store, write_ros2_bag  # noqa: E402
from evcal.io.rosbag import IMAGE  # noqa: E402
from evcal.io.wire import decode_calibration  # noqa: E402
from evcal.service.ros2 import (  # noqa: E402
    SPECIAL_SCALE,
    dds_type,
    decode_attachment,
    parse_topic_key,
)
from evcal.service.transport import Transport, ZenohOptions  # noqa: E402
from evcal.sim.ideal import SimConfig, simulate_ideal  # noqa: E402
from evcal.testing import (  # noqa: E402
    ServiceProcess,
    endpoint,
    free_port,
    python_env,
    run_client,
    wait_for,
)

pytestmark = pytest.mark.timeout(240)

ZARGS = ["--no-multicast-scouting"]
CAMERA = "sim/cam0"
SHARED_N = 571_266  # the shared bag's decoded event count (tests/test_io_ros.py)


@pytest.fixture(scope="module")
def sim_bag(tmp_path_factory: pytest.TempPathFactory) -> tuple[Any, Path]:
    sim = simulate_ideal(SimConfig(height=48, width=64, duration_s=3.0, seed=1))
    path = write_ros2_bag(sim.recording, tmp_path_factory.mktemp("bag") / "sim.mcap",
                          namespace="/" + CAMERA, encoding="libcaer_cmp")
    return sim, path


@pytest.fixture(scope="module")
def service(tmp_path_factory: pytest.TempPathFactory):
    d = tmp_path_factory.mktemp("ros2_service")
    ep = endpoint(free_port())
    args = ["--listen", ep, *ZARGS, "--ros2", "--on-full", "block", "--n-small", "15000",
            "--n-large", "10000000", "--log-offset", "30", "--status-period", "0.2", "-v"]
    with ServiceProcess(args, log_path=d / "service.log") as sp:
        with Transport(ZenohOptions.loopback(connect=[ep])) as t:
            wait_for(lambda: t.alive("@ros2_lv/0/*/0/0/NN/%/%/evcal", timeout_s=1.0),
                     timeout_s=60, what="the service's ROS 2 node token")
            yield {"ep": ep, "dir": d, "proc": sp, "t": t}
        if sp.alive():
            assert sp.stop() == 0, sp.log_text()


def status_of(t: Transport, camera: str) -> dict[str, Any]:
    replies = t.get(f"evcal/{camera}/status", timeout_s=2.0)
    return json.loads(replies[0].payload) if replies and replies[0].ok else {}


def test_ros2_publisher_to_service_to_ros2_images(service, sim_bag, tmp_path: Path) -> None:
    sim, bag = sim_bag
    t: Transport = service["t"]
    lock = threading.Lock()
    ros_images: list[tuple[str, bytes, bytes | None]] = []
    evcal_cals: list[bytes] = []

    def on_ros(key: str, payload: bytes, enc: str, att: bytes | None) -> None:
        with lock:
            ros_images.append((key, payload, att))

    def on_evcal(key: str, payload: bytes, enc: str) -> None:
        with lock:
            evcal_cals.append(payload)

    t.subscribe(f"0/{CAMERA}/calibration/*/{dds_type(IMAGE)}/*", on_ros, attachment=True)
    t.subscribe(f"evcal/{CAMERA}/calibration", on_evcal)
    # `evcal record --ros2` hears the domain meanwhile (stopped with SIGINT below)
    out = tmp_path / "domain.mcap"
    recorder = subprocess.Popen(
        [sys.executable, "-m", "evcal.clients.record", "--ros2", "--out", str(out),
         "--connect", service["ep"], *ZARGS], env=python_env(), stderr=subprocess.PIPE,
        text=True)
    try:
        assert recorder.stderr is not None
        assert "recording ROS 2 domain 0" in recorder.stderr.readline()  # it has subscribed
        res = run_client("replay", [str(bag), "--ros2", "--connect", service["ep"], *ZARGS,
                                    "--max-rate"])
        assert res.returncode == 0, res.stderr
        assert "the service processed 300 event messages" in res.stderr, res.stderr
        n_frames = len(sim.recording.frames)
        st = wait_for(lambda: (s := status_of(t, CAMERA)).get("frames") == n_frames and s,
                      timeout_s=60, what="every frame processed")
        assert st["events"] == sim.recording.n_events
        assert st["errors"] == {}
        assert st["lost_messages"] == {"events": 0, "frames": 0}
        assert st["updates"] >= 1

        # the latest update on evcal's key and as three ROS 2 Images, stamped alike
        def latest() -> dict[str, Any] | None:
            with lock:
                if not evcal_cals:
                    return None
                cal, header = decode_calibration(evcal_cals[-1])
                images = {}
                for key, payload, att in ros_images:
                    msg = ros2_store().deserialize_cdr(payload, IMAGE)
                    t_ns = msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec
                    if t_ns == header["t_us"] * 1000:
                        parsed = parse_topic_key(key)
                        assert parsed is not None
                        assert decode_attachment(att) is not None
                        images[parsed.topic.rpartition("/")[2]] = msg
            return {"cal": cal, "images": images} if len(images) == 3 else None

        got = wait_for(latest, timeout_s=30, what="the ROS 2 images of the latest update")
        cal, images = got["cal"], got["images"]
        for name in ("contrast", "bias"):
            msg = images[name]
            assert (msg.encoding, msg.height, msg.width) == ("32FC1", 48, 64)
            np.testing.assert_array_equal(
                np.frombuffer(msg.data.tobytes(), "<f4").reshape(48, 64), getattr(cal, name))
        np.testing.assert_array_equal(images["special"].data.reshape(48, 64) // SPECIAL_SCALE,
                                      cal.special)
        # evcal is a ROS 2 node with three publishers and two subscriptions
        tokens = t.alive("@ros2_lv/0/**", timeout_s=2.0)
        mine = [k.split("/") for k in tokens if k.split("/")[8:9] == ["evcal"]]
        assert sorted(c[9] for c in mine if c[5] == "MP") == [
            f"%{CAMERA.replace('/', '%')}%calibration%{n}" for n in ("bias", "contrast",
                                                                     "special")]
        assert sorted(c[9] for c in mine if c[5] == "MS") == [
            f"%{CAMERA.replace('/', '%')}%{n}" for n in ("events", "image_raw")]
        assert [c for c in mine if c[5] == "NN"]
    finally:
        if recorder.poll() is None:
            recorder.send_signal(signal.SIGINT)
        _, err = recorder.communicate(timeout=60)
    assert recorder.returncode == 0, err
    # the recording: the driver's topics and evcal's images, in a ROS 2 MCAP evcal reads
    back = open_recording(out)  # evcal's calibration images are not taken for frames
    assert back.metadata["frames_topic"] == f"/{CAMERA}/image_raw"
    np.testing.assert_array_equal(back.events, sim.recording.events)
    np.testing.assert_array_equal(back.frames.images, sim.recording.frames.images)
    res = subprocess.run([sys.executable, "-m", "evcal", "info", str(out)],
                         capture_output=True, text=True, timeout=120, env=python_env())
    assert res.returncode == 0, res.stderr
    assert "64x48" in res.stdout
    from rosbags.rosbag2 import Reader

    with Reader(out) as reader:
        topics = {c.topic: c.msgtype for c in reader.connections}
    assert topics[f"/{CAMERA}/calibration/contrast"] == IMAGE


def test_the_shared_bag_streams_into_the_service(service, shared_data: Path) -> None:
    bag = shared_data / "ros2_event_packet_mcap"
    if not (bag / "metadata.yaml").is_file():
        pytest.skip(f"the shared ROS 2 bag is not at {bag}")
    t: Transport = service["t"]
    res = run_client("replay", [str(bag), "--ros2", "--connect", service["ep"], *ZARGS,
                                "--max-rate"])
    assert res.returncode == 0, res.stderr
    st = wait_for(lambda: (s := status_of(t, "event_camera")).get("events") == SHARED_N and s,
                  timeout_s=60, what="every event of the shared bag")
    assert st["sensor"] == "346x260"
    assert st["event_messages"] == 100
    assert st["errors"] == {}
    assert st["lost_messages"] == {"events": 0, "frames": 0}


def test_replay_ros2_says_when_nobody_listens(sim_bag) -> None:
    _, bag = sim_bag
    ep = endpoint(free_port())
    with Transport(ZenohOptions.loopback(listen=[ep])):
        res = run_client("replay", [str(bag), "--ros2", "--connect", ep, *ZARGS, "--max-rate",
                                    "--wait-subscriber", "0.5"])
    assert res.returncode == 3, res.stderr
    assert "nobody subscribes" in res.stderr
    res = run_client("replay", [str(bag), "--ros2", "--camera", "x", "--connect", ep, *ZARGS])
    assert res.returncode == 2
    assert "do not go with --ros2" in res.stderr


def test_replay_ros2_to_a_listener_that_is_no_service_is_unconfirmed(sim_bag) -> None:
    """Something subscribes to the topics (a ROS 2 node, a recorder) but no evcal service
    answers for the camera: delivery is unconfirmed, exit 7 as `evcal replay`'s table says
    (before: 0, with a note)."""
    _, bag = sim_bag
    ep = endpoint(free_port())
    with Transport(ZenohOptions.loopback(listen=[ep])) as t:
        t.subscribe("0/**", lambda key, payload, enc: None)
        res = run_client("replay", [str(bag), "--ros2", "--connect", ep, *ZARGS, "--max-rate",
                                    "--wait-subscriber", "10"])
    assert res.returncode == 7, res.stderr
    assert f"camera {CAMERA}: delivery not confirmed" in res.stderr, res.stderr
    assert "unconfirmed (exit code 7)" in res.stderr, res.stderr


def test_replay_ros2_judges_exit_codes_in_replays_order(capsys) -> None:
    """The cameras' accounts are judged as `evcal replay` judges one run: refused (5) before
    dropped (6) before lost (4) before unconfirmed (7); before, all of these were 4 (or 0)."""
    from evcal.clients.replay import ReplayStats
    from evcal.clients.rosreplay import BagReplayStats, report

    def account(sent: int, *, processed: int, dropped: int = 0, rejected: int = 0,
                confirmed: bool = True) -> ReplayStats:
        acc = ReplayStats(event_messages=sent, confirmed=confirmed)
        acc.delivered = {"event_messages": processed, "events": 10 * processed, "frames": 0,
                         "dropped_messages": dropped, "rejected_messages": rejected,
                         "refused_messages": 0,
                         "accounted_messages": processed + dropped + rejected}
        return acc

    def code(accounts: dict[str, ReplayStats], unmatched: int = 0) -> int:
        stats = BagReplayStats(messages={"/a/events": 10, "/b/events": 10},
                               cameras={"a": ["/a/events"], "b": ["/b/events"]},
                               accounts=accounts, unmatched_messages=unmatched)
        return report("evcal replay", stats, 5.0, 0)

    ok = account(10, processed=10)
    assert code({"a": ok, "b": ok}) == 0
    assert code({"a": ok, "b": account(10, processed=9, rejected=1)}) == 5
    assert code({"a": account(10, processed=9, dropped=1),
                 "b": account(10, processed=9, rejected=1)}) == 5
    assert code({"a": account(10, processed=9, dropped=1), "b": ok}, unmatched=2) == 6
    assert code({"a": account(10, processed=9), "b": ok}) == 4  # one never arrived
    assert code({"a": ok, "b": ok}, unmatched=1) == 4
    assert code({"a": ok, "b": account(10, processed=3, confirmed=False)}) == 7
    assert code({"a": account(10, processed=9), "b": account(10, processed=3,
                                                              confirmed=False)}) == 4
    assert "dropped (exit code 6)" in capsys.readouterr().err
