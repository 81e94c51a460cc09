"""The service without a network: wire of calibrations, input checks, errors, queues, state."""

from __future__ import annotations

import json
import threading
import time

import msgpack
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from evcal.calibration import Calibration
from evcal.events import make_events
from evcal.io.wire import (
    CALIBRATION_MAP_DTYPES,
    WireError,
    decode_calibration,
    decode_calibration_maps,
    encode_calibration,
    encode_events,
    encode_frame,
)
from evcal.online import OnEIConfig
from evcal.service import keys
from evcal.service.core import CameraQueue, Service, ServiceConfig, classify_wire_error
from evcal.service.state import StateStore

# ----------------------------------------------------------------------------- wire


def random_calibration(rng: np.random.Generator, h: int, w: int) -> Calibration:
    valid = rng.random((h, w)) > 0.3
    return Calibration(
        contrast=rng.uniform(0.05, 0.5, (h, w)), bias=rng.normal(0, 0.02, (h, w)),
        valid=valid, reason=np.where(valid, 0, 2), stderr_contrast=rng.random((h, w)),
        stderr_bias=np.where(valid, rng.random((h, w)), np.inf),
        special=rng.integers(0, 6, (h, w)), log_offset=float(rng.uniform(1, 50)),
        method="onei", n_events=rng.integers(0, 1000, (h, w)), params={"a": [1, 2], "b": "x"})


@settings(max_examples=30, deadline=None)
@given(h=st.integers(1, 20), w=st.integers(1, 20), seed=st.integers(0, 2**32 - 1),
       t_us=st.integers(-(2**63), 2**63 - 1), seq=st.integers(0, 2**64 - 1))
def test_calibration_roundtrip(h, w, seed, t_us, seq):
    cal = random_calibration(np.random.default_rng(seed), h, w)
    out, header = decode_calibration(encode_calibration(cal, t_us=t_us, seq=seq))
    assert header["t_us"] == t_us and header["seq"] == seq
    assert header["n_events_used"] == int(cal.n_events.sum())
    for name in CALIBRATION_MAP_DTYPES:
        np.testing.assert_array_equal(getattr(out, name), getattr(cal, name))
    assert out.params == cal.params and out.log_offset == cal.log_offset


def test_calibration_partial_and_malformed():
    cal = random_calibration(np.random.default_rng(0), 4, 5)
    msg = encode_calibration(cal, t_us=1, seq=2, fields=["bias"])
    maps, _ = decode_calibration_maps(msg)
    assert list(maps) == ["bias"]
    with pytest.raises(WireError, match="missing"):
        decode_calibration(msg)
    with pytest.raises(WireError, match="unknown field"):
        encode_calibration(cal, t_us=1, seq=2, fields=["nope"])
    obj = msgpack.unpackb(encode_calibration(cal, t_us=1, seq=2))
    obj["maps"]["contrast"] = obj["maps"]["contrast"][:-1]
    with pytest.raises(WireError, match="truncated"):
        decode_calibration(msgpack.packb(obj))


# ----------------------------------------------------------------------------- service


class Collector:
    def __init__(self):
        self.items: list[tuple[str, bytes, str]] = []
        self.lock = threading.Lock()

    def __call__(self, key, payload, enc):
        with self.lock:
            self.items.append((key, payload, enc))

    def on(self, key):
        with self.lock:
            return [p for k, p, _ in self.items if k == key]


def make_service(**kw) -> tuple[Service, Collector]:
    pub = Collector()
    cfg = ServiceConfig(onei=OnEIConfig(n_small=50, n_large=10_000), error_rate_hz=1000, **kw)
    return Service(cfg, pub), pub


def stream(h=6, w=8, n_frames=12, seed=0, t0=0):
    """(kind, payload) messages of a tiny random camera, in send order."""
    rng = np.random.default_rng(seed)
    out = []
    for k in range(n_frames):
        t = t0 + k * 10_000
        out.append(("frames", encode_frame(t, rng.integers(20, 230, (h, w)).astype(np.uint8),
                                           exposure_us=0, seq=k)))
        n = 200
        ev = make_events(np.sort(rng.integers(t, t + 10_000, n)), rng.integers(0, w, n),
                         rng.integers(0, h, n), rng.integers(0, 2, n))
        out.append(("events", encode_events(ev, height=h, width=w, seq=k)))
    return out


