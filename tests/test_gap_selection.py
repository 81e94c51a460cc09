"""How the gap workflow chooses: the registry of effects, the fitters' evidence and reasons,
physics that tells effects apart which mimic each other, the held-out rows and the null
calibration.

Recordings are those of tests/test_gap.py (48x64, 2 s, a still stretch then a pan, 200 Hz
frames) with their own seeds; the properties, not the figures of a seed, are asserted.
"""

from __future__ import annotations

from functools import cache

import numpy as np
import pytest
from test_gap import hidden_recording

from evcal.errors import ConfigError
from evcal.gap import effects as registry
from evcal.gap.effects import EffectSpec, Fitted, NoEvidence
from evcal.gap.frames import LagByLight, _basin_minimum, _lag_minimum
from evcal.gap.model import fit_base, simulate_model
from evcal.gap.null import calibrate
from evcal.gap.runner import Evaluation, Evaluator, GapConfig
from evcal.gap.stats import STATISTICS
from evcal.gap.workflow import run_gap
from evcal.recording import Recording
from evcal.sim.effects import (
    EFFECT_NAMES,
    Bandwidth,
    Effect,
    Exposure,
    Leak,
    ShotNoise,
)


@cache
def _evaluated(key: str, seed: int) -> tuple[Recording, Evaluator, Evaluation]:
    effects: dict[str, list[Effect]] = {
        "none": [],
        "leak": [Leak(rate_hz=1.5, spread_log=0.2)],
        "shot": [ShotNoise(rate_hz=2.0)],
        "lag": [Exposure(lag_us=2500.0, exposure_us=5000.0)],
        "lowpass": [Bandwidth(cutoff_hz=40.0)],
    }
    rec = hidden_recording(effects[key], seed)
    ev = Evaluator(rec, GapConfig(seed=2, candidates=tuple(registry.names())),
                   lambda _w: None)
    return rec, ev, ev.evaluate(fit_base(rec), "base")


def _fit(key: str, seed: int, name: str) -> Fitted | NoEvidence:
    _, ev, cur = _evaluated(key, seed)
    return registry.spec(name).fit(ev.fit_context(cur.model, cur.sims))


def test_every_effect_of_the_simulator_has_one_spec() -> None:
    assert set(registry.names()) == set(EFFECT_NAMES)
    _, ev, _ = _evaluated("none", 31)
    stats = set(ev.meas_stats)
    assert len(stats) == len(STATISTICS)
    kinds = set()
    for name in registry.names():
        spec = registry.spec(name)
        assert spec.effect.name == name
        kinds.add(spec.kind)
        eff = spec.effect()
        assert spec.says(eff)  # the report's words for a value
        assert spec.strength(eff, 100.0) >= 0.0
        assert spec.alternatives(eff)[0] is eff
        assert spec.moves, name
        assert set(spec.moves) <= stats, (name, set(spec.moves) - stats)
    assert kinds == {"sensor", "frames", "scheme", "scene", "start"}
    with pytest.raises(ConfigError, match="registered already"):
        registry.register(registry.spec("leak"))
    with pytest.raises(ConfigError, match="known"):
        registry.spec("flux_capacitor")


def test_a_spec_must_hold_its_own_effect() -> None:
    spec = registry.spec("leak")
    with pytest.raises(ConfigError, match="holds effect"):
        EffectSpec("shot_noise", Leak, spec.fit, spec.strength, spec.moves, spec.says)


def test_fitters_that_see_nothing_say_why() -> None:
    """Nothing hidden: the fitters of effects that add or remove events find none, and each
    says why in words (the report prints them). (Fitters of subtler signatures may read
    something into what the interpolated frames miss: the held-out gain judges those.)"""
    for name in ("leak", "shot_noise", "hot_pixels", "row_noise", "refractory"):
        res = _fit("none", 31, name)
        assert isinstance(res, NoEvidence), (name, res)
        assert len(res.reason) > 20, name
    for name in registry.names():
        res = _fit("none", 31, name)
        assert isinstance(res, Fitted | NoEvidence)


