"""The APS-frame effects: DSNU (``aps_fpn``) and exposure placement (``exposure``).

Simulator side: the frames carry the dark offsets and the DVS events do not; a frame is the
mean over its exposure, wherever its stamp sits. Gap side: :func:`evcal.gap.frames.
model_frames` removes the fitted map and moves the frame times; the fitters recover the
hidden effect from one recording against the base model's simulations (the workflow's
hidden-effect tests of ``tests/test_gap.py`` run the whole loop on the same kind of
recording).
"""

from __future__ import annotations

from dataclasses import replace
from functools import cache

import numpy as np
import pytest

from evcal.gap.effects import FitContext, FitResult, Fitted, NoEvidence
from evcal.gap.frames import fit_aps_fpn, fit_exposure, model_frames
from evcal.gap.model import Model, SimSettings, estimate_read_noise, fit_base, simulate_model
from evcal.gap.stats import observe
from evcal.recording import Frames, Recording
from evcal.sim.effects import ApsConfig, ApsFpn, Effect, EffectError, Exposure
from evcal.sim.ideal import SimConfig
from evcal.sim.nonideal import simulate
from evcal.sim.scene import Trajectory

CFG = SimConfig(height=24, width=32, duration_s=0.3, frame_rate_hz=50.0,
                internal_rate_hz=1000.0, log_offset=1.0, seed=5,
                trajectory=Trajectory(pan_px=30.0, seed=5))


# ------------------------------------------------------------------------------ simulator


def test_dsnu_is_in_the_frames_and_not_in_the_events() -> None:
    aps = ApsConfig(quantise=False)
    plain = simulate(CFG, aps=aps).recording
    fpn = ApsFpn(sigma_dn=4.0, mean_dn=2.0, seed=3)
    res = simulate(CFG, [fpn], aps=aps).recording
    np.testing.assert_array_equal(res.events, plain.events)
    diff = res.frames.images.astype(np.float64) - plain.frames.images
    o = fpn.offsets_dn(CFG.sensor.shape)
    # the same offset in every frame (up to the floor at 0 DN, float32 rounding)
    lit = plain.frames.images > 20
    np.testing.assert_allclose(diff[lit], np.broadcast_to(o, diff.shape)[lit], atol=1e-3)
    assert o.std() == pytest.approx(4.0, rel=0.1)
    assert o.mean() == pytest.approx(2.0, abs=0.3)
    # deterministic: the seed gives the same pattern, another seed another
    np.testing.assert_array_equal(o, ApsFpn(sigma_dn=4.0, mean_dn=2.0, seed=3)
                                  .offsets_dn(CFG.sensor.shape))
    other = ApsFpn(sigma_dn=4.0, mean_dn=2.0, seed=4).offsets_dn(CFG.sensor.shape)
    assert abs(np.corrcoef(o.ravel(), other.ravel())[0, 1]) < 0.2


class _Ramp:
    """Uniform intensity rising 1 DN per ms from 20 DN."""

    def __call__(self, t_s: float) -> np.ndarray:
        return np.full((CFG.height, CFG.width), 20.0 + 1000.0 * t_s, np.float32)


@pytest.mark.parametrize(("stamp", "shift_us"), [("start", 2000), ("middle", 0),
                                                  ("end", -2000)])
def test_exposure_is_averaged_where_the_stamp_says(stamp: str, shift_us: int) -> None:
    aps = ApsConfig(exposure_us=4000, timestamp=stamp, quantise=False)
    rec = simulate(CFG, source=_Ramp(), aps=aps).recording
    t = (rec.frames.t_us - rec.frames.t_us[0]).astype(np.float64)
    # a linear ramp averaged over the exposure is its value at the exposure's centre
    expected = 20.0 + 1e-3 * np.maximum(t + shift_us, 0.0)
    got = rec.frames.images.mean(axis=(1, 2))
    np.testing.assert_allclose(got[1:], expected[1:], atol=1e-3)
    assert (rec.frames.exposure_us == 4000).all()
    assert aps.centre_lag_us == shift_us


def test_exposure_effect_sets_the_frame_model() -> None:
    aps = ApsConfig(quantise=False).with_effects({"exposure": Exposure(lag_us=1500.0,
                                                                       exposure_us=3000.0)})
    assert aps.exposure_us == 3000
    assert aps.centre_lag_us == 1500.0
    via_effect = simulate(CFG, [Exposure(lag_us=2000.0, exposure_us=4000.0)],
                          source=_Ramp(), aps=ApsConfig(quantise=False)).recording
    via_stamp = simulate(CFG, source=_Ramp(), aps=ApsConfig(
        exposure_us=4000, timestamp="start", quantise=False)).recording
    np.testing.assert_allclose(via_effect.frames.images, via_stamp.frames.images, atol=1e-4)


