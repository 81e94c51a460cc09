"""``evcal serve --workers N`` without a network: shards, the supervisor, worker commands.

The end-to-end run (a real supervisor, two workers, replays, a killed worker) is in
``test_service_workers_e2e.py``.
"""

from __future__ import annotations

import argparse
import hashlib
import os
import sys
import time

import pytest
from test_service_core import Collector, feed, make_service, settle, stream

from evcal.online import OnEIConfig
from evcal.service import keys
from evcal.service.cli import build_parser, config_from_args
from evcal.service.core import Service, ServiceConfig
from evcal.service.state import StateStore, snapshot_name
from evcal.service.workers import (
    OWN_OPTIONS,
    Supervisor,
    worker_command,
    worker_env,
    worker_rrd,
)


def ids_of_shard(shard: int, count: int, n: int, stem: str = "lab/cam") -> list[str]:
    """``n`` camera ids that hash to ``shard`` of ``count``."""
    out = [f"{stem}{k}" for k in range(200) if keys.shard_of(f"{stem}{k}", count) == shard]
    return out[:n]


def _blake2b_shard(camera: bytes, n: int) -> int:
    return int.from_bytes(hashlib.blake2b(camera, digest_size=8).digest(), "big") % n


def test_shard_of_is_a_well_mixed_stable_hash_of_the_id():
    assert keys.shard_of("lab/rig1/cam0", 7) == _blake2b_shard(b"lab/rig1/cam0", 7)
    assert keys.shard_of("kamera/ö", 3) == _blake2b_shard("kamera/ö".encode(), 3)
    assert keys.shard_of("lab/rig1/cam0", 2) == 0  # the same in every run and process
    # ids that differ in one character spread (CRC-32 put cam0..cam3 on one of 2 shards)
    assert len({keys.shard_of(f"lab/rig1/cam{k}", 2) for k in range(4)}) == 2
    assert {keys.shard_of(f"c{k}", 1) for k in range(20)} == {0}
    counts = [sum(keys.shard_of(f"lab/cam{k}", 4) == s for k in range(400)) for s in range(4)]
    assert min(counts) > 70, counts  # spread over every shard
    assert keys.parse_shard("1/3") == (1, 3)
    for bad in ("3/3", "-1/2", "0/0", "a/2", "1", "1/"):
        with pytest.raises(ValueError, match="I/N"):
            keys.parse_shard(bad)


def test_a_shard_ignores_other_shards_cameras_before_counting():
    ours, theirs = ids_of_shard(0, 2, 1)[0], ids_of_shard(1, 2, 1)[0]
    svc, pub = make_service(shard=(0, 2))
    try:
        feed(svc, theirs, stream(n_frames=4))
        svc.on_sample(f"evcal/{theirs}/events", b"junk")  # would be an error of ours
        # an invalid id is counted only by the shard it hashes to
        bad = next(f"bad*{k}" for k in range(50) if keys.shard_of(f"bad*{k}", 2) == 1)
        svc.on_sample(f"evcal/{bad}/events", b"x")
        settle(svc)
        assert svc.cameras == {}
        assert svc.invalid_camera_ids == 0
        assert pub.items == []
        assert not svc.accepts_key(f"evcal/{theirs}/events")
        assert svc.accepts_key(f"evcal/{ours}/frames")
        assert svc.accepts_key("evcal/x")
        feed(svc, ours, stream(n_frames=4))
        settle(svc)
        assert sorted(svc.cameras) == [ours]
        assert svc.query_calibration(f"evcal/{theirs}/calibration", {}) == []
        info = svc.cameras_info()
        assert info["shard"] == "0/2"
        assert [c["id"] for c in info["cameras"]] == [ours]
    finally:
        svc.close()


def test_each_shard_restores_only_its_own_snapshots(tmp_path):
    store = StateStore(tmp_path)
    cams = ids_of_shard(0, 2, 1) + ids_of_shard(1, 2, 1)
    svc = Service(ServiceConfig(onei=OnEIConfig(n_small=50, n_large=10_000)), Collector(),
                  store=store)
    for cam in cams:
        feed(svc, cam, stream(n_frames=6))
    settle(svc)
    svc.close()  # writes both snapshots
    for shard, cam in enumerate(cams):
        part = Service(ServiceConfig(shard=(shard, 2)), Collector(), store=store)
        try:
            assert part.restore() == [cam]
        finally:
            part.close()
    # a damaged file is judged by its camera's shard alone (never read by the other)
    (tmp_path / "x").mkdir()
    theirs = ids_of_shard(1, 2, 1)[0]
    (tmp_path / "x" / snapshot_name(theirs)).write_bytes(b"not a zip")
    other = StateStore(tmp_path / "x")
    assert other.snapshots(want=lambda cam: keys.shard_of(cam, 2) == 0) == []
    assert other.bad == 0
    assert other.snapshots() == []
    assert other.bad == 1


