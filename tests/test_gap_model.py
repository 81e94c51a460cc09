"""The gap's base model: shrinkage by standard errors scaled to the recording
(evcal.gap.model.noise_scale)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from evcal.calibration import Calibration, OffEIDiagnostics
from evcal.gap import model as model_module
from evcal.gap.model import (
    Model,
    NoiseScale,
    SimSettings,
    _shrink,
    anchor,
    fit_base,
    noise_scale,
    simulate_model,
)
from evcal.gap.stats import observe
from evcal.offline import OffEIConfig, offei
from evcal.sim.ideal import SimConfig, simulate_ideal


@pytest.fixture(scope="module")
def ideal():
    """A small ideal recording (the recovery tests' scene and motion, 96x128, 4 s, 25 Hz)."""
    return simulate_ideal(SimConfig(height=96, width=128, duration_s=4.0, seed=3)).recording


def test_shrink_takes_the_errors_times_the_scale(ideal) -> None:
    """Errors twice as large with a quarter of the scale shrink exactly alike: the shrinkage
    depends on the scaled errors only."""
    cal = offei(ideal, OffEIConfig(log_offset=30.0))
    doubled = cal.replace(stderr_contrast=2 * cal.stderr_contrast,
                          stderr_bias=2 * cal.stderr_bias)
    for a, b in zip(_shrink(cal, 30.0, NoiseScale(contrast=4.0, bias=4.0)),
                    _shrink(doubled, 30.0), strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-6)
    # and a larger scale shrinks more: the maps' spread falls
    plain = _shrink(cal, 30.0)
    more = _shrink(cal, 30.0, NoiseScale(contrast=4.0, bias=4.0))
    v = cal.valid
    assert np.std(more[0][v]) < np.std(plain[0][v])
    assert np.std(more[1][v]) < np.std(plain[1][v])


def test_shrink_keeps_a_precisely_measured_threshold() -> None:
    """A pixel whose events are nearly all OFF has large, nearly equal errors of ``c`` and
    ``b`` but a precise OFF threshold ``c - b``: shrinkage keeps that threshold within
    THRESHOLD_LIMIT_SE of its standard error of the fit (v2e mix/gravel's busiest pixel: OFF
    0.011, c 0.126 +- 0.014, b 0.115 +- 0.013), while shrinking c and b each on its own
    pulls it to several times that. Pixels with uncorrelated errors shrink as before."""
    rng = np.random.default_rng(8)
    shape = (40, 50)
    c = rng.normal(0.2, 0.03, shape)
    b = rng.normal(0.0, 0.02, shape)
    se = np.full(shape, 0.01)
    rho = np.zeros(shape)
    c[7, 9], b[7, 9], rho[7, 9] = 0.126, 0.115, 0.99
    se_c, se_b = se.copy(), se.copy()
    se_c[7, 9], se_b[7, 9] = 0.014, 0.013
    cal = Calibration.uniform(shape, method="offei", log_offset=30.0).replace(
        contrast=c, bias=b, valid=np.ones(shape, bool), stderr_contrast=se_c,
        stderr_bias=se_b, diagnostics=OffEIDiagnostics(error_correlation=rho))
    c1, b1 = _shrink(cal, 30.0)
    c0, b0 = _shrink(cal.replace(diagnostics=OffEIDiagnostics()), 30.0)
    sc, sb = float(cal.stderr_contrast[7, 9]), float(cal.stderr_bias[7, 9])
    se_off = np.sqrt(sc**2 + sb**2 - 2 * 0.99 * sc * sb)
    off_fit = float(cal.contrast[7, 9]) - float(cal.bias[7, 9])
    assert abs((c1 - b1)[7, 9] - off_fit) <= model_module.THRESHOLD_LIMIT_SE * se_off + 1e-7
    assert (c0 - b0)[7, 9] > 3 * off_fit  # without the correlation: pulled far
    # its ON threshold, poorly measured, is still shrunk towards the population
    assert abs((c1 + b1)[7, 9] - 0.2) < abs(0.241 - 0.2)
    # uncorrelated pixels: the limit (3 standard errors of sqrt(2) x 0.01) binds on a few
    # of the population's far tail at most
    same = np.isclose(c1, c0, rtol=0, atol=1e-12) & np.isclose(b1, b0, rtol=0, atol=1e-12)
    assert same.mean() > 0.99


def test_offei_states_the_correlation_of_its_errors() -> None:
    """OffEI's ``diagnostics.error_correlation`` orders the pixels by how their errors of
    ``c`` and ``b`` correlate: on the ideal simulator (240x180, 10 s, seeds 7 and 0) the
    errors' correlation in bins of the stated one, -0.5..-0.2 / -0.2..0.2 / 0.2..0.5 / 0.5..1,
    was -0.34 / -0.08 / +0.09 / +0.43 (stated -0.28 / +0.07 / +0.37 / +0.64: here it
    overstates by up to 0.3); on v2e's ``none`` recordings it was within 0.03 (camera) and
    0.13 (gravel) of the errors' in every bin."""
    sim = simulate_ideal(SimConfig(height=96, width=128, duration_s=4.0, seed=7))
    cal = offei(sim.recording, OffEIConfig(log_offset=30.0))
    rho = cal.diagnostics.error_correlation
    v = cal.valid
    assert rho.shape == cal.shape
    assert np.isnan(rho[~v]).all()
    assert (np.abs(rho[v]) <= 1).all()
    r = rho[v]
    zc = (cal.contrast[v] - sim.truth["contrast"][v]) / cal.stderr_contrast[v]
    zb = (cal.bias[v] - sim.truth["bias"][v]) / cal.stderr_bias[v]
    found = []
    for lo, hi in ((-0.2, 0.2), (0.2, 0.5), (0.5, 1.01)):
        m = (r >= lo) & (r < hi)
        assert m.sum() > 100
        found.append(float(np.corrcoef(zc[m], zb[m])[0, 1]))
    assert found[0] < found[1] < found[2]
    assert found[2] > 0.25
    # in memory only: files and messages do not carry it
    assert "error_correlation" not in cal.diagnostics.to_dict()


def test_noise_scale_follows_the_errors_formula(ideal, monkeypatch) -> None:
    """Near 1 where the stated errors are calibrated; four times larger for the same fits
    with their errors halved, so the scaled errors, and the shrinkage, stay the same."""
    cfg = OffEIConfig(log_offset=30.0)
    cal = offei(ideal, cfg)
    base = Model(*_shrink(cal, 30.0), 30.0)
    scale = noise_scale(ideal, cfg, cal, base)
    assert scale.n_pixels >= 200
    assert scale.reason == ""
    # measured 0.96 / 0.93 (c / b; seeds 4 and 5 of the scene: 0.94 / 0.91, 0.93 / 0.93)
    assert 0.75 < scale.contrast < 1.3, scale
    assert 0.75 < scale.bias < 1.3, scale

    def halved(rec, config):
        fit = offei(rec, config)
        return fit.replace(stderr_contrast=fit.stderr_contrast / 2,
                           stderr_bias=fit.stderr_bias / 2)

    monkeypatch.setattr(model_module, "offei", halved)
    quarter = noise_scale(ideal, cfg, cal, base)
    assert quarter.contrast == pytest.approx(4 * scale.contrast, rel=1e-5)
    assert quarter.bias == pytest.approx(4 * scale.bias, rel=1e-5)


def test_too_few_pixels_keep_the_stated_errors() -> None:
    """96 pixels, at most 192 z-scores from the two simulations (183 here): fewer than 200,
    the stated errors are kept."""
    rec = simulate_ideal(SimConfig(height=8, width=12, duration_s=1.0, seed=1)).recording
    model = fit_base(rec, log_offset=30.0)
    assert model.noise_scale.contrast == model.noise_scale.bias == 1.0
    assert "pixels" in model.noise_scale.reason


def test_anchor_gives_pixels_without_a_fit_the_population_correction(ideal) -> None:
    """Pixels the measurement has no fit for keep the population's threshold, so they take
    the population's correction (the median over every pixel fitted in both), not that of
    the least active bin they share with the barely fitted pixels."""
    meas = observe(ideal)
    n_pix = meas.on.shape[1]
    # a third of the pixels without a usable window: no measured fit there
    cols = np.arange(n_pix) % 3 == 0
    usable = meas.usable.copy()
    usable[:, cols] = False
    meas = replace(meas, usable=usable, extra={}, shared={})
    base = fit_base(ideal, 30.0)
    settings = SimSettings()
    anchored, first = anchor(base, ideal, meas, 7, settings, max_iter=1)
    assert first is None  # one correction, not simulated again
    fm = model_module.block_fit(meas)
    assert not fm["ok"][cols].any()
    assert fm["ok"][~cols].mean() > 0.5
    # the anchor's own simulation (the same seed and settings) and its fits
    fs = model_module.block_fit(observe(simulate_model(base, ideal, 7, settings)))
    both = fm["ok"] & fs["ok"]
    lr_all = float(np.median(np.log(fm["c"][both] / fs["c"][both])))
    k = (anchored.contrast / base.contrast).ravel()
    np.testing.assert_allclose(k[cols], np.exp(np.clip(lr_all, -0.7, 0.7)), rtol=1e-9)
    # the fitted pixels follow their activity bins: not one factor for all
    assert np.ptp(k[~cols]) > 1e-3


@pytest.mark.parametrize(("contrast", "seed"), [(0.5, 5), (0.6, 2)])
def test_anchor_matches_unfitted_pixels_to_their_events(contrast, seed) -> None:
    """A sparse recording (a few events per pixel: OffEI fits none, so every pixel holds the
    fit's default threshold, 0.15): the anchored model's unfitted pixels fire as many events
    as the measured ones where the frames change slowly, and their thresholds move from the
    default to the truth: ``c`` within 10 %, ``b`` within 0.02 (the ideal sensor loses no
    events; the latent intensity between frames follows the motion, as in the workflow)."""
    rec = simulate_ideal(SimConfig(height=60, width=80, duration_s=1.0, contrast_mean=contrast,
                                   bias_mean=0.03, seed=seed)).recording
    base = fit_base(rec, 30.0)
    meas = observe(rec)
    unfit = model_module._quiet(meas)
    u = unfit.reshape(base.contrast.shape)
    assert unfit.mean() > 0.5
    assert abs(np.median(base.contrast[u]) / contrast - 1) > 0.5
    settings = SimSettings(interpolation="flow")
    anchored, _ = anchor(base, rec, meas, 3, settings)
    counted = model_module._counted(meas)
    n_meas = model_module._unfitted_counts(meas, counted, unfit)
    assert min(n_meas) >= model_module.COUNT_MATCH_MIN_EVENTS
    # another seed's simulation of the anchored model
    again = observe(simulate_model(anchored, rec, 4, settings))
    n_sim = model_module._unfitted_counts(again, counted, unfit)
    for s, m in zip(n_sim, n_meas, strict=True):
        # another seed: its Poisson noise and the anchor's tolerance (2 sigma) on top
        assert abs(s / m - 1) < 0.1
    assert abs(np.median(anchored.contrast[u]) / contrast - 1) < 0.1
    assert abs(np.median(anchored.bias[u]) - 0.03) < 0.02


def test_anchor_leaves_a_model_without_countable_unfitted_events_alone(ideal) -> None:
    """A dense recording whose unfitted pixels fire fewer than COUNT_MATCH_MIN_EVENTS events
    of a polarity in windows of slow change: no count match, the anchor as before (at most
    max_iter simulations, the unfitted pixels with the population's correction)."""
    meas = observe(ideal)
    counted = model_module._counted(meas)
    n_meas = model_module._unfitted_counts(meas, counted, model_module._quiet(meas))
    assert min(n_meas) < model_module.COUNT_MATCH_MIN_EVENTS
    calls = []
    real = model_module.simulate_model

    def counting(*a, **k):
        calls.append(1)
        return real(*a, **k)

    base = fit_base(ideal, 30.0)
    try:
        model_module.simulate_model = counting
        anchor(base, ideal, meas, 7, SimSettings(), max_iter=2)
    finally:
        model_module.simulate_model = real
    assert len(calls) <= 2


def test_the_anchors_fit_follows_the_thresholds_where_the_light_changes_slowly() -> None:
    """Under a slow motion a pixel fires in one frame interval of several: the fit over
    single intervals then follows the thresholds only in part, the anchor's fit over
    blocks of intervals (evcal.gap.stats.block_fit) in proportion. Thresholds twice as
    large (0.15 -> 0.3, the same scene, motion and seed) give a block fit's median at least
    1.75x as large, and nearer 2x than the single intervals' fit."""
    from evcal.gap.stats import _fit, block_fit
    from evcal.sim.scene import Trajectory

    medians = []
    for c in (0.15, 0.3):
        rec = simulate_ideal(SimConfig(height=60, width=80, duration_s=3.0, contrast_mean=c,
                                       bias_mean=0.0, seed=4,
                                       trajectory=Trajectory(speed=0.2, seed=4))).recording
        obs = observe(rec)
        one, blocks = _fit(obs), block_fit(obs)
        assert blocks["frames"] == 5
        medians.append([float(np.median(f["c"][f["ok"]])) for f in (one, blocks)])
    ratio_one, ratio_blocks = np.array(medians[1]) / np.array(medians[0])
    assert ratio_blocks >= 1.75
    assert abs(ratio_blocks - 2.0) < abs(ratio_one - 2.0) - 0.2


def test_base_maps_keep_the_sensors_spread_where_the_fit_cannot_say() -> None:
    """Shrunk maps hold one threshold in every pixel without a fit; the base model adds one
    fixed draw of what the fit does not know of each pixel, so its maps spread as the
    sensor's do (the truth's standard deviation of c and b within 25 %, where the shrunk
    maps' c falls below 70 % of it on this short recording, a third of its pixels without
    a fit), the same draw on every run, and the pixels the fit measures well stay near
    their fits."""
    res = simulate_ideal(SimConfig(height=60, width=80, duration_s=1.0, contrast_mean=0.25,
                                   contrast_std=0.05, bias_std=0.015, seed=12))
    rec = res.recording
    c_true = np.asarray(res.truth["contrast"])
    b_true = np.asarray(res.truth["bias"])
    cal = offei(rec, OffEIConfig(window_frames=5, log_offset=30.0))
    c_shrunk, b_shrunk = _shrink(cal, 30.0)
    assert np.std(c_shrunk) < 0.7 * np.std(c_true)
    base = fit_base(rec, 30.0)
    for x, shrunk, truth in ((base.contrast, c_shrunk, c_true), (base.bias, b_shrunk, b_true)):
        assert abs(np.std(x) / np.std(truth) - 1) < 0.25
        assert abs(np.std(x) - np.std(truth)) < abs(np.std(shrunk) - np.std(truth))
    again = fit_base(rec, 30.0)
    np.testing.assert_array_equal(base.contrast, again.contrast)
    # pixels measured better than the population spreads move little from their shrunk value
    se = cal.stderr_contrast
    sharp = cal.valid & (se < 0.3 * np.std(c_true))
    if sharp.sum() >= 20:
        assert np.median(np.abs(base.contrast - c_shrunk)[sharp]) < 0.3 * np.std(c_true)
