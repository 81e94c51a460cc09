"""Event integration, frame-pair selection and the evaluation against DI."""

from __future__ import annotations

import numpy as np
import pytest

from evcal.calibration import Calibration
from evcal.events import EventError, SensorSize, empty_events, make_events
from evcal.metrics import image_metrics
from evcal.reconstruct import (
    FALLBACK_LOG_OFFSET,
    EvaluationError,
    evaluate,
    integrate,
    select_pairs,
    to_intensity,
)
from evcal.recording import Frames, Recording
from evcal.sim.ideal import SimConfig, SimResult, simulate_ideal
from evcal.solver import log_intensity

SHAPE = (48, 64)


@pytest.fixture(scope="module")
def sim() -> SimResult:
    # 3 s at 25 Hz: 76 frames, ~240k events; < 1 s to simulate
    cfg = SimConfig(height=SHAPE[0], width=SHAPE[1], duration_s=3.0, internal_rate_hz=500.0,
                    seed=7)
    return simulate_ideal(cfg)


def true_calibration(sim: SimResult) -> Calibration:
    t = sim.truth
    return Calibration.uniform(SHAPE, method="truth", log_offset=t["log_offset"]).replace(
        contrast=t["contrast"], bias=t["bias"]
    )


# ----------------------------------------------------------------------------------------
# integrate / to_intensity


