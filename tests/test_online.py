"""OnEI's streaming contract: bounded buffers, the drop rule, bad input, state round trips.

Synthetic random streams (no simulator): these tests are about bookkeeping, not accuracy
(accuracy is tests/test_recovery.py's).
"""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

from evcal.bench import random_recording
from evcal.errors import CalibrationError, ConfigError
from evcal.events import EventError, SensorSize, make_events
from evcal.online import OnEIConfig, OnlineCalibrator, onei
from evcal.solver import NormalEquations, log_intensity, usable
from evcal.stream import frame_intervals

SENSOR = SensorSize(20, 30)


def feed(cal: OnlineCalibrator, rec, frames=None) -> list[dict]:
    t_ev = rec.events["t_us"]
    cuts = np.searchsorted(t_ev, rec.frames.t_us)
    prev = 0
    out = []
    for k in range(len(rec.frames)) if frames is None else frames:
        cal.feed_events(rec.events[prev : cuts[k]])
        prev = int(cuts[k])
        cal.feed_frame(int(rec.frames.t_us[k]), rec.frames.images[k])
        out.append(cal.status())
    return out


def test_large_buffer_holds_at_most_n_large_events_and_drops_oldest_first():
    rec = random_recording(SENSOR, 60 * 3000, 60)  # ~3000 events per frame interval
    cal = OnlineCalibrator(SENSOR, OnEIConfig(n_small=5000, n_large=20_000))
    statuses = feed(cal, rec)
    assert max(s["buffer_events"] for s in statuses) <= 20_000
    last = statuses[-1]
    assert 5 <= last["buffer_frames"] <= 8  # 20 k / 3 k intervals
    # a small buffer opens at every frame whose window has closed: about frames - 2 of them
    assert last["buffer_equations"] >= last["buffer_frames"] - 3
    assert last["n_updates"] >= 60 * 3000 // 5000 - 8
    # the per-pixel counts are those of the buffered intervals
    t0 = int(rec.frames.t_us[-last["buffer_frames"]])
    ev = rec.events[(rec.events["t_us"] >= t0) & (rec.events["t_us"] < rec.frames.t_us[-1])]
    counts = np.bincount(ev["y"].astype(int) * SENSOR.width + ev["x"], minlength=SENSOR.n_pixels)
    np.testing.assert_array_equal(cal.calibration().n_events.ravel(), counts)


def test_frame_cap_bounds_a_static_scene():
    rec = random_recording(SENSOR, 200, 100)  # almost no events: the count never overflows
    cal = OnlineCalibrator(SENSOR, OnEIConfig(n_small=5000, n_large=20_000,
                                              max_buffer_frames=12))
    statuses = feed(cal, rec)
    assert max(s["buffer_frames"] for s in statuses) == 12
    assert statuses[-1]["n_updates"] == 0
    assert cal.buffer_bytes <= 12 * SENSOR.n_pixels * 2 + 200 * 12


def test_an_interval_larger_than_the_buffer_is_kept_alone():
    rec = random_recording(SENSOR, 10 * 30_000, 10)
    cal = OnlineCalibrator(SENSOR, OnEIConfig(n_small=2000, n_large=10_000))
    statuses = feed(cal, rec)
    assert all(s["buffer_frames"] <= 2 for s in statuses)
    assert statuses[-1]["buffer_equations"] == 1
    assert statuses[-1]["n_updates"] >= 8


def test_bad_input_is_refused_with_the_reason():
    cal = OnlineCalibrator(SENSOR, OnEIConfig(n_small=100, n_large=1000))
    img = np.full(SENSOR.shape, 100, np.uint8)
    cal.feed_frame(1000, img)
    with pytest.raises(ValueError, match="shape"):
        cal.feed_frame(2000, np.zeros((3, 4), np.uint8))
    with pytest.raises(ValueError, match="NaN"):
        cal.feed_frame(2000, np.full(SENSOR.shape, np.nan, np.float32))
    with pytest.raises(ValueError, match="backwards"):
        cal.feed_frame(1000, img)
    with pytest.raises(EventError, match="outside"):
        cal.feed_events(make_events([1500], [30], [0], [1]))
    cal.feed_events(make_events([1500, 1600], [1, 2], [1, 2], [1, 0]))
    with pytest.raises(EventError, match="sorted|before"):
        cal.feed_events(make_events([1550], [1], [1], [1]))
    with pytest.raises(EventError, match="backwards"):
        cal.feed_events(make_events([1580], [1], [1], [1]))
    # events before the latest frame arrive late: counted, never silently mixed in
    cal.feed_frame(3000, img)
    cal.feed_events(make_events([2500, 3100], [1, 1], [1, 1], [1, 1]))
    assert cal.status()["late_events"] == 1


