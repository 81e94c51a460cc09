"""The non-ideal simulator: it extends the ideal one, each effect does what it says, and
everything is deterministic for a seed."""

from __future__ import annotations

import numpy as np
import pytest

from evcal.errors import ConfigError
from evcal.recording import Recording
from evcal.sim import bench_simulator
from evcal.sim.effects import (
    EFFECT_NAMES,
    LABEL_HOT_PIXEL,
    LABEL_LEAK,
    LABEL_SHOT_NOISE,
    ApsConfig,
    Bandwidth,
    EffectError,
    HotPixels,
    Leak,
    LogOffset,
    Refractory,
    ShotNoise,
    StartReset,
    ThresholdLight,
    ThresholdNoise,
    TimestampJitter,
    make_effect,
)
from evcal.sim.ideal import SimConfig, draw_maps, simulate_ideal
from evcal.sim.nonideal import simulate
from evcal.sim.scene import Trajectory
from evcal.sim.sources import FrameInterpolator, Illumination, MovingScene, SpeedProfile

CFG = SimConfig(height=24, width=32, duration_s=0.6, frame_rate_hz=50.0, internal_rate_hz=1000.0,
                log_offset=1.0, seed=5, trajectory=Trajectory(pan_px=30.0, seed=5))


def _same_pixel_iei(ev: np.ndarray, width: int) -> np.ndarray:
    pix = ev["y"].astype(np.int64) * width + ev["x"]
    order = np.argsort(pix, kind="stable")
    ps, ts = pix[order], ev["t_us"][order]
    same = ps[1:] == ps[:-1]
    return (ts[1:] - ts[:-1])[same]


def test_no_effect_reproduces_the_ideal_simulator() -> None:
    a = simulate_ideal(CFG).recording
    b = simulate(CFG).recording
    assert a.n_events > 1000
    np.testing.assert_array_equal(a.events, b.events)
    np.testing.assert_array_equal(a.frames.images, b.frames.images)
    np.testing.assert_array_equal(a.frames.t_us, b.frames.t_us)


def test_the_ideal_simulator_takes_given_maps() -> None:
    """Maps given in place of the drawn ones are the truth and drive the events: a pixel
    given half the threshold fires about twice as often; the same maps as drawn give the
    same recording."""
    drawn = simulate_ideal(CFG)
    c, b = draw_maps(CFG, np.random.default_rng(CFG.seed))  # what it draws
    same = simulate_ideal(CFG, maps=(c, b))
    np.testing.assert_array_equal(same.recording.events, drawn.recording.events)
    hot = np.zeros(c.shape, bool)
    hot[::4, ::4] = True
    halved = simulate_ideal(CFG, maps=(np.where(hot, 0.5 * c, c), np.where(hot, 0.5 * b, b)))
    np.testing.assert_allclose(halved.truth["contrast"][hot], 0.5 * c[hot], rtol=1e-6)
    width = CFG.width

    def count(ev: np.ndarray) -> np.ndarray:
        return np.bincount(ev["y"].astype(np.int64) * width + ev["x"],
                           minlength=c.size).reshape(c.shape)

    n0, n1 = count(drawn.recording.events), count(halved.recording.events)
    assert 1.6 < n1[hot].sum() / n0[hot].sum() < 2.4
    assert abs(n1[~hot].sum() / n0[~hot].sum() - 1.0) < 0.02
    with pytest.raises(ConfigError, match="shapes"):
        simulate_ideal(CFG, maps=(c[:-1], b))


@pytest.mark.parametrize("name", EFFECT_NAMES)
def test_deterministic_for_a_seed(name: str) -> None:
    eff = make_effect(name)
    r1 = simulate(CFG, [eff])
    r2 = simulate(CFG, [eff])
    np.testing.assert_array_equal(r1.recording.events, r2.recording.events)
    np.testing.assert_array_equal(r1.truth["labels"], r2.truth["labels"])
    assert r1.truth["labels"].shape == (r1.recording.n_events,)
    assert r1.truth["effects"] == {name: eff.parameters()}
    r3 = simulate(SimConfig(**{**CFG.to_dict(), "seed": 6, "trajectory": CFG.trajectory}), [eff])
    assert r3.recording.n_events != r1.recording.n_events or not np.array_equal(
        r3.recording.events, r1.recording.events)


