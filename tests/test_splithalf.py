"""The split-half check of stated errors (issue 39, item 3): a factor by which an estimator's
errors are off is read from the recording's two halves without the truth, errors that are
right are left about as they are, and what the halves cannot measure is said, not guessed."""

from __future__ import annotations

import numpy as np
import pytest

import evcal
from evcal.calibration import Calibration, Special
from evcal.errors import ConfigError
from evcal.io import load_calibration
from evcal.recording import Recording
from evcal.sim.ideal import SimConfig, simulate_ideal
from evcal.splithalf import MIN_PIXELS, halves, scale_of, split_half_scale, with_scale


@pytest.fixture(scope="module")
def sim():
    return simulate_ideal(SimConfig(height=90, width=120, duration_s=3.0, seed=21,
                                    scene="astronaut"))


def _std_z(cal: Calibration, truth: dict, name: str) -> float:
    se = getattr(cal, f"stderr_{name}")
    m = cal.valid & (cal.special == Special.NORMAL) & np.isfinite(se) & (se > 0)
    return float(np.std((getattr(cal, name)[m] - truth[name][m]) / se[m]))


def _inflated(cal: Calibration, k_c: float, k_b: float) -> Calibration:
    return cal.replace(stderr_contrast=(cal.stderr_contrast * k_c).astype(np.float32),
                       stderr_bias=(cal.stderr_bias * k_b).astype(np.float32))


def test_the_halves_split_the_frames_and_their_events(sim):
    rec = sim.recording
    a, b = halves(rec)
    k = len(rec.frames)
    assert len(a.frames) + len(b.frames) == k + 1  # the middle frame in both
    assert a.frames.t_us[-1] == b.frames.t_us[0]
    for h in (a, b):
        t = h.events["t_us"]
        assert t.size
        assert t[0] >= h.frames.t_us[0]
        assert t[-1] <= h.frames.t_us[-1]
    assert a.n_events + b.n_events <= rec.n_events


def test_a_hidden_error_factor_is_recovered(sim):
    """An estimator whose errors are 2x (c) and 0.6x (b) what they are: the factors are read
    off its two halves, and the rescaled errors are calibrated again against the truth."""
    rec, truth = sim.recording, sim.truth

    def run(r: Recording, log_offset: float) -> Calibration:
        return _inflated(evcal.calibrate(r, "offei", log_offset=log_offset), 2.0, 0.6)

    full = run(rec, 30.0)
    assert _std_z(full, truth, "contrast") < 0.6
    assert _std_z(full, truth, "bias") > 1.4
    scale = split_half_scale(rec, full, run)
    assert scale.applied
    assert scale.pixels >= MIN_PIXELS
    # the honest errors' own halves scale (0.9-1.1 here) times the injected factors
    assert 0.40 < scale.contrast < 0.60
    assert 1.40 < scale.bias < 2.00
    fixed = with_scale(full, scale)
    for name in ("contrast", "bias"):
        assert 0.8 < _std_z(fixed, truth, name) < 1.25, name
    assert fixed.diagnostics.extra["error_scale"]["applied"] is True


def test_onei_is_checked_by_default_and_stays_calibrated(sim):
    """OnEI's errors are checked on its halves unless told not to; on a recording its error
    model fits, the check leaves them calibrated."""
    rec, truth = sim.recording, sim.truth
    cal = evcal.calibrate(rec, "onei")
    info = cal.diagnostics.extra["error_scale"]
    assert info["applied"]
    assert 0.75 < info["contrast"] < 1.33
    assert 0.75 < info["bias"] < 1.33
    for name in ("contrast", "bias"):
        assert 0.8 < _std_z(cal, truth, name) < 1.25, name
    plain = evcal.calibrate(rec, "onei", error_scale="none")
    assert "error_scale" not in plain.diagnostics.extra
    np.testing.assert_allclose(cal.stderr_contrast[cal.valid],
                               plain.stderr_contrast[cal.valid] * np.float32(info["contrast"]),
                               rtol=1e-5)
    np.testing.assert_array_equal(cal.contrast, plain.contrast)  # the estimates are the same
    # OffEI's errors come from its own residuals: not checked unless asked
    assert "error_scale" not in evcal.calibrate(rec, "offei").diagnostics.extra


def test_an_error_both_halves_share_is_not_taken_for_noise(sim):
    """A bias of every pixel alike cancels between the halves: the scale does not move."""
    rec = sim.recording
    a, b = (evcal.calibrate(h, "offei", log_offset=30.0) for h in halves(rec))
    base = scale_of(a, b)
    shifted = scale_of(a.replace(contrast=a.contrast + np.float32(0.05)),
                       b.replace(contrast=b.contrast + np.float32(0.05)))
    assert shifted.contrast == pytest.approx(base.contrast, rel=1e-3)


def test_too_little_evidence_keeps_the_errors_and_says_why(sim):
    rec = sim.recording
    a, b = (evcal.calibrate(h, "offei", log_offset=30.0) for h in halves(rec))
    few = np.zeros(a.shape, bool)
    few[:5, :20] = True  # 100 pixels
    scale = scale_of(a.replace(valid=a.valid & few), b.replace(valid=b.valid & few))
    assert not scale.applied
    assert "needed" in scale.reason
    assert (scale.contrast, scale.bias) == (1.0, 1.0)
    out = with_scale(a, scale)
    np.testing.assert_array_equal(out.stderr_contrast, a.stderr_contrast)
    assert out.diagnostics.extra["error_scale"]["reason"] == scale.reason
    # an estimator without stated errors (DI) has nothing to check
    di = evcal.calibrate(rec, "di", error_scale="split-half")
    assert di.diagnostics.extra["error_scale"]["applied"] is False


def test_a_bad_mode_is_refused(sim):
    with pytest.raises(ConfigError, match="error_scale"):
        evcal.calibrate(sim.recording, "onei", error_scale="halves")


def test_the_cli_writes_the_scale_into_the_file(tmp_path, sim, capsys):
    from evcal.cli import main
    from evcal.io.npz import write_npz

    src = tmp_path / "rec.npz"
    write_npz(sim.recording, src)
    out = tmp_path / "cal.npz"
    assert main(["calibrate", str(src), "--method", "onei", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    cal = load_calibration(out)
    info = cal.diagnostics.extra["error_scale"]
    assert info["method"] == "split-half"
    assert info["pixels"] >= MIN_PIXELS
    assert f"scaled by c {info['contrast']:.3f}" in printed  # the user is told
    out2 = tmp_path / "cal2.npz"
    assert main(["calibrate", str(src), "--method", "onei", "--out", str(out2),
                 "--error-scale", "none"]) == 0
    assert "error_scale" not in load_calibration(out2).diagnostics.extra
    # OffEI corrected by a gap model: the halves would need the correction too; refused
    assert main(["calibrate", str(src), "--out", str(tmp_path / "c3.npz"), "--model",
                 str(tmp_path / "report.json"), "--error-scale", "split-half"]) == 2