def test_state_round_trip_mid_stream_and_bad_states():
    rec = random_recording(SENSOR, 40 * 3000, 40)
    cfg = OnEIConfig(n_small=5000, n_large=20_000)
    a = OnlineCalibrator(SENSOR, cfg)
    feed(a, rec, range(20))
    state = a.state_dict()
    b = OnlineCalibrator.from_state(state)
    cuts = np.searchsorted(rec.events["t_us"], rec.frames.t_us)
    for cal in (a, b):
        prev = int(cuts[19])
        for k in range(20, 40):
            cal.feed_events(rec.events[prev : cuts[k]])
            prev = int(cuts[k])
            cal.feed_frame(int(rec.frames.t_us[k]), rec.frames.images[k])
    np.testing.assert_array_equal(a.calibration().contrast, b.calibration().contrast)
    np.testing.assert_array_equal(a.calibration().stderr_bias, b.calibration().stderr_bias)
    assert a.status() == b.status()
    # a state written before the smoothed estimate's variance was kept: its estimate's
    # errors start as one solve's
    old = OnlineCalibrator.from_state({k: v for k, v in state.items() if k != "track"})
    seen = old.estimate.seen
    assert seen.any()
    np.testing.assert_array_equal(old.estimate.smoothed_errors()[0][seen],
                                  old.estimate.se_c[seen])
    assert np.isinf(old.estimate.smoothed_errors()[1][~seen]).all()
    bad = dict(state, fr_images=state["fr_images"][:, :5])
    with pytest.raises(ValueError, match="frames have shapes"):
        OnlineCalibrator.from_state(bad)
    with pytest.raises(ValueError, match="lacks 'counts'"):
        OnlineCalibrator.from_state({k: v for k, v in state.items() if k != "counts"})
    with pytest.raises(ValueError, match="format"):
        OnlineCalibrator.from_state(dict(state, format=np.array("evcal.onei.v1")))


@pytest.mark.parametrize(("scene", "seed"), [("astronaut", 31), ("camera", 32),
                                             ("coffee", 33), ("chelsea", 34)])
def test_the_stated_errors_are_the_errors(scene, seed):
    """std(z) of (estimate - truth) / stated error over the valid normal pixels of a
    simulated recording: near 1 (c 0.8-1.25, b 0.7-1.2: the sandwich's b is a little
    pessimistic). The solves' own errors, inflated by the small buffers an event lies in,
    give 0.5-0.65 for c and 0.35-0.45 for b here, and the low-pass's averaging of
    overlapping solves comes on top of that."""
    from evcal.calibration import Special
    from evcal.sim.ideal import SimConfig, simulate_ideal

    sim = simulate_ideal(SimConfig(height=96, width=128, duration_s=4.0, seed=seed,
                                   scene=scene))
    cal = onei(sim.recording)
    info = cal.diagnostics.stderr_calibration
    assert info["method"] == "sandwich", info
    assert info["sample_pixels"] > 1000, info
    m = cal.valid & (cal.special == Special.NORMAL)
    assert m.mean() > 0.8
    for est, se, truth, (lo, hi) in (
            (cal.contrast, cal.stderr_contrast, sim.truth["contrast"], (0.8, 1.25)),
            (cal.bias, cal.stderr_bias, sim.truth["bias"], (0.7, 1.2))):
        z = (est[m].astype(np.float64) - truth[m]) / se[m]
        assert lo <= float(np.std(z)) <= hi, (scene, float(np.std(z)), info)


def test_onei_needs_frames():
    rec = random_recording(SENSOR, 100, 1)
    with pytest.raises(CalibrationError, match="needs frames"):
        onei(rec)


@pytest.mark.parametrize(("true_offset", "seed"), [(0.0, 5), (0.0, 6), (30.0, 5), (80.0, 6)])
def test_the_log_offset_is_estimated_online(true_offset, seed):
    """log_offset="auto" (the service's default): the criterion of --log-offset auto on the
    buffer, re-checked each time the frames seen double, the checks' criterion curves summed.
    Measured at 120x90, 6 s: found 0.69, 0.69, 28.2 and 85.1, and c RMSE within 1.2x of the
    run told the true offset. On these frames (8..240 DN) the criterion cannot tell 0 from
    1 DN (it changes in its fifth digit), hence the wider tolerance at 0."""
    from evcal.sim.ideal import SimConfig, simulate_ideal

    sim = simulate_ideal(SimConfig(height=90, width=120, duration_s=6.0, seed=seed,
                                   log_offset=true_offset))

    def c_rmse(cal):
        v = cal.valid
        return float(np.sqrt(np.mean((cal.contrast[v] - sim.truth["contrast"][v]) ** 2)))

    cfg = OnEIConfig(n_small=50_000, n_large=400_000)
    auto = onei(sim.recording, replace(cfg, log_offset="auto"))
    told = onei(sim.recording, replace(cfg, log_offset=true_offset))
    tolerance = 1.0 if true_offset == 0 else 0.5
    assert abs(np.log1p(auto.log_offset) - np.log1p(true_offset)) < tolerance, auto.log_offset
    assert auto.diagnostics.log_offset_estimation["method"] == "auto"
    assert auto.valid.mean() > 0.95
    assert c_rmse(auto) <= 1.3 * c_rmse(told), (c_rmse(auto), c_rmse(told))


def _reference_equations(state: dict, weights: dict[int, float] | None = None
                         ) -> tuple[NormalEquations, np.ndarray]:
    """The normal equations and per-pixel counts of a state, recomputed from scratch: every
    small buffer the large buffer holds added once with ``NormalEquations.add`` (the
    definition of OnEI's sums, as the first implementation computed them). With
    ``weights`` (absolute number of the opening frame -> weight) only those small buffers,
    each times its weight."""
    s = json.loads(str(state["scalars"]))
    sat = OnEIConfig.from_json(s["config"]).saturation_dn
    meta, images, last_p = state["fr_meta"], state["fr_images"], state["fr_last_p"]
    n = images.shape[1]
    bounds = np.concatenate([[0], np.cumsum(meta[:, 2])])
    on = np.zeros((len(meta), n))
    off = np.zeros((len(meta), n))
    for i in range(len(meta)):
        sl = slice(bounds[i], bounds[i + 1])
        on[i, state["fr_idx"][sl]] = state["fr_on"][sl]
        off[i, state["fr_idx"][sl]] = state["fr_off"][sl]
    ne = NormalEquations(n)
    for j, closes_at in enumerate(meta[:, 4]):
        if closes_at < 0 or (weights is not None and j + s["base"] not in weights):
            continue
        k = int(closes_at) - s["base"]
        wt = 1.0 if weights is None else weights[j + s["base"]]
        e_on, e_off = on[j + 1 : k + 1].sum(0), off[j + 1 : k + 1].sum(0)
        idx = np.flatnonzero(e_on + e_off)
        raw_j, raw_k = images[j][idx], images[k][idx]
        w = usable(raw_j, sat) & usable(raw_k, sat)
        with np.errstate(invalid="ignore"):
            dl = log_intensity(raw_k, s["log_offset"]) - log_intensity(raw_j, s["log_offset"])
        qj, qk = last_p[j][idx].astype(float), last_p[k][idx].astype(float)
        ne.add(e_on[idx] - e_off[idx], e_on[idx] + e_off[idx], qk - qj,
               np.abs(qk) - np.abs(qj), np.where(w, dl, 0.0), wt * w.astype(float), idx=idx)
    return ne, (on[1:] + off[1:]).sum(0)


