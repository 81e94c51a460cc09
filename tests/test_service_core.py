"""The service without a network: wire of calibrations, input checks, errors, queues, state."""

from __future__ import annotations

import json
import threading

import msgpack
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from evcal.calibration import Calibration, OnEIDiagnostics
from evcal.events import make_events
from evcal.io.wire import (
    CALIBRATION_MAP_DTYPES,
    WireError,
    decode_calibration,
    decode_calibration_maps,
    decode_events,
    encode_calibration,
    encode_events,
    encode_frame,
)
from evcal.online import OnEIConfig
from evcal.service import keys
from evcal.service.core import (
    LATENCY_PARTS,
    CameraQueue,
    Service,
    ServiceConfig,
)
from evcal.service.state import StateStore
from evcal.testing import settle

# ----------------------------------------------------------------------------- wire


def random_calibration(rng: np.random.Generator, h: int, w: int) -> Calibration:
    valid = rng.random((h, w)) > 0.3
    return Calibration(
        contrast=rng.uniform(0.05, 0.5, (h, w)), bias=rng.normal(0, 0.02, (h, w)),
        valid=valid, reason=np.where(valid, 0, 2), stderr_contrast=rng.random((h, w)),
        stderr_bias=np.where(valid, rng.random((h, w)), np.inf),
        special=rng.integers(0, 6, (h, w)), log_offset=float(rng.uniform(1, 50)),
        method="onei", n_events=rng.integers(0, 1000, (h, w)),
        diagnostics=OnEIDiagnostics(n_updates=3, config={"a": [1, 2]}, warnings=("x",)))


@settings(max_examples=30, deadline=None)
@given(h=st.integers(1, 20), w=st.integers(1, 20), seed=st.integers(0, 2**32 - 1),
       t_us=st.integers(-(2**63), 2**63 - 1), seq=st.integers(0, 2**64 - 1))
def test_calibration_roundtrip(h, w, seed, t_us, seq):
    cal = random_calibration(np.random.default_rng(seed), h, w)
    out, header = decode_calibration(encode_calibration(cal, t_us=t_us, seq=seq))
    assert header["t_us"] == t_us
    assert header["seq"] == seq
    assert header["n_events_used"] == int(cal.n_events.sum())
    for name in CALIBRATION_MAP_DTYPES:
        np.testing.assert_array_equal(getattr(out, name), getattr(cal, name))
    # (as dicts: a NaN offset in the diagnostics is never equal to itself)
    assert type(out.diagnostics) is type(cal.diagnostics)
    assert out.diagnostics.to_dict() == cal.diagnostics.to_dict()
    assert out.log_offset == cal.log_offset


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
        self.attachments: dict[str, bytes] = {}  # the latest per key
        self.lock = threading.Lock()

    def __call__(self, key, payload, enc, attachment=None):
        with self.lock:
            self.items.append((key, payload, enc))
            if attachment is not None:
                self.attachments[key] = attachment

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


def test_a_camera_has_one_stream_guard():
    """The camera's StreamGuard checks its streams; its calibrator, fed checked input, keeps
    the stream's latest times and no guard of its own (restarts included)."""
    svc, _ = make_service()
    try:
        feed(svc, "cam0", stream())
        feed(svc, "cam0", stream(seed=1))  # sequence numbers and time from 0 again
        settle(svc)
        st = svc.cameras["cam0"].state
        assert st.guard.sessions == 1
        assert st.calibrator is not None
        assert st.calibrator._guard is None
        assert st.calibrator.last_event_t_us == st.guard.last_event_t_us
        assert st.calibrator.last_frame_t_us == st.guard.last_frame_t_us
    finally:
        svc.close()