def test_leak_and_shot_noise_are_told_apart_by_polarity() -> None:
    """A leak adds ON events only: the shot-noise fitter, which needs an excess of both
    polarities, sees none of it; shot noise adds both alike: the leak fitter, which needs
    a net excess of ON, sees none of it."""
    on_leak = _fit("leak", 33, "shot_noise")
    assert isinstance(on_leak, NoEvidence)
    assert "OFF" in on_leak.reason
    leak = _fit("leak", 33, "leak")
    assert isinstance(leak, Fitted)
    on_shot = _fit("shot", 35, "leak")
    assert isinstance(on_shot, NoEvidence)
    shot = _fit("shot", 35, "shot_noise")
    assert isinstance(shot, Fitted)


def test_a_frame_lag_is_not_read_as_a_slow_photoreceptor() -> None:
    """A late frame stamp delays every pixel's events alike; a photoreceptor low-pass
    delays the dark pixels' more (its cutoff follows the photocurrent). The exposure fitter
    refuses the low-pass's light-dependent lag; the low-pass fitter may read a cutoff off a
    frame lag (a window's light mixes dark and bright moments, so alike thirds do not
    refuse it), and its simulation then explains the recording several times worse than
    the frame lag's."""
    rec, ev, cur = _evaluated("lag", 37)
    lag = _fit("lag", 37, "exposure")
    assert isinstance(lag, Fitted)
    as_lowpass = _fit("lag", 37, "bandwidth")
    if isinstance(as_lowpass, Fitted):
        gaps = {name: ev.evaluate(ev.candidate_model(cur.model, eff), name).held_gap
                for name, eff in (("exposure", lag.effect), ("bandwidth", as_lowpass.effect))}
        assert gaps["bandwidth"] > 3.0 * gaps["exposure"], gaps
    low = _fit("lowpass", 39, "bandwidth")
    assert isinstance(low, Fitted)
    assert isinstance(_fit("lowpass", 39, "exposure"), NoEvidence)


def test_a_low_pass_whose_thirds_are_alike_is_still_fitted() -> None:
    """The lag by light refuses a low-pass only when the dark moments are clearly earlier
    than the bright ones; thirds alike, or the dark beyond the grid's late end, leave it to
    the simulations. A third's lag is the minimum in the basin of the whole recording's: a
    periodic scene matches itself again a period off, lower perhaps, which is no delay."""
    assert not LagByLight([5941.0, 5583.0, 5546.0], 1172.0).earlier_in_the_dark()
    assert not LagByLight([np.inf, 4700.0, 3046.0], 625.0).earlier_in_the_dark()
    assert LagByLight([1000.0, 2500.0, 4000.0], 625.0).earlier_in_the_dark()
    assert LagByLight([-np.inf, 2500.0, 4000.0], 625.0).earlier_in_the_dark()
    lags = np.linspace(-15.0, 15.0, 25)
    r = 0.5 - 0.4 * np.cos(2 * np.pi * (lags - 5.0) / 20.0) - 0.05 * (lags < -10)
    assert int(np.argmin(r)) == 0  # the period's match at the grid's end is lower
    assert _basin_minimum(r, 13) == 16
    assert _lag_minimum(lags, r, _basin_minimum(r, 13)) == pytest.approx(5.0, abs=0.2)


