"""Event timing in the service (serve --event-timing): each OnEI update fused with OffE's
maps of the same events, without a network (tests/test_service_e2e.py runs the service over
zenoh)."""

from __future__ import annotations

import numpy as np
import pytest
from test_service_core import Collector
from test_service_posterior import ONEI, messages, rmse

from evcal.calibration import Special
from evcal.fusion import fuse
from evcal.io.wire import decode_calibration
from evcal.offe import StreamingOffE
from evcal.posterior import estimate_of, posterior_maps
from evcal.recording import Recording
from evcal.service.core import Service, ServiceConfig
from evcal.service.outputs import camera_status
from evcal.service.state import StateStore, read_snapshot
from evcal.sim.ideal import SimConfig, simulate_ideal
from evcal.testing import settle

KEY = "evcal/lab/cam0/calibration"
CAM = "lab/cam0"


@pytest.fixture(scope="module")
def sim():
    # 4 s of a 96x72 sensor: OffE's neighbours and the stated errors of both estimates
    return simulate_ideal(SimConfig(height=72, width=96, duration_s=4.0, seed=11,
                                    scene="camera"))


def run(rec: Recording, *, store: StateStore | None = None, start: int = 0,
        upto: int | None = None, svc: Service | None = None, **kw) -> tuple[Service, Collector]:
    pub = Collector()
    if svc is None:
        svc = Service(ServiceConfig(onei=ONEI, **kw), pub, store=store)
    for i, (kind, payload) in enumerate(messages(rec)):
        if i < start:
            continue
        if upto is not None and i >= upto:
            break
        svc.on_sample(f"evcal/{CAM}/{kind}", payload)
    settle(svc)
    return svc, pub


def latest(pub: Collector):
    return decode_calibration(pub.on(KEY)[-1])[0]


def test_fused_updates_recover_the_truth_better_than_onei_alone(sim):
    plain, pub0 = run(sim.recording)
    timed, pub1 = run(sim.recording, event_timing=True)
    try:
        raw, fused = latest(pub0), latest(pub1)
        info = fused.diagnostics.extra["fusion"]
        assert "reason" not in info
        assert info["pixels"] > 500
        assert estimate_of(fused) == "raw"  # fused per-pixel estimates, no pull
        c, b = sim.truth["contrast"], sim.truth["bias"]
        m = raw.valid & fused.valid & (raw.special == Special.NORMAL)
        assert m.sum() > 1000
        assert rmse(fused.contrast, c, m) < 0.98 * rmse(raw.contrast, c, m)
        assert rmse(fused.bias, b, m) < 0.95 * rmse(raw.bias, b, m)
        # OnEI's maps are the same with or without the timing beside them: the published
        # ones are those fused with the camera's OffE maps of the same events
        st = timed.cameras[CAM].state
        assert st.timing is not None
        assert st.timing.n_events == sim.recording.events.size
        assert st.timing_maps is not None
        again = fuse(raw, st.timing_maps)
        np.testing.assert_allclose(fused.contrast, again.contrast, rtol=0, atol=1e-6)
        status = camera_status(timed.cameras[CAM])["event_timing"]
        assert status["events"] == sim.recording.events.size
        assert status["not_fused"] is None
        assert camera_status(plain.cameras[CAM])["event_timing"] is None
    finally:
        plain.close()
        timed.close()


def test_offe_maps_are_taken_again_by_sensor_time(sim):
    svc, pub = run(sim.recording, event_timing=True, offe_period_us=500_000)
    try:
        taken = set()
        for payload in pub.on(KEY):
            cal, _ = decode_calibration(payload)
            info = cal.diagnostics.extra.get("fusion")
            assert info is not None  # every update says whether and how it was fused
            if "reason" not in info:
                taken.add(info["offe_maps_t_us"])
        # one set of OffE maps per half second of a 4 s recording (the early ones have too
        # few steps or pixels): several, not one per update
        n_updates = len(pub.on(KEY))
        assert 3 <= len(taken) <= 9 < n_updates
    finally:
        svc.close()