def test_ros_router_leaves_other_shards_topics_alone():
    from evcal.service.ros2 import IMAGE, RosNode, RosRouter, topic_key

    delivered: list[str] = []
    ours, theirs = ids_of_shard(0, 2, 1)[0], ids_of_shard(1, 2, 1)[0]
    router = RosRouter(RosNode(zid="ab", domain=0),
                       lambda cam, kind, payload, t: delivered.append(cam),
                       owns=lambda cam: keys.shard_of(cam, 2) == 0)
    for cam in (ours, theirs):
        key = topic_key(0, f"/{cam}/image_raw", IMAGE)
        assert router.accepts(key) == (cam == ours)
        router.on_sample(key, b"", "", None)
    assert delivered == [ours]
    assert router.ignored == {}
    assert router.declare_pending(lambda token: None) == 1  # a token for our topic only


def test_worker_command_passes_the_users_options_through():
    parser = build_parser()
    args = parser.parse_args([
        "--workers", "3", "--listen", "tcp/0.0.0.0:7447", "--cfg", "a:1", "--instance", "lab",
        "--state-dir", "st", "--rrd", "out/run.rrd", "--rerun-serve", "9000", "--on-full",
        "block", "--queue-mb", "48", "--log-offset", "30", "--window-frames", "0", "-vv",
        "--ros2", "--ros-topic-map", "/dvs=lab/cam0", "--ros-topic-map", "/x/events=b",
        "--cameras", "lab/**", "--sign-key", "k.key"])
    assert args.workers == 3
    cmd = worker_command(parser, args, index=2, count=3, endpoint="unixsock-stream//t/r.sock",
                         instance="lab-w2")
    assert cmd[:3] == [sys.executable, "-m", "evcal.service"]
    worker = parser.parse_args(cmd[3:])
    for dest, value in vars(args).items():
        if dest not in OWN_OPTIONS and dest != "threads":
            assert getattr(worker, dest) == value, dest
    # the re-solve's threads: the cores shared out among the workers, unless given
    from evcal.online import usable_cores  # noqa: PLC0415

    assert worker.threads == max(1, usable_cores() // 3)
    given = parser.parse_args(["--workers", "3", "--threads", "5"])
    cmd = worker_command(parser, given, index=0, count=3, endpoint="e", instance="w0")
    assert parser.parse_args(cmd[3:]).threads == 5
    # not the user's --cfg: the worker's link without shared memory (issue 23)
    assert (worker.mode, worker.connect, worker.listen, worker.cfg) == (
        "client", ["unixsock-stream//t/r.sock"], [], ["transport/shared_memory/enabled:false"])
    assert worker.no_multicast_scouting
    assert worker.workers == 1
    assert (worker.shard, worker.instance, worker.rrd, worker.rerun_serve) == (
        (2, 3), "lab-w2", "out/run.w2.rrd", 9002)
    assert config_from_args(worker).shard == (2, 3)
    # the command line's OnEI defaults are the library's service defaults
    from evcal.service.core import ServiceConfig  # noqa: PLC0415

    assert config_from_args(parser.parse_args([])).onei == ServiceConfig().onei
    assert worker_rrd("run", 1) == "run.w1"
    env = worker_env({"EVCAL_CONNECT": "tcp/x:1", "EVCAL_MODE": "peer", "HOME": "/h"})
    assert env["HOME"] == "/h"
    assert "EVCAL_CONNECT" not in env
    assert "EVCAL_MODE" not in env
    with pytest.raises(SystemExit):
        parser.parse_args(["--workers", "0"])


def test_workers_and_shard_are_exclusive(capsys):
    from evcal.service.cli import main_serve

    assert main_serve(["--workers", "2", "--shard", "0/2"]) == 2
    assert "--shard goes with one worker" in capsys.readouterr().err


def test_as_router_listens_where_the_service_would_have():
    pytest.importorskip("zenoh")
    from evcal.service.transport import ZenohOptions, as_router

    local = "unixsock-stream//tmp/x/r.sock"
    peer = as_router(ZenohOptions(), local)  # zenoh's default: a peer on a free port
    assert peer.mode == "router"
    assert peer.listen == ("tcp/[::]:0", local)
    client = as_router(ZenohOptions(mode="client", connect=("tcp/r:7447",),
                                    extra=(("listen/endpoints", '["tcp/[::]:1"]'),)), local)
    assert client.listen == ("tcp/[::]:1", local)
    assert client.connect == ("tcp/r:7447",)
    assert client.extra == ()
    assert as_router(ZenohOptions(mode="router"), local).listen == ("tcp/[::]:7447", local)


def _script(code: str) -> list[str]:
    return [sys.executable, "-c", code]


def _poll_until(sup: Supervisor, done, timeout_s: float = 20.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not done() and time.monotonic() < deadline:
        if not sup.poll():
            return
        time.sleep(0.02)


def test_supervisor_restarts_with_backoff_then_gives_up():
    sup = Supervisor([_script("import sys; sys.exit(3)")], ["w0"], first_backoff_s=0.05,
                     max_backoff_s=0.2, max_quick_failures=3)
    t0 = time.monotonic()
    _poll_until(sup, lambda: sup.failed is not None)
    assert sup.failed is not None
    assert "failed 4 time(s)" in sup.failed
    assert sup.slots[0].exit_codes == [3, 3, 3, 3]
    assert sup.restarts == 3
    assert time.monotonic() - t0 >= 0.05 + 0.1 + 0.2  # the back-offs
    usage = Supervisor([_script("import sys; sys.exit(2)")], ["w0"])
    _poll_until(usage, lambda: usage.failed is not None)
    assert usage.failed is not None
    assert "bad usage" in usage.failed
    assert usage.restarts == 0


def test_supervisor_stops_workers_and_reports_unclean_ones():
    term = ("import signal, sys, time\n"
            "signal.signal(signal.SIGTERM, lambda *a: sys.exit(0))\n"
            "time.sleep(60)\n")
    sup = Supervisor([_script(term), _script("import time; time.sleep(60)")], ["w0", "w1"])
    sup.poll()
    time.sleep(1.0)  # both running, the handler installed
    info = sup.info()
    assert [w["alive"] for w in info["workers"]] == [True, True]
    pids = [w["pid"] for w in info["workers"]]
    assert sup.stop(timeout_s=10) is False  # w1 dies of SIGTERM: not a clean stop
    assert [s.exit_codes for s in sup.slots] == [[0], [-15]]
    for pid in pids:
        with pytest.raises(ProcessLookupError):
            os.kill(pid, 0)


def test_a_worker_stops_when_its_supervisor_goes_away(tmp_path):
    """The worker side: stdin at end-of-file (the supervisor's end closed) sets stop."""
    import subprocess

    code = ("import sys, threading, os\n"
            "from evcal.service.workers import watch_parent\n"
            "stop = threading.Event()\n"
            "watch_parent(os.getppid(), stop)\n"
            "print('watching', flush=True)\n"
            "sys.exit(0 if stop.wait(20) else 1)\n")
    proc = subprocess.Popen(_script(code), stdin=subprocess.PIPE, stdout=subprocess.PIPE)
    assert proc.stdout is not None
    assert proc.stdin is not None
    assert proc.stdout.readline() == b"watching\n"
    proc.stdin.close()
    assert proc.wait(20) == 0
    proc.stdout.close()
    gone = subprocess.run(_script(code.replace("os.getppid()", "1")), capture_output=True,
                          stdin=subprocess.PIPE, timeout=20)
    assert gone.returncode == 0  # a supervisor that is not its parent: gone already


def test_parser_has_the_supervisor_options():
    parser = build_parser()
    dests = {a.dest for a in parser._actions}
    assert OWN_OPTIONS <= dests | {"help"}
    assert isinstance(parser, argparse.ArgumentParser)


def test_an_update_between_frames_is_snapshotted(tmp_path):
    """A calibration published by ``on_idle`` (an offset estimate that finished after the
    last frame) marks the camera changed: the next snapshot keeps it, so a restarted worker
    answers with it (it used to be lost: only messages marked a camera changed)."""
    store = StateStore(tmp_path)
    svc = Service(ServiceConfig(onei=OnEIConfig(n_small=50, n_large=10_000)), Collector(),
                  store=store)
    try:
        feed(svc, "lab/cam0", stream(n_frames=6))
        settle(svc)
        cam = svc.cameras["lab/cam0"]
        svc.snapshot()
        with cam.lock:
            assert not cam.state.dirty
            cal = cam.state.calibrator
            assert cal is not None
            finished = iter([True])  # an estimate just finished, once
            cal.poll_offset = lambda: next(finished, False)
            (upd,) = cam.state.on_idle(now_s=0.0)
            assert cam.state.dirty
        assert svc.snapshot() == 1
        snap = store.load("lab/cam0")
        assert snap is not None
        assert snap.arrays["calibration_msg"].tobytes() == upd.message
    finally:
        svc.close()