def feed(svc: Service, camera: str, msgs) -> None:
    for kind, payload in msgs:
        svc.on_sample(f"evcal/{camera}/{kind}", payload)


def settle(svc: Service, timeout_s: float = 10.0) -> None:
    deadline = time.monotonic() + timeout_s
    while any(len(c.queue) for c in svc.cameras.values()) and time.monotonic() < deadline:
        time.sleep(0.01)
    time.sleep(0.05)


def test_camera_discovery_and_outputs():
    svc, pub = make_service()
    try:
        feed(svc, "lab/rig1/cam0", stream())
        settle(svc)
        cam = svc.cameras["lab/rig1/cam0"]
        assert cam.counters.frames == 12 and cam.counters.events == 12 * 200
        assert cam.counters.updates >= 1
        cals = pub.on("evcal/lab/rig1/cam0/calibration")
        cal, header = decode_calibration(cals[-1])
        assert cal.shape == (6, 8) and header["seq"] == len(cals) - 1
        svc.tick(force=True)
        status = json.loads(pub.on("evcal/lab/rig1/cam0/status")[-1])
        assert status["sensor"] == "8x6" and status["errors_total"] == 0
        assert status["latency_ms"]["max"] is not None
        replies = svc.query_calibration("evcal/**/calibration", {"format": "npz"})
        assert [k for k, _, _ in replies] == ["evcal/lab/rig1/cam0/calibration"]
        assert replies[0][2] == keys.ENC_CALIBRATION_NPZ
    finally:
        svc.close()


def bad_messages():
    ev = make_events([1, 2, 3], [1, 2, 3], [1, 1, 1], [1, 0, 1])
    ok = msgpack.unpackb(encode_events(ev, height=6, width=8, seq=0))
    out = {}
    m = dict(ok, version=2)
    out["version"] = msgpack.packb(m)
    m = dict(ok, x=ok["x"][:-1])
    out["truncated"] = msgpack.packb(m)
    m = dict(ok, x=np.array([1, 2, 9], "<u2").tobytes())
    out["out_of_sensor"] = msgpack.packb(m)
    m = dict(ok, t_us=np.array([3, 2, 1], "<i8").tobytes())
    out["unsorted"] = msgpack.packb(m)
    out["not_msgpack"] = b"\xc1\x00garbage"
    out["malformed"] = msgpack.packb({"version": 1})
    out["sensor_changed"] = encode_events(ev, height=7, width=8, seq=1)
    out["too_large"] = b"\x00" * 5000
    return out


def test_every_bad_input_is_rejected_with_its_reason():
    svc, pub = make_service(max_message_bytes=4096, queue_bytes=1 << 20)
    try:
        feed(svc, "cam0", stream()[:4])  # establishes the 8x6 sensor
        settle(svc)
        for reason, payload in bad_messages().items():
            before = dict(svc.cameras["cam0"].counters.errors)
            svc.on_sample("evcal/cam0/events", payload)
            settle(svc)
            after = svc.cameras["cam0"].counters.errors
            assert after.get(reason, 0) == before.get(reason, 0) + 1, (reason, after)
        # time going backwards: a chunk before the last one
        ev = make_events([5], [1], [1], [1])
        svc.on_sample("evcal/cam0/events", encode_events(ev, height=6, width=8, seq=99))
        svc.on_sample("evcal/cam0/frames",
                      encode_frame(0, np.zeros((6, 8), np.uint8), exposure_us=0, seq=99))
        settle(svc)
        errs = svc.cameras["cam0"].counters.errors
        assert errs["time_backwards"] == 2
        published = [json.loads(p) for p in pub.on("evcal/cam0/errors")]
        assert {p["reason"] for p in published} >= set(bad_messages()) | {"time_backwards"}
        assert all(p["camera"] == "cam0" and p["message"] for p in published)
        # a camera whose sensor is absurdly large is refused before any allocation
        big = make_events([1], [0], [0], [1])
        svc.on_sample("evcal/huge/events", encode_events(big, height=65535, width=65535, seq=0))
        settle(svc)
        assert svc.cameras["huge"].counters.errors == {"sensor_too_large": 1}
        assert svc.cameras["huge"].calibrator is None
    finally:
        svc.close()