SHORTCUT_CASES = {
    "ideal": [],
    "all": [Refractory(period_us=300.0), Leak(rate_hz=3.0), ShotNoise(rate_hz=20.0),
            ThresholdNoise(sigma=0.2)],
    "delay, light-dependent leak": [Refractory(period_us=300.0, mode="delay"),
                                    Leak(rate_hz=3.0, light_exponent=0.5)],
    "bandwidth": [Bandwidth(cutoff_hz=30.0), Leak(rate_hz=3.0)],
    "threshold_light": [ThresholdLight(exponent=0.4), Refractory(period_us=300.0),
                        ShotNoise(rate_hz=20.0), ThresholdNoise(sigma=0.2)],
    "threshold_light, leak": [ThresholdLight(exponent=0.7), Leak(rate_hz=3.0)],
}


@pytest.mark.parametrize("case", SHORTCUT_CASES)
def test_the_no_crossing_shortcut_changes_no_event(case: str, monkeypatch) -> None:
    """The kernel skips the crossing search for pixels that cannot fire; every pixel running
    the search must give the same events, labels and frames."""
    from evcal.sim import kernel, nonideal  # noqa: PLC0415

    cfg = SimConfig(**{**CFG.to_dict(), "duration_s": 0.3, "trajectory": CFG.trajectory})
    fast = simulate(cfg, SHORTCUT_CASES[case])
    monkeypatch.setattr(nonideal, "run_steps",
                        lambda *args, **kw: kernel.run_steps(*args, False, **kw))
    exact = simulate(cfg, SHORTCUT_CASES[case])
    assert fast.recording.n_events > 1000
    np.testing.assert_array_equal(fast.recording.events, exact.recording.events)
    np.testing.assert_array_equal(fast.truth["labels"], exact.truth["labels"])


def test_step_sort_is_a_stable_sort_by_time() -> None:
    """The kernel's per-step sort (counting sort on microseconds, insertion inside them, merge
    where a microsecond is crowded, coarser buckets for long steps) is a stable argsort."""
    from evcal.sim.kernel import _sort_step  # noqa: PLC0415

    rng = np.random.default_rng(0)
    for dt, m, n_keys in ((1000.0, 5000, 1003), (1000.0, 3000, 1003), (1e6, 4000, 1003),
                          (1000.0, 2000, 50)):
        t_f = 500.0 + np.round(rng.uniform(0, dt, m), 1)
        if m == 3000:  # a crowded microsecond
            t_f[:1000] = 900.0 + np.round(rng.uniform(0, 0.9, 1000), 2)
        t_i = np.arange(m, dtype=np.int64)
        others = [rng.integers(0, 100, m).astype(d) for d in (np.int32, np.int8, np.uint8)]
        expect = np.argsort(t_f, kind="stable")
        key = np.empty(n_keys, np.int64)
        scratch = [np.empty(m, d) for d in (np.int64, np.int32, np.int64, np.int32, np.int8,
                                            np.uint8, np.float64)]
        sorted_t = t_f[expect]
        _sort_step(t_f, t_i, *others, 0, m, 500.0, dt, key, *scratch)
        np.testing.assert_array_equal(t_i, expect)
        np.testing.assert_array_equal(t_f, sorted_t)  # the times too: runs merge by them


@pytest.mark.parametrize("case", SHORTCUT_CASES)
def test_pixel_ranges_in_threads_change_no_event(case: str) -> None:
    """A run split into ranges of pixels simulated side by side (their events merged by time)
    gives the events, labels and frames of one run over all pixels, whatever the split."""
    cfg = SimConfig(**{**CFG.to_dict(), "duration_s": 0.3, "trajectory": CFG.trajectory})
    one = simulate(cfg, SHORTCUT_CASES[case])
    assert one.recording.n_events > 1000
    for threads in (2, 3, 7):
        split = simulate(cfg, SHORTCUT_CASES[case], threads=threads)
        np.testing.assert_array_equal(split.recording.events, one.recording.events)
        np.testing.assert_array_equal(split.truth["labels"], one.truth["labels"])
        np.testing.assert_array_equal(split.recording.frames.images,
                                      one.recording.frames.images)