def test_frame_effects_validate_and_keep_the_map() -> None:
    with pytest.raises(EffectError):
        ApsFpn(sigma_dn=-1.0)
    with pytest.raises(EffectError):
        Exposure(exposure_us=-5.0)
    with pytest.raises(EffectError):
        ApsConfig(timestamp="centre")
    m = np.arange(12.0).reshape(3, 4)
    e = ApsFpn(sigma_dn=2.0, offset_dn=m)
    assert "offset_dn" not in e.parameters()  # reports stay small
    e2 = e.with_params(sigma_dn=3.0)
    assert isinstance(e2, ApsFpn)
    assert e2.sigma_dn == 3.0
    # the map scales about its mean with sigma (the workflow's search moves what it simulates)
    np.testing.assert_allclose(e2.offsets_dn((3, 4)), 5.5 + 1.5 * (m - 5.5))
    np.testing.assert_array_equal(e.with_params(seed=1).offsets_dn((3, 4)), m)
    with pytest.raises(EffectError):
        e.offsets_dn((4, 4))


# ------------------------------------------------------------------------------ model_frames


def _frames() -> Frames:
    rng = np.random.default_rng(0)
    imgs = rng.integers(10, 200, (5, 3, 4)).astype(np.uint8)
    return Frames(np.arange(5, dtype=np.int64) * 5000 + 100, imgs, np.full(5, 4000))


def test_model_frames_removes_the_map_and_moves_the_times() -> None:
    fr = _frames()
    base = Model(np.full((3, 4), 0.2), np.zeros((3, 4)), 1.0)
    assert model_frames(base, fr) is fr
    # a pattern without a map cannot be removed: the frames stay
    assert model_frames(base.with_effect(ApsFpn(sigma_dn=3.0)), fr) is fr
    m = np.linspace(-5, 5, 12).reshape(3, 4)
    out = model_frames(base.with_effect(ApsFpn(sigma_dn=3.0, offset_dn=m))
                       .with_effect(Exposure(lag_us=1234.4, exposure_us=4000.0)), fr)
    np.testing.assert_allclose(out.images, np.maximum(fr.images - m[None], 0.0), atol=1e-5)
    np.testing.assert_array_equal(out.t_us, fr.t_us + 1234)
    np.testing.assert_array_equal(out.exposure_us, fr.exposure_us)
    again = model_frames(base.with_effect(ApsFpn(sigma_dn=3.0, offset_dn=m)), fr)
    np.testing.assert_array_equal(again.images, model_frames(
        base.with_effect(ApsFpn(sigma_dn=3.0, offset_dn=m)), fr).images)
    np.testing.assert_array_equal(again.t_us, fr.t_us)


# ------------------------------------------------------------------------------ fitters


def frames_recording(effects: list[Effect], seed: int) -> Recording:
    """The hidden-effect recording of tests/test_gap.py (48x64, 2 s, 200 Hz frames)."""
    from test_gap import hidden_recording  # noqa: PLC0415

    return hidden_recording(effects, seed)


@cache
def _fit_setup(name: str, seed: int) -> tuple[Recording, FitContext, Model]:
    truth = FIT_CASES[name]
    rec = frames_recording([truth] if truth is not None else [], seed)
    base = fit_base(rec)
    st = SimSettings(read_noise_dn=estimate_read_noise(rec.frames), interpolation="linear")
    sims = [observe(simulate_model(base, rec, 1000 + k, st)) for k in range(3)]
    meas = observe(rec)
    return rec, FitContext(meas, sims, base, rec, meas), base


def _fitted(res: FitResult) -> Effect | None:
    return res.effect if isinstance(res, Fitted) else None


FIT_CASES: dict[str, Effect | None] = {
    "aps_fpn": ApsFpn(sigma_dn=5.0, seed=2),
    "exposure": Exposure(lag_us=2000.0, exposure_us=4000.0),
    "none": None,
}


def test_fpn_fitter_recovers_the_pattern() -> None:
    # measured (seed 97): sigma 5.39 for 5; map correlation 0.88
    rec, ctx, base = _fit_setup("aps_fpn", 97)
    e = _fitted(fit_aps_fpn(ctx))
    assert isinstance(e, ApsFpn)
    assert e.offset_dn is not None
    assert e.sigma_dn == pytest.approx(5.0, rel=0.3)
    true = ApsFpn(sigma_dn=5.0, seed=2).offsets_dn(rec.sensor.shape)
    assert np.corrcoef(true.ravel(), e.offset_dn.ravel())[0, 1] > 0.7
    # the corrected frames are closer to the light the events saw
    m = Model(base.contrast, base.bias, base.log_offset).with_effect(e)
    fixed = model_frames(m, rec.frames).images.astype(np.float64)
    clean = rec.frames.images.astype(np.float64) - true[None]
    assert np.abs(fixed - clean).mean() < 0.6 * np.abs(rec.frames.images - clean).mean()