def test_camera_discovery_and_outputs():
    svc, pub = make_service()
    try:
        feed(svc, "lab/rig1/cam0", stream())
        settle(svc)
        cam = svc.cameras["lab/rig1/cam0"]
        assert cam.counters.frames == 12
        assert cam.counters.events == 12 * 200
        assert cam.counters.updates >= 1
        cals = pub.on("evcal/lab/rig1/cam0/calibration")
        cal, header = decode_calibration(cals[-1])
        # every calibration names its instance (signed when the service has a key)
        from evcal.service.signing import read_attachment

        assert read_attachment(pub.attachments["evcal/lab/rig1/cam0/calibration"]) == {
            "v": 1, "instance": svc.instance}
        assert cal.shape == (6, 8)
        assert header["seq"] == len(cals) - 1
        svc.tick(force=True)
        status = json.loads(pub.on("evcal/lab/rig1/cam0/status")[-1])
        assert status["sensor"] == "8x6"
        assert status["errors_total"] == 0
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
    # continuing the stream (next seq, later time) with another size; a publisher restart
    # (seq and time back) may change the sensor: tests/test_service_lifecycle.py
    later = make_events([10**6, 10**6 + 1, 10**6 + 2], [1, 2, 3], [1, 1, 1], [1, 0, 1])
    out["sensor_changed"] = encode_events(later, height=7, width=8, seq=2)
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
        assert svc.cameras["huge"].state.calibrator is None
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
        assert c.errors_published <= 10
        assert c.errors_suppressed >= 190
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
            dropped = sum(cam.dropped.values())  # counted on arrival, folded into the status
            assert dropped > 0
        settle(svc)
        svc.tick(force=True)
        counted = svc.status(cam)["dropped"]
        assert counted["events"] + counted["frames"] == dropped
    finally:
        svc.close()


def test_too_many_cameras():
    svc, pub = make_service(max_cameras=2)
    try:
        for cam in ("a", "b", "c"):
            feed(svc, cam, stream()[:2])
        settle(svc)
        assert sorted(svc.cameras) == ["a", "b"]
        assert svc.rejected_cameras == 2
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


def _events_msg(**changes):
    ev = make_events([1, 2], [3, 4], [1, 2], [1, 0])
    obj = msgpack.unpackb(encode_events(ev, height=6, width=8, seq=1))
    obj.update(changes)
    return msgpack.packb(obj)


@pytest.mark.parametrize(("payload", "reason"), [
    (b"\xc1 not msgpack", "not_msgpack"),
    (b"", "not_msgpack"),
    (msgpack.packb([1, 2]), "not_msgpack"),
    (_events_msg(version=2), "version"),
    (_events_msg(x=b"\x01"), "truncated"),
    (_events_msg(x=np.array([9, 1], "<u2").tobytes()), "out_of_sensor"),
    (_events_msg(t_us=np.array([5, 1], "<i8").tobytes()), "unsorted"),
    (_events_msg(p=np.array([3, 1], "i1").tobytes()), "bad_polarity"),
    (_events_msg(width=0), "out_of_range"),
    (_events_msg(n="2"), "malformed"),
])
def test_wire_errors_carry_their_reason(payload, reason):
    # the reason comes with the error (no message-text matching anywhere)
    with pytest.raises(WireError) as info:
        decode_events(payload)
    assert str(info.value.reason) == reason


# ----------------------------------------------------------------------------- latency path


def test_status_reports_latency_median_and_its_steps():
    svc, pub = make_service()
    try:
        feed(svc, "cam0", stream())
        settle(svc)
        cam = svc.cameras["cam0"]
        lat = svc.status(cam)["latency_ms"]
        st = cam.state
        # one latency per published update, and each one is exactly the sum of its steps
        assert len(st.latency_ms) == len(st.latency_parts_ms) == cam.counters.updates > 0
        for total_ms, steps_s in zip(st.latency_ms, st.latency_parts_ms, strict=True):
            assert all(s >= 0 for s in steps_s)
            assert sum(steps_s) * 1e3 == pytest.approx(total_ms, rel=1e-9, abs=1e-9)
        assert 0 < lat["median"] < 5_000  # ms: tiny frames on an idle service
        assert lat["median"] == pytest.approx(float(np.median(st.latency_ms)))
        parts = lat["parts_median"]
        assert list(parts) == list(LATENCY_PARTS)
        assert parts == pytest.approx({k: float(np.median([p[i] for p in st.latency_parts_ms])
                                                * 1e3) for i, k in enumerate(LATENCY_PARTS)})
    finally:
        svc.close()


def test_published_calibration_does_not_change_afterwards():
    # the cached Calibration answers field queries later: it must be the published one,
    # not a view of the estimator's live state
    svc, pub = make_service()
    try:
        msgs = stream(n_frames=30)
        feed(svc, "cam0", msgs[:20])
        settle(svc)
        cam = svc.cameras["cam0"]
        first, first_msg = cam.calibration, pub.on("evcal/cam0/calibration")[-1]
        assert first is not None
        feed(svc, "cam0", msgs[20:])
        settle(svc)
        assert cam.counters.updates >= 2
        assert cam.calibration is not first
        ref, _ = decode_calibration(first_msg)
        for name in CALIBRATION_MAP_DTYPES:
            np.testing.assert_array_equal(getattr(first, name), getattr(ref, name))
    finally:
        svc.close()