def test_an_update_without_offe_maps_keeps_onei_and_says_why(sim):
    # OffE's maps are asked for at the first update (a few frames in: too few steps or
    # pixels), then not again for 100 s of sensor time
    svc, pub = run(sim.recording, event_timing=True, offe_period_us=100_000_000)
    try:
        reasons = {decode_calibration(p)[0].diagnostics.extra["fusion"].get("reason")
                   for p in pub.on(KEY)}
        assert len(reasons) == 1
        why = reasons.pop()
        assert why is not None
        assert why.startswith("no OffE maps yet")
        assert camera_status(svc.cameras[CAM])["event_timing"]["not_fused"] == why
        plain, pub0 = run(sim.recording)
        try:  # the maps published are OnEI's own
            a, b = latest(pub), latest(pub0)
            np.testing.assert_array_equal(a.contrast, b.contrast)
            np.testing.assert_array_equal(a.stderr_bias, b.stderr_bias)
        finally:
            plain.close()
    finally:
        svc.close()


def test_the_events_only_sums_go_on_when_frames_come(sim):
    rec = sim.recording
    msgs = list(messages(rec))
    # the events before the first frame, then everything
    first_frame = next(i for i, (k, _) in enumerate(msgs) if k == "frames")
    pub = Collector()
    svc = Service(ServiceConfig(onei=ONEI, event_timing=True), pub)
    try:
        for kind, payload in msgs[first_frame + 1:first_frame + 40]:
            if kind == "events":
                svc.on_sample(f"evcal/{CAM}/{kind}", payload)
        settle(svc)
        st = svc.cameras[CAM].state
        only = st.events_only
        assert only is not None
        assert only.n_events > 0
        assert st.timing is None
        for kind, payload in msgs[first_frame + 40:]:
            svc.on_sample(f"evcal/{CAM}/{kind}", payload)
        settle(svc)
        assert st.events_only is None
        assert st.timing is only
    finally:
        svc.close()


