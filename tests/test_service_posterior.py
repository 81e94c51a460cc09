"""Posterior maps in the service (serve --posterior, queries with estimate=raw|posterior) and
the live priors they use, without a network (the e2e module queries them over zenoh)."""

from __future__ import annotations

import numpy as np
import pytest
from test_service_core import Collector

from evcal.calibration import Special
from evcal.clients.replay import schedule
from evcal.io.wire import decode_calibration, encode_events, encode_frame
from evcal.online import OnEIConfig
from evcal.posterior import LivePosterior, estimate_of, posterior_maps
from evcal.recording import Recording
from evcal.service.camera import Rejected
from evcal.service.core import Service, ServiceConfig
from evcal.service.outputs import calibration_reply
from evcal.service.state import StateStore
from evcal.sim.ideal import SimConfig, simulate_ideal
from evcal.testing import settle

ONEI = OnEIConfig(n_small=4000, n_large=2_000_000, window_frames=5, log_offset=30.0,
                  eager=True)
KEY = "evcal/lab/cam0/calibration"


@pytest.fixture(scope="module")
def sim():
    # few events per pixel (64x48, 3 s): the pixels' own estimates are noisy, so the pull
    # toward the population has something to gain
    return simulate_ideal(SimConfig(height=48, width=64, duration_s=3.0, seed=5,
                                    scene="camera"))


def messages(rec: Recording):
    h, w = rec.sensor.shape
    seq = {"frame": 0, "events": 0}
    for kind, _, i0, i1 in schedule(rec):
        if kind == "frame":
            yield "frames", encode_frame(int(rec.frames.t_us[i0]), rec.frames.images[i0],
                                         exposure_us=0, seq=seq[kind])
        else:
            yield "events", encode_events(rec.events[i0:i1], height=h, width=w,
                                          seq=seq[kind])
        seq[kind] += 1


def run(rec: Recording, *, store: StateStore | None = None, upto: int | None = None,
        **kw) -> tuple[Service, Collector]:
    pub = Collector()
    svc = Service(ServiceConfig(onei=ONEI, **kw), pub, store=store)
    for i, (kind, payload) in enumerate(messages(rec)):
        if upto is not None and i >= upto:
            break
        svc.on_sample(f"evcal/lab/cam0/{kind}", payload)
    settle(svc)
    return svc, pub


def rmse(a, b, m):
    return float(np.sqrt(np.mean((a[m].astype(float) - b[m]) ** 2)))


def test_serve_posterior_publishes_the_posterior_and_answers_raw(sim):
    svc, pub = run(sim.recording, posterior=True, posterior_refresh_us=0)
    try:
        published, _ = decode_calibration(pub.on(KEY)[-1])
        assert estimate_of(published) == "posterior"
        (_, payload, _), = svc.query_calibration(KEY, {"estimate": "raw"})
        raw, _ = decode_calibration(payload)
        assert estimate_of(raw) == "raw"
        # priors taken at every update (refresh 0): the published maps are the posterior of
        # the raw ones
        np.testing.assert_allclose(published.contrast, posterior_maps(raw).contrast,
                                   rtol=0, atol=1e-7)
        np.testing.assert_array_equal(published.valid, raw.valid)
        # the pull helps where the evidence is thin, and special pixels keep their own values
        c, b = sim.truth["contrast"], sim.truth["bias"]
        m = raw.valid & (raw.special == Special.NORMAL)
        assert m.sum() > 500
        assert rmse(published.contrast, c, m) < 0.97 * rmse(raw.contrast, c, m)
        assert rmse(published.bias, b, m) < rmse(raw.bias, b, m)
        sp = raw.special != Special.NORMAL
        np.testing.assert_array_equal(published.contrast[sp], raw.contrast[sp])
        st = svc.cameras["lab/cam0"].state
        assert st.live_posterior is not None
        assert st.live_posterior.refreshes >= 2
        from evcal.service.outputs import camera_status

        assert camera_status(svc.cameras["lab/cam0"])["estimate"] == "posterior"
    finally:
        svc.close()