def test_errors_are_rate_limited():
    pub = Collector()
    svc = Service(ServiceConfig(error_rate_hz=5), pub)
    try:
        for _ in range(200):
            svc.on_sample("evcal/c/events", b"junk")
        settle(svc)
        c = svc.cameras["c"].counters
        assert c.errors["not_msgpack"] == 200
        assert c.errors_published <= 10 and c.errors_suppressed >= 190
        assert len(pub.on("evcal/c/errors")) == c.errors_published
    finally:
        svc.close()


def test_drop_policy_bounds_the_queue():
    q = CameraQueue(1000)
    assert q.put(("events", b"x" * 600, 0.0), block=False)
    assert not q.put(("events", b"x" * 600, 0.0), block=False)  # would exceed: dropped
    assert q.nbytes == 600
    # a single message larger than the queue is still accepted when the queue is empty
    q2 = CameraQueue(10)
    assert q2.put(("events", b"x" * 20, 0.0), block=False)


def test_drop_counts_when_the_worker_is_slow():
    svc, _ = make_service(queue_bytes=20_000, max_message_bytes=20_000)
    try:
        cam = svc.camera("slow")
        assert cam is not None
        with cam.lock:  # hold the worker: everything queues up
            for kind, payload in stream(n_frames=40):
                svc.on_sample(f"evcal/slow/{kind}", payload)
            assert cam.queue.nbytes <= 20_000
            dropped = sum(cam.counters.dropped.values())
            assert dropped > 0
        settle(svc)
        svc.tick(force=True)
        assert cam.status()["dropped"]["events"] + cam.status()["dropped"]["frames"] == dropped
    finally:
        svc.close()


def test_too_many_cameras():
    svc, pub = make_service(max_cameras=2)
    try:
        for cam in ("a", "b", "c"):
            feed(svc, cam, stream()[:2])
        settle(svc)
        assert sorted(svc.cameras) == ["a", "b"] and svc.rejected_cameras == 2
        assert json.loads(pub.on("evcal/c/errors")[0])["reason"] == "too_many_cameras"
    finally:
        svc.close()


def test_snapshot_restore_answers_at_once(tmp_path):
    store = StateStore(tmp_path)
    pub = Collector()
    cfg = ServiceConfig(onei=OnEIConfig(n_small=50, n_large=10_000))
    svc = Service(cfg, pub, store=store)
    msgs = stream(n_frames=20)
    feed(svc, "lab/cam0", msgs[:24])
    settle(svc)
    svc.close()  # snapshots
    last = pub.on("evcal/lab/cam0/calibration")[-1]
    svc2 = Service(cfg, pub, store=store, match=lambda e, k: True)
    try:
        assert svc2.restore() == ["lab/cam0"]
        (key, payload, _), = svc2.query_calibration("evcal/lab/cam0/calibration", {})
        assert payload == last
        # and it continues from the restored state: same result as an uninterrupted run
        feed(svc2, "lab/cam0", msgs[24:])
        settle(svc2)
        ref, ref_pub = make_service()
        feed(ref, "lab/cam0", msgs)
        settle(ref)
        ref.close()
        a = decode_calibration(pub.on("evcal/lab/cam0/calibration")[-1])[0]
        b = decode_calibration(ref_pub.on("evcal/lab/cam0/calibration")[-1])[0]
        np.testing.assert_allclose(a.contrast, b.contrast, atol=1e-6)
        np.testing.assert_allclose(a.bias, b.bias, atol=1e-6)
    finally:
        svc2.close()


@pytest.mark.parametrize(("message", "reason"), [
    ("events message: not a valid msgpack message (x)", "not_msgpack"),
    ("events message: unsupported version 2, this reader knows version 1", "version"),
    ("events message seq 1: field 'x' is truncated: 1 bytes", "truncated"),
    ("events: event 0 at (x=9, y=1) is outside the 8x6 sensor (1 such events)",
     "out_of_sensor"),
    ("events: timestamps are not sorted: event 1", "unsorted"),
    ("events: event 0 has polarity 3, expected +1 or -1", "bad_polarity"),
    ("events message: missing field(s) ['n']", "malformed"),
])
def test_classify_wire_errors(message, reason):
    assert classify_wire_error(message) == reason
