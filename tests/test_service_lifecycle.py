"""Service reliability as an operator meets it: junk cameras, bad snapshots, idle cameras,
its own drops, a failing periodic step (each of these failed before the fix)."""

from __future__ import annotations

import json
import sys
import time
import zipfile

import msgpack
import numpy as np
import pytest
from test_service_core import Collector, feed, make_service, settle, stream

from evcal.errors import EvcalError
from evcal.events import SensorSize, make_events
from evcal.io.wire import encode_events, encode_frame
from evcal.online import OnEIConfig
from evcal.service import keys
from evcal.service.core import Service, ServiceConfig
from evcal.service.state import MAX_STEM, StateStore, snapshot_name


def _cfg(**kw) -> ServiceConfig:
    return ServiceConfig(onei=OnEIConfig(n_small=50, n_large=10_000), error_rate_hz=1000, **kw)


def test_junk_camera_ids_cannot_lock_real_cameras_out():
    svc, pub = make_service(max_cameras=4, probation_s=60.0)
    try:
        for i in range(50):  # junk: every message refused
            svc.on_sample(f"evcal/junk{i}/events", b"not msgpack")
        settle(svc)
        assert len(svc.cameras) <= 4
        feed(svc, "real/cam0", stream())
        settle(svc)
        assert "real/cam0" in svc.cameras
        assert svc.cameras["real/cam0"].counters.updates >= 1
        assert svc.evicted_cameras >= 1
    finally:
        svc.close()


def test_invalid_camera_ids_are_counted():
    svc, _ = make_service()
    try:
        for cam in ("x" * (keys.MAX_CAMERA_ID + 1), "a/../b", "a/./b"):
            svc.on_sample(f"evcal/{cam}/events", b"x")
        assert svc.invalid_camera_ids == 3
        assert svc.cameras == {}
        assert svc.cameras_info()["invalid_camera_ids"] == 3
    finally:
        svc.close()


def test_long_camera_ids_snapshot_under_a_bounded_name(tmp_path):
    long_id = "/".join(["rig" + "x" * 60] * 3)  # 191 characters, quoted much longer
    assert len(long_id) <= keys.MAX_CAMERA_ID
    name = snapshot_name(long_id)
    assert len(name) <= MAX_STEM + len(".npz")
    assert name != snapshot_name(long_id + "y")
    store = StateStore(tmp_path)
    svc = Service(_cfg(), Collector(), store=store)
    feed(svc, long_id, stream())
    settle(svc)
    svc.close()
    assert [s.camera for s in store.snapshots()] == [long_id]
    svc2 = Service(_cfg(), Collector(), store=store)
    try:
        assert svc2.restore() == [long_id]
    finally:
        svc2.close()


def _snapshot(tmp_path):
    store = StateStore(tmp_path / "state")
    svc = Service(_cfg(), Collector(), store=store)
    feed(svc, "cam0", stream())
    settle(svc)
    svc.close()
    path = store.path("cam0")
    with np.load(path, allow_pickle=False) as z:
        return store, path, {k: z[k] for k in z.files}