@pytest.mark.parametrize(("sensor", "float_frames"), [(SensorSize(20, 30), False),
                                                      (SensorSize(20, 30), True),
                                                      (SensorSize(96, 100), False)])
def test_incremental_sums_equal_a_recomputation(sensor, float_frames):
    """The sums OnEI keeps incrementally (sliding sums of intervals, queued equations added
    block by block) equal the equations of the buffer recomputed from scratch, through busy
    (dense) and quiet (sparse) intervals, a hot pixel (its counts overflow the packed byte),
    lost events, a frame cap, a new session and a restart from the saved state."""
    n = sensor.n_pixels
    rng = np.random.default_rng(3)
    n_frames = 90
    t_f = np.arange(n_frames) * 40_000
    per_frame = np.where(np.arange(n_frames) % 17 < 9, 2 * n, n // 8)  # busy, then quiet
    chunks = []
    for k in range(n_frames):
        m = int(per_frame[k])
        pix = np.concatenate([rng.integers(0, n, m), np.full(300, 7)])  # pixel 7 is hot
        t = np.sort(rng.integers(t_f[k] - 40_000 + 1, t_f[k], pix.size))
        chunks.append(make_events(t, pix % sensor.width, pix // sensor.width,
                                  rng.choice([-1, 1], pix.size)))
    base = rng.integers(20, 230, n)
    images = np.clip(base + rng.integers(-30, 31, (n_frames, n)), 0, 255).astype(np.uint8)
    images[:, :5] = 255  # saturated pixels weigh nothing
    if float_frames:
        images = images.astype(np.float32) * np.float32(0.9)
    cfg = OnEIConfig(n_small=3 * n, n_large=14 * n, max_buffer_frames=25, rebuild_every=10**6)
    cal = OnlineCalibrator(sensor, cfg)
    checked = 0
    for k in range(n_frames):
        if k == 55:
            cal.new_session()
        if k in (30, 31, 70):
            cal.mark_gap()
        if k == 62:
            cal = OnlineCalibrator.from_state(cal.state_dict())
        cal.feed_events(chunks[k])
        cal.feed_frame(int(t_f[k]), images[k].reshape(sensor.shape))
        if k % 6 == 5:
            state = cal.state_dict()
            ref, counts = _reference_equations(state)
            for name, v in ref.arrays().items():
                scale = max(1.0, float(np.abs(v).max()))
                np.testing.assert_allclose(state[f"ne_{name}"], v, rtol=1e-9,
                                           atol=1e-12 * scale, err_msg=name)
            np.testing.assert_array_equal(state["counts"], counts)
            assert json.loads(str(state["scalars"]))["n_equations"] == int(
                (state["fr_meta"][:, 4] >= 0).sum())
            checked += int(ref.n_eq.max() > 0)
    assert checked >= 8
    assert cal.n_updates > 10
    assert cal.status()["gaps"] == 3
    assert cal.status()["sessions"] == 1


def test_the_forgotten_history_holds_what_left_the_buffer_with_its_weights(monkeypatch):
    """``history``: the equations that left the large buffer (by event count and by the frame
    cap) are kept beside it, each weighted ``exp(-E / (history * n_large))``, ``E`` the
    events that left after it. Checked against a calibrator whose buffer never drops:
    its equations, split by the small calibrator's buffer start, reweighted and recomputed
    from scratch; through dense and sparse intervals, a renormalisation and a restart."""
    sensor = SensorSize(20, 30)
    n = sensor.n_pixels
    rng = np.random.default_rng(11)
    n_frames = 70
    t_f = np.arange(n_frames) * 40_000
    per_frame = np.where(np.arange(n_frames) % 13 < 7, 2 * n, n // 6)
    images = np.clip(rng.integers(20, 230, n) + rng.integers(-30, 31, (n_frames, n)), 0,
                     255).astype(np.uint8)
    chunks = []
    for k in range(n_frames):
        pix = rng.integers(0, n, int(per_frame[k]))
        t = np.sort(rng.integers(t_f[k] - 40_000 + 1, t_f[k], pix.size))
        chunks.append(make_events(t, pix % sensor.width, pix // sensor.width,
                                  rng.choice([-1, 1], pix.size)))
    from evcal.onei.equations import NormalSums

    history = 0.2
    monkeypatch.setattr(NormalSums, "HISTORY_RENORMALISE", 20.0)  # passed on the way
    base_cfg = OnEIConfig(n_small=3 * n, n_large=12 * n, window_frames=3, log_offset=10.0,
                          rebuild_every=10**6)
    small = OnlineCalibrator(sensor, replace(base_cfg, max_buffer_frames=20, history=history))
    full = OnlineCalibrator(sensor, replace(base_cfg, n_large=10**9, max_buffer_frames=10**4))
    tau = history * small.n_large
    checked = renormalised = 0
    for k in range(n_frames):
        if k == 40:
            small = OnlineCalibrator.from_state(small.state_dict())
        for cal in (small, full):
            cal.feed_events(chunks[k])
            cal.feed_frame(int(t_f[k]), images[k].reshape(sensor.shape))
        if k % 5 != 4:
            continue
        s_state, f_state = small.state_dict(), full.state_dict()
        sc = json.loads(str(s_state["scalars"]))
        renormalised += sc["hist_ref"] > 0
        left_now = int(s_state["fr_meta"][0, 1])
        cum = f_state["fr_meta"][:, 1]  # the full buffer starts at frame 0
        weights = {j: float(np.exp(-(left_now - cum[j + 1]) / tau))
                   for j in range(sc["base"]) if f_state["fr_meta"][j, 4] >= 0}
        if not weights:
            continue
        ref, _ = _reference_equations(f_state, weights)
        got = s_state["hist_m"] * np.exp(-(left_now - sc["hist_ref"]) / tau)
        for i, (name, v) in enumerate(ref.arrays().items()):
            scale = max(1.0, float(np.abs(v).max()))
            np.testing.assert_allclose(got[i], v, rtol=1e-9, atol=1e-12 * scale,
                                       err_msg=name)
        checked += 1
    assert checked >= 8
    assert renormalised
    assert small.n_updates > 10


def test_an_unforgetting_history_solves_as_a_buffer_that_never_drops():
    """``history`` very large: the buffer plus its history is every equation of the stream,
    so each solve equals that of a buffer that never drops (up to rounding; smoothing 1
    makes the estimate the latest solve)."""
    rec = random_recording(SENSOR, 40 * 3000, 40)
    cfg = OnEIConfig(n_small=5000, n_large=20_000, window_frames=3, log_offset=20.0,
                     smoothing=1.0)
    kept = onei(rec, replace(cfg, history=1e12))
    full = onei(rec, replace(cfg, n_large=10**9))
    plain = onei(rec, cfg)
    np.testing.assert_array_equal(kept.valid, full.valid)
    np.testing.assert_allclose(kept.contrast, full.contrast, rtol=1e-9)
    assert not np.allclose(plain.contrast, full.contrast, rtol=1e-6)


def test_open_interval_counts_survive_a_restart():
    """The counts of the interval not yet closed by a frame (kept packed, one byte per pixel,
    with spills) are saved as the ON/OFF maps of the state format and restored exactly."""
    sensor = SensorSize(4, 5)
    cal = OnlineCalibrator(sensor, OnEIConfig(n_small=100, n_large=1000, max_pending_events=5))
    img = np.full(sensor.shape, 100, np.uint8)
    cal.feed_frame(1000, img)
    x = np.array([1] * 20 + [2] * 3 + [3])
    p = np.array([1] * 12 + [-1] * 8 + [1, -1, -1] + [1])
    for t0 in (1100, 3100):
        cal.feed_events(make_events(np.arange(t0, t0 + x.size), x, np.zeros_like(x), p))
    cal.feed_events(make_events([5000], [0], [0], [1]))  # overflows: the rest is folded
    assert cal.status()["folded_late_events"] == 2 * x.size
    state = cal.state_dict()
    np.testing.assert_array_equal(state["acc_on"][:4], [0, 24, 2, 2])
    np.testing.assert_array_equal(state["acc_off"][:4], [0, 16, 4, 0])
    assert list(state["acc_last_p"][:4]) == [0, -1, -1, 1]
    b = OnlineCalibrator.from_state(state)
    for key in ("acc_on", "acc_off", "acc_last_p", "counts"):
        np.testing.assert_array_equal(b.state_dict()[key], state[key])
    for c in (cal, b):
        c.feed_frame(6000, img)
    np.testing.assert_array_equal(cal.state_dict()["fr_on"], b.state_dict()["fr_on"])
    np.testing.assert_array_equal(cal.state_dict()["counts"][:4], [1, 40, 6, 2])


def test_residual_lambda_blocks_cover_small_sensors_and_spread_over_large_ones():
    """lam is estimated on every pixel up to LAMBDA_BLOCKS blocks, else on that many blocks
    spread from the first to the last (a 1280x720 sensor has 113)."""
    from evcal.onei.kernels import BLOCK
    from evcal.onei.solve import LAMBDA_BLOCKS, lambda_block_list

    small = OnlineCalibrator(SensorSize(260, 346)).buffer.sums.n_blocks
    np.testing.assert_array_equal(lambda_block_list(small), np.arange(small))
    hd = OnlineCalibrator(SensorSize(720, 1280)).buffer.sums.n_blocks
    blocks = lambda_block_list(hd)
    assert hd == -(-720 * 1280 // BLOCK) > LAMBDA_BLOCKS
    assert blocks.size == LAMBDA_BLOCKS == np.unique(blocks).size
    assert blocks[0] == 0
    assert blocks[-1] == hd - 1


def test_a_live_calibrator_never_waits_for_the_offset_criterion(monkeypatch):
    """offset_wait=False (the service): a criterion still running when its frame comes does
    not block the frame path; its result is taken as soon as it is done, at the next frame or
    between frames (poll_offset)."""
    import threading

    from evcal.onei import offset as offset_mod

    release = threading.Event()
    real = offset_mod.offset_criterion

    def slow(*args):
        assert release.wait(30), "the test never released the criterion"
        return real(*args)

    monkeypatch.setattr(offset_mod, "offset_criterion", slow)
    rec = random_recording(SENSOR, 60 * SENSOR.n_pixels, 60, seed=4)
    cal = OnlineCalibrator(SENSOR, OnEIConfig(log_offset="auto", n_small=2 * SENSOR.n_pixels,
                                              offset_wait=False))
    cuts = np.searchsorted(rec.events["t_us"], rec.frames.t_us)
    for k in range(40):
        cal.feed_events(rec.events[cuts[k - 1] if k else 0 : cuts[k]])
        cal.feed_frame(int(rec.frames.t_us[k]), rec.frames.images[k])
    # the criterion started at frame 11 and is still running: nothing waited for it
    assert np.isnan(cal.log_offset)
    assert cal.n_updates == 0
    assert not cal.poll_offset()
    release.set()
    cal.offset.job[1].result(timeout=30)
    # the stream has stopped: between frames the estimate is taken and solved at once
    assert cal.poll_offset()
    assert np.isfinite(cal.log_offset)
    assert cal.n_updates == 1
    assert cal.calibration().valid.any()  # random frames: a fifth of the pixels fit
    assert cal.offset_info["method"] == "auto"
    assert not cal.poll_offset()  # nothing more to take


def test_the_frame_that_takes_the_first_offset_estimate_is_solved():
    """The frame at which the first online offset estimate lands forms the buffer's
    equations and is solved at once: a stream that ends there still has a calibration."""
    rec = random_recording(SENSOR, 60 * SENSOR.n_pixels, 60, seed=6)
    cal = OnlineCalibrator(SENSOR, OnEIConfig(log_offset="auto", n_small=2 * SENSOR.n_pixels))
    cuts = np.searchsorted(rec.events["t_us"], rec.frames.t_us)
    for k in range(60):
        cal.feed_events(rec.events[cuts[k - 1] if k else 0 : cuts[k]])
        updated = cal.feed_frame(int(rec.frames.t_us[k]), rec.frames.images[k])
        if np.isfinite(cal.log_offset):
            break
    assert np.isfinite(cal.log_offset)
    assert updated
    assert cal.n_updates == 1


def test_the_first_offset_estimate_waits_for_enough_busy_pixels():
    """A scene that begins still but for a few pixels: the first online offset estimate waits
    until 5 % of the pixels are busy (it is then computed from them), not judged from a
    handful (v2e recordings: 33-59 busy pixels gave 64-400 DN for a true 0)."""
    sensor = SensorSize(40, 50)
    n = sensor.n_pixels
    rec = random_recording(sensor, 60 * 2 * n, 60, seed=2)
    ev = rec.events
    few = (ev["y"] * sensor.width + ev["x"]) < 30  # 30 busy pixels ...
    early = ev["t_us"] < rec.frames.t_us[25]  # ... until frame 25
    events = ev[~early | few]
    cal = OnlineCalibrator(sensor, OnEIConfig(log_offset="auto", n_small=n, n_large=10**7))
    cuts = np.searchsorted(events["t_us"], rec.frames.t_us)
    first_at = None
    states = []
    for k in range(60):
        cal.feed_events(events[cuts[k - 1] if k else 0 : cuts[k]])
        cal.feed_frame(int(rec.frames.t_us[k]), rec.frames.images[k])
        states.append(cal.status()["log_offset_state"])
        if first_at is None and np.isfinite(cal.log_offset):
            first_at, info = k, dict(cal.offset_info)
    assert first_at is not None
    assert first_at > 25
    # the operator's status says what the estimate waits for
    assert states[0] == "waiting for 11 buffered frames"
    assert states[20] == "waiting for busy pixels: 30 of 100, or for 32 frames"
    assert states[first_at] == f"estimated at frame {first_at + 1}"
    assert info["pixels"] >= 0.05 * n
    # a full large buffer does not wait for busy pixels: what it holds is all there is
    cal = OnlineCalibrator(sensor, OnEIConfig(log_offset="auto", n_small=100, n_large=600))
    for k in range(25):
        cal.feed_events(events[cuts[k - 1] if k else 0 : cuts[k]])
        cal.feed_frame(int(rec.frames.t_us[k]), rec.frames.images[k])
    assert np.isfinite(cal.log_offset)
    assert cal.offset_info["pixels"] < 0.05 * n


def test_the_re_solve_gives_the_same_result_on_any_number_of_threads(monkeypatch):
    """The re-solve's blocks and the per-frame passes over the pixels are split over threads
    (OnEIConfig.threads): every figure is the same with 1, 2 or 3 threads, with the history's
    combination and a residual correction estimated on blocks spread over a sensor of more
    than LAMBDA_BLOCKS blocks."""
    from evcal.onei import executor as executor_mod
    from evcal.onei.kernels import BLOCK
    from evcal.onei.solve import LAMBDA_BLOCKS

    # every per-frame pass split too (at the default only from 262,144 pixels)
    monkeypatch.setattr(executor_mod, "PIXELS_PER_THREAD", 1000)

    sensor = SensorSize(300, 480)
    assert -(-sensor.n_pixels // BLOCK) > LAMBDA_BLOCKS
    n = sensor.n_pixels
    rec = random_recording(sensor, 2 * n * 16, 16, seed=4)
    cfg = OnEIConfig(n_small=3 * n, n_large=10 * n, log_offset=30.0, history=1.0)
    cals = [onei(rec, replace(cfg, threads=t)) for t in (1, 2, 3)]
    assert cals[0].diagnostics.n_updates >= 6
    assert cals[0].diagnostics.residual_lambda > 0
    assert cals[0].valid.mean() > 0.5
    for other in cals[1:]:
        assert other.diagnostics.residual_lambda == cals[0].diagnostics.residual_lambda
        for name in ("contrast", "bias", "stderr_contrast", "stderr_bias", "reason", "valid",
                     "special"):
            np.testing.assert_array_equal(getattr(other, name), getattr(cals[0], name))
    with pytest.raises(ConfigError, match="threads"):
        OnEIConfig(threads=-1)


def test_the_live_maps_are_the_estimate_classified():
    """calibration()'s maps, made in one threaded pass: the float32 estimate (inf standard
    errors where never valid), its calibrated standard errors and classify()'s classes of
    them, population from the lattice."""
    from evcal.special import classify

    sensor = SensorSize(60, 80)
    n = sensor.n_pixels
    rec = random_recording(sensor, 2 * n * 20, 20, seed=6)
    cal = OnlineCalibrator(sensor, OnEIConfig(n_small=3 * n, n_large=10 * n, log_offset=30.0,
                                              threads=2))
    for k, chunk in frame_intervals(rec.events, rec.frames.t_us):
        cal.feed_events(chunk)
        cal.feed_frame(int(rec.frames.t_us[k]), rec.frames.images[k])
    est = cal.estimate
    est.POPULATION_SAMPLE = 1000  # below the valid pixels: the lattice is used
    assert 1000 < est.seen.sum() < n
    got = cal.calibration()
    scale = cal.error_scale()
    se_c, se_b = (se * f for se, f in zip(est.smoothed_errors(), (scale.c, scale.b),
                                          strict=True))
    np.testing.assert_array_equal(got.stderr_contrast.ravel(),
                                  np.where(est.seen, se_c, np.inf).astype(np.float32))
    want = classify(est.c, est.b, se_c, se_b, est.seen.copy(), population_sample=1000)
    np.testing.assert_array_equal(got.special.ravel(), want)
    assert {0, 1, 3, 4, 5} <= set(np.unique(want))  # unobserved, normal, cold, warm, cool
    np.testing.assert_array_equal(got.valid.ravel(), est.seen)
    np.testing.assert_array_equal(got.contrast.ravel(), est.c.astype(np.float32))


def _contrast_in_child(rec, cfg):
    return onei(rec, cfg).contrast


def test_a_forked_child_re_solves_on_threads_of_its_own():
    """A process forked after a threaded re-solve (multiprocessing's fork) has none of the
    parent's pool threads: its calibrators start pools of their own instead of queueing
    work for threads that do not exist there."""
    import multiprocessing

    sensor = SensorSize(60, 80)
    n = sensor.n_pixels
    rec = random_recording(sensor, 2 * n * 12, 12, seed=7)
    cfg = OnEIConfig(n_small=3 * n, n_large=10 * n, log_offset=30.0, threads=2)
    want = onei(rec, cfg).contrast  # the parent's pool has its threads now
    with multiprocessing.get_context("fork").Pool(1) as pool:
        got = pool.apply_async(_contrast_in_child, (rec, cfg)).get(timeout=120)
    np.testing.assert_array_equal(got, want)


_SHARED: dict = {}


def _contrast_on_the_parents_executor(rec, cfg):
    with OnlineCalibrator(rec.sensor, cfg, executor=_SHARED["executor"]) as cal:
        for k, chunk in frame_intervals(rec.events, rec.frames.t_us):
            cal.feed_events(chunk)
            cal.feed_frame(int(rec.frames.t_us[k]), rec.frames.images[k])
        return cal.calibration().contrast


def test_an_executor_used_before_a_fork_works_in_the_child():
    """The executor object itself is safe across fork: in the child it forgets the parent's
    pool threads (which do not exist there) and starts its own."""
    import multiprocessing

    from evcal.online import OnEIExecutor

    sensor = SensorSize(100, 100)  # two blocks: a threaded re-solve
    n = sensor.n_pixels
    rec = random_recording(sensor, 2 * n * 12, 12, seed=7)
    cfg = OnEIConfig(n_small=3 * n, n_large=10 * n, log_offset=30.0)
    with OnEIExecutor(2) as executor:
        _SHARED["executor"] = executor
        try:
            want = _contrast_on_the_parents_executor(rec, cfg)  # its pool has threads now
            assert executor._solve is not None
            with multiprocessing.get_context("fork").Pool(1) as pool:
                got = pool.apply_async(_contrast_on_the_parents_executor,
                                       (rec, cfg)).get(timeout=120)
        finally:
            _SHARED.clear()
    np.testing.assert_array_equal(got, want)


def test_a_calibrator_closes_its_own_threads_and_never_a_callers():
    """A calibrator's own executor is shut down with it (``close`` or ``with``); one passed in
    stays the caller's, may serve several calibrators, and gives the same figures. A closed
    calibrator still answers, on the caller's thread."""
    from evcal.online import OnEIExecutor

    sensor = SensorSize(100, 100)  # two blocks: a threaded re-solve
    n = sensor.n_pixels
    rec = random_recording(sensor, 2 * n * 30, 30, seed=8)
    cfg = OnEIConfig(n_small=3 * n, n_large=30 * n, log_offset="auto", threads=2)

    def run(cal: OnlineCalibrator) -> np.ndarray:
        for k, chunk in frame_intervals(rec.events, rec.frames.t_us):
            cal.feed_events(chunk)
            cal.feed_frame(int(rec.frames.t_us[k]), rec.frames.images[k])
        return cal.calibration().contrast

    with OnlineCalibrator(sensor, cfg) as own:
        want = run(own)
        assert own.n_updates >= 1
        pools = [own.executor._solve, own.executor._offset]
        assert all(p is not None for p in pools)
    assert own.executor.closed
    assert not any(t.is_alive() for p in pools for t in p._threads)
    np.testing.assert_array_equal(own.calibration().contrast, want)  # on this thread

    with OnEIExecutor(2) as shared:
        cals = [OnlineCalibrator(sensor, cfg, executor=shared) for _ in range(2)]
        for cal in cals:
            np.testing.assert_array_equal(run(cal), want)
            cal.close()
            assert not shared.closed
        resumed = OnlineCalibrator.from_state(cals[0].state_dict(), executor=shared)
        assert resumed.executor is shared
    assert shared.closed


def test_the_status_says_why_no_offset_was_estimated():
    """A scene whose frames never change: the online offset criterion has nothing to
    explain; the calibrator asks again later and its status says so (the state an operator
    saw when a benchmark repeated one frame: no estimate, no equation, no update)."""
    sensor = SensorSize(40, 50)
    n = sensor.n_pixels
    rec = random_recording(sensor, 50 * 2 * n, 50, seed=3)
    still = np.full(sensor.shape, 120, np.uint8)
    cal = OnlineCalibrator(sensor, OnEIConfig(log_offset="auto", n_small=n, n_large=10**7))
    states = []
    for k, chunk in frame_intervals(rec.events, rec.frames.t_us):
        cal.feed_events(chunk)
        cal.feed_frame(int(rec.frames.t_us[k]), still)
        states.append(cal.status()["log_offset_state"])
    assert np.isnan(cal.log_offset)
    assert cal.n_updates == 0
    assert cal.n_equations == 0
    # started at frame 11, found nothing 8 frames later, tried again 25 frames after that
    assert states[10] == "criterion started at frame 11"
    assert states[18] == ("no estimate at frame 19: no window explains a change of the "
                          "frames (a still scene?); next try at frame 44")
    assert states[42] == states[18]
    assert states[43] == "criterion started at frame 44"


def _fed_in_chunks(cal: OnlineCalibrator, events: np.ndarray, frame_t_us: np.ndarray,
                   images: np.ndarray, chunk: int, delay_us: int,
                   on_chunk=None) -> None:
    """Events in chunks of ``chunk``, each frame fed once the stream has passed its time by
    ``delay_us`` (as a camera sends a frame after its exposure, events meanwhile)."""
    k = 0
    for lo in range(0, events.size, chunk):
        part = events[lo : lo + chunk]
        while k < frame_t_us.size and int(part["t_us"][0]) >= frame_t_us[k] + delay_us:
            cal.feed_frame(int(frame_t_us[k]), images[k])
            k += 1
        cal.feed_events(part)
        if on_chunk is not None:
            on_chunk(cal)
    for j in range(k, frame_t_us.size):
        cal.feed_frame(int(frame_t_us[j]), images[j])


def test_events_counted_ahead_of_their_frame_give_the_same_equations():
    """Events are counted into the open interval as they come, up to 3/4 of the shortest
    recent frame interval after the latest frame; a frame that comes earlier (here: every
    frame after a stretch at a third of the rate) has its interval counted again. Every
    array of the state, the estimate and the counts are those of a calibrator that counts
    each interval only when its frame comes; a state saved with events counted ahead
    resumes to the same result."""
    rec = random_recording(SENSOR, 60 * 3000, 60, seed=3)
    keep = np.r_[np.arange(0, 27, 3), np.arange(27, 60)]  # 120 ms intervals, then 40 ms
    t_fr, images = rec.frames.t_us[keep], rec.frames.images[keep]
    cfg = OnEIConfig(n_small=4000, n_large=20_000, log_offset=30.0)

    ref = OnlineCalibrator(SENSOR, cfg)
    ref.AHEAD_FRACTION = 0.0  # nothing counted before its frame
    _fed_in_chunks(ref, rec.events, t_fr, images, chunk=rec.events.size, delay_us=0)

    ahead: list[int] = []
    saved: list[dict] = []

    def watch(cal: OnlineCalibrator) -> None:
        ahead.append(cal.buffer.intake.n_ahead)
        if cal.buffer.intake.n_ahead > 1000 and cal.n_refolds and not saved:
            saved.append(cal.state_dict())

    got = OnlineCalibrator(SENSOR, cfg)
    _fed_in_chunks(got, rec.events, t_fr, images, chunk=371, delay_us=9000, on_chunk=watch)
    assert max(ahead) > 1000  # counted ahead of their frame
    assert got.n_refolds >= 1
    assert ref.n_refolds == 0
    assert got.n_updates == ref.n_updates >= 5

    resumed = OnlineCalibrator.from_state(saved[0])
    t_saved = json.loads(str(saved[0]["scalars"]))["last_event_t_us"]
    rest = rec.events[np.searchsorted(rec.events["t_us"], t_saved, side="right") :]
    later = t_fr > json.loads(str(saved[0]["scalars"]))["last_frame_t_us"]
    _fed_in_chunks(resumed, rest, t_fr[later], images[later], chunk=371, delay_us=9000)

    want = ref.state_dict()
    scalars = json.loads(str(want.pop("scalars")))
    for cal in (got, resumed):
        state = cal.state_dict()
        other = json.loads(str(state.pop("scalars")))
        assert {k: v for k, v in other.items() if k != "n_refolds"} == {
            k: v for k, v in scalars.items() if k != "n_refolds"}
        assert state.keys() == want.keys()
        for key, value in want.items():
            np.testing.assert_array_equal(state[key], value, err_msg=key)
        for name in ("contrast", "bias", "valid", "special"):
            np.testing.assert_array_equal(getattr(cal.calibration(), name),
                                          getattr(ref.calibration(), name))


def test_a_new_time_base_forgets_the_events_counted_ahead():
    """A camera restarts (its clock jumps back) while events are counted ahead of a frame:
    the new session starts from empty counts, as for a calibrator that counts at the frame."""
    rec = random_recording(SENSOR, 30 * 3000, 30, seed=5)
    t_fr, images = rec.frames.t_us, rec.frames.images
    cfg = OnEIConfig(n_small=4000, n_large=20_000, log_offset=30.0)
    half = int(np.searchsorted(rec.events["t_us"], (t_fr[14] + t_fr[15]) // 2))
    cals = []
    for fraction in (0.0, OnlineCalibrator.AHEAD_FRACTION):
        cal = OnlineCalibrator(SENSOR, cfg)
        cal.AHEAD_FRACTION = fraction
        _fed_in_chunks(cal, rec.events[:half], t_fr[:15], images[:15], chunk=200, delay_us=0)
        assert (cal.buffer.intake.n_ahead > 0) == (fraction > 0)
        cal.new_session()  # the same recording again, from its start
        assert cal.status()["pending_events"] == 0
        _fed_in_chunks(cal, rec.events, t_fr, images, chunk=200, delay_us=5000)
        cals.append(cal)
    ref, got = (c.state_dict() for c in cals)
    assert cals[0].n_updates == cals[1].n_updates >= 3
    for key, value in ref.items():
        if key != "scalars":
            np.testing.assert_array_equal(got[key], value, err_msg=key)


def test_a_growing_small_buffer_calibrates_a_camera_that_sends_few_events():
    """Sizes not given: the small buffer starts at 1/8 of the events seen (at least 1000)
    and grows to the paper's scaled size; a stream of fewer events than one scaled small
    buffer is calibrated, each update replacing the last while the buffer holds it all."""
    sensor = SensorSize(64, 48)  # the scaled small buffer: 14,222 events
    rec = random_recording(sensor, 40 * 600, 40, seed=4)  # 24 k events in all
    cal = OnlineCalibrator(sensor, OnEIConfig(log_offset=30.0, window_frames=5))
    assert cal.n_small == 14_222
    assert cal.buffer.n_small == 1000
    statuses = feed(cal, rec)
    assert cal.n_updates >= 3
    sizes = [s["n_small"] for s in statuses]
    assert sizes == sorted(sizes)
    assert sizes[-1] == cal.n_events // 8 < cal.n_small
    assert statuses[-1]["n_small_target"] == 14_222
    assert statuses[-1]["waiting_for"] is None
    assert cal.calibration().valid.any()  # random events: bookkeeping, not accuracy
    # a size given is kept: no update from fewer events than one small buffer, and the
    # status says what is missing, with the figures
    fixed = OnlineCalibrator(sensor, OnEIConfig(log_offset=30.0, window_frames=5,
                                                n_small=50_000))
    last = feed(fixed, rec)[-1]
    assert fixed.n_updates == 0
    assert last["n_small"] == 50_000
    assert last["waiting_for"].startswith("50,000 events needed per small buffer, ")
    assert f"({fixed.n_events:,} in all)" in last["waiting_for"]


def test_waiting_for_says_what_the_first_update_needs():
    sensor = SensorSize(20, 30)
    rec = random_recording(sensor, 20 * 600, 20, seed=5)
    cal = OnlineCalibrator(sensor, OnEIConfig(log_offset=30.0, window_frames=5))
    assert cal.waiting_for() == ("OnEI needs frames: 2 at least, 0 received (events between "
                                 "two frames make an equation)")
    feed(cal, rec, frames=range(3))
    assert cal.waiting_for() == ("each equation spans 5 frame intervals: 6 buffered frames "
                                 "needed, 3 held")
    auto = OnlineCalibrator(sensor, OnEIConfig(log_offset="auto"))
    feed(auto, rec, frames=range(3))
    assert auto.waiting_for().startswith("the log offset is being estimated from the frames "
                                         "and events (waiting for 11 buffered frames; 3 "
                                         "frames received)")


def test_a_still_scene_gets_its_first_offset_estimate_after_32_frames():
    """Few busy pixels for ever (a still camera): the first estimate does not wait for 5 %
    of them past FIRST_PATIENCE_FRAMES frames."""
    sensor = SensorSize(40, 50)
    rec = random_recording(sensor, 60 * 2 * sensor.n_pixels, 60, seed=2)
    ev = rec.events
    events = ev[(ev["y"] * sensor.width + ev["x"]) < 30]  # 30 busy pixels
    cal = OnlineCalibrator(sensor, OnEIConfig(log_offset="auto", n_small=100,
                                              n_large=10**7))
    cuts = np.searchsorted(events["t_us"], rec.frames.t_us)
    first_at = None
    for k in range(60):
        cal.feed_events(events[cuts[k - 1] if k else 0 : cuts[k]])
        cal.feed_frame(int(rec.frames.t_us[k]), rec.frames.images[k])
        if first_at is None and np.isfinite(cal.log_offset):
            first_at = k
    assert first_at is not None
    assert 32 <= first_at <= 32 + 8


def test_onei_fits_the_small_buffer_to_a_short_recording():
    sensor = SensorSize(64, 48)
    rec = random_recording(sensor, 40 * 600, 40, seed=4)
    cal = onei(rec, OnEIConfig(log_offset=30.0))
    d = cal.diagnostics
    assert d.n_small == rec.n_events // 8
    assert d.n_updates > 0
    assert any("fitted to the recording" in w for w in cal.warnings)
    # given sizes are kept, and a run without an update says why
    cal = onei(rec, OnEIConfig(log_offset=30.0, n_small=10**6))
    assert cal.diagnostics.n_small == 10**6
    assert any(w.startswith("OnEI made no update: 1,000,000 events needed per small "
                            "buffer") for w in cal.warnings)
