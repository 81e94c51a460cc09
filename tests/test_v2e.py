"""evcal on recordings made by an independent simulator: v2e (tests/data/v2e, made by
scripts/v2e_data/generate.py at a pinned v2e commit; truth = v2e's own per-pixel thresholds).

64x48, 3 s, 25 Hz APS frames, fast textured motion with still parts; v2e's log is ln(DN)
above 20 DN and every frame is above 25 DN, so the true log offset is 0.
"""

from __future__ import annotations

import hashlib
import json
from functools import cache
from pathlib import Path

import numpy as np
import pytest

from evcal.calibration import Calibration
from evcal.io import open_recording
from evcal.offline import OffEIConfig, offei
from evcal.reconstruct import evaluate
from evcal.recording import Recording

DATA = Path(__file__).parent / "data" / "v2e"
MANIFEST = json.loads((DATA / "manifest.json").read_text())
SCENES = tuple(MANIFEST["scenes"])


@cache
def load(case: str, scene: str) -> tuple[Recording, np.ndarray, np.ndarray]:
    path = DATA / f"{case}_{scene}.npz"
    rec = open_recording(path)
    with np.load(path) as z:
        return rec, z["truth_contrast"].astype(np.float64), z["truth_bias"].astype(np.float64)


def test_every_recording_is_what_the_manifest_says() -> None:
    assert len(MANIFEST["recordings"]) == 24
    for item in MANIFEST["recordings"]:
        path = DATA / item["file"]
        assert hashlib.sha256(path.read_bytes()).hexdigest() == item["sha256"], item["file"]
        rec, tc, tb = load(item["case"], item["scene"])
        assert rec.n_events == item["n_events"]
        assert len(rec.frames) == item["n_frames"] == 75
        assert rec.sensor.shape == tc.shape == tb.shape == (48, 64)
        # v2e's thresholds: ON = c + b, OFF = c - b around 0.2
        assert 0.15 < np.median(tc) < 0.25
        assert np.all(tc - np.abs(tb) > 0)


@pytest.mark.parametrize("scene", SCENES)
def test_offei_recovers_v2e_thresholds_at_offset_zero(scene: str) -> None:
    """Measured: c RMSE 0.010-0.016 over valid pixels (truth spread 0.021), 72-100 % valid."""
    rec, tc, tb = load("none", scene)
    cal = offei(rec, OffEIConfig(log_offset=0.0))
    v = cal.valid
    assert v.mean() > 0.6
    assert np.sqrt(np.mean((cal.contrast[v] - tc[v]) ** 2)) < 0.02
    assert np.sqrt(np.mean((cal.bias[v] - tb[v]) ** 2)) < 0.006


@pytest.mark.parametrize("scene", SCENES)
def test_evaluate_at_offset_zero_ranks_truth_offei_and_di(scene: str) -> None:
    """An explicit offset 0 is honoured; the true maps beat DI (measured by 7-11 dB) and OffEI
    comes within 0.5 dB of them (measured -0.2..+0.05 dB)."""
    rec, tc, tb = load("none", scene)
    cal = offei(rec, OffEIConfig(log_offset=0.0))
    assert cal.log_offset == 0.0
    truth = cal.replace(contrast=tc.astype(cal.contrast.dtype),
                        bias=tb.astype(cal.bias.dtype), valid=np.ones(tc.shape, bool))
    r_true = evaluate(rec, truth)
    r_off = evaluate(rec, cal)
    assert r_true.log_offset == 0.0
    assert r_true.log_offset_note == "from the calibration"
    s_true, s_off = r_true.summary(), r_off.summary()
    assert s_true["calibrated"]["psnr"] > s_true["di"]["psnr"] + 5.0
    assert s_off["calibrated"]["psnr"] > s_true["calibrated"]["psnr"] - 0.5
    assert r_off.params["filled_invalid_pixels"] == int((~cal.valid).sum())