def test_raw_service_computes_a_posterior_once_per_update_on_demand(sim):
    svc, pub = run(sim.recording)
    try:
        published, _ = decode_calibration(pub.on(KEY)[-1])
        assert estimate_of(published) == "raw"
        (_, p1, _), = svc.query_calibration(KEY, {"estimate": "posterior", "format": "npz"})
        st = svc.cameras["lab/cam0"].state
        cached = st.posterior_cache
        assert cached is not None
        assert estimate_of(cached[1]) == "posterior"
        np.testing.assert_allclose(cached[1].contrast, posterior_maps(published).contrast,
                                   rtol=0, atol=1e-7)
        svc.query_calibration(KEY, {"estimate": "posterior"})
        assert st.posterior_cache is cached  # the same update: not computed again
        # raw is what is published: the published message itself
        (_, p2, _), = svc.query_calibration(KEY, {"estimate": "raw"})
        assert p2 == pub.on(KEY)[-1]
        with pytest.raises(Rejected, match="estimate='best'") as info:
            svc.query_calibration(KEY, {"estimate": "best"})
        assert str(info.value.reason) == "bad_query"
    finally:
        svc.close()


def test_raw_maps_are_not_kept_across_a_restart_and_come_back(sim, tmp_path):
    store = StateStore(tmp_path)
    n = sum(1 for _ in messages(sim.recording))
    svc, _ = run(sim.recording, store=store, upto=2 * n // 3, posterior=True)
    svc.close()  # snapshots
    pub = Collector()
    svc2 = Service(ServiceConfig(onei=ONEI, posterior=True), pub, store=store,
                   match=lambda e, k: True)
    try:
        assert svc2.restore() == ["lab/cam0"]
        (_, payload, _), = svc2.query_calibration(KEY, {})
        assert estimate_of(decode_calibration(payload)[0]) == "posterior"
        with pytest.raises(Rejected, match="not kept across a restart"):
            svc2.query_calibration(KEY, {"estimate": "raw"})
        for i, (kind, msg) in enumerate(messages(sim.recording)):
            if i >= 2 * n // 3:
                svc2.on_sample(f"evcal/lab/cam0/{kind}", msg)
        settle(svc2)
        (_, payload, _), = svc2.query_calibration(KEY, {"estimate": "raw"})
        assert estimate_of(decode_calibration(payload)[0]) == "raw"
    finally:
        svc2.close()


def test_an_events_only_camera_has_no_posterior_to_give(sim):
    rec = sim.recording
    pub = Collector()
    svc = Service(ServiceConfig(onei=ONEI, posterior=True, offe_period_us=200_000), pub)
    try:
        h, w = rec.sensor.shape
        ev = rec.events
        for k, i0 in enumerate(range(0, ev.size, 20_000)):
            svc.on_sample("evcal/lab/cam0/events",
                          encode_events(ev[i0:i0 + 20_000], height=h, width=w, seq=k))
        settle(svc)
        cam = svc.cameras["lab/cam0"]
        with cam.lock:
            payload, _ = calibration_reply(cam.state, "msgpack", None)
        assert decode_calibration(payload)[0].method == "offe"  # published raw, as it is
        with pytest.raises(Rejected, match="calibrated standard errors") as info:
            svc.query_calibration(KEY, {"estimate": "posterior"})
        assert str(info.value.reason) == "bad_query"
    finally:
        svc.close()


def test_live_priors_are_refreshed_by_sensor_time_and_on_a_jump_back(sim):
    from evcal.online import onei

    cal = onei(sim.recording, ONEI)
    live = LivePosterior(refresh_us=1_000_000)
    first = live.apply(cal, 5_000_000)
    priors = live.priors
    np.testing.assert_array_equal(first.contrast, posterior_maps(cal).contrast)
    live.apply(cal, 5_900_000)
    assert live.priors is priors
    assert live.refreshes == 1
    live.apply(cal, 6_000_000)
    assert live.refreshes == 2
    assert live.priors_t_us == 6_000_000
    live.apply(cal, 100)  # the sensor's clock went back (a new session)
    assert live.refreshes == 3
    assert live.priors_t_us == 100
    out = live.apply(cal, 200)
    assert out.diagnostics.extra["posterior"]["priors_t_us"] == 100
    with pytest.raises(ValueError, match="refresh_us"):
        LivePosterior(refresh_us=-1)


def test_priors_from_a_sample_are_as_good_as_those_of_every_pixel():
    """Large sensors: the priors come from a strided sample of the pool (2,048 pixels a
    bin). Their sampling error moves each pixel's posterior by a few percent of its own
    error, second order in its squared error: the posterior's RMSE against the truth is
    within 1 % of that with priors from every pixel, and well below the raw RMSE."""
    import evcal.posterior as post
    from evcal.calibration import Calibration

    rng = np.random.default_rng(3)
    shape = (720, 1280)
    se = rng.uniform(0.005, 0.05, shape).astype(np.float32)
    truth = rng.normal(0.2, 0.03, shape)
    est = (truth + se * rng.standard_normal(shape)).astype(np.float32)
    cal = Calibration.uniform(shape, method="offei", log_offset=30.0).replace(
        contrast=est, stderr_contrast=se)
    assert est.size > 8 * post.PRIOR_PIXELS
    sampled = posterior_maps(cal)
    old = post.PRIOR_PIXELS
    try:
        post.PRIOR_PIXELS = est.size  # every pixel
        full = post.posterior_maps(cal)
    finally:
        post.PRIOR_PIXELS = old
    every = np.ones(shape, bool)
    r_sampled = rmse(sampled.contrast, truth, every)
    r_full = rmse(full.contrast, truth, every)
    assert r_sampled < 1.01 * r_full
    assert r_full < 0.8 * rmse(est, truth, every)


def test_a_periodic_refresh_on_a_worker_keeps_the_old_priors_until_done(sim):
    from concurrent.futures import Future

    from evcal.online import onei
    from evcal.posterior import apply_priors

    cal = onei(sim.recording, ONEI)
    jobs: list[tuple[Future, object]] = []

    def submit(fn):
        fut: Future = Future()
        jobs.append((fut, fn))
        return fut

    live = LivePosterior(refresh_us=1000, submit=submit)
    live.apply(cal, 0)  # the first priors: at once, on the caller's thread
    first = live.priors
    assert not jobs
    live.apply(cal, 5000)  # due: submitted, the old priors still used
    assert len(jobs) == 1
    assert live.priors is first
    live.apply(cal, 6000)  # still running: not submitted twice
    assert len(jobs) == 1
    fut, fn = jobs[0]
    fut.set_result(fn())
    out = live.apply(cal, 7000)
    assert live.priors is not first
    assert live.priors_t_us == 5000  # the time it was asked for
    assert out.diagnostics.extra["posterior"]["priors_t_us"] == 5000
    # a refresh that failed is dropped; the next due one is submitted again
    live.apply(cal, 9000)
    jobs[-1][0].set_exception(RuntimeError("worker gone"))
    live.apply(cal, 9100)
    assert live.priors_t_us == 5000
    live.apply(cal, 9200)
    assert len(jobs) == 3
    # split over pixel ranges: the same maps as one pass
    ranges = []

    def split(n, work):
        cuts = [0, n // 3, 2 * n // 3, n]
        for lo, hi in zip(cuts[:-1], cuts[1:], strict=True):
            ranges.append((lo, hi))
            work(lo, hi)

    a = apply_priors(cal, first, split=split)
    b = apply_priors(cal, first)
    n = cal.contrast.size
    assert ranges == [(0, n // 3), (n // 3, 2 * n // 3), (2 * n // 3, n)]  # both maps at once
    for name in ("contrast", "bias", "stderr_contrast", "stderr_bias"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))


def test_serve_flags_reach_the_service_config():
    from evcal.errors import ConfigError
    from evcal.service.cli import build_parser, config_from_args

    parse = build_parser().parse_args
    cfg = config_from_args(parse(["--posterior", "--posterior-refresh", "0.5"]))
    assert cfg.posterior is True
    assert cfg.posterior_refresh_us == 500_000
    assert config_from_args(parse([])).posterior is False
    with pytest.raises(ConfigError, match="--posterior-refresh"):
        config_from_args(parse(["--posterior", "--posterior-refresh", "-1"]))
