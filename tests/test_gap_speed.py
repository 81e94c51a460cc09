"""The gap workflow's cost-saving parts: the shared render of the interpolated frames, the
screening spread, the working window, the read-noise runs of still pixels, and the words for
what remains unexplained."""

from __future__ import annotations

import numpy as np
import pytest

from evcal.gap.compare import discrepancy
from evcal.gap.explain import sentence, summary, unexplained
from evcal.gap.model import SimSettings, fit_base, latent_frames, simulate_model
from evcal.gap.render import RenderCache
from evcal.gap.runner import Evaluator
from evcal.gap.stats import StatValue, observe, summarise
from evcal.gap.workflow import GapConfig, working_window
from evcal.recording import Frames, Recording
from evcal.sim.effects import Refractory
from evcal.sim.ideal import SimConfig
from evcal.sim.nonideal import simulate
from evcal.sim.scene import Trajectory
from evcal.sim.sources import FrameInterpolator, MovingScene, SpeedProfile

H, W = 32, 40


def small_recording(seed: int, effects: list, *, duration_s: float = 1.0,
                    frame_rate_hz: float = 100.0) -> Recording:
    traj = Trajectory(pan_px=20.0, seed=seed)
    cfg = SimConfig(height=H, width=W, duration_s=duration_s, frame_rate_hz=frame_rate_hz,
                    internal_rate_hz=1000.0, log_offset=1.0, seed=seed, trajectory=traj)
    src = MovingScene(cfg.scene, (H, W), traj, speed=SpeedProfile(
        segments=((0.3 * duration_s, 0.0), (0.7 * duration_s, 1.5))))
    return simulate(cfg, effects, source=src).recording


@pytest.mark.parametrize("interpolation", ["linear", "flow"])
def test_a_cached_render_gives_the_same_events(interpolation: str) -> None:
    rec = small_recording(5, [])
    model = fit_base(rec).with_effect(Refractory(period_us=700.0))
    settings = SimSettings(interpolation=interpolation)
    plain = [simulate_model(model, rec, s, settings).events for s in (1, 2)]
    cache = RenderCache()
    cached = [simulate_model(model, rec, s, settings, cache).events for s in (1, 2)]
    assert cache.renders == 1  # rendered once, the second seed read it
    assert cache.hits == 1
    for a, b in zip(plain, cached, strict=True):
        np.testing.assert_array_equal(a, b)
    # 16-bit fixed point when float32 does not fit: the same events but for a few near-ties
    half = RenderCache(max_bytes=int(2.5 * cache.nbytes() / 2))
    ev16 = simulate_model(model, rec, 1, settings, half).events
    assert half.nbytes() * 2 == cache.nbytes()
    assert abs(ev16.size - plain[0].size) <= 0.01 * plain[0].size
    # nothing kept when even float16 does not fit: rendered on the fly, same events
    none = RenderCache(max_bytes=1000)
    np.testing.assert_array_equal(simulate_model(model, rec, 1, settings, none).events,
                                  plain[0])
    assert none.nbytes() == 0