def test_unknown_offset_is_not_zero() -> None:
    """A uniform calibration that does not say its offset (NaN) is integrated with the
    fallback and says so; an explicit 0 is used as 0."""
    rec, tc, _ = load("none", SCENES[0])
    unknown = Calibration.uniform(tc.shape, 0.2, 0.0, method="di", log_offset=float("nan"))
    r = evaluate(rec, unknown)
    assert r.log_offset == 30.0
    assert "nan" in r.log_offset_note
    zero = Calibration.uniform(tc.shape, 0.2, 0.0, method="di", log_offset=0.0)
    assert evaluate(rec, zero).log_offset == 0.0


@pytest.mark.parametrize("scene", SCENES)
def test_onei_on_v2e(scene: str) -> None:
    """The still first 0.4 s once made the online offset criterion all-NaN and crashed OnEI
    (ValueError from nanargmin); now it waits for windows it can judge. With the true offset
    the online c RMSE measured 0.020-0.028 (1.6-2.2x offline OffEI on 3 s of data, one large
    buffer)."""
    from evcal.online import OnEIConfig, onei  # noqa: PLC0415

    rec, tc, _ = load("none", scene)
    auto = onei(rec, OnEIConfig(log_offset="auto"))
    assert np.isfinite(auto.log_offset)
    assert auto.log_offset >= 0
    given = onei(rec, OnEIConfig(log_offset=0.0))
    v = given.valid
    assert v.mean() > 0.8
    assert np.sqrt(np.mean((given.contrast[v] - tc[v]) ** 2)) < 0.035


def test_service_defaults_on_v2e_at_offset_zero() -> None:
    """The service's OnEI (its default config: offset estimated online, equations over 5 frame
    intervals; test_service_e2e shows the live service computes exactly ``onei``) against
    offline OffEI with default options, c RMSE over the pixels both trust: each within 1.5x.
    Measured: 1.33, 1.32, 1.11, 1.48x; with ``--history 1`` 1.23, 1.18, 1.11, 1.21x (gravel's
    3 s are two paper-sized large buffers: the history keeps the first). Was 1.05, 1.35,
    1.11, 1.69x when the first offset estimate was taken from the 33-59 pixels busy in the
    still first frames (64-400 DN for a true 0): its correction 50 frames later restarted the
    estimate from one large buffer.
    """
    from dataclasses import replace  # noqa: PLC0415

    from evcal.online import onei  # noqa: PLC0415
    from evcal.service.core import ServiceConfig  # noqa: PLC0415

    ratios, with_history = [], []
    for scene in SCENES:
        rec, tc, _ = load("none", scene)
        off = offei(rec)
        for cfg, out in ((ServiceConfig().onei, ratios),
                         (replace(ServiceConfig().onei, history=1.0), with_history)):
            live = onei(rec, cfg)
            v = live.valid & off.valid
            assert live.valid.mean() > 0.9
            assert v.mean() > 0.8
            est = live.diagnostics.log_offset_estimation
            assert est["method"] == "auto"
            assert est["pixels"] >= 0.05 * tc.size

            def rmse(cal: Calibration, v: np.ndarray = v, tc: np.ndarray = tc) -> float:
                return float(np.sqrt(np.mean((cal.contrast[v] - tc[v]) ** 2)))

            out.append(rmse(live) / rmse(off))
    assert max(ratios) < 1.5, ratios
    assert max(with_history) < 1.3, with_history
    assert sum(with_history) < sum(ratios), (with_history, ratios)