class RecordingObserver:
    def __init__(self, gate: threading.Event | None = None):
        self.calls: list[tuple] = []
        self.threads: set[str] = set()
        self.gate = gate
        self.closed = False

    def _note(self, *call):
        if self.gate is not None:
            self.gate.wait(10)
        self.threads.add(threading.current_thread().name)
        self.calls.append(call)

    def events(self, camera, events):
        self._note("events", camera, int(events.size))

    def frame(self, camera, t_us, image):
        self._note("frame", camera, t_us)

    def updated(self, camera, cal, t_us, status, extra_maps):
        self._note("updated", camera, t_us)

    def discard(self, camera, dropped):
        self.calls.append(("discard", camera, dropped))

    def close(self):
        self.closed = True


def test_recorder_runs_in_its_own_thread_in_stream_order():
    obs = RecordingObserver()
    pub = Collector()
    svc = Service(ServiceConfig(onei=OnEIConfig(n_small=50, n_large=10_000)), pub, observer=obs)
    feed(svc, "cam0", stream())
    settle(svc)
    svc.close()  # drains the recorder's queue
    assert obs.threads == {"evcal-recorder"}
    frames = [c[2] for c in obs.calls if c[0] == "frame"]
    assert frames == sorted(frames)
    assert len(frames) == 12
    updates = [c for c in obs.calls if c[0] == "updated"]
    assert len(updates) == svc.cameras["cam0"].counters.updates >= 1
    assert svc.observer_dropped == 0


def test_a_slow_recorder_never_holds_the_publication():
    gate = threading.Event()  # the recorder is stuck until set
    obs = RecordingObserver(gate)
    pub = Collector()
    svc = Service(ServiceConfig(onei=OnEIConfig(n_small=50, n_large=10_000)), pub, observer=obs)
    try:
        svc._observer_thread.max_bytes = 2_000  # a few calls' worth
        feed(svc, "cam0", stream(n_frames=20))
        settle(svc)
        cam = svc.cameras["cam0"]
        assert cam.counters.frames == 20
        assert cam.counters.updates >= 1
        assert len(pub.on("evcal/cam0/calibration")) == cam.counters.updates
        assert svc.observer_dropped > 0
        assert svc.cameras_info()["recorder_dropped"] > 0
    finally:
        gate.set()
        feed(svc, "cam0", stream(n_frames=2, t0=10_000_000)[:1])  # one more call after drops
        settle(svc)
        svc.close()
    kinds = [c[0] for c in obs.calls]
    assert "discard" in kinds  # told that calls were dropped, before the next one
    assert kinds.index("discard") < len(kinds) - 1


# ----------------------------------------------------------------------------- fast solve


def _reference_solve(ne, n_events, limits, overlap, lam):
    """The numpy formulas the compiled per-pixel pass replaced (lsq before the rewrite)."""
    a11, a12, a22, r1, r2, yy = ne.system(lam)
    det = a11 * a22 - a12 * a12
    scale = a11 * a22
    with np.errstate(divide="ignore", invalid="ignore"):
        ok = (scale > 0) & (det > limits.min_decorrelation * scale)
        safe = np.where(ok, det, 1.0)
        c = np.where(ok, (a22 * r1 - a12 * r2) / safe, 0.1)
        b = np.where(ok, (a11 * r2 - a12 * r1) / safe, 0.0)
        rss = np.maximum(yy - 2 * (c * r1 + b * r2) + c * c * a11 + 2 * c * b * a12
                         + b * b * a22, 0.0)
        n_eff = ne.n_eq / max(overlap, 1.0)
        sigma2 = np.where(n_eff > 2.0, rss / np.maximum(ne.n_eq, 1e-9) * n_eff
                          / np.maximum(n_eff - 2.0, 1e-9), np.inf)
        se_c = np.sqrt(sigma2 * overlap * np.where(ok, a22 / safe, np.inf))
        se_b = np.sqrt(sigma2 * overlap * np.where(ok, a11 / safe, np.inf))
    reason = np.zeros(ne.n_pixels, np.uint8)
    reason[~ok] = 3
    in_range = (c > limits.min_contrast) & (c < limits.max_contrast) & (
        np.abs(b) < limits.max_bias_ratio * c)
    reason[ok & ~in_range] = 6
    reason[(n_events < limits.min_events) | (ne.n_eq < limits.min_equations)] = 2
    reason[n_events == 0] = 1
    valid = reason == 0
    mask = ok & (n_events >= limits.min_events) & in_range
    out = (np.where(valid, c, 0.1), np.where(valid, b, 0.0), valid, reason,
           np.where(valid & np.isfinite(se_c), se_c, np.inf),
           np.where(valid & np.isfinite(se_b), se_b, np.inf))
    return out, (c, b, mask)