def test_exposure_fitter_recovers_the_lag() -> None:
    rec, ctx, base = _fit_setup("exposure", 97)
    e = _fitted(fit_exposure(ctx))
    # measured (seed 97): 2180 us for 2000 (the workflow's bias correction takes it closer)
    assert isinstance(e, Exposure)
    assert e.exposure_us == 4000.0
    assert e.lag_us == pytest.approx(2000.0, rel=0.3)


def test_frame_fitters_see_nothing_when_nothing_is_hidden() -> None:
    # measured (seed 97): sigma 1.47 DN, lag 101 us. The DSNU estimator has a floor of about
    # 1.5 DN here: the interpolated frames put their own per-pixel misfit into the
    # simulations, which the measurement does not share. The gap decides (not named, see
    # test_gap.py test_nothing_hidden_names_nothing)
    rec, ctx, base = _fit_setup("none", 97)
    e = fit_aps_fpn(ctx)
    assert isinstance(e, NoEvidence) or (isinstance(e.effect, ApsFpn) and e.effect.sigma_dn < 2.5)
    x = fit_exposure(ctx)
    assert isinstance(x, NoEvidence) or \
        (isinstance(x.effect, Exposure) and abs(x.effect.lag_us) < 300.0)
    for res in (e, x):
        if isinstance(res, NoEvidence):
            assert res.reason  # the fitter says why


def test_the_simulation_is_driven_by_the_corrected_frames() -> None:
    """With the true map in the model the re-simulation sees the light the sensor saw: its
    events match a simulation of the clean frames, not of the frames with DSNU."""
    rec, _ctx, base = _fit_setup("aps_fpn", 97)
    true = ApsFpn(sigma_dn=5.0, seed=2).offsets_dn(rec.sensor.shape)
    st = SimSettings(dither=False, interpolation="linear")
    m = base.with_effect(ApsFpn(sigma_dn=5.0, offset_dn=true))
    clean = Frames(rec.frames.t_us, np.maximum(rec.frames.images.astype(np.float32)
                                               - true.astype(np.float32)[None], np.float32(0)),
                   rec.frames.exposure_us)
    a = simulate_model(m, rec, 3, st)
    b = simulate_model(base, replace(rec, frames=clean), 3, st)
    np.testing.assert_array_equal(a.events, b.events)


def test_a_sweep_of_lags_counts_the_windows_as_counting_anew() -> None:
    """The exposure fitter moves the frame times through its lags and updates the counts
    by the events that change window (``_lag_moves``): the counts must be those of counting
    every lag anew, also with repeated lags, events outside the frames and moves across
    more than one window."""
    from evcal.gap.frames import _apply_moves, _count_windows, _lag_moves  # noqa: PLC0415

    rng = np.random.default_rng(3)
    for _ in range(40):
        n_w, npix = int(rng.integers(2, 8)), int(rng.integers(1, 6))
        ft = np.cumsum(rng.integers(5, 40, n_w + 1)).astype(np.int64)
        n = int(rng.integers(0, 400))
        t = np.sort(rng.integers(ft[0] - 50, ft[-1] + 50, n)).astype(np.int64)
        pix = rng.integers(0, npix, n).astype(np.int32)
        p = rng.choice(np.array([-1, 1], np.int8), n)
        lags = np.sort(rng.integers(-60, 60, int(rng.integers(1, 12)))).astype(np.int64)
        P = np.zeros((n_w, npix), np.int32)
        E = np.zeros_like(P)
        _count_windows(t, pix, p, ft + lags[0], P, E)
        ev, win, start = _lag_moves(t, ft, lags)
        for i in range(lags.size):
            if i:
                _apply_moves(pix, p, ev, win, int(start[i]), int(start[i + 1]), n_w, P, E)
            P2, E2 = np.zeros_like(P), np.zeros_like(E)
            _count_windows(t, pix, p, ft + lags[i], P2, E2)
            np.testing.assert_array_equal(P, P2)
            np.testing.assert_array_equal(E, E2)


def test_no_pixel_with_a_fit_leaves_the_lag_by_light_unsaid() -> None:
    """A measurement in which no pixel has enough events for a fit (a sparse recording:
    dev1026 of the gap benchmark) has no lag of least residual to start the thirds' search
    from: the split by light says nothing (``None``) instead of raising, and the bandwidth
    fitter goes on without it."""
    from evcal.gap.fitters import fit_bandwidth
    from evcal.gap.frames import LAG_GRID, _lag_by_light, lag_residuals

    rec, ctx, _base = _fit_setup("none", 97)
    ev = rec.events
    _, first = np.unique(ev["y"].astype(np.int64) * rec.sensor.width + ev["x"],
                         return_index=True)
    silent = observe(rec.with_events(ev[np.sort(first)]))  # one event a pixel
    lags = LAG_GRID * 4000.0
    assert not np.isfinite(lag_residuals(silent, lags)).any()
    assert _lag_by_light(silent, ctx.sims, lags) is None
    res = fit_bandwidth(replace(ctx, meas=silent, whole=silent))
    assert isinstance(res, NoEvidence)
    assert res.reason