def test_model_corrected_offei_under_v2e_shot_noise() -> None:
    """``calibrate --model`` with shot noise named: the measurement and the simulations with
    the effect are cleaned (support by a same-polarity neighbour within 10 ms either side,
    and no events where the frames show less than a tenth of a threshold of change), then the
    bias removed. The model: v2e's 2 Hz shot noise falls to 0.5 Hz at white
    (scripts/v2e_data/README.md), 1.35 Hz at these scenes' typical 100 DN, which evcal's 1/I
    law gives with ref_dn 100 (the gap workflow fits its own: docs/GAP.md has both). c RMSE
    against the same scene without noise, measured 1.28, 1.19, 1.14, 1.28x (plain OffEI 2.36,
    1.75, 1.82, 1.71x; with the plain background-activity filter 1.35-1.49x). What remains
    is variance of the noise events the filter cannot tell from an edge's: the corrected
    median c / true c is within 3 % of the noise-free fit's."""
    from evcal.gap.correct import model_corrected  # noqa: PLC0415
    from evcal.sim.effects import ShotNoise  # noqa: PLC0415

    ratios, plain = [], []
    for scene in SCENES:
        clean, tc, _ = load("none", scene)
        noisy = load("shot_noise", scene)[0]
        cfg = OffEIConfig(log_offset=0.0)

        def rmse(cal: Calibration, tc: np.ndarray = tc) -> float:
            v = cal.valid
            return float(np.sqrt(np.mean((cal.contrast[v] - tc[v]) ** 2)))

        fit_clean = offei(clean, cfg)
        ref = rmse(fit_clean)
        cor = model_corrected(noisy, [ShotNoise(rate_hz=1.35, ref_dn=100.0)], cfg)
        mc = cor.diagnostics.model_correction
        assert mc["denoise_us"] == 10_000
        assert 0.85 < mc["denoise_kept_fraction"] < 0.99
        v, w = cor.valid, fit_clean.valid
        assert abs(np.median(cor.contrast[v] / tc[v])
                   - np.median(fit_clean.contrast[w] / tc[w])) < 0.03
        ratios.append(rmse(cor) / ref)
        plain.append(rmse(offei(noisy, cfg)) / ref)
    assert max(ratios) <= 1.3, ratios
    assert all(r < p for r, p in zip(ratios, plain, strict=True)), (ratios, plain)


@cache
def gap_run(case: str, scene: str):  # noqa: ANN201 - a GapResult
    from evcal.gap.workflow import GapConfig, run_gap  # noqa: PLC0415

    return run_gap(load(case, scene)[0], GapConfig(max_effects=3, n_seeds=3, seed=1))


@pytest.mark.slow
def test_gap_names_v2e_timestamp_scheme_and_nothing_else_when_nothing_is_hidden() -> None:
    """v2e's 2 kHz steps (500 us) with frames 230 us after a step: named as
    timestamp_quantisation, step 500, phase 270; gap measured 436 -> 1.1 (camera; the other
    scenes 0.8, 0.4 and 3.1, see the closing note of issue 9)."""
    res = gap_run("none", "camera")
    assert res.named_effects == ["timestamp_quantisation"]
    q = res.steps[0].effect.parameters()
    assert q["step_us"] == 500.0
    # the phase is the most common residue of integer-µs event times: within one tick
    assert q["phase_us"] == pytest.approx(270.0, abs=1.0)
    assert res.final.gap <= 3.0


@pytest.mark.slow
def test_gap_names_v2e_shot_noise_first_among_sensor_effects() -> None:
    res = gap_run("shot_noise", "camera")
    sensor = [n for n in res.named_effects if n != "timestamp_quantisation"]
    assert sensor[:1] == ["shot_noise"], res.named_effects
    assert res.final.gap < 0.02 * res.initial.gap


@pytest.mark.slow
def test_gap_names_v2e_refractory_period_through_its_timestamp_slots() -> None:
    """v2e's 2 ms refractory period shows only in the slots of its 500 us steps (their
    number comes from the counts before the dead time): named after the timestamp scheme,
    with the dead time applied to the stamps. Measured: 2000 us (delay) on camera, gap 37.9
    -> 1.0; the other scenes in docs/GAP.md."""
    res = gap_run("refractory", "camera")
    assert res.named_effects[0] == "timestamp_quantisation"
    sensor = [s.effect for s in res.steps if s.effect.name != "timestamp_quantisation"]
    assert [e.name for e in sensor[:1]] == ["refractory"], res.named_effects
    p = sensor[0].parameters()
    assert p["period_us"] == pytest.approx(2000.0, rel=0.3)
    assert p["mode"] == "delay"
    assert res.final.gap <= 3.0


