"""Posterior maps (issue 39, item 1): OffEI's estimates pulled toward the population recover
the true maps better than the raw ones, their stated errors stay calibrated, special and
invalid pixels keep their own values, and the file says which estimate it holds."""

from __future__ import annotations

import numpy as np
import pytest

import evcal
from evcal.calibration import Special
from evcal.errors import ConfigError
from evcal.posterior import estimate_of, posterior_maps
from evcal.sim.ideal import SimConfig, simulate_ideal


@pytest.fixture(scope="module", params=[("astronaut", 11), ("coffee", 12)])
def fitted(request):
    scene, seed = request.param
    sim = simulate_ideal(SimConfig(height=90, width=120, duration_s=3.0, seed=seed,
                                   scene=scene))
    cal = evcal.offei(sim.recording)
    return sim, cal, posterior_maps(cal)


def _rmse(a, t, m):
    return float(np.sqrt(np.mean((a[m] - t[m]) ** 2)))


def test_the_posterior_recovers_the_truth_better(fitted):
    sim, raw, post = fitted
    tc, tb = sim.truth["contrast"], sim.truth["bias"]
    m = raw.valid & (raw.special == Special.NORMAL)
    assert m.sum() > 2000
    # measured 0.84-0.87 (c) and 0.87-0.89 (b) on these and other scenes and seeds
    assert _rmse(post.contrast, tc, m) < 0.95 * _rmse(raw.contrast, tc, m)
    assert _rmse(post.bias, tb, m) < 0.95 * _rmse(raw.bias, tb, m)


def test_its_stated_errors_stay_calibrated(fitted):
    sim, raw, post = fitted
    m = raw.valid & (raw.special == Special.NORMAL)
    for name, truth in (("contrast", sim.truth["contrast"]), ("bias", sim.truth["bias"])):
        est, se = getattr(post, name), getattr(post, f"stderr_{name}")
        z = (est[m] - truth[m]) / se[m]
        assert 0.8 < float(np.std(z)) < 1.25, name
        # and they are smaller than the raw ones: the population adds information
        assert np.all(se[m] <= getattr(raw, f"stderr_{name}")[m] + 1e-7)


def test_special_and_invalid_pixels_keep_their_own_values(fitted):
    _, raw, post = fitted
    keep = ~(raw.valid & (raw.special == Special.NORMAL))
    assert keep.any()
    for name in ("contrast", "bias", "stderr_contrast", "stderr_bias"):
        np.testing.assert_array_equal(getattr(post, name)[keep], getattr(raw, name)[keep])
    for name in ("valid", "reason", "special", "n_events"):
        np.testing.assert_array_equal(getattr(post, name), getattr(raw, name))


def test_planted_hot_pixels_are_not_pulled_in():
    cfg = SimConfig(height=60, width=80, duration_s=3.0, seed=5)
    sim = simulate_ideal(cfg)
    cal = evcal.offei(sim.recording)
    hot = cal.special == Special.HOT
    # make some pixels special by hand: their values must come out as they went in
    rng = np.random.default_rng(0)
    idx = rng.choice(np.flatnonzero(cal.valid), 20, replace=False)
    special = cal.special.copy()
    special.flat[idx] = Special.COLD
    cal = cal.replace(special=special)
    post = posterior_maps(cal)
    np.testing.assert_array_equal(post.contrast.flat[idx], cal.contrast.flat[idx])
    np.testing.assert_array_equal(post.contrast[hot], cal.contrast[hot])


def test_the_file_says_it_holds_the_posterior(fitted, tmp_path):
    _, raw, post = fitted
    assert estimate_of(raw) == "raw"
    assert estimate_of(post) == "posterior"
    back = evcal.load_calibration(evcal.save_calibration(post, tmp_path / "p.npz"))
    assert estimate_of(back) == "posterior"
    assert back.diagnostics.extra["posterior"]["bins"] >= 1
    np.testing.assert_array_equal(back.contrast, post.contrast)
    with pytest.raises(ConfigError, match="already"):
        posterior_maps(post)


def test_only_calibrated_errors_are_used():
    sim = simulate_ideal(SimConfig(height=24, width=32, duration_s=1.0, seed=1))
    cal = evcal.calibrate(sim.recording, "offe")  # no stated error of c
    with pytest.raises(ConfigError, match="offe does not"):
        posterior_maps(cal)
    onei = evcal.calibrate(sim.recording, "onei")  # calibrated (evcal.onei.stderr)
    assert estimate_of(posterior_maps(onei)) == "posterior"


def test_a_calibration_with_few_or_no_valid_pixels_is_left_alone():
    sim = simulate_ideal(SimConfig(height=24, width=32, duration_s=1.0, seed=1))
    cal = evcal.offei(sim.recording)
    none = cal.replace(valid=np.zeros_like(cal.valid))
    post = posterior_maps(none)
    np.testing.assert_array_equal(post.contrast, none.contrast)
    few = posterior_maps(cal)  # 768 pixels: fewer bins, never an error
    assert np.isfinite(few.contrast[cal.valid]).all()