def _corruptions(arrays, raw: bytes):
    meta = json.loads(str(arrays["service_json"]))
    scal = json.loads(str(arrays["est__scalars"]))
    yield "truncated", raw[: len(raw) // 3], None
    flipped = bytearray(raw)
    for i in range(200, len(flipped), 997):
        flipped[i] ^= 0x5A
    yield "bit flips", bytes(flipped), None
    yield "service_json null", None, {**arrays, "service_json": np.array("null")}
    yield "service_json not json", None, {**arrays, "service_json": np.array("{")}
    huge = dict(scal, height=65535, width=65535)
    yield "a 65535x65535 sensor", None, {**arrays, "est__scalars": np.array(json.dumps(huge))}
    yield "fields missing", None, {k: v for k, v in arrays.items() if k != "est__c"}
    yield "wrong shapes", None, {**arrays, "est__c": np.zeros(3)}
    yield "counters not a dict", None, {**arrays, "service_json": np.array(json.dumps(
        dict(meta, counters=5)))}


def test_corrupt_snapshots_never_prevent_the_start(tmp_path):
    store, path, arrays = _snapshot(tmp_path)
    raw = path.read_bytes()
    for what, data, arr in _corruptions(arrays, raw):
        for p in store.dir.iterdir():
            p.unlink()
        if data is not None:
            path.write_bytes(data)
        else:
            with open(path, "wb") as f:
                np.savez(f, **arr)
        svc = Service(_cfg(max_pixels=1000), Collector(), store=store)
        try:
            assert svc.restore() == [], what
            assert list(store.dir.glob("*.bad")), f"{what}: not moved aside"
            assert svc.cameras_info()["bad_snapshots"] >= 1, what
            # and the camera starts afresh on its next message
            feed(svc, "cam0", stream())
            settle(svc)
            assert svc.cameras["cam0"].counters.updates >= 1, what
        finally:
            svc.close()


def test_a_valid_zip_that_is_not_an_npz_is_moved_aside(tmp_path):
    store = StateStore(tmp_path)
    with zipfile.ZipFile(store.path("cam9"), "w") as z:
        z.writestr("hello.txt", "not numpy")
    svc = Service(_cfg(), Collector(), store=store)
    try:
        assert svc.restore() == []
        assert (tmp_path / (snapshot_name("cam9") + ".bad")).exists()
    finally:
        svc.close()


def test_idle_cameras_are_evicted_and_come_back_from_their_snapshot(tmp_path):
    store = StateStore(tmp_path)
    svc = Service(_cfg(idle_evict_s=5.0), Collector(), store=store)
    try:
        msgs = stream(n_frames=20)
        feed(svc, "cam0", msgs[:24])
        settle(svc)
        before = svc.cameras["cam0"].counters.updates
        assert before >= 1
        assert svc.evict_idle(now_s=time.monotonic() + 1.0) == []
        assert svc.evict_idle(now_s=time.monotonic() + 10.0) == ["cam0"]
        assert "cam0" not in svc.cameras
        assert store.load("cam0") is not None
        feed(svc, "cam0", msgs[24:])  # the same stream goes on: state from the snapshot
        settle(svc)
        cam = svc.cameras["cam0"]
        assert cam.counters.updates > before
        assert cam.counters.errors == {}
    finally:
        svc.close()


def test_forget_drops_memory_and_disk(tmp_path):
    store = StateStore(tmp_path)
    svc = Service(_cfg(), Collector(), store=store)
    try:
        feed(svc, "cam0", stream())
        settle(svc)
        svc.snapshot()
        assert store.load("cam0") is not None
        assert svc.forget("cam0")
        assert "cam0" not in svc.cameras
        assert store.load("cam0") is None
        assert not svc.forget("cam0")
        assert svc.cameras_info()["forgotten_cameras"] == 1
    finally:
        svc.close()


def test_own_drops_are_not_counted_as_upstream_loss():
    svc, _ = make_service(queue_bytes=20_000, max_message_bytes=20_000)
    try:
        cam = svc.camera("slow")
        assert cam is not None
        with cam.lock:  # hold the worker: the queue overflows
            feed(svc, "slow", stream(n_frames=40))
        settle(svc)
        st = svc.status(cam)
        assert sum(st["dropped_messages"].values()) > 0
        assert st["lost_messages"] == {"events": 0, "frames": 0}, st
        # a real upstream gap is still seen
        msgs = stream(n_frames=60)[80:]
        feed(svc, "slow", msgs[2:])  # seq 40 skipped by the publisher
        settle(svc)
        assert svc.status(cam)["lost_messages"] == {"events": 1, "frames": 1}
    finally:
        svc.close()


def test_frame_dtype_cannot_change_mid_stream():
    svc, _ = make_service()
    try:
        feed(svc, "cam0", stream(n_frames=2))
        svc.on_sample("evcal/cam0/frames", encode_frame(
            30_000, np.full((6, 8), 0.5, np.float32), exposure_us=0, seq=2))
        settle(svc)
        assert svc.cameras["cam0"].counters.errors == {"malformed": 1}
    finally:
        svc.close()


def test_a_failing_periodic_step_is_counted_never_raised(monkeypatch):
    svc, _ = make_service()
    try:
        feed(svc, "cam0", stream(n_frames=2))
        settle(svc)

        def boom(cam):
            raise RuntimeError("deque mutated during iteration")

        monkeypatch.setattr(svc, "status", boom)
        svc.tick(force=True)  # must not raise
        assert svc.tick_errors >= 1
    finally:
        monkeypatch.undo()
        svc.close()


def test_status_and_snapshots_while_cameras_run_at_full_rate(tmp_path):
    """The crash of issue 8: status() walked OnEI's frame buffer while the camera's worker
    changed it ('deque mutated during iteration' in the ticker, then the service exited).
    Status, queries and snapshots now read under the camera's lock: hammer them from other
    threads while three cameras with long buffers run flat out. (Without the lock in
    Service.status this test fails within seconds.)"""
    import threading

    store = StateStore(tmp_path)
    cfg = ServiceConfig(onei=OnEIConfig(n_small=50, n_large=10**9, max_buffer_frames=400),
                        error_rate_hz=1000, snapshot_period_s=0.2)
    svc = Service(cfg, Collector(), store=store)
    failures: list[BaseException] = []
    stop = threading.Event()

    def hammer() -> None:
        while not stop.is_set():
            try:
                for cam in list(svc.cameras.values()):
                    svc.status(cam)
                svc.tick()
                try:
                    svc.query_calibration("evcal/**", {"format": "npz"})
                except EvcalError:
                    pass  # no calibration yet
            except Exception as exc:  # noqa: BLE001 - what the test looks for
                failures.append(exc)
                return

    threads = [threading.Thread(target=hammer) for _ in range(2)]
    old_interval = sys.getswitchinterval()
    sys.setswitchinterval(1e-5)  # switch threads often: a race shows within seconds
    for th in threads:
        th.start()
    try:
        deadline = time.monotonic() + 8.0
        k = 0
        while time.monotonic() < deadline and not failures:
            for c in range(3):
                feed(svc, f"cam{c}", stream(n_frames=20, seed=k, t0=k * 200_000))
            settle(svc)
            k += 1
    finally:
        stop.set()
        for th in threads:
            th.join(30)
        sys.setswitchinterval(old_interval)
        svc.close()
    assert not failures, repr(failures[0])
    assert svc.tick_errors == 0
    assert all(c.counters.errors == {} for c in svc.cameras.values())
    assert min(c.state.calibrator.status()["buffer_frames"]
               for c in svc.cameras.values()) > 100


# ----------------------------------------------------------------------------- stream sessions


def test_a_publisher_restart_starts_a_new_session_instead_of_a_lock_out():
    # a replay run twice: sequence numbers and time start again from 0
    svc, _ = make_service()
    try:
        msgs = stream(n_frames=20)
        feed(svc, "cam0", msgs)
        settle(svc)
        cam = svc.cameras["cam0"]
        updates = cam.counters.updates
        feed(svc, "cam0", msgs)  # the same recording again
        settle(svc)
        assert cam.counters.errors == {}, cam.counters.errors
        assert cam.counters.restarts == {"events": 0, "frames": 1}
        assert cam.counters.frames == 40
        assert cam.counters.updates > updates
        assert cam.state.calibrator.status()["sessions"] == 1
    finally:
        svc.close()


def test_one_absurd_timestamp_is_refused_without_poisoning_later_input():
    svc, _ = make_service()
    try:
        msgs = stream(n_frames=20)
        feed(svc, "cam0", msgs[:20])
        glitch = make_events([2**62], [1], [1], [1])
        svc.on_sample("evcal/cam0/events", encode_events(glitch, height=6, width=8, seq=10))
        feed(svc, "cam0", [(k, p) for k, p in msgs[20:]])
        settle(svc)
        cam = svc.cameras["cam0"]
        assert cam.counters.errors == {"time_jump": 1}
        assert cam.counters.frames == 20
        assert cam.counters.restarts == {"events": 0, "frames": 0}
    finally:
        svc.close()


def test_a_confirmed_new_time_base_starts_a_session():
    # the clock jumps back by an hour with sequence numbers continuing (a camera whose clock
    # was reset): refused until three messages agree, then a new session
    svc, _ = make_service()
    try:
        first = stream(n_frames=10, t0=3_600_000_000)
        feed(svc, "cam0", first)
        second = [(k, p) for k, p in stream(n_frames=10, t0=0)]
        # renumber: the publisher's sequence goes on from 10
        renum = []
        for i, (kind, payload) in enumerate(second):
            obj = msgpack.unpackb(payload)
            obj["seq"] = 10 + i // 2
            renum.append((kind, msgpack.packb(obj)))
        feed(svc, "cam0", renum)
        settle(svc)
        cam = svc.cameras["cam0"]
        assert cam.counters.errors.get("time_jump", 0) == 4  # 2 per stream before confirmed
        assert cam.counters.restarts["events"] + cam.counters.restarts["frames"] >= 1
        assert cam.counters.frames > 10
    finally:
        svc.close()


def test_a_sensor_change_is_accepted_with_a_publisher_restart():
    svc, _ = make_service()
    try:
        feed(svc, "cam0", stream(n_frames=12))
        settle(svc)
        feed(svc, "cam0", stream(h=7, w=9, n_frames=12))  # seq and time from 0, new size
        settle(svc)
        cam = svc.cameras["cam0"]
        assert cam.counters.errors == {}
        assert str(cam.sensor) == "9x7"
        assert cam.state.calibration is not None
        assert cam.state.calibration.shape == (7, 9)
    finally:
        svc.close()


# ----------------------------------------------------------------------------- lossless block


def test_block_mode_is_lossless_across_a_stall_longer_than_zenoh_s_5_s(tmp_path):
    """The service's worker stalls for 7 s (longer than zenoh's default 5 s before a blocked
    link is closed) while a replay publishes as fast as it can: with replay's block timeout
    nothing is lost, and replay's own account says so."""
    import dataclasses
    import threading

    pytest.importorskip("zenoh")
    # far more than the socket and zenoh buffers hold (~50 MB), so the publisher must block
    from evcal.bench import random_recording
    from evcal.clients.replay import replay
    from evcal.service.server import run
    from evcal.service.transport import Transport, ZenohOptions
    from evcal.testing import endpoint, free_port

    rec = random_recording(SensorSize(48, 64), 4_000_000, 40)
    ep = endpoint(free_port())
    stop, ready = threading.Event(), threading.Event()
    box: dict = {}

    def ready_cb(svc):
        box["svc"] = svc
        ready.set()

    cfg = ServiceConfig(on_full="block", queue_bytes=256 << 10, max_message_bytes=256 << 10,
                        onei=OnEIConfig(n_small=3000, n_large=10**6))
    th = threading.Thread(target=run, args=(ZenohOptions.loopback(listen=[ep]), cfg),
                          kwargs={"stop": stop, "ready": ready_cb})
    th.start()
    try:
        assert ready.wait(30)
        svc = box["svc"]
        opts = ZenohOptions.loopback(connect=[ep])
        opts = dataclasses.replace(opts, extra=(
            ("transport/link/tx/queue/congestion_control/block/wait_before_close",
             "60000000"),))
        with Transport(opts) as t:
            # the first message creates the camera; then hold its worker for 7 s
            stats_box: dict = {}
            sender = threading.Thread(target=lambda: stats_box.update(
                s=replay(t, rec, "stall/cam0", speed=None, chunk_events=20_000)))
            sender.start()
            deadline = time.monotonic() + 10
            while "stall/cam0" not in svc.cameras and time.monotonic() < deadline:
                time.sleep(0.01)
            cam = svc.cameras["stall/cam0"]
            with cam.lock:
                time.sleep(7.0)
            sender.join(120)
            st = stats_box["s"]
        assert st.subscribed
        assert not st.service_gone  # with zenoh's default 5 s it is: the link is closed
        assert st.delivered is not None
        assert st.missing_messages == 0, (st, st.delivered)
        assert st.delivered["dropped_messages"] == 0
        assert cam.counters.frames == len(rec.frames)
        assert cam.counters.events == rec.n_events
    finally:
        stop.set()
        th.join(60)