def test_integrate_by_hand() -> None:
    c = np.array([[0.2, 0.3, 0.1]])
    b = np.array([[0.05, -0.1, 0.0]])
    cal = Calibration.uniform((1, 3)).replace(contrast=c, bias=b)
    # pixel 0: ON, ON, OFF -> c + 3b ... SP = 1, SE = 3; pixel 1: OFF -> -(c - b); pixel 2: none
    ev = make_events([0, 1, 2, 3], [0, 0, 1, 0], [0, 0, 0, 0], [1, 1, -1, -1])
    start = np.array([[1.0, 2.0, 3.0]])
    L = integrate(start, ev, cal)  # noqa: N806
    # the maps are stored as float32; the sums are done in float64
    c32, b32 = (m.astype(np.float32).astype(np.float64) for m in (c, b))
    expected = [1.0 + c32[0, 0] * 1 + b32[0, 0] * 3, 2.0 - c32[0, 1] + b32[0, 1], 3.0]
    np.testing.assert_allclose(L[0], expected, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(integrate(start, empty_events(), cal), start)


def test_integrate_errors() -> None:
    cal = Calibration.uniform((2, 3))
    with pytest.raises(ValueError, match=r"log_start has shape \(3, 2\).*\(2, 3\)"):
        integrate(np.zeros((3, 2)), empty_events(), cal)
    outside = make_events([0], [3], [0], [1])
    with pytest.raises(EventError, match="outside the 3x2 sensor"):
        integrate(np.zeros((2, 3)), outside, cal)


def test_to_intensity_inverts_log_intensity_and_clips() -> None:
    img = np.arange(256, dtype=np.uint8).reshape(16, 16)
    np.testing.assert_allclose(to_intensity(log_intensity(img, 30.0), 30.0), img, atol=1e-9)
    out = to_intensity(np.log(np.array([1.0, 20.0, 1000.0])), 30.0)
    np.testing.assert_array_equal(out, [0.0, 0.0, 255.0])


def test_true_calibration_integrates_exactly(sim: SimResult) -> None:
    """With the true maps, ``L_j - (L_k + c SP + b SE) = r_j - r_k``: the sub-threshold residual.

    Both residuals lie in ``(-(c - b), c + b)``, so per pixel ``|error| < 2c`` (up to the 8-bit
    quantisation of the frames, < 0.5 / (8 + 30) in log units); on average it is about
    ``c / 2`` (0.1 here), and DI's is over twice that.
    """
    rec, cal = sim.recording, true_calibration(sim)
    off = sim.truth["log_offset"]
    di = Calibration.uniform(SHAPE, 0.1, 0.0)
    f = rec.frames
    assert f is not None
    bounds = np.searchsorted(rec.events["t_us"], f.t_us)
    quant = 0.5 / (8.0 + off)
    c = sim.truth["contrast"].astype(np.float64)
    mae, mae_di, violations = [], [], 0
    for k in range(0, len(f) - 5, 5):
        j = k + 5
        ev = rec.events[bounds[k]:bounds[j]]
        target = log_intensity(f.images[j], off)
        err = integrate(log_intensity(f.images[k], off), ev, cal) - target
        err_di = integrate(log_intensity(f.images[k], off), ev, di) - target
        violations += int((np.abs(err) >= 2 * c + 2 * quant).sum())
        mae.append(np.abs(err).mean())
        mae_di.append(np.abs(err_di).mean())
    # an event rounded onto a frame time is counted in the next window: allow a handful
    assert violations <= 1e-3 * len(mae) * c.size
    assert np.mean(mae) < 0.6 * c.mean()  # ~0.11 for c ~ 0.2
    assert np.mean(mae_di) > 2 * np.mean(mae)


# ----------------------------------------------------------------------------------------
# select_pairs


FT = np.arange(0, 101, 10, dtype=np.int64)  # 11 frames, 0..100 µs


def test_select_pairs_frames_per_image() -> None:
    ev = np.arange(100, dtype=np.int64)
    assert select_pairs(FT, ev, frames_per_image=3) == [(0, 3), (3, 6), (6, 9)]
    assert select_pairs(FT, ev, frames_per_image=10) == [(0, 10)]
    assert select_pairs(FT, ev, frames_per_image=11) == []
    # frames_per_image takes precedence over the default events_per_image; no events needed
    assert select_pairs(FT, np.zeros(0, np.int64), frames_per_image=5) == [(0, 5), (5, 10)]
    # skip 25 µs: the first frame at least 25 µs after frame 0 is frame 3 (t = 30)
    assert select_pairs(FT, ev, frames_per_image=2, skip_s=25e-6) == [(3, 5), (5, 7), (7, 9)]
    assert select_pairs(FT, ev, frames_per_image=2, skip_s=30e-6)[0] == (3, 5)


def test_select_pairs_events_per_image() -> None:
    rng = np.random.default_rng(0)
    ev = np.sort(rng.integers(0, 105, 400)).astype(np.int64)
    for need in (1, 7, 40, 90, 200):
        pairs = select_pairs(FT, ev, events_per_image=need)
        counts = lambda k, j: int(((ev >= FT[k]) & (ev < FT[j])).sum())  # noqa: E731
        assert pairs, need
        assert pairs[0][0] == 0
        for (k, j), nxt in zip(pairs, pairs[1:] + [None], strict=False):
            assert j > k
            assert counts(k, j) >= need  # enough events ...
            assert counts(k, j - 1) < need or j - 1 == k  # ... at the first frame that has them
            if nxt is not None:
                assert nxt[0] == j  # non-overlapping, contiguous
        # the last dropped pair: not enough events left after the last end
        k_last = pairs[-1][1]
        assert counts(k_last, len(FT) - 1) < need


def test_select_pairs_events_per_image_by_hand() -> None:
    # 4 events in [0, 10), none in [10, 20), 4 in [20, 30), 1 in [30, 40), none after
    ev = np.array([0, 1, 2, 9, 20, 21, 22, 29, 35], np.int64)
    assert select_pairs(FT, ev, events_per_image=4) == [(0, 1), (1, 3)]
    assert select_pairs(FT, ev, events_per_image=5) == [(0, 3)]
    assert select_pairs(FT, ev, events_per_image=9) == [(0, 4)]
    assert select_pairs(FT, ev, events_per_image=10) == []
    assert select_pairs(FT, ev, events_per_image=4, skip_s=5e-6) == [(1, 3)]
    # events at a frame time belong after that frame: [t_k, t_j)
    assert select_pairs(np.array([0, 20]), np.array([20]), events_per_image=1) == []


def test_select_pairs_errors() -> None:
    ev = np.arange(10, dtype=np.int64)
    with pytest.raises(ValueError, match="give events_per_image or frames_per_image"):
        select_pairs(FT, ev, events_per_image=None)
    with pytest.raises(ValueError, match="frames_per_image=0"):
        select_pairs(FT, ev, frames_per_image=0)
    with pytest.raises(ValueError, match="events_per_image=0"):
        select_pairs(FT, ev, events_per_image=0)
    with pytest.raises(ValueError, match="skip_s"):
        select_pairs(FT, ev, skip_s=-1.0)
    with pytest.raises(ValueError, match="frame times must increase"):
        select_pairs(np.array([0, 10, 10]), ev)
    with pytest.raises(ValueError, match="event times must be sorted"):
        select_pairs(FT, ev[::-1])


# ----------------------------------------------------------------------------------------
# evaluate


def test_true_calibration_beats_di(sim: SimResult) -> None:
    rec, cal = sim.recording, true_calibration(sim)
    for kw in ({"frames_per_image": 5}, {"events_per_image": 20_000}):
        res = evaluate(rec, cal, **kw)
        s = res.summary()
        assert s["n_images"] == res.n_images >= 5
        assert s["gain_db"] > 3.0, (kw, s)  # ~5-7 dB on this scene
        assert s["calibrated"]["psnr"] > s["di"]["psnr"] + 3.0
        assert s["calibrated"]["ssim"] > s["di"]["ssim"]
        assert s["calibrated"]["ssim_paper"] > s["di"]["ssim_paper"]
        assert s["calibrated"]["rmse"] < s["di"]["rmse"]
        assert s["calibrated"]["psnr_paper"] == pytest.approx(2 * s["calibrated"]["psnr"])
        assert res.log_offset == sim.truth["log_offset"]


def test_evaluate_per_image_matches_manual(sim: SimResult) -> None:
    rec, cal = sim.recording, true_calibration(sim)
    f = rec.frames
    assert f is not None
    res = evaluate(rec, cal, events_per_image=30_000, skip_s=0.5)
    assert res.per_image[0]["t_start_us"] >= f.t_us[0] + 500_000
    for prev, item in zip(res.per_image, res.per_image[1:], strict=False):
        assert item["k"] == prev["j"]
    item = res.per_image[1]
    k, j = item["k"], item["j"]
    ev = rec.events_between(int(f.t_us[k]), int(f.t_us[j]))
    assert item["n_events"] == ev.size >= 30_000
    assert (item["t_start_us"], item["t_end_us"]) == (int(f.t_us[k]), int(f.t_us[j]))
    off = sim.truth["log_offset"]
    recon = to_intensity(integrate(log_intensity(f.images[k], off), ev, cal), off)
    expected = image_metrics(recon, f.images[j].astype(np.float64))
    for name, value in expected.items():
        assert item["calibrated"][name] == pytest.approx(value, rel=1e-12)


def test_evaluate_di_against_itself_and_offset_fallback(sim: SimResult) -> None:
    # a uniform calibration does not say its offset (NaN): the fallback is used and noted
    di = Calibration.uniform(SHAPE, 0.1, 0.0)
    assert not di.log_offset_known
    res = evaluate(sim.recording, di, frames_per_image=10)
    assert res.log_offset == FALLBACK_LOG_OFFSET
    assert "used 30" in res.log_offset_note
    s = res.summary()
    assert s["gain_db"] == 0.0
    assert s["calibrated"] == s["di"]
    # an infinite or negative offset is not an offset
    for bad in (float("inf"), -1.0):
        with pytest.raises(ValueError, match="log_offset="):
            di.replace(log_offset=bad)
    assert evaluate(sim.recording, di, frames_per_image=10, log_offset=50.0).log_offset == 50.0


def test_an_offset_of_zero_is_honoured(sim: SimResult) -> None:
    # 0 is a legitimate offset (log of DN, as v2e uses), never "not estimated"
    zero = Calibration.uniform(SHAPE, 0.1, 0.0, log_offset=0.0)
    assert zero.log_offset_known
    res = evaluate(sim.recording, zero, frames_per_image=10)
    assert res.log_offset == 0.0
    assert res.log_offset_note == "from the calibration"
    assert evaluate(sim.recording, di_nan := Calibration.uniform(SHAPE), frames_per_image=10,
                    log_offset=0.0).log_offset == 0.0
    assert not di_nan.log_offset_known


def test_short_recordings_get_fewer_events_per_image(sim: SimResult) -> None:
    rec = sim.recording
    cal = Calibration.uniform(SHAPE, 0.1, 0.0, log_offset=30.0)
    res = evaluate(rec, cal, events_per_image=10 * rec.n_events)  # far more than it holds
    assert res.n_images >= 2
    assert "fewer than events_per_image" in res.params["events_per_image_note"]
    with pytest.raises(EvaluationError, match="no frame pair"):
        evaluate(rec, cal, events_per_image=10 * rec.n_events, adapt_events_per_image=False)


def test_evaluate_errors(sim: SimResult) -> None:
    rec = sim.recording
    cal = true_calibration(sim)
    no_frames = Recording(SensorSize(*SHAPE), rec.events[:100])
    with pytest.raises(EvaluationError, match="no frames \\(100 events\\)"):
        evaluate(no_frames, cal)
    with pytest.raises(
        EvaluationError,
        match=rf"76 frames and {rec.n_events} events .* asked events_per_image=500000",
    ):
        # ~240k events: not one window of 500k (and adapting the size is switched off)
        evaluate(rec, cal, adapt_events_per_image=False)
    one_frame = Recording(rec.sensor, rec.events, Frames(rec.frames.t_us[:1],
                                                         rec.frames.images[:1],
                                                         rec.frames.exposure_us[:1]))
    with pytest.raises(EvaluationError, match="1 frames .* frames_per_image=1"):
        evaluate(one_frame, cal, frames_per_image=1)
    with pytest.raises(EvaluationError,
                       match="calibration is 3x2, the recording's sensor is 64x48"):
        evaluate(rec, Calibration.uniform((2, 3)), frames_per_image=1)
    with pytest.raises(ValueError, match="log_offset=-1.0 must be"):
        evaluate(rec, cal, frames_per_image=1, log_offset=-1.0)


def test_invalid_pixels_are_integrated_with_the_valid_median() -> None:
    from evcal.calibration import Calibration  # noqa: PLC0415

    cal = Calibration.uniform((2, 3), 0.1, 0.0, log_offset=0.0)
    c = np.array([[0.2, 0.3, 0.1], [0.25, 0.1, 0.1]], np.float32)
    b = np.array([[0.01, 0.03, 0.0], [0.02, 0.0, 0.0]], np.float32)
    valid = np.array([[True, True, False], [True, False, False]])
    cal = cal.replace(contrast=c, bias=b, valid=valid)
    filled = cal.with_invalid_filled()
    np.testing.assert_allclose(filled.contrast, [[0.2, 0.3, 0.25], [0.25, 0.25, 0.25]])
    np.testing.assert_allclose(filled.bias, [[0.01, 0.03, 0.02], [0.02, 0.02, 0.02]])
    assert filled.contrast.dtype == np.float32
    assert cal.replace(valid=np.ones((2, 3), bool)).with_invalid_filled().contrast is c
    assert cal.replace(valid=np.zeros((2, 3), bool)).with_invalid_filled().contrast is c
