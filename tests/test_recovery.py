"""Recovery of known per-pixel c, b from the ideal simulator (the core's acceptance figures).

One 240x180, 10 s simulation with textured motion and 25 Hz frames, c ~ N(0.2, 0.03),
b ~ N(0.02, 0.01), log offset 30, seed 7 (the estimators were tuned on seed 0).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from evcal.brandli import brandli
from evcal.calibration import Calibration, Reason
from evcal.offe import offe
from evcal.offline import OffEIConfig, estimate_log_offset, offei
from evcal.online import OnEIConfig, OnlineCalibrator, onei
from evcal.reconstruct import evaluate
from evcal.recording import Frames, Recording
from evcal.sim.ideal import SimConfig, simulate_ideal
from evcal.solver import OverlapNoise, noise_overlap


@pytest.fixture(scope="module")
def sim():
    return simulate_ideal(SimConfig(height=180, width=240, duration_s=10.0, seed=7))


def _errors(cal: Calibration, truth: dict) -> tuple[float, float]:
    v = cal.valid
    ec = cal.contrast[v] - truth["contrast"][v]
    eb = cal.bias[v] - truth["bias"][v]
    return float(np.sqrt(np.mean(ec**2))), float(np.sqrt(np.mean(eb**2)))


@pytest.fixture(scope="module")
def offei_cal(sim):
    return offei(sim.recording, OffEIConfig(log_offset=30.0))


def test_offei_recovers_c_and_b(sim, offei_cal):
    rmse_c, rmse_b = _errors(offei_cal, sim.truth)
    assert offei_cal.valid.mean() > 0.9
    assert rmse_c <= 0.01, rmse_c
    assert rmse_b <= 0.005, rmse_b


def test_residual_correction_removes_the_contrast_bias(sim, offei_cal):
    plain = offei(sim.recording, OffEIConfig(log_offset=30.0, residual_correction="off"))
    v = plain.valid & offei_cal.valid
    bias_plain = float(np.mean(plain.contrast[v] - sim.truth["contrast"][v]))
    bias_corr = float(np.mean(offei_cal.contrast[v] - sim.truth["contrast"][v]))
    # a plain least squares over-estimates c by a few percent; the correction removes most of it
    assert bias_plain > 0.004
    assert abs(bias_corr) < 0.4 * bias_plain
    # measured 0.110 on seeds 0, 3, 7 and 11 (this scene and motion): within 20 %
    assert 0.09 < offei_cal.diagnostics.residual_lambda < 0.13


def test_invalid_pixels_keep_defaults_and_say_why(offei_cal):
    inv = ~offei_cal.valid
    assert np.all(offei_cal.contrast[inv] == np.float32(0.1))
    assert np.all(offei_cal.bias[inv] == 0)
    assert np.all(offei_cal.reason[inv] != Reason.VALID)
    assert np.all(np.isinf(offei_cal.stderr_contrast[inv]))
    assert np.isfinite(offei_cal.stderr_contrast[offei_cal.valid]).all()


@pytest.mark.parametrize("seed", [0, 3, 7])
def test_standard_errors_are_calibrated(seed, sim, offei_cal):
    """The stated standard errors of c and b match the actual errors over the valid pixels:
    z = (estimate - truth) / standard error has a spread near 1 (evcal.solver.
    overlap_standard_errors: overlapping windows' noise, telescoping along the regressors'
    mean, the spread of the pixels' residual-correction factors)."""
    if seed == 7:
        truth, cal = sim.truth, offei_cal
    else:
        other = simulate_ideal(SimConfig(height=180, width=240, duration_s=10.0, seed=seed))
        truth, cal = other.truth, offei(other.recording, OffEIConfig(log_offset=30.0))
    v = cal.valid
    zc = (cal.contrast[v] - truth["contrast"][v]) / cal.stderr_contrast[v]
    zb = (cal.bias[v] - truth["bias"][v]) / cal.stderr_bias[v]
    # measured on seeds 0, 3, 7: std(z) 0.99 for c and 0.98 for b (before, with the noise
    # counted as shared whole by the d overlapping windows: 1.06 and 0.55)
    assert 0.9 < float(np.std(zc)) < 1.25
    assert 0.9 < float(np.std(zb)) < 1.25
    # measured 1.84: far less than the d = 5 windows an interval lies in
    assert 1.5 < cal.diagnostics.noise_overlap < 2.2


@pytest.mark.parametrize(("kind", "expected"), [("white", 1.0), ("walk", 3.4)])
def test_noise_overlap_of_known_frame_noise(kind, expected):
    """kappa of evcal.solver.noise_overlap on frames whose log intensity is the model plus a
    known noise: noise independent from frame to frame shares nothing between overlapping
    windows (kappa 1); a random walk is shared as the windows share intervals,
    1 + 2 sum_l (1 - l/d)^2 = 3.4 for d = 5."""
    rng = np.random.default_rng(5)
    n_frames, n_pix, d, c, b = 300, 400, 5, 0.2, 0.02
    on = np.cumsum(rng.poisson(1.0, (n_frames, n_pix)), axis=0).astype(np.int32)
    off = np.cumsum(rng.poisson(1.0, (n_frames, n_pix)), axis=0).astype(np.int32)
    step = rng.normal(0.0, 0.05, (n_frames, n_pix))
    noise = step if kind == "white" else np.cumsum(step, axis=0)
    lg = c * (on - off) + b * (on + off) + noise
    frames = OverlapNoise(window_frames=d, moments=np.zeros((2, n_pix)),
                          sample=np.arange(n_pix), on=on, off=off,
                          last_p=np.zeros((n_frames, n_pix), np.int8), lg=lg,
                          ok=np.ones((n_frames, n_pix), bool))
    kappa = noise_overlap(frames, np.full(n_pix, c), np.full(n_pix, b), np.ones(n_pix, bool),
                          0.0)
    assert kappa == pytest.approx(expected, abs=0.15)


def test_log_offset_auto_recovers_the_simulated_offset(sim):
    off, info = estimate_log_offset(sim.recording, OffEIConfig())
    assert abs(off - 30.0) <= 5.0, (off, info)
    assert not info["at_grid_edge"]


def test_reconstruction_offei_close_to_truth_and_above_di(sim, offei_cal):
    truth = Calibration.uniform(sim.recording.sensor.shape, method="truth", log_offset=30.0)
    truth = truth.replace(contrast=sim.truth["contrast"], bias=sim.truth["bias"])
    kw = dict(events_per_image=500_000)
    with_truth = evaluate(sim.recording, truth, **kw).summary()
    with_offei = evaluate(sim.recording, offei_cal, **kw).summary()
    assert with_offei["n_images"] >= 5
    assert with_offei["calibrated"]["psnr"] >= with_truth["calibrated"]["psnr"] - 0.5
    assert with_offei["calibrated"]["psnr"] >= with_offei["di"]["psnr"] + 3.0
    assert with_offei["calibrated"]["psnr_paper"] == pytest.approx(
        2 * with_offei["calibrated"]["psnr"], rel=1e-9)


def test_onei_converges_within_1p5x_of_offei(sim, offei_cal):
    cal = onei(sim.recording, OnEIConfig(log_offset=30.0), history_every=1)
    rmse_c, rmse_b = _errors(cal, sim.truth)
    off_c, off_b = _errors(offei_cal, sim.truth)
    hist = cal.diagnostics.history
    first = next(h for h in hist if h[3].mean() > 0.5)
    e_first = float(np.sqrt(np.mean((first[1] - sim.truth["contrast"])[first[3]] ** 2)))
    assert rmse_c < e_first  # it improves as data arrive
    assert cal.valid.mean() > 0.9
    # the paper's buffer sizes see ~1.7 M of the 6.3 M events at a time; measured on seed 7:
    # c 0.0119 vs 0.0093, b 0.0038 vs 0.0031 (seed 0: 0.0120 vs 0.0094, 0.0038 vs 0.0031)
    assert rmse_c <= 1.5 * off_c, (rmse_c, off_c)
    assert rmse_b <= 1.5 * off_b, (rmse_b, off_b)
    # the large buffer holds at most n_large events
    d = cal.diagnostics
    assert d.buffer_events <= d.n_large
    assert d.buffer_equations > d.n_large / d.n_small


def test_onei_sliding_equations_equal_a_rebuild(sim):
    """Subtracting a dropped small buffer is exact: rebuilding after every drop changes nothing
    beyond rounding."""
    rec = sim.recording
    short = Recording(rec.sensor, rec.events[rec.events["t_us"] < 4_000_000],
                      rec.frames.select(rec.frames.t_us < 4_000_000))
    cfg = OnEIConfig(log_offset=30.0, n_small=50_000, n_large=300_000)
    a = onei(short, cfg)
    b = onei(short, replace(cfg, rebuild_every=1))
    assert a.diagnostics.n_updates == b.diagnostics.n_updates > 10
    np.testing.assert_allclose(a.contrast, b.contrast, rtol=0, atol=1e-9)
    np.testing.assert_allclose(a.bias, b.bias, rtol=0, atol=1e-9)
    np.testing.assert_array_equal(a.valid, b.valid)


def _feed(cal: OnlineCalibrator, rec: Recording, *, lose=None, gap_frames=()) -> None:
    t_ev = rec.events["t_us"]
    cuts = np.searchsorted(t_ev, rec.frames.t_us)
    prev = 0
    for k in range(len(rec.frames)):
        ev = rec.events[prev : cuts[k]]
        prev = int(cuts[k])
        if lose is not None and k in lose:
            ev = ev[: ev.size // 4]  # three quarters of this interval's events never arrive
            cal.mark_gap()
        if k in gap_frames:
            cal.mark_gap()
        cal.feed_events(ev)
        cal.feed_frame(int(rec.frames.t_us[k]), rec.frames.images[k])


@pytest.fixture(scope="module")
def small_sims():
    base = SimConfig(height=72, width=96, duration_s=5.0)
    return (simulate_ideal(replace(base, seed=11)),
            simulate_ideal(replace(base, seed=12, duration_s=8.0, contrast_mean=0.27,
                                   bias_mean=-0.01)))


def test_onei_mark_gap_keeps_lost_events_out(small_sims):
    sim = small_sims[0]
    rec = sim.recording
    cfg = OnEIConfig(log_offset=30.0)
    lose = set(range(10, len(rec.frames), 20))  # every 20th interval loses events
    errs = {}
    for name, kw in (("complete", {}), ("marked", {"lose": lose}), ("unmarked", {"lose": lose})):
        cal = OnlineCalibrator(rec.sensor, cfg)
        if name == "unmarked":
            cal.mark_gap = lambda: None  # a caller that does not report the loss
        _feed(cal, rec, **kw)
        errs[name] = _errors(cal.calibration(), sim.truth)
    # measured (c, b): complete (0.0105, 0.0033), marked (0.0122, 0.0053): fewer equations;
    # unmarked (0.0158, 0.0078): equations with missing events
    assert errs["marked"][0] < 1.3 * errs["complete"][0], errs
    assert errs["unmarked"][0] > 1.15 * errs["marked"][0], errs
    assert errs["unmarked"][1] > 1.3 * errs["marked"][1], errs


def test_onei_tracks_a_change_of_thresholds(small_sims):
    """Two recordings back to back, the second with other c, b maps (a marked gap between):
    the online estimate follows the second; OffEI on everything would average them."""
    one, two = small_sims
    r1, r2 = one.recording, two.recording
    shift = int(r1.frames.t_us[-1]) + 40_000 - int(r2.frames.t_us[0])
    ev2 = r2.events.copy()
    ev2["t_us"] += shift
    cal = OnlineCalibrator(r1.sensor, OnEIConfig(log_offset=30.0))
    _feed(cal, r1)
    after_first = _errors(cal.calibration(), one.truth)[0]
    r2s = Recording(r2.sensor, ev2, Frames(r2.frames.t_us + shift, r2.frames.images,
                                           r2.frames.exposure_us))
    _feed(cal, r2s, gap_frames={0})
    c_to_2, b_to_2 = _errors(cal.calibration(), two.truth)
    c_to_1, _ = _errors(cal.calibration(), one.truth)
    c_est = cal.calibration()
    moved = float(np.mean(c_est.contrast[c_est.valid]))
    # measured: 0.0105 after the first; then 0.0156 (c) and 0.0058 (b) against the second
    # truth, 0.073 against the first; mean c 0.263 for a true mean near 0.27
    assert after_first < 0.02
    assert c_to_2 < 0.02, (c_to_2, b_to_2)
    assert b_to_2 < 0.01, (c_to_2, b_to_2)
    assert c_to_1 > 3 * c_to_2
    assert abs(moved - float(np.mean(two.truth["contrast"][c_est.valid]))) < 0.015


def test_onei_state_round_trip_resumes_identically(sim):
    rec = sim.recording
    half = len(rec.frames) // 2
    cfg = OnEIConfig(log_offset=30.0)
    a = OnlineCalibrator(rec.sensor, cfg)
    t_ev = rec.events["t_us"]
    cuts = np.searchsorted(t_ev, rec.frames.t_us)
    prev = 0
    for k in range(len(rec.frames)):
        a.feed_events(rec.events[prev : cuts[k]])
        prev = int(cuts[k])
        a.feed_frame(int(rec.frames.t_us[k]), rec.frames.images[k])
        if k == half:
            b = OnlineCalibrator.from_state(a.state_dict())
            resume_at = k
    prev = int(cuts[resume_at])
    for k in range(resume_at + 1, len(rec.frames)):
        b.feed_events(rec.events[prev : cuts[k]])
        prev = int(cuts[k])
        b.feed_frame(int(rec.frames.t_us[k]), rec.frames.images[k])
    ca, cb = a.calibration(), b.calibration()
    np.testing.assert_array_equal(ca.contrast, cb.contrast)
    np.testing.assert_array_equal(ca.valid, cb.valid)
    assert a.n_updates == b.n_updates


def test_offe_and_brandli_beat_di(sim, offei_cal):
    kw = dict(events_per_image=500_000)
    res = {}
    for name, cal in (("offe", offe(sim.recording)), ("brandli", brandli(sim.recording))):
        cal = cal.replace(log_offset=30.0)
        res[name] = evaluate(sim.recording, cal, **kw).summary()
    res["offei"] = evaluate(sim.recording, offei_cal, **kw).summary()
    di = res["offei"]["di"]["psnr"]
    assert res["offe"]["calibrated"]["psnr"] > di
    assert di < res["brandli"]["calibrated"]["psnr"] < res["offei"]["calibrated"]["psnr"]


def _offe_scores(cal: Calibration, truth: dict) -> dict[str, float]:
    v = cal.valid
    c, b = truth["contrast"][v], truth["bias"][v]
    err_c, err_b = cal.contrast[v] - c, cal.bias[v] - b
    return {"c_rmse": float(np.sqrt(np.mean(err_c ** 2))),
            "b_rmse": float(np.sqrt(np.mean(err_b ** 2))),
            "c_z": float(np.std(err_c / cal.stderr_contrast[v])),
            "b_z": float(np.std(err_b / cal.stderr_bias[v]))}


def test_offe_against_its_neighbours_beats_the_population_reference(sim):
    """The paper's OffE compares each pixel's light excursion in events with the whole
    population's, so the pixels' own light (sky against texture) lands in ``c``; against its
    neighbours' (which see nearly the same light) it does not. Both anchored at the true
    median contrast: the neighbours' reference has 0.09x the paper's ``c`` RMSE and 0.20x
    its ``b`` RMSE here (15 other recordings, simulated and v2e: 0.14-0.65x and 0.18-0.87x);
    asserted at 0.5x."""
    from evcal.offe import OffEConfig

    c0 = float(np.median(sim.truth["contrast"]))
    local = _offe_scores(offe(sim.recording, OffEConfig(c0=c0)), sim.truth)
    paper = _offe_scores(offe(sim.recording, OffEConfig(c0=c0, neighbourhood_px=0)),
                         sim.truth)
    assert local["c_rmse"] < 0.5 * paper["c_rmse"]
    assert local["b_rmse"] < 0.5 * paper["b_rmse"]
    # and near what the frames give (here 0.012 / 0.003; OffEI about 0.01 / 0.003)
    assert local["c_rmse"] < 0.02
    assert local["b_rmse"] < 0.006


def test_offe_states_errors_from_its_two_halves():
    """OffE's stated errors come from the recording's halves in time, fitted apart: the
    z-scores (estimate - truth) / stderr spread about 1 (here 0.90 for ``c``, 1.21 for
    ``b``; 0.81-1.38 and 0.53-1.56 on 14 other recordings, simulated and v2e: they are
    read on the halves, not on the truth). A motion that repeats within the recording puts
    the same light, so the same error, in both halves, which the halves cannot see: 1.28
    and 2.11 on this scene's 10 s (the ``sim`` fixture), whose halves' errors correlate
    0.35. The live stream's OffE has no halves and states none."""
    from evcal.offe import OffEConfig, StreamingOffE

    sim = simulate_ideal(SimConfig(height=180, width=240, duration_s=4.0, seed=7))
    cal = offe(sim.recording, OffEConfig(c0=float(np.median(sim.truth["contrast"]))))
    assert cal.valid.mean() > 0.5
    assert np.isfinite(cal.stderr_contrast[cal.valid]).all()
    assert np.isfinite(cal.stderr_bias[cal.valid]).all()
    halves = cal.diagnostics.extra["errors"]
    assert halves["pixels"] > 1000
    assert halves["read_now"]
    assert "reason" not in halves
    sc = _offe_scores(cal, sim.truth)
    assert 0.6 < sc["c_z"] < 1.4
    assert 0.6 < sc["b_z"] < 1.4
    live = StreamingOffE(sim.recording.sensor)
    live.feed_events(sim.recording.events)
    assert np.isinf(live.calibration().stderr_contrast).all()  # its first maps: no parts