@pytest.mark.slow
def test_gap_names_v2e_bandwidth_not_a_frame_lag() -> None:
    """v2e's photoreceptor low-pass (30 Hz at full scale) delays events by ~11 ms, which a
    frame lag also explains: the bandwidth's cutoff is read off that lag (the frame-rate
    filter, which read 3.5 Hz, only says there is one) and the two are compared finished.
    Measured on coffee: 15.09 Hz at 128 DN (v2e's 16.15 Hz there), gap 719 -> 0.8; the
    other scenes in docs/GAP.md."""
    res = gap_run("cutoff", "coffee")
    sensor = [s.effect for s in res.steps if s.effect.name != "timestamp_quantisation"]
    assert [e.name for e in sensor[:1]] == ["bandwidth"], res.named_effects
    # v2e's cutoff at 128 DN in evcal's law (scripts/v2e_data/gap_table.py): 30 * 148 / 275
    assert sensor[0].parameters()["cutoff_hz"] == pytest.approx(30.0 * 148 / 275, rel=0.3)
    assert res.final.gap <= 3.0


@pytest.mark.slow
def test_gap_names_the_effects_of_v2e_realistic_mix() -> None:
    """v2e's mix (30 Hz low-pass, 1 ms dead time, 5 Hz shot noise, 0.1 Hz leak, threshold
    spread 0.05) on astronaut: the low-pass, the shot noise and the dead time, each near
    v2e's value, and a final gap within the aim of 3. Measured: 18.08 Hz at 128 DN (+12 %),
    shot noise 0.99x v2e's mean rate over the still pixels, 1000 us (delay); gap 1199 ->
    2.2 (the other scenes in docs/GAP.md: 1.7, 2.5 and 6.5)."""
    res = gap_run("mix", "astronaut")
    sensor = {s.effect.name: s.effect for s in res.steps
              if s.effect.name != "timestamp_quantisation"}
    assert {"bandwidth", "shot_noise", "refractory"} <= set(sensor), res.named_effects
    assert sensor["bandwidth"].parameters()["cutoff_hz"] == pytest.approx(30.0 * 148 / 275,
                                                                         rel=0.3)
    assert sensor["refractory"].parameters()["period_us"] == pytest.approx(1000.0, rel=0.3)
    assert res.final.gap <= 3.0


@pytest.mark.slow
def test_gap_refits_an_effect_named_before_others_in_the_final_model() -> None:
    """On v2e's mix/camera several sensor effects are named; each but the last is searched
    again in the final model (its value was settled in a model that lacked the effects named
    after it), keeping its value unless another clearly beats it on every seed: its record
    says what it was named with and the final gap before and after; the last is not searched
    again (it was finished in that model). The v2e effects named are v2e's."""
    res = gap_run("mix", "camera")
    sensor = [s for s in res.steps if s.effect.name != "timestamp_quantisation"]
    assert len(sensor) >= 2, res.named_effects
    assert {s.effect.name for s in sensor} <= {"bandwidth", "shot_noise", "refractory",
                                               "leak", "threshold_noise"}, res.named_effects
    for s in sensor[:-1]:
        assert s.refit is not None
        key = s.refit["parameter"]
        assert key == s.effect.primary
        kept = s.effect.parameters()[key] == s.refit["named_value"]
        # a new value is kept only when it lowers the final gap
        assert kept or s.refit["gap_after"] < s.refit["gap_before"]
    assert sensor[-1].refit is None
    assert res.final.gap < 0.1 * res.initial.gap