def random_normal_equations(seed: int, n: int = 3000):
    from evcal.solver import NormalEquations

    rng = np.random.default_rng(seed)
    ne = NormalEquations(n)
    c_true = rng.uniform(0.05, 0.4, n)
    b_true = rng.normal(0, 0.03, n)
    for _ in range(12):
        on = rng.poisson(rng.uniform(0, 6, n)).astype(float)
        off = rng.poisson(rng.uniform(0, 6, n)).astype(float)
        q = rng.integers(-1, 2, n).astype(float) - rng.integers(-1, 2, n)
        a = rng.integers(0, 2, n).astype(float) - rng.integers(0, 2, n)
        dl = c_true * (on - off) + b_true * (on + off) + rng.normal(0, 0.05, n)
        ne.add(on - off, on + off, q, a, dl, (rng.random(n) > 0.1).astype(float))
    ne.m[:, : n // 10] = 0.0  # never observed
    ne.m[:, n // 10: n // 5] *= 1e-300  # degenerate scales
    n_events = rng.integers(0, 60, n)
    return ne, n_events


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("lam", [0.0, 0.17])
def test_compiled_solve_is_bit_identical_to_the_numpy_formulas(seed, lam):
    from evcal.solver import SolveLimits, correction_lambda, solve_pixels

    ne, n_events = random_normal_equations(seed)
    limits = SolveLimits(min_events=10, min_equations=3.0)
    for overlap in (0.5, 1.0, 3.7):
        sol = solve_pixels(ne, n_events, limits=limits, overlap=overlap, residual_lambda=lam)
        want, _ = _reference_solve(ne, n_events, limits, overlap, lam)
        got = (sol.c, sol.b, sol.valid, sol.reason, sol.se_c, sol.se_b)
        for g, w in zip(got, want, strict=True):
            np.testing.assert_array_equal(g, w)
        assert 0.2 < sol.valid.mean() < 0.9  # the cases are mixed
    # the residual-correction factor: the plain fit's trusted pixels, numpy's sums
    _, (c0, b0, mask) = _reference_solve(ne, n_events, limits, 1.0, 0.0)
    ref_lam = float(np.clip(ne.residual_lambda(0.0, c0, b0, mask), 0.0, 0.5))
    assert correction_lambda(ne, "auto", limits, n_events) == ref_lam


def test_compiled_classify_equals_the_generic_path():
    from evcal.special import classify

    rng = np.random.default_rng(3)
    for n_valid_fraction in (0.0005, 0.5, 1.0):
        c = rng.normal(0.2, 0.02, (40, 50))
        b = rng.normal(0.0, 0.01, (40, 50))
        c[::7, ::5] += rng.choice([-0.15, 0.2], c[::7, ::5].shape)
        b[::9, ::4] += rng.choice([-0.05, 0.05], b[::9, ::4].shape)
        se_c = rng.uniform(0, 0.02, c.shape)
        se_b = np.where(rng.random(c.shape) < 0.1, np.inf, rng.uniform(0, 0.01, c.shape))
        valid = rng.random(c.shape) < n_valid_fraction
        fast = classify(c, b, se_c, se_b, valid)
        ref = _reference_classify(c, b, se_c, se_b, valid)
        np.testing.assert_array_equal(fast, ref)
        assert fast.dtype == np.uint8
        assert fast.shape == c.shape
    assert set(np.unique(ref)) >= {1, 2, 3, 4, 5}


def test_classify_from_a_population_sample_is_the_sampled_reference():
    """``population_sample`` (OnEI's live maps above 131 k valid pixels): the medians come
    from the valid pixels of an even lattice of the sensor; the labels are then exactly those of the
    reference rule with the lattice's statistics, and differ from the exact ones only at the
    class boundaries."""
    from evcal.special import classify

    rng = np.random.default_rng(5)
    c = rng.normal(0.2, 0.02, (300, 400))
    b = rng.normal(0.0, 0.01, c.shape)
    c[::7, ::5] += rng.choice([-0.15, 0.2], c[::7, ::5].shape)
    se_c = rng.uniform(0, 0.004, c.shape)
    se_b = rng.uniform(0, 0.002, c.shape)
    valid = rng.random(c.shape) < 0.9
    sampled = classify(c, b, se_c, se_b, valid, population_sample=10_000)
    exact = classify(c, b, se_c, se_b, valid)
    idx = np.arange(0, c.size, int(valid.sum()) // 10_000)  # the lattice's valid pixels
    idx = idx[valid.ravel()[idx]]
    lattice = np.zeros(c.shape, bool)
    lattice.flat[idx] = True
    # the reference rule, its statistics from the lattice
    k, z = 3.0, 2.0
    c_med = np.median(c[lattice])
    c_s = 1.4826 * np.median(np.abs(c[lattice] - c_med))
    b_med = np.median(b[lattice])
    b_s = 1.4826 * np.median(np.abs(b[lattice] - b_med))
    ref = np.where(valid, 1, 0).astype(np.uint8)
    ref[valid & (b + z * se_b < b_med - k * b_s)] = 4
    ref[valid & (b - z * se_b > b_med + k * b_s)] = 5
    ref[valid & (c + z * se_c < c_med - k * c_s)] = 2
    ref[valid & (c - z * se_c > c_med + k * c_s)] = 3
    np.testing.assert_array_equal(sampled, ref)
    assert 0 < np.count_nonzero(sampled != exact) < 0.002 * c.size
    # at or below the sample size nothing changes
    np.testing.assert_array_equal(classify(c, b, se_c, se_b, valid,
                                           population_sample=c.size), exact)


def _reference_classify(c, b, se_c, se_b, valid, k=3.0, z=2.0):
    out = np.zeros(c.shape, np.uint8)
    out[valid] = 1
    if np.count_nonzero(valid) < 10:
        return out

    def spread(v):
        med = float(np.median(v))
        return med, 1.4826 * float(np.median(np.abs(v - med)))

    c_med, c_s = spread(c[valid])
    b_med, b_s = spread(b[valid])
    out[valid & (b + z * se_b < b_med - k * b_s)] = 4
    out[valid & (b - z * se_b > b_med + k * b_s)] = 5
    out[valid & (c + z * se_c < c_med - k * c_s)] = 2
    out[valid & (c - z * se_c > c_med + k * c_s)] = 3
    return out


@pytest.mark.parametrize("n", [0, 1, 255, 256, 65535, 65536, 70_000])
def test_calibration_messages_are_msgpack_s_own_bytes(n):
    """The calibration encoder writes its maps straight into the message: the bytes are
    those msgpack.packb gives, at the sizes where its bin header changes (8, 16, 32 bits)."""
    from evcal.io.wire import _packb_large_bins

    rng = np.random.default_rng(n)
    msg = {"version": 1, "seq": 2**64 - 1, "t_us": -5, "method": "onei", "log_offset": 0.5,
           "maps": {"a": rng.integers(0, 255, n).astype(np.uint8).data,
                    "b": rng.random(n).astype(np.float32).data}}
    assert _packb_large_bins(msg) == msgpack.packb(msg, use_bin_type=True)


def test_gc_policy_freezes_and_measures_collections() -> None:
    import gc

    from evcal.service.gcpolicy import GcPolicy

    pol = GcPolicy()
    pol.install()
    try:
        before = gc.get_freeze_count()
        gc.collect(0)
        gc.collect(2)
        st = pol.stats()
        assert st["collections"][0] >= 1
        assert st["collections"][2] >= 1
        assert st["max_pause_ms"] > 0
        assert st["pause_ms"][2] > 0
        pol.freeze()
        assert pol.stats()["freezes"] == 1
        assert gc.get_freeze_count() > before
    finally:
        pol.uninstall()
        gc.unfreeze()
    n = pol.stats()["collections"][0]
    gc.collect(0)
    assert pol.stats()["collections"][0] == n  # uninstalled: no longer called
    assert pol._callback not in gc.callbacks


def _strict(text: bytes | str):
    """json.loads that refuses NaN and infinities, as JavaScript, Go and jq do."""
    def refuse(name: str):
        raise AssertionError(f"not strict JSON: {name}")

    return json.loads(text, parse_constant=refuse)


def _leaves(doc):
    if isinstance(doc, dict):
        return [x for v in doc.values() for x in _leaves(v)]
    if isinstance(doc, list):
        return [x for v in doc for x in _leaves(v)]
    return [doc]


def test_every_document_the_service_emits_is_strict_json():
    from evcal.jsonable import strict_dumps
    from evcal.service.outputs import error_reply

    pub = Collector()
    svc = Service(ServiceConfig(onei=OnEIConfig(n_small=50, n_large=10_000, log_offset="auto"),
                                error_rate_hz=1000), pub)
    try:
        # before it is estimated the online offset is unknown (NaN): null, still strict
        feed(svc, "cam0", stream(n_frames=2))
        settle(svc)
        svc.tick(force=True)
        assert "NaN" in json.dumps(svc.status(svc.cameras["cam0"]))  # what json.dumps makes
        status = _strict(pub.on("evcal/cam0/status")[-1])
        assert None in _leaves(status)
        for _, payload, _ in svc.query_status("evcal/**/status"):
            _strict(payload)
        _strict(strict_dumps(svc.cameras_info()))
        feed(svc, "cam0", [("events", b"\x00junk")])
        settle(svc)
        assert pub.on("evcal/cam0/errors")
        for p in pub.on("evcal/cam0/errors"):
            _strict(p)
        _strict(error_reply(svc_error := __import__("evcal").EvcalError("bad")))
        assert svc_error.reason.value == "malformed"
    finally:
        svc.close()
    assert strict_dumps({"x": float("nan"), "y": [np.inf, 1.5]}) == '{"x": null, "y": [null, 1.5]}'


def test_no_calibration_yet_says_why_and_what_to_do():
    from evcal.service.outputs import no_calibration_message

    pub = Collector()
    svc = Service(ServiceConfig(error_rate_hz=1000), pub)  # default buffers: 1000 events
    try:
        feed(svc, "cam0", stream(n_frames=3))  # 600 events
        settle(svc)
        msg = no_calibration_message(svc.cameras["cam0"].state)
        assert "3 frames, 600 events received" in msg
        assert "the log offset is being estimated" in msg
        assert "--log-offset" in msg
        # the status says it too
        status = svc.status(svc.cameras["cam0"])
        assert status["estimator"]["waiting_for"] in msg
        with pytest.raises(Exception, match="the log offset is being estimated") as info:
            svc.query_calibration("evcal/cam0/calibration", {})
        from evcal.errors import ErrorReason

        assert getattr(info.value, "reason", None) == ErrorReason.NO_CALIBRATION
    finally:
        svc.close()


# ----------------------------------------------------------------------------- counters


def _with_seq(payload: bytes, seq: int) -> bytes:
    obj = msgpack.unpackb(payload)
    obj["seq"] = seq
    return msgpack.packb(obj)


def _two_chunks_per_frame(n_frames: int = 16, h: int = 6, w: int = 8, seed: int = 0):
    """Like :func:`stream`, each frame interval's events in two chunks (seq 2k, 2k + 1)."""
    out = []
    for kind, payload in stream(h, w, n_frames, seed):
        if kind == "frames":
            out.append((kind, payload))
            continue
        ev, hd = decode_events(payload)
        half = ev.size // 2
        for j, part in enumerate((ev[:half], ev[half:])):
            out.append(("events", encode_events(part, height=h, width=w,
                                                seq=2 * hd["seq"] + j)))
    return out


def _counts(svc: Service, camera: str) -> dict:
    st = svc.status(svc.cameras[camera])
    return {k: st.get(k) for k in ("errors", "lost_messages", "restarts", "frames",
                                   "event_messages")}


def test_a_refused_glitch_is_not_also_counted_lost():
    # one t_us = 2**62 chunk with its own sequence number, the stream going on after it:
    # refused as time_jump, and that is all (it arrived, so it is not lost)
    svc, _ = make_service()
    try:
        msgs = stream(n_frames=20)
        glitch = encode_events(make_events([2**62], [1], [1], [1]), height=6, width=8, seq=10)
        later = [(k, _with_seq(p, msgpack.unpackb(p)["seq"] + 1) if k == "events" else p)
                 for k, p in msgs[21:]]
        feed(svc, "cam0", [*msgs[:21], ("events", glitch), *later])
        settle(svc)
        c = _counts(svc, "cam0")
        assert c["errors"] == {"time_jump": 1}
        assert c["lost_messages"] == {"events": 0, "frames": 0}, c
        assert c["restarts"] == {"events": 0, "frames": 0}
        assert c["frames"] == 20
        assert c["event_messages"] == 20
    finally:
        svc.close()


def test_a_glitch_at_the_end_of_a_normal_message_costs_that_message_only():
    # issue 40: a 2**62 timestamp after a message's normal events passed the check of its
    # first event, became the stream's last time, and cost the next 2 messages (time_jump)
    # and a new session; the message itself is refused now, and nothing after it
    svc, _ = make_service()
    try:
        msgs = stream(n_frames=20)
        k = next(i for i in range(21, len(msgs)) if msgs[i][0] == "events")
        hd = msgpack.unpackb(msgs[k][1])
        ev = decode_events(msgs[k][1])[0]
        bad = np.concatenate([ev, make_events([2**62], [1], [1], [1])])
        msgs[k] = ("events", encode_events(bad, height=6, width=8, seq=hd["seq"]))
        feed(svc, "cam0", msgs)
        settle(svc)
        c = _counts(svc, "cam0")
        assert c["errors"] == {"time_jump": 1}
        assert c["restarts"] == {"events": 0, "frames": 0}
        assert c["lost_messages"] == {"events": 0, "frames": 0}, c
        assert c["event_messages"] == 19
        assert c["frames"] == 20
    finally:
        svc.close()


def test_refused_unreadable_messages_are_not_counted_lost():
    # a message refused before its sequence number could be read (not msgpack, too large)
    # arrived: it is an error of its reason, not a gap of upstream loss
    svc, _ = make_service(max_message_bytes=4000, queue_bytes=1 << 20)
    try:
        msgs = stream(n_frames=12)
        msgs[9] = ("events", b"\x00junk")  # events seq 4
        msgs[13] = ("events", b"\x00" * 5000)  # events seq 6, over the size limit
        feed(svc, "cam0", msgs)
        settle(svc)
        c = _counts(svc, "cam0")
        assert c["errors"] == {"not_msgpack": 1, "too_large": 1}
        assert c["lost_messages"] == {"events": 0, "frames": 0}, c
    finally:
        svc.close()


def test_a_swapped_pair_of_event_chunks_is_refused_not_a_new_session():
    svc, _ = make_service()
    try:
        msgs = _two_chunks_per_frame()
        i = next(j for j, (k, p) in enumerate(msgs)
                 if k == "events" and msgpack.unpackb(p)["seq"] == 10)
        msgs[i], msgs[i + 1] = msgs[i + 1], msgs[i]  # chunk 11 before chunk 10
        feed(svc, "cam0", msgs)
        settle(svc)
        cam = svc.cameras["cam0"]
        c = _counts(svc, "cam0")
        assert c["lost_messages"] == {"events": 0, "frames": 0}, c
        assert c["restarts"] == {"events": 0, "frames": 0}, c
        assert c["errors"] == {"time_backwards": 1}, c  # chunk 10 cannot go after chunk 11
        assert cam.state.calibrator.status()["sessions"] == 0  # the buffers were kept
        assert c["event_messages"] == 31
        assert c["frames"] == 16
    finally:
        svc.close()


def test_a_late_message_whose_time_still_fits_is_accepted():
    # a swapped pair whose second message has the time of the first (events may share a
    # t_us): it is placed, neither refused nor lost
    from evcal.stream import StreamGuard

    g = StreamGuard()
    size = (6, 8)
    assert g.accept("events", t_first_us=0, t_last_us=10, what="m0", seq=0, size=size).lost == 0
    assert g.accept("events", t_first_us=10, t_last_us=10, what="m2", seq=2,
                    size=size).lost == 1
    chk = g.accept("events", t_first_us=10, t_last_us=10, what="m1", seq=1, size=size)
    assert chk.recovered == 1
    assert not chk.restart
    assert not chk.new_session
    assert g.accept("events", t_first_us=11, t_last_us=12, what="m3", seq=3,
                    size=size).lost == 0
    assert g.sessions == 0


def test_a_sequence_number_far_ahead_is_a_new_numbering_not_loss():
    # issue 40: seq 2**64 - 1 after 0, 1 counted 2**64 - 3 messages lost; a jump beyond
    # MAX_SEQ_GAP is a counter that started anew (counted as a restart), a smaller one loss
    from evcal.stream import StreamGuard

    g = StreamGuard()
    size = (6, 8)
    for k in range(2):
        assert g.accept("events", t_first_us=10 * k, t_last_us=10 * k + 5, what=f"m{k}",
                        seq=k, size=size).lost == 0
    far = g.accept("events", t_first_us=20, t_last_us=25, what="far", seq=2**64 - 1, size=size)
    assert far.lost == 0
    assert far.restart
    nxt = g.accept("events", t_first_us=30, t_last_us=35, what="next", seq=2**64, size=size)
    assert nxt.lost == 0
    assert not nxt.restart
    near = g.accept("events", t_first_us=40, t_last_us=45, what="near",
                    seq=2**64 + 1 + StreamGuard.MAX_SEQ_GAP, size=size)
    assert near.lost == StreamGuard.MAX_SEQ_GAP
    assert not near.restart
    assert g.sessions == 0


def test_an_exact_duplicate_is_dropped_and_counted_not_a_restart():
    svc, pub = make_service()
    try:
        msgs = stream(n_frames=20)
        dup = [*msgs[:13], msgs[12], *msgs[13:16], msgs[15], *msgs[16:]]  # frame 6, events 7
        feed(svc, "cam0", dup)
        settle(svc)
        cam = svc.cameras["cam0"]
        c = _counts(svc, "cam0")
        assert c["errors"] == {"duplicate": 2}, c  # a copy is dropped and counted as such
        assert c["restarts"] == {"events": 0, "frames": 0}, c
        assert {json.loads(p)["stream"] for p in pub.on("evcal/cam0/errors")} == {
            "events", "frames"}
        assert c["lost_messages"] == {"events": 0, "frames": 0}
        assert c["frames"] == 20
        assert c["event_messages"] == 20
        assert cam.counters.events == 20 * 200
        assert cam.state.calibrator.status()["sessions"] == 0
        # a publisher that restarts sends its first messages again: still a new session
        feed(svc, "cam0", msgs)
        settle(svc)
        assert _counts(svc, "cam0")["restarts"]["frames"] == 1
    finally:
        svc.close()


def test_input_while_stopping_is_counted_not_queued():
    """Once close() has begun, messages are neither queued behind the drain (a SIGTERM with
    cameras still sending would wait the drain out) nor lost silently: they are counted."""
    svc, _pub = make_service()
    msgs = stream()
    feed(svc, "cam0", msgs[:4])
    settle(svc)
    with svc._lock:  # noqa: SLF001 - what close() sets first
        svc._closed = True  # noqa: SLF001
    feed(svc, "cam0", msgs[4:8])
    feed(svc, "cam1", msgs[:2])
    assert svc.refused_while_closing == 6
    assert "cam1" not in svc.cameras
    assert not svc.cameras["cam0"].in_flight
    svc.close()
    assert svc.cameras_info()["refused_while_closing"] == 6


def test_a_restart_counts_what_it_rolled_back_not_as_lost(tmp_path):
    """Issue 40: a worker killed 30 s after its snapshot came back with the camera's counts
    70 M events lower and reported nothing; the sequence gap showed as thousands of lost
    messages. The messages after the snapshot are counted as rolled back, the restore is
    described in the status, and a gap after that first message is still loss."""
    store = StateStore(tmp_path)
    pub = Collector()
    cfg = ServiceConfig(onei=OnEIConfig(n_small=50, n_large=10_000))
    msgs = stream(n_frames=20)
    svc = Service(cfg, pub, store=store)
    feed(svc, "lab/cam0", msgs[:24])
    settle(svc)
    svc.close()  # its snapshot; then msgs[24:30] reach a process that dies before the next
    skipped = [kind for kind, _ in msgs[24:30]]
    svc2 = Service(cfg, pub, store=store, match=lambda e, k: True)
    try:
        assert svc2.restore() == ["lab/cam0"]
        cam = svc2.camera("lab/cam0")
        assert cam is not None
        st0 = svc2.status(cam)
        assert st0["restores"] == 1
        assert st0["restored"]["snapshot_age_s"] >= 0
        assert st0["restored"]["rolled_back"] == {"events": None, "frames": None}
        feed(svc2, "lab/cam0", msgs[30:34])
        settle(svc2)
        st1 = svc2.status(cam)
        assert st1["rolled_back_messages"] == {"events": skipped.count("events"),
                                               "frames": skipped.count("frames")}
        assert st1["restored"]["rolled_back"] == st1["rolled_back_messages"]
        assert sum(st1["lost_messages"].values()) == 0
        feed(svc2, "lab/cam0", msgs[35:])  # a real gap later: loss
        settle(svc2)
        assert sum(svc2.status(cam)["lost_messages"].values()) == 1
    finally:
        svc2.close()