def test_calibrate_posterior_on_the_command_line(tmp_path):
    from evcal import cli
    from evcal.io import write_recording

    sim = simulate_ideal(SimConfig(height=40, width=50, duration_s=2.0, seed=2))
    path = write_recording(sim.recording, tmp_path / "sim.npz")
    out = tmp_path / "cal.npz"
    assert cli.main(["calibrate", str(path), "--out", str(out), "--posterior", "-q"]) == 0
    assert estimate_of(evcal.load_calibration(out)) == "posterior"
    assert cli.main(["calibrate", str(path), "--out", str(out), "--method", "offe",
                     "--posterior", "-q"]) == 2


def test_a_pixel_without_a_stated_error_keeps_its_own_estimate():
    """An infinite or NaN standard error gives nothing to weigh the pixel's estimate by:
    it keeps it and its error (no NaN leaks into the maps), and such pixels do not enter
    the priors; the pixels with one are pulled as before."""
    from evcal.calibration import Calibration
    from evcal.posterior import posterior_priors

    rng = np.random.default_rng(5)
    shape = (40, 50)
    se = rng.uniform(0.005, 0.03, shape).astype(np.float32)
    est = rng.normal(0.2, 0.03, shape).astype(np.float32)
    se[0, 0], se[0, 1] = np.nan, np.inf
    est[0, 0], est[0, 1] = 0.9, 0.01  # far from the population: they would move the most
    cal = Calibration.uniform(shape, method="offei", log_offset=30.0).replace(
        contrast=est, stderr_contrast=se)
    prior = posterior_priors(cal).contrast
    assert prior is not None
    assert prior.pixels.sum() == est.size - 2
    post = posterior_maps(cal)
    np.testing.assert_array_equal(post.contrast[0, :2], est[0, :2])
    assert np.isinf(post.stderr_contrast[0, :2]).all()
    assert np.isfinite(post.contrast).all()
    moved = np.abs(post.contrast - est)
    moved[0, :2] = 0.0
    assert (moved > 0).mean() > 0.99


def _correlated_estimates(rho: float, seed: int = 9, shape: tuple[int, int] = (120, 160)):
    """True maps drawn from a population and estimates of them whose errors of c and b
    correlate by ``rho`` with stated errors that are right (OffEI's diagnostics carry the
    correlation, as its fit states it)."""
    from evcal.calibration import Calibration, OffEIDiagnostics

    rng = np.random.default_rng(seed)
    tc = rng.normal(0.2, 0.02, shape)
    tb = rng.normal(0.0, 0.01, shape)
    se_c = rng.uniform(0.005, 0.04, shape)
    se_b = se_c * rng.uniform(0.6, 1.0, shape)
    z1, z2 = rng.standard_normal(shape), rng.standard_normal(shape)
    ec = se_c * z1
    eb = se_b * (rho * z1 + np.sqrt(1 - rho ** 2) * z2)
    diag = OffEIDiagnostics(error_correlation=np.full(shape, rho, np.float32))
    cal = Calibration.uniform(shape, method="offei", log_offset=30.0).replace(
        contrast=(tc + ec).astype(np.float32), bias=(tb + eb).astype(np.float32),
        stderr_contrast=se_c.astype(np.float32), stderr_bias=se_b.astype(np.float32),
        diagnostics=diag)
    return cal, tc, tb


def test_correlated_errors_pull_c_and_b_together():
    """Where a pixel's errors of c and b correlate, the joint pull (by their covariance)
    recovers both maps better than pulling each alone, and its stated errors stay
    calibrated; without a stated correlation the pull is each map's alone."""
    from evcal.calibration import OffEIDiagnostics

    cal, tc, tb = _correlated_estimates(0.8)
    joint = posterior_maps(cal)
    alone = posterior_maps(cal.replace(diagnostics=OffEIDiagnostics()))
    assert joint.diagnostics.extra["posterior"]["joint"] is True
    assert alone.diagnostics.extra["posterior"]["joint"] is False
    m = np.ones(tc.shape, bool)
    raw_c, raw_b = _rmse(cal.contrast, tc, m), _rmse(cal.bias, tb, m)
    j_c, j_b = _rmse(joint.contrast, tc, m), _rmse(joint.bias, tb, m)
    a_c, a_b = _rmse(alone.contrast, tc, m), _rmse(alone.bias, tb, m)
    assert j_c < a_c < raw_c
    assert j_b < a_b < raw_b
    assert j_b < 0.97 * a_b  # b's error is mostly c's here: the joint pull takes it out
    # stated errors: calibrated as the one-map pull's are (whose priors of the noisiest
    # bins are themselves noisy: 0.97-1.22 for b over seeds 9-12 of this draw, the same both
    # ways)
    for name, t in (("contrast", tc), ("bias", tb)):
        z_j = float(np.std((getattr(joint, name) - t) / getattr(joint, f"stderr_{name}")))
        z_a = float(np.std((getattr(alone, name) - t) / getattr(alone, f"stderr_{name}")))
        assert 0.9 < z_j < 1.15, name
        assert abs(z_j - z_a) < 0.05, name
    # no correlation: the joint pull is the one-map pull
    cal0, _, _ = _correlated_estimates(0.0)
    j0 = posterior_maps(cal0)
    a0 = posterior_maps(cal0.replace(diagnostics=OffEIDiagnostics()))
    for name in ("contrast", "bias", "stderr_contrast", "stderr_bias"):
        np.testing.assert_allclose(getattr(j0, name), getattr(a0, name), rtol=1e-5,
                                   atol=1e-7)