def test_merged_runs_put_the_lower_range_first_among_equal_times() -> None:
    from evcal.sim.kernel import merge_runs  # noqa: PLC0415

    a = [np.array([1.0, 2.0, 2.0, 5.0, 9.0]), np.arange(5, dtype=np.int64),
         np.zeros(5, np.int32), np.ones(5, np.int8), np.zeros(5, np.uint8)]
    b = [np.array([0.5, 2.0, 6.0, 99.0]), np.arange(10, 14, dtype=np.int64),
         np.ones(4, np.int32), -np.ones(4, np.int8), np.ones(4, np.uint8)]
    t_f, t_i, pix, pol, lab = merge_runs(*a, 5, *b, 3)  # b's last is past its count
    np.testing.assert_array_equal(t_f, [0.5, 1.0, 2.0, 2.0, 2.0, 5.0, 6.0, 9.0])
    np.testing.assert_array_equal(t_i, [10, 0, 1, 2, 11, 3, 12, 4])
    np.testing.assert_array_equal(pix, [1, 0, 0, 0, 1, 0, 1, 0])


def test_refractory_drop_removes_short_intervals_and_delay_keeps_the_count() -> None:
    ideal = simulate(CFG).recording
    drop = simulate(CFG, [Refractory(period_us=2000.0, mode="drop")]).recording
    delay = simulate(CFG, [Refractory(period_us=2000.0, mode="delay")]).recording
    assert (_same_pixel_iei(ideal.events, CFG.width) < 1999).any()
    # rounding of event times to integer us allows one microsecond
    assert _same_pixel_iei(drop.events, CFG.width).min() >= 1999
    assert _same_pixel_iei(delay.events, CFG.width).min() >= 1999
    assert drop.n_events < 0.95 * ideal.n_events
    assert delay.n_events == ideal.n_events  # delayed, not lost


def test_leak_adds_on_events_at_the_rate_in_a_still_scene() -> None:
    still = SimConfig(**{**CFG.to_dict(), "duration_s": 2.0,
                         "trajectory": Trajectory(pan_px=0, rotation_rad=0, zoom=0, seed=1)})
    res = simulate(still, [Leak(rate_hz=2.0, spread_log=0.3)])
    ev = res.recording.events
    assert (ev["p"] > 0).all()
    rate = ev.size / (still.height * still.width * still.duration_s)
    # the reference starts half a cell (on average) below the ON level: half an event less
    assert rate == pytest.approx(2.0 - 0.5 / still.duration_s, rel=0.1)
    assert (res.truth["labels"] == LABEL_LEAK).mean() > 0.9


def test_a_reset_at_the_start_makes_every_pixel_wait_a_whole_threshold() -> None:
    """A still scene under leak (2 Hz: the reference falls by a threshold each 0.5 s): a
    running sensor's references start anywhere within a threshold of the light (with the
    OFF one below), so the first events come at any time up to about two periods; a sensor
    reset at the start sets each at its light, and every pixel's first event comes after
    exactly one period."""
    still = SimConfig(**{**CFG.to_dict(), "duration_s": 2.0,
                         "trajectory": Trajectory(pan_px=0, rotation_rad=0, zoom=0, seed=1)})
    leak = Leak(rate_hz=2.0, spread_log=0.0)

    def first_s(events: np.ndarray) -> np.ndarray:
        pix = events["y"].astype(np.int64) * still.width + events["x"]
        first = np.full(still.height * still.width, np.inf)
        np.minimum.at(first, pix, events["t_us"] * 1e-6)
        return first

    running = first_s(simulate(still, [leak]).recording.events)
    reset = first_s(simulate(still, [leak, StartReset()]).recording.events)
    assert np.isfinite(reset).all()
    np.testing.assert_allclose(reset, 0.5, atol=0.01)
    assert running.min() < 0.1
    assert np.std(running) > 0.15