def test_the_timing_sums_survive_a_restart(sim, tmp_path):
    store = StateStore(tmp_path)
    n = len(list(messages(sim.recording)))
    svc, _ = run(sim.recording, store=store, upto=n // 2, event_timing=True)
    before = svc.cameras[CAM].state.timing.state_dict()
    svc.close()  # snapshots
    with open(next(tmp_path.glob("*.npz")), "rb") as f:
        arrays = read_snapshot(f)
    assert any(k.startswith("timing__") for k in arrays)
    pub = Collector()
    svc2 = Service(ServiceConfig(onei=ONEI, event_timing=True), pub, store=store,
                   match=lambda e, k: True)
    try:
        assert svc2.restore() == [CAM]
        after = svc2.cameras[CAM].state.timing.state_dict()
        for k, v in before.items():
            np.testing.assert_array_equal(after[k], v, err_msg=k)
        run(sim.recording, start=n // 2, svc=svc2)
        full, _ = run(sim.recording, event_timing=True)
        try:
            a = svc2.cameras[CAM].state.timing.state_dict()
            b = full.cameras[CAM].state.timing.state_dict()
            for k in ("sums", "counts"):
                np.testing.assert_array_equal(a[k], b[k], err_msg=k)
        finally:
            full.close()
    finally:
        svc2.close()


def test_a_service_without_event_timing_drops_the_sums_of_a_snapshot(sim, tmp_path):
    store = StateStore(tmp_path)
    svc, _ = run(sim.recording, store=store, upto=60, event_timing=True)
    svc.close()
    svc2 = Service(ServiceConfig(onei=ONEI), Collector(), store=store,
                   match=lambda e, k: True)
    try:
        assert svc2.restore() == [CAM]
        assert svc2.cameras[CAM].state.timing is None
    finally:
        svc2.close()


def test_serve_flag_reaches_the_service_config():
    from evcal.service.cli import build_parser, config_from_args

    parse = build_parser().parse_args
    assert config_from_args(parse(["--event-timing"])).event_timing is True
    assert config_from_args(parse([])).event_timing is False


def test_a_timing_state_of_the_wrong_shape_is_refused(sim, tmp_path):
    store = StateStore(tmp_path)
    svc, _ = run(sim.recording, store=store, upto=60, event_timing=True)
    svc.close()
    path = next(tmp_path.glob("*.npz"))
    with np.load(path) as z:
        arrays = dict(z)
    arrays["timing__sums"] = arrays["timing__sums"][:-1]
    np.savez(path, **arrays)
    from evcal.errors import StateError

    with open(path, "rb") as f, pytest.raises(StateError, match="timing__sums"):
        read_snapshot(f)


def test_streaming_offe_sums_are_those_of_the_events_only_estimator(sim):
    # the timing sums are a plain StreamingOffE of every event: same state as one fed alone
    svc, _ = run(sim.recording, event_timing=True)
    try:
        est = StreamingOffE(sim.recording.sensor, ServiceConfig().offe)
        est.feed_events(sim.recording.events)
        got = svc.cameras[CAM].state.timing.state_dict()
        want = est.state_dict()
        for k in ("sums", "counts"):  # the mark moves when maps are asked for
            np.testing.assert_array_equal(got[k], want[k], err_msg=k)
    finally:
        svc.close()


@pytest.mark.timeout(240)
def test_serve_event_timing_over_zenoh(sim, tmp_path):
    """`evcal serve --event-timing` in its own process: a replay over loopback zenoh, the
    status says the updates were fused and the queried maps are those of the fusion."""
    pytest.importorskip("zenoh")
    import json

    from evcal.io import load_calibration, write_recording
    from evcal.service.transport import Transport, ZenohOptions
    from evcal.testing import ServiceProcess, endpoint, free_port, run_client, wait_for

    path = write_recording(sim.recording, tmp_path / "rec.npz")
    ep, z = endpoint(free_port()), ["--no-multicast-scouting"]
    args = ["--listen", ep, *z, "--on-full", "block", "--n-small", str(ONEI.n_small),
            "--n-large", str(ONEI.n_large), "--log-offset", "30", "--status-period", "0.2",
            "--event-timing"]
    cam = "lab/timing/cam0"
    n_ev, n_fr = sim.recording.events.size, len(sim.recording.frames)
    with ServiceProcess(args, log_path=tmp_path / "service.log") as sp, \
            Transport(ZenohOptions.loopback(connect=[ep])) as t:
        wait_for(lambda: t.alive("evcal/@service/*", timeout_s=1.0), timeout_s=60,
                 what="the service's liveliness token")
        res = run_client("replay", [str(path), "--camera", cam, "--connect", ep, *z,
                                    "--max-rate"])
        assert res.returncode == 0, res.stderr

        def status():
            replies = t.get(f"evcal/{cam}/status", timeout_s=2.0)
            s = json.loads(replies[0].payload) if replies and replies[0].ok else {}
            return (s.get("frames", 0) >= n_fr and s.get("events", 0) >= n_ev
                    and s.get("in_flight_messages") == 0 and s)

        st = wait_for(status, timeout_s=60, what="the replay processed")
        assert st["event_timing"]["events"] == n_ev
        assert st["event_timing"]["not_fused"] is None
        res = run_client("query", ["--camera", cam, "--connect", ep, *z, "--out",
                                   str(tmp_path / "cal.npz"), "--timeout", "5"])
        assert res.returncode == 0, res.stderr
        cal = load_calibration(tmp_path / "cal.npz")
        c = sim.truth["contrast"]
        m = cal.valid
        assert m.sum() > 1000
        assert rmse(cal.contrast, c, m) < 0.02
        info = cal.diagnostics.extra["fusion"]  # the query's maps are the fused ones
        assert "reason" not in info
        assert info["pixels"] > 1000
        assert 0 < info["offe_maps_t_us"] <= int(sim.recording.events["t_us"][-1])
        assert sp.alive()


def test_with_posterior_the_fused_maps_are_pulled_and_raw_is_the_fused(sim):
    svc, pub = run(sim.recording, event_timing=True, posterior=True, posterior_refresh_us=0)
    try:
        published = latest(pub)
        assert estimate_of(published) == "posterior"
        (_, payload, _), = svc.query_calibration(KEY, {"estimate": "raw"})
        raw, _ = decode_calibration(payload)
        assert estimate_of(raw) == "raw"
        # the raw maps are the fused ones, before the pull
        assert "reason" not in raw.diagnostics.extra["fusion"]
        np.testing.assert_allclose(published.contrast, posterior_maps(raw).contrast,
                                   rtol=0, atol=1e-7)
    finally:
        svc.close()