def test_a_map_is_fitted_on_the_fit_rows_and_drawn_on_the_others() -> None:
    rec, ev, cur = _evaluated("none", 31)
    ctx = ev.fit_context(cur.model, cur.sims)
    assert ctx.rows is not None
    assert ctx.meas.shape == (rec.sensor.height // 2, rec.sensor.width)
    part = np.arange(ctx.meas.n_pixels, dtype=np.float64).reshape(ctx.meas.shape)
    whole = ctx.whole_map(part, spread=2.0)
    assert whole.shape == rec.sensor.shape
    np.testing.assert_array_equal(whole[ctx.rows], part)
    held = np.setdiff1d(np.arange(rec.sensor.height), ctx.rows)
    assert np.std(whole[held]) == pytest.approx(2.0, rel=0.15)
    # the fit rows and the held-out rows interleave and cover the sensor once
    assert np.intersect1d(ctx.rows, ev.whole.held_rows).size == 0
    assert ctx.rows.size + ev.whole.held_rows.size == rec.sensor.height


def test_null_calibration_reads_every_fitter_on_the_models_own_simulations() -> None:
    _, ev, cur = _evaluated("none", 31)
    names = [n for n in registry.names() if registry.spec(n).kind != "scheme"]
    null = calibrate(ev, cur, names)
    assert set(null.strengths) == set(names)
    for name in names:
        assert null.limit(name, 2.0) == pytest.approx(2.0 * max(null.strengths[name]))
        assert null.gain(ev, name) >= 0.0
    # the tested fitters see nothing in a simulation of the model itself
    for name in ("leak", "shot_noise", "hot_pixels", "row_noise"):
        assert null.strengths[name] == [0.0], name
        assert null.reasons[name]


@pytest.mark.slow
def test_nothing_is_named_on_a_recording_of_the_model_itself() -> None:
    """The base model fitted to a recording, simulated anew with another seed, is a
    recording from which nothing is missing: the workflow names nothing on it."""
    rec = hidden_recording([Leak(rate_hz=0.5)], 41)
    base = fit_base(rec)
    own = simulate_model(base, rec, 777, Evaluator(rec, GapConfig(), lambda _w: None).settings)
    res = run_gap(own, GapConfig(seed=3, max_effects=2))
    assert [n for n in res.named_effects if n != "timestamp_quantisation"] == []


def _held(per_stat: dict[str, float]) -> Evaluation:
    from evcal.gap.compare import Discrepancy  # noqa: PLC0415

    d = Discrepancy({}, {}, {}, {}, dict(per_stat), {}, 3)
    return Evaluation(None, [], d, d)  # type: ignore[arg-type]  # judged by statistics only


def test_a_candidate_whose_gain_lies_outside_its_statistics_is_passed_over() -> None:
    """The best-scoring confirmed candidate gains only where its effect has no signature
    (a jitter of timestamps lowering the still pixels' rate misfit); a leak gains less but
    on its own statistics: the leak is chosen, and with the check off the jitter."""
    from evcal.gap.search import Candidate, Round, signature_ok  # noqa: PLC0415
    from evcal.sim.effects import TimestampJitter  # noqa: PLC0415

    base = {k: 1.0 for k in _evaluated("none", 31)[1].meas_stats}
    base.update(static_rate_vs_intensity=40.0, static_balance_vs_intensity=30.0,
                on_fraction_over_time=12.0, fit_population=30.0)
    # the jitter's gain all outside the statistics a jitter moves (intervals, stamps)
    jitter_after = dict(base, static_rate_vs_intensity=1.0, fit_population=1.0)
    leak_after = dict(base, static_balance_vs_intensity=1.5, on_fraction_over_time=1.2,
                      static_rate_vs_intensity=20.0)
    on = _held(base)
    jitter = Candidate("timestamp_jitter", "confirmed", effect=TimestampJitter(sigma_us=300.0),
                       evaluation=_held(jitter_after))
    leak = Candidate("leak", "confirmed", effect=Leak(rate_hz=0.5),
                     evaluation=_held(leak_after))
    def judged(cands: list[Candidate], min_share: float) -> Round:
        for c in cands:
            c.passed_over, c.reason = False, ""
        rnd = Round({c.name: c for c in cands}, on.held_gap, on.held_gap)
        rnd.judge_signatures(on, min_share)
        return rnd

    assert jitter.score(0.1) < leak.score(0.1)
    assert jitter.signature_share(on) == 0.0
    assert leak.signature_share(on) == pytest.approx(1.0)
    assert not signature_ok(jitter, on, 0.5)
    assert signature_ok(leak, on, 0.5)
    rnd = judged([jitter, leak], 0.5)
    assert rnd.best(0.1) is leak
    assert jitter.passed_over
    assert "falls on the statistics" in rnd.to_json(0.1)["timestamp_jitter"]["reason"]
    assert not leak.passed_over
    assert judged([jitter, leak], 0.0).best(0.1) is jitter
    # nothing on its own statistics anywhere: nothing is chosen
    assert judged([jitter], 0.5).best(0.1) is None


def test_a_pair_is_named_only_when_each_effect_adds_to_the_other() -> None:
    """Two effects that explain the data only together (a frame lag and a dark level: each
    alone gains little or loses) are named as a pair; not when the second adds less to the
    first than naming a single needs, nor when the pair's gain lies outside the statistics
    either effect moves, nor when the pair gains too little over the model."""
    from evcal.gap.search import Candidate, Pair  # noqa: PLC0415
    from evcal.gap.workflow import GapRun  # noqa: PLC0415
    from evcal.sim.effects import LogOffset  # noqa: PLC0415

    rec, ev, _ = _evaluated("none", 31)
    run = GapRun(rec, GapConfig(seed=2))
    run.ev = ev
    run.null.gains.update(exposure=0.0, log_offset=0.0, timestamp_jitter=0.0)
    base = {k: 1.0 for k in ev.meas_stats}
    base.update(lag_vs_intensity=20.0, offei_residual_vs_dl=20.0,
                sensitivity_vs_intensity=20.0, offei_residual_vs_intensity=20.0)
    on = _held(base)
    lag_alone = dict(base, lag_vs_intensity=10.0, sensitivity_vs_intensity=28.0)
    dark_alone = dict(base, sensitivity_vs_intensity=12.0, offei_residual_vs_dl=40.0)
    both = {k: 1.0 for k in base}

    def pair(first_after: dict[str, float], alone_after: dict[str, float],
             pair_after: dict[str, float]) -> Pair:
        lag = Exposure(lag_us=3000.0, exposure_us=500.0)
        return Pair(Candidate("exposure", "confirmed", effect=lag,
                              evaluation=_held(first_after)),
                    Candidate("log_offset", "confirmed", effect=LogOffset(dark_dn=50.0),
                              evaluation=_held(pair_after)),
                    Candidate("log_offset", "confirmed", effect=LogOffset(dark_dn=50.0),
                              evaluation=_held(alone_after)))

    named = run._pair_why(pair(lag_alone, dark_alone, both), on)
    assert named["named"], named
    assert named["pair"] == ["exposure", "log_offset"]
    assert all(a["added_gain"] > a["needed_gain"] for a in named["each_adds"].values())
    # the dark level adds nothing to the lag alone
    lag_enough = dict(both, lag_vs_intensity=1.2)
    idle = run._pair_why(pair(lag_enough, dark_alone, dict(lag_enough)), on)
    assert not idle["named"]
    assert "adds less" in idle["reason"]
    # the pair's gain falls where neither effect has a signature
    away = dict(base, iei_distribution=1.0)
    off_base = _held(dict(base, iei_distribution=400.0))
    outside = run._pair_why(pair(dict(base, iei_distribution=300.0),
                                 dict(base, iei_distribution=350.0), away), off_base)
    assert not outside["named"]
    assert "falls on the statistics" in outside["reason"]
    # a pair that gains too little over the model
    small = run._pair_why(pair(dict(base, lag_vs_intensity=19.0),
                               dict(base, lag_vs_intensity=19.5),
                               dict(base, lag_vs_intensity=18.0)), on)
    assert not small["named"]
    assert "below" in small["reason"]


def test_a_named_effect_the_others_make_redundant_is_taken_out_again() -> None:
    """The backward step: in a model of a recording with a dark level hidden, the dark
    level (whose absence costs much on the held-out rows) stays, and a timestamp jitter too
    small to move anything (named, say, in an early round) is dropped and reported."""
    from evcal.gap.workflow import GapRun, Step  # noqa: PLC0415
    from evcal.sim.effects import LogOffset, TimestampJitter  # noqa: PLC0415

    rec = hidden_recording([LogOffset(dark_dn=45.0)], 47)
    run = GapRun(rec, GapConfig(seed=2))
    run.ev = ev = Evaluator(rec, run.cfg, lambda _w: None)
    dark, idle = LogOffset(dark_dn=45.0), TimestampJitter(sigma_us=1.0)
    base = fit_base(rec, 45.0)
    cur = ev.evaluate(base.with_effect(idle).with_effect(dark), "both")
    run.steps = [Step(idle, cur, cur, {}), Step(dark, cur, cur, {})]
    out = run._prune(cur)
    assert [s.effect.name for s in run.steps] == ["log_offset"]
    assert [d["effect"] for d in run.dropped] == ["timestamp_jitter"]
    assert "timestamp_jitter" not in out.model.effects
    assert out.model.effects["log_offset"] == dark
    d = run.dropped[0]
    assert d["held_out_gap_without"] - d["held_out_gap_with"] < d["needed_gain"]


def test_a_screening_leaves_out_a_component_whose_spread_is_unknown() -> None:
    """A candidate screened on one seed takes its spread from a neighbouring model; where
    one of that model's simulations had too little data (NaN), the component is left out
    of the candidate's discrepancy, not turned into a NaN gap."""
    from evcal.gap.compare import discrepancy  # noqa: PLC0415
    from evcal.gap.stats import StatValue  # noqa: PLC0415

    def sv(v: list[float]) -> dict[str, StatValue]:
        return {"s": StatValue("s", np.asarray(v, np.float64), ["a", "b"], 0.01)}

    spread = discrepancy(sv([0.5, 0.5]), [sv([0.5, np.nan]), sv([0.52, 0.4])])
    assert np.isnan(spread.sim_std["s"][1])
    one = discrepancy(sv([0.5, 0.5]), [sv([0.6, 0.45])], spread=spread)
    assert np.isfinite(one.per_stat["s"])
    assert one.z["s"][1] == 0.0
    assert one.z["s"][0] != 0.0


def _pairs_recording(iei_us: int) -> Recording:
    """8x8 pixels, each firing alternating polarities every ``iei_us`` for 1 s, under four
    still frames."""
    from evcal.events import SensorSize, make_events
    from evcal.recording import Frames

    sensor = SensorSize(8, 8)
    n = sensor.n_pixels
    t0 = np.arange(1000, 990_000, 20_000)  # a pair of events every 20 ms at each pixel
    t = np.concatenate([t0, t0 + iei_us])
    p = np.concatenate([np.ones(t0.size), -np.ones(t0.size)])
    tt = np.tile(t, n)
    pix = np.repeat(np.arange(n), t.size)
    pp = np.tile(p, n)
    order = np.argsort(tt, kind="stable")
    ev = make_events(tt[order], pix[order] % 8, pix[order] // 8, pp[order])
    images = np.full((4, 8, 8), 100, np.uint8)
    frames = Frames(np.array([0, 330_000, 660_000, 1_000_000]), images, np.zeros(4, np.int64))
    return Recording(sensor, ev, frames)


def test_a_share_of_too_few_pairs_is_left_out_of_the_comparison() -> None:
    """The polarity alternation of pairs under 2 ms apart is a share of those pairs: with
    fewer than stats.MIN_BIN_SAMPLES of them (a model whose dead time lies a little above 2 ms has
    none) it is NaN and left out, not a share of 0 with no spread against the measured one
    (a discrepancy of thousands in a bin the interval statistics judge already)."""
    from evcal.gap.compare import discrepancy
    from evcal.gap.stats import observe, stat_polarity_alternation

    measured = stat_polarity_alternation(observe(_pairs_recording(1900)))
    model = stat_polarity_alternation(observe(_pairs_recording(2200)))
    assert measured.values[1] == pytest.approx(1.0)  # every pair under 2 ms alternates
    assert np.isnan(model.values[1])  # no pair under 2 ms: nothing to share
    assert model.values[0] == pytest.approx(measured.values[0])
    d = discrepancy({"polarity_alternation": measured},
                    [{"polarity_alternation": model}] * 3)
    assert d.z["polarity_alternation"][1] == 0.0
    assert d.per_stat["polarity_alternation"] < 2.0