def test_shot_noise_rate_rises_in_the_dark_and_is_labelled() -> None:
    still = SimConfig(**{**CFG.to_dict(), "duration_s": 2.0,
                         "trajectory": Trajectory(pan_px=0, rotation_rad=0, zoom=0, seed=1)})
    res = simulate(still, [ShotNoise(rate_hz=5.0, ref_dn=16.0)])
    ev = res.recording.events
    assert (res.truth["labels"] == LABEL_SHOT_NOISE).all()
    assert 0.4 < (ev["p"] > 0).mean() < 0.6
    img = res.recording.frames.images[0].astype(float)
    n = np.bincount(ev["y"].astype(int) * still.width + ev["x"],
                    minlength=img.size).reshape(img.shape)
    dark, bright = img < np.percentile(img, 25), img > np.percentile(img, 75)
    assert n[dark].mean() > 2 * n[bright].mean()
    expected = ShotNoise(rate_hz=5.0).rate_at(img).sum() * still.duration_s
    assert ev.size == pytest.approx(expected, rel=0.1)


def test_bandwidth_loses_events_mostly_in_the_dark() -> None:
    fast = SimConfig(**{**CFG.to_dict(), "trajectory": Trajectory(pan_px=30, speed=3, seed=5)})
    ideal = simulate(fast).recording
    slow = simulate(fast, [Bandwidth(cutoff_hz=20.0)]).recording
    assert slow.n_events < 0.9 * ideal.n_events


def test_threshold_noise_keeps_the_mean_count_and_hot_pixels_fire() -> None:
    ideal = simulate(CFG).recording
    noisy = simulate(CFG, [ThresholdNoise(sigma=0.2)]).recording
    assert noisy.n_events == pytest.approx(ideal.n_events, rel=0.1)
    assert not np.array_equal(noisy.events, ideal.events)
    hot = simulate(CFG, [HotPixels(fraction=0.01, rate_hz=200.0)])
    mask = hot.truth["hot_pixels"]
    assert mask.sum() == round(0.01 * CFG.height * CFG.width)
    labels = hot.truth["labels"]
    ev = hot.recording.events
    assert (mask[ev["y"][labels == LABEL_HOT_PIXEL], ev["x"][labels == LABEL_HOT_PIXEL]]).all()
    assert (labels == LABEL_HOT_PIXEL).sum() == pytest.approx(
        mask.sum() * 200.0 * CFG.duration_s, rel=0.25)


def test_log_offset_and_jitter() -> None:
    ideal = simulate(CFG)
    dark = simulate(CFG, [LogOffset(dark_dn=60.0)])
    assert dark.truth["log_offset"] == 60.0
    assert dark.recording.n_events < 0.8 * ideal.recording.n_events
    jit = simulate(CFG, [TimestampJitter(sigma_us=200.0, quantum_us=50)]).recording
    assert (jit.events["t_us"] % 50 == 0).all()
    assert np.all(np.diff(jit.events["t_us"]) >= 0)
    d = np.sort(jit.events["t_us"]) - np.sort(ideal.recording.events["t_us"])
    assert 100 < np.std(d) < 400 or jit.n_events == ideal.recording.n_events


def test_aps_frames_blur_noise_and_sources(tmp_path) -> None:
    res = simulate(CFG, aps=ApsConfig(exposure_us=8000, read_noise_dn=2.0))
    fr = res.recording.frames
    assert fr.images.dtype == np.uint8
    assert (fr.exposure_us == 8000).all()
    sharp = simulate(CFG).recording.frames
    # blur and noise change the frames but not the events (the DVS sees the scene)
    assert not np.array_equal(sharp.images, fr.images)
    np.testing.assert_array_equal(res.recording.events, simulate(CFG).recording.events)
    # a frame sequence drives the simulator like a scene
    src = FrameInterpolator(sharp, (CFG.height, CFG.width))
    again = simulate(CFG, source=src, frames=sharp)
    assert isinstance(again.recording, Recording)
    assert again.recording.n_events > 0
    # speed profile (still, then moving) and illumination ramp
    scene = MovingScene(CFG.scene, (CFG.height, CFG.width), CFG.trajectory,
                        speed=SpeedProfile(segments=((0.3, 0.0), (0.3, 2.0))),
                        illumination=Illumination(gain_start=1.0, gain_end=0.5, ramp_s=0.6))
    r = simulate(CFG, source=scene).recording
    t = r.events["t_us"]
    assert (t < 250_000).sum() < 0.05 * (t >= 300_000).sum()


def test_effect_validation() -> None:
    with pytest.raises(EffectError, match="mode"):
        Refractory(mode="skip")
    with pytest.raises(EffectError, match="unknown effect"):
        make_effect("strobe")
    with pytest.raises(EffectError, match="unknown parameter"):
        make_effect("leak", rate=1.0)
    with pytest.raises(EffectError, match="twice"):
        simulate(CFG, [Leak(), Leak()])