def test_fixed_point_render_reads_back_within_its_step() -> None:
    rec = small_recording(3, [], duration_s=0.3)
    times_us = np.arange(0, 300_001, 1000, dtype=np.int64)
    shape = rec.sensor.shape
    n_bytes = times_us.size * shape[0] * shape[1] * 2

    def interp() -> FrameInterpolator:
        return FrameInterpolator(rec.frames, shape)

    exact = interp().render_block(times_us * 1e-6)
    fixed = RenderCache(max_bytes=n_bytes + 10).source(b"k", times_us, shape, interp)
    got = fixed.render_block(times_us * 1e-6)
    step = (float(exact.max()) - float(exact.min())) / 65535
    assert np.abs(got - exact).max() <= 0.51 * step + 1e-4
    lag = RenderCache(max_bytes=n_bytes + 10).source(b"k", times_us, shape, interp,
                                                     lag_s=0.0025)
    # read at t - 2.5 ms: held at the first sample before it, halfway between two after
    want = np.concatenate([exact[[0, 0, 0]], 0.5 * (exact[:-3] + exact[1:-2])])
    np.testing.assert_allclose(lag.render_block(times_us * 1e-6), want,
                               atol=0.51 * step + 1e-4)

    class NoRange:  # a source that does not say its range: float16
        def render_block(self, t_s: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
            return interp().render_block(t_s, out=out)

    half = RenderCache(max_bytes=n_bytes + 10)
    src16 = half.source(b"k", times_us, shape, NoRange)  # type: ignore[arg-type]
    np.testing.assert_allclose(src16.render_block(times_us * 1e-6), exact, rtol=1e-3)


def test_one_seed_borrows_the_spread_of_an_evaluation() -> None:
    meas = {"s": StatValue("s", np.array([1.0, 2.0]), ["a", "b"], 0.0)}
    sims = [{"s": StatValue("s", np.array([v, 2.0 + v]), ["a", "b"], 0.0)}
            for v in (0.9, 1.1, 1.0)]
    full = discrepancy(meas, sims)
    one = discrepancy(meas, sims[:1], spread=full)
    sd = full.sim_std["s"]
    mu = np.array([0.9, 2.9])
    expect = (np.array([1.0, 2.0]) - mu) / np.sqrt(sd**2 * 2 + (0.03 * mu) ** 2)
    np.testing.assert_allclose(one.z["s"], expect)
    assert one.n_sims == 1
    assert full.n_sims == 3


def test_a_long_recording_is_cut_to_its_busiest_frames() -> None:
    rec = small_recording(9, [], duration_s=2.0)
    whole, info = working_window(rec, 10**9, 1000.0)
    assert whole is rec
    assert not info["cut"]
    budget = H * W * 600  # 0.6 s at 1 kHz
    cut, info = working_window(rec, budget, 1000.0)
    assert info["cut"]
    assert info["frames"] < info["of_frames"]
    t0, t1 = cut.frames.t_us[0], cut.frames.t_us[-1]
    assert (t1 - t0) * 1e-6 <= 0.6 + 1e-9
    # the busiest stretch: the scene moves in the last 70 %, so the window lies there
    assert t0 >= rec.frames.t_us[0] + 0.3e6 - 10_000
    assert cut.n_events == info["events"]
    assert (cut.events["t_us"] >= t0).all()
    assert (cut.events["t_us"] <= t1).all()
    # the whole recording's figures stay in the description (the report says what was kept)
    assert info["of_events"] == rec.n_events
    assert info["of_duration_s"] == rec.duration_s


def test_a_busy_recording_is_cut_to_an_event_budget() -> None:
    rec = small_recording(9, [], duration_s=2.0)
    t = rec.frames.t_us
    between = int(np.searchsorted(rec.events["t_us"], t[-1]) - np.searchsorted(rec.events["t_us"],
                                                                               t[0]))
    budget = between // 3
    cut, info = working_window(rec, 10**9, 1000.0, max_events=budget)
    assert info["cut"]
    assert info["events"] <= budget + 1  # the events at the last frame's stamp
    assert info["frames"] >= 4
    # the busiest stretch of that many events: no window of as many frames holds more
    k = info["frames"] - 1
    at = np.searchsorted(rec.events["t_us"], t, side="left")
    counts = at[k:] - at[:-k]
    assert info["events"] >= counts[counts <= budget].max() - 1
    # no budget, or one above what it holds: the recording as it is
    assert working_window(rec, 10**9, 1000.0, max_events=None)[0] is rec
    assert working_window(rec, 10**9, 1000.0, max_events=between)[0] is rec


def test_read_noise_of_still_pixels_is_taken_out_and_motion_kept() -> None:
    rng = np.random.default_rng(0)
    k = 30
    still = np.full((k, 4, 4), 40.0)
    ramp = np.linspace(20, 370, k)[:, None, None] * np.ones((1, 4, 4))
    imgs = np.concatenate([still, ramp], axis=2) + rng.normal(0, 1.0, (k, 4, 8))
    frames = Frames(np.arange(k, dtype=np.int64) * 10_000, imgs.astype(np.float32),
                    np.zeros(k, np.int64))
    lat = latent_frames(frames, 1.0)
    # still pixels: one run, their mean, constant in time
    assert np.ptp(lat[:, :, :4], axis=0).max() < 1e-4
    assert np.abs(lat[:, :, :4] - 40.0).max() < 1.0
    # a ramp of 12 DN per frame (far beyond the noise): every frame kept as it is
    np.testing.assert_array_equal(lat[:, :, 4:], frames.images[:, :, 4:])
    # no noise to take out: unchanged
    np.testing.assert_array_equal(latent_frames(frames, 0.2), frames.images)


def test_a_slow_change_of_the_light_is_kept_in_still_pixels() -> None:
    """Still pixels under a light that ramps by 1.5 % a frame (about 1 DN, within the
    noise): the latent frames follow the ramp (a sensor fires all the while) and lose the
    noise; a moving pixel is kept as it is."""
    rng = np.random.default_rng(1)
    k, h, w = 40, 16, 16
    gain = 1.015 ** np.arange(k)
    scene = rng.uniform(40.0, 120.0, (h, w))
    clean = gain[:, None, None] * scene[None]
    imgs = clean + rng.normal(0.0, 1.0, clean.shape)
    imgs[:, 0, 0] = 60.0 + 40.0 * (np.arange(k) % 2)  # a pixel an edge crosses back and forth
    frames = Frames(np.arange(k, dtype=np.int64) * 40_000, imgs.astype(np.float32),
                    np.zeros(k, np.int64))
    lat = latent_frames(frames, 1.0)
    still = np.ones((h, w), bool)
    still[0, 0] = False
    err_lat = np.abs(lat - clean)[:, still].mean()
    err_raw = np.abs(imgs - clean)[:, still].mean()
    assert err_lat < 0.5 * err_raw  # the noise is taken out ...
    ratio = lat[-1][still] / lat[0][still]
    assert np.median(ratio) == pytest.approx(gain[-1] / gain[0], rel=0.02)  # ... the ramp kept
    np.testing.assert_allclose(lat[:, 0, 0], imgs[:, 0, 0], rtol=1e-5)


def test_the_common_light_keeps_a_breathing_light_and_drops_an_aliased_flicker() -> None:
    from evcal.gap.model import smooth_gain

    k = np.arange(60)
    breathing = np.exp(0.2 * np.sin(2 * np.pi * k / 25.0))  # 1 Hz at 25 frames per second
    np.testing.assert_allclose(smooth_gain(breathing), breathing, rtol=0.02)
    ramp = 1.01 ** k
    np.testing.assert_allclose(smooth_gain(ramp), ramp, rtol=1e-6)
    rng = np.random.default_rng(2)
    flicker = np.exp(0.08 * rng.uniform(-1, 1, k.size))  # a mains flicker sampled by frames
    assert np.std(np.log(smooth_gain(flicker))) < 0.7 * np.std(np.log(flicker))


def test_an_evaluation_that_let_go_of_its_simulations_is_extended_anew() -> None:
    """A round lets go of the simulations of candidates it does not keep; confirming one of
    them later simulates every seed again rather than counting its first seed's summary
    twice."""
    rec = small_recording(17, [])
    run = Evaluator(rec, GapConfig(n_seeds=3, seed=1), lambda _m: None)
    assert run.band is None
    base = run.evaluate(fit_base(rec), "base")
    screened = run.evaluate(base.model, "screen", spread=base)
    assert screened.screened
    kept = run.extend(screened, 3, "confirm")
    screened.sims.clear()
    again = run.extend(screened, 3, "confirm")
    assert len(again.sims) == len(again.summaries) == len(again.held_summaries) == 3
    assert again.gap == pytest.approx(kept.gap, rel=1e-12)
    assert again.held_gap == pytest.approx(kept.held_gap, rel=1e-12)


def test_what_remains_is_said_in_words() -> None:
    s = sentence("static_rate_vs_intensity", "static, I (DN) 12..31", 0.41, 1.27, -8.2)
    assert s.startswith("still pixels (static, I (DN) 12..31) fire 3.1x fewer events than "
                        "the model (0.41 vs 1.27 events per pixel-second, z = -8.2)")
    s = sentence("offei_residual_vs_intensity", "log I - pixel median -inf..-0.4", 0.27, 0.14,
                 23.5)
    assert "more positive than the model by 0.13" in s
    rec = small_recording(17, [])
    obs = observe(rec)
    st = summarise(obs)
    shifted = {k: StatValue(v.name, v.values * (3.0 if k == "static_rate_vs_intensity"
                                                 else 1.0) + (0.5 if k == "static_rate_vs_"
                                                              "intensity" else 0.0),
                            v.labels, v.floor) for k, v in st.items()}
    disc = discrepancy(shifted, [st, st])
    items = unexplained(disc)
    assert items
    assert items[0]["statistic"] == "static_rate_vs_intensity"
    assert "more events than the model" in items[0]["sentence"]
    nothing = summary(discrepancy(st, [st, st]))
    assert nothing == ["nothing significant: every statistic within the model's noise "
                       "(D < 2)"]


def test_counting_order_is_the_stable_argsort() -> None:
    from evcal.accumulate import order_by_key
    from evcal.errors import EvcalError

    rng = np.random.default_rng(3)
    key = rng.integers(0, 50, 10_000)
    np.testing.assert_array_equal(order_by_key(key, 50), np.argsort(key, kind="stable"))
    assert order_by_key(np.zeros(0, np.int64), 5).size == 0
    with pytest.raises(EvcalError, match=r"\[0, 50\)"):
        order_by_key(np.array([3, 50]), 50)


def test_one_pass_window_sums_give_the_per_pixel_fit_and_residual() -> None:
    from evcal.gap.stats import fit_from_sums, fit_pixels, residual_from_sums, window_sums

    rng = np.random.default_rng(4)
    n_w, npix = 30, 200
    P = rng.integers(-3, 4, (n_w, npix))
    E = np.abs(P) + rng.integers(0, 3, (n_w, npix))
    dL = 0.2 * P + 0.01 * E + rng.normal(0, 0.02, (n_w, npix))
    w = (rng.random((n_w, npix)) > 0.1).astype(np.float64)
    sums = window_sums(P, E, dL, w)
    for k, t in enumerate([P * P, P * E, E * E, P * dL, E * dL, E, dL * dL]):
        np.testing.assert_allclose(sums[k], (w * t).sum(0), rtol=1e-12, atol=1e-9)
    halves = window_sums(P, E, dL, w, split=12)
    np.testing.assert_allclose(halves[0], window_sums(P[:12], E[:12], dL[:12], w[:12]))
    np.testing.assert_allclose(halves[0] + halves[1], sums, atol=1e-9)
    c, b, ok = fit_pixels(P, E, dL, w)
    assert ok.all()
    assert abs(np.median(c) - 0.2) < 0.01
    assert abs(np.median(b) - 0.01) < 0.01
    res = dL - c * P - b * E
    np.testing.assert_allclose(residual_from_sums(sums, c, b), (w * res * res).sum(0),
                               rtol=1e-6, atol=1e-12)
    c2, b2, _ = fit_from_sums(*sums[:6])
    np.testing.assert_array_equal(c, c2)
    # arrays in column order (pixels taken from an observation with an index) are summed
    # through their transposes, in the same order: the very same figures
    cols = [np.asfortranarray(a) for a in (P, E, dL, w)]
    np.testing.assert_array_equal(window_sums(*cols), sums)
    np.testing.assert_array_equal(window_sums(*cols, split=12), halves)


def test_observations_of_the_same_frames_share_their_frame_arrays() -> None:
    from evcal.gap.stats import every_nth_row

    rec = small_recording(6, [])
    meas = observe(rec)
    sim = observe(simulate_model(fit_base(rec), rec, 1, SimSettings(interpolation="linear")))
    assert sim.log_i is meas.log_i
    assert sim.usable is meas.usable
    assert sim.shared is meas.shared
    assert not meas.log_i.flags.writeable  # shared: nobody may write into them
    # a sample of rows: the same per-pixel arrays and events of those rows
    sub = every_nth_row(meas, 3)
    rows = np.arange(0, H, 3)
    assert sub.shape == (rows.size, W)
    assert sub.n_pixels == rows.size * W
    keep = np.isin(meas.pix // W, rows)
    assert sub.t_us.size == keep.sum()
    np.testing.assert_array_equal(sub.on.sum(), meas.on.reshape(-1, H, W)[:, rows].sum())
    np.testing.assert_array_equal(np.bincount(sub.pix, minlength=sub.n_pixels),
                                  (sub.on + sub.off).sum(0))


def test_progress_without_a_terminal_prints_lines_with_the_time_left(capsys,
                                                                   monkeypatch) -> None:
    from evcal.progress import Progress

    monkeypatch.setattr(Progress, "EVERY_S", 0.0)
    # as `evcal gap` makes it
    p = Progress(10.0, "gap", unit="simulations planned", tty=False, decimals=1,
                 skip_first=True)
    p.update(0.25)  # a screening on a quarter of the rows
    p.plan(6.0)  # a round fewer than planned
    p.update(1.0)
    p.close()
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 2
    assert lines[0].startswith("evcal gap: 0.2 of 10.0 simulations planned")
    assert lines[0].endswith("about ? left")  # no rate from the first simulation alone
    assert "1.2 of 6.0 simulations planned" in lines[1]
    assert "left" in lines[1]
    # an opening line at once; a run past its plan says 0:00 left, not a negative time
    with Progress(2.0, "gap", unit="simulations planned", tty=False, decimals=1,
                  opening="fitting the base model") as o:
        first = capsys.readouterr().err.strip().splitlines()
        o.update(1.0)
        o.update(2.0)
        assert "-" not in o.line().split("elapsed")[1]
        assert o.line().endswith("about 0:00 left")
    assert first == ["evcal gap: 0.0 of 2.0 simulations planned, 0:00 elapsed, about ? left; "
                     "fitting the base model"]
    capsys.readouterr()
    quiet = Progress(10.0, "gap", unit="simulations planned", quiet=True, tty=False)
    quiet.update(1.0)
    assert capsys.readouterr().err == ""
    # an unknown total: what is done and the time, no estimate
    with Progress(None, "calibrate", unit="messages read", tty=False) as q:
        q.set(4096)
    assert capsys.readouterr().err.strip().startswith("evcal calibrate: 4096 messages read, 0:00")


def test_with_forecasts_the_time_left_is_the_callers_never_negative(capsys,
                                                                     monkeypatch) -> None:
    """`evcal gap`'s progress: "?" until the workflow's first forecast (not a rate from
    the base model's simulations), then the time to the forecast end, 0:00 once past it."""
    import time

    from evcal.progress import Progress

    monkeypatch.setattr(Progress, "EVERY_S", 0.0)
    p = Progress(10.0, "gap", unit="simulations planned", tty=False, decimals=1,
                 skip_first=True, forecasts=True, opening="fitting the base model")
    p.update(1.0)
    p.update(1.0)  # a rate exists, yet no forecast: unknown
    p.forecast(time.monotonic() + 125.0)
    p.update(1.0)
    p.forecast(time.monotonic() - 5.0)  # the run overran its forecast
    p.update(1.0)
    p.close()
    lines = capsys.readouterr().err.strip().splitlines()
    assert lines[0].endswith("about ? left; fitting the base model")
    assert lines[1].endswith("about ? left")
    assert lines[2].endswith("about ? left")
    assert lines[3].endswith("about 2:05 left") or lines[3].endswith("about 2:04 left")
    assert lines[4].endswith("about 0:00 left")


def test_a_terminal_bar_shows_the_forecast_as_its_time_left(capsys) -> None:
    """On a terminal the bar's bracket says "about ? left" until the first forecast, then
    the time to it (tqdm's own estimate from the rate is not shown)."""
    import time

    from evcal.progress import Progress

    p = Progress(10.0, "gap", unit="simulations planned", tty=True, decimals=1,
                 skip_first=True, forecasts=True)
    p.update(1.0)
    before = capsys.readouterr().err
    p.forecast(time.monotonic() + 65.4)
    p.update(1.0)
    p.close()
    after = capsys.readouterr().err
    assert "about ? left]" in before
    assert "about 1:05 left]" in after
    assert ", ," not in after


def test_the_workflow_forecasts_its_end_at_every_round() -> None:
    """run_gap says when it expects to end at the start of each round, after the base
    model (the time it took sets the scale), and always later than the moment it says so
    (how close it comes is measured on the benchmark's recordings, not here: a timed test
    flakes on a busy machine)."""
    import time

    from evcal.gap.workflow import GapConfig, run_gap
    from evcal.sim.effects import Leak

    rec = small_recording(5, [Leak(rate_hz=0.3)])
    t0 = time.monotonic()
    said: list[tuple[float, float]] = []
    run_gap(rec, GapConfig(max_effects=1, candidates=("leak", "shot_noise")),
            forecast=lambda end: said.append((time.monotonic(), end)))
    assert said
    assert all(end > now > t0 for now, end in said)


def test_a_drift_below_the_noise_is_kept_and_its_noise_taken_out() -> None:
    """Pixels that brighten by 0.4 DN a frame apart from the rest of the scene (below the
    1 DN noise frame to frame, 12 DN over the run): the latent frames keep the drift (a
    sensor fires on it), lose most of the noise, and pixels beside them that stay still
    stay flat."""
    rng = np.random.default_rng(3)
    k, h, w = 30, 16, 16
    clean = np.full((k, h, w), 60.0)
    drift = np.zeros((h, w), bool)
    drift[:, : w // 2] = True
    clean[:, drift] += 0.4 * np.arange(k)[:, None]
    imgs = clean + rng.normal(0.0, 1.0, clean.shape)
    frames = Frames(np.arange(k, dtype=np.int64) * 40_000, imgs.astype(np.float32),
                    np.zeros(k, np.int64))
    lat = latent_frames(frames, 1.0)
    rise = lat[-1] - lat[0]
    assert np.median(rise[drift]) == pytest.approx(0.4 * (k - 1), rel=0.2)
    assert np.abs(np.median(rise[~drift])) < 1.0
    err_lat = np.abs(lat - clean).mean()
    err_raw = np.abs(imgs - clean).mean()
    assert err_lat < 0.5 * err_raw