def test_bench_simulator_reports_events_per_second() -> None:
    out = bench_simulator(height=26, width=34, duration_s=0.1)
    assert out["events_per_s"] > 0
    assert out["n_events"] > 0
    assert out["sensor"] == "34x26"


def test_flicker_is_a_line_in_the_net_polarity_and_in_the_frames() -> None:
    """A flicker of the light: the events' ON minus OFF count carries a line at its
    frequency (none without it), and the frames (exposure 4 ms, stamped at its middle)
    each see the light's mean over their exposure, the flicker's factor at their phase."""
    from evcal.gap.flicker import find_line, line_at, net_series  # noqa: PLC0415
    from evcal.gap.model import light_gain  # noqa: PLC0415
    from evcal.gap.stats import observe  # noqa: PLC0415
    from evcal.sim.effects import Flicker  # noqa: PLC0415

    cfg = SimConfig(**{**CFG.to_dict(), "duration_s": 1.5, "frame_rate_hz": 23.0,
                       "trajectory": CFG.trajectory})
    aps = ApsConfig(exposure_us=4000, quantise=False)
    flick = Flicker(freq_hz=100.0, depth=0.08, phase_rad=0.7)
    lines = []
    for effects in ([], [flick]):
        rec = simulate(cfg, effects, aps=aps).recording
        t0, x = net_series(observe(rec))
        f, ratio = find_line(t0, x)
        lines.append((f, ratio, abs(line_at(t0, x, 100.0))))
    assert lines[0][1] < 30.0
    assert lines[1][0] == pytest.approx(100.0, abs=0.5)
    assert lines[1][1] > 100.0
    assert lines[1][2] > 20 * lines[0][2]
    # the frames of a still scene: their common light is the flicker's exposure mean
    still = SimConfig(**{**cfg.to_dict(), "trajectory": Trajectory(pan_px=0.0, seed=5)})
    fr = simulate(still, [flick], aps=aps).recording.frames
    # (from the second frame: the first one's exposure starts before the recording; five
    # samples of it against the mean of a sine over it, within 1 %)
    want = flick.exposure_mean(fr.t_us, fr.exposure_us)[1:]
    got = light_gain(fr.images)[1:]
    np.testing.assert_allclose(got / got[0], want / want[0], rtol=1e-2)
    with pytest.raises(EffectError, match="depth"):
        Flicker(depth=1.2)


def test_a_flicker_frequency_error_is_read_off_the_phase_drift_against_a_simulation() -> None:
    """The measured net polarity's line drifts in phase against a simulated one at a
    slightly wrong frequency; the drift, segment by segment, gives the error (the line's
    swelling with the motion, shared by both, does not move it), also for a simulation
    with its own noise and another origin of its bins."""
    from evcal.gap.flicker import BIN_US, frequency_error  # noqa: PLC0415

    rng = np.random.default_rng(3)
    n = 6000  # 3 s of bins
    t0 = 1_250_000
    t = (t0 + (np.arange(n) + 0.5) * BIN_US) * 1e-6
    swell = 20 * (1.2 + np.sin(2 * np.pi * 0.7 * t)) ** 2  # the motion's share near a threshold
    meas = swell * np.cos(2 * np.pi * 100.04 * t + 0.4) + rng.normal(0, 15, n)
    for f_sim, t0_sim in ((100.0, t0), (100.1, t0 + BIN_US), (100.04, t0)):
        ts = (t0_sim + (np.arange(n) + 0.5) * BIN_US) * 1e-6
        sim = 0.6 * (20 * (1.2 + np.sin(2 * np.pi * 0.7 * ts)) ** 2) * np.cos(
            2 * np.pi * f_sim * ts - 1.1) + rng.normal(0, 15, n)
        step = frequency_error(t0, meas, t0_sim, sim, f_sim)
        assert step == pytest.approx(100.04 - f_sim, abs=0.005)
    # nothing to compare: NaN, not a step
    assert np.isnan(frequency_error(t0, np.zeros(n), t0, np.zeros(n), 100.0))
    assert np.isnan(frequency_error(t0, meas[:20], t0, meas[:20], 100.0))
