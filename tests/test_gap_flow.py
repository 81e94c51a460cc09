"""The gap workflow at 25 Hz: motion-compensated interpolation, the timestamp scheme of
frame-driven simulators as its own item, and model-corrected calibration.

Recordings are made by evcal's own simulator with the measured 25 Hz frames as the only input
the workflow sees (the events come from a 1 kHz rendering of the moving scene); the v2e
recordings of tests/test_v2e.py check the same on an independent simulator.
"""

from __future__ import annotations

import json
from functools import cache
from types import SimpleNamespace

import numpy as np
import pytest

from evcal.cli import main as cli_main
from evcal.gap.correct import ModelFileError, load_model_effects, model_corrected
from evcal.gap.fitters import late_slot_intervals
from evcal.gap.flow import FlowInterpolator, trusted_windows
from evcal.gap.workflow import GapConfig, run_gap
from evcal.io import load_calibration, write_recording
from evcal.offline import OffEIConfig, offei
from evcal.recording import Frames
from evcal.sim.effects import (
    Leak,
    Refractory,
    TimestampQuantisation,
    make_effect,
    quantise_events,
)
from evcal.sim.ideal import SimConfig
from evcal.sim.nonideal import SimResult, simulate
from evcal.sim.scene import Trajectory
from evcal.sim.sources import FrameInterpolator, MovingScene, SpeedProfile

pytest.importorskip("cv2")

H, W = 48, 64
SPEED = SpeedProfile(segments=((0.5, 0.0), (0.75, 1.0), (0.5, 0.0), (0.75, 2.5)))


def scene(seed: int) -> tuple[SimConfig, MovingScene]:
    traj = Trajectory(pan_px=30.0, seed=seed)
    cfg = SimConfig(height=H, width=W, duration_s=3.0, frame_rate_hz=25.0,
                    internal_rate_hz=1000.0, log_offset=1.0, seed=seed, trajectory=traj)
    return cfg, MovingScene(cfg.scene, (H, W), traj, speed=SPEED)


@cache
def recording(key: str, seed: int) -> SimResult:
    """48x64, 3 s, 25 Hz frames: still, pan, still, fast pan; events from 1 kHz."""
    effects = {"none": [], "refractory": [Refractory(period_us=1000.0)],
               "leak": [Leak(rate_hz=1.0)],
               "quantised": [TimestampQuantisation(step_us=1000.0)]}[key]
    cfg, src = scene(seed)
    return simulate(cfg, effects, source=src)


def c_rmse(contrast: np.ndarray, valid: np.ndarray, truth: np.ndarray) -> float:
    return float(np.sqrt(np.mean((contrast[valid] - truth[valid]) ** 2)))


# ------------------------------------------------------------------ timestamp quantisation


def _quantised(t: list[int], pix: list[int], q: TimestampQuantisation, *,
               pol: list[int] | None = None, lab: list[int] | None = None,
               refractory: Refractory | None = None, t_end_us: float | None = None
               ) -> list[tuple[int, int, int]]:
    n = len(t)
    out = quantise_events(np.array(t, np.int64), np.array(pix, np.int32),
                          np.array(pol or [1] * n, np.int8), np.array(lab or [0] * n, np.uint8),
                          q, 0, n_pix=4, t_end_us=t_end_us, refractory=refractory)
    return list(zip(out[0].tolist(), out[1].tolist(), out[2].tolist(), strict=True))


def test_quantise_events_follows_the_spread_and_end_schemes() -> None:
    t = [100, 200, 300, 950, 1000, 1001, 1500, 1999, 2000, 2600]
    pix = [0, 0, 1, 0, 0, 1, 2, 2, 2, 0]
    # step (0, 1000]: pixel 0 has 4 crossings (N = 4), pixel 1 one; (1000, 2000]: pixel 2
    # three (N = 3), pixel 1 one; a pixel's events take the first slots
    spread = _quantised(t, pix, TimestampQuantisation(step_us=1000.0))
    assert [e[0] for e in spread] == [250, 250, 500, 750, 1000, 1333, 1333, 1667, 2000, 3000]
    assert [e[1] for e in spread] == [0, 1, 0, 0, 0, 1, 2, 2, 2, 0]
    end = _quantised(t, pix, TimestampQuantisation(step_us=1000.0, scheme="end"))
    assert [e[0] for e in end] == [1000] * 5 + [2000] * 4 + [3000]
    shifted = _quantised(t, pix, TimestampQuantisation(step_us=1000.0, phase_us=500.0))
    assert [e[0] for e in shifted] == [0, 0, 500, 1000, 1000, 1000, 1500, 2000, 2500, 3500]
    # crossings of opposite sign in one step cancel (the step's end is compared)
    assert _quantised([100, 200, 300], [0, 0, 0], TimestampQuantisation(step_us=1000.0),
                      pol=[1, -1, 1]) == [(1000, 0, 1)]
    # shot noise: at the step's end, after the signal events
    assert _quantised([100, 200, 300], [0, 1, 2], TimestampQuantisation(step_us=1000.0),
                      lab=[0, 2, 0]) == [(1000, 0, 1), (1000, 2, 1), (1000, 1, 1)]
    empty = quantise_events(np.zeros(0, np.int64), np.zeros(0, np.int32), np.zeros(0, np.int8),
                            np.zeros(0, np.uint8), TimestampQuantisation(), 0, n_pix=1)
    assert all(a.size == 0 for a in empty)
    with pytest.raises(ValueError, match="scheme"):
        TimestampQuantisation(scheme="middle")
    with pytest.raises(ValueError, match="step_us"):
        TimestampQuantisation(step_us=0.0)


def _scheme_fit(t_us: np.ndarray, sim_t_us: np.ndarray):  # noqa: ANN202 - a fit result
    from evcal.gap.effects import FitContext  # noqa: PLC0415
    from evcal.gap.fitters import fit_timestamp_quantisation  # noqa: PLC0415

    meas, sim = SimpleNamespace(t_us=t_us), SimpleNamespace(t_us=sim_t_us)
    rec = SimpleNamespace(frames=SimpleNamespace(t_us=np.array([0], np.int64)))
    return fit_timestamp_quantisation(FitContext(meas, [sim], None, rec, meas))  # type: ignore[arg-type]


def test_the_scheme_is_seen_when_busy_steps_put_most_events_short_of_their_end() -> None:
    """v2e in a busy scene: a step's N is the most any pixel has pending (here 3-5), so most
    events take the first slot, step / N from its start, and only the busiest pixel's last
    one the step's end: few events lie on the grid of step ends, all on the slots."""
    from evcal.gap.effects import Fitted, NoEvidence  # noqa: PLC0415

    rng = np.random.default_rng(3)
    n_pix, steps, step = 400, 600, 500
    t, pix = [], []
    for k in range(steps):
        n_max = int(rng.integers(3, 6))
        busy = int(rng.integers(n_pix))
        t += list(rng.uniform(k * step, (k + 1) * step, n_max))
        pix += [busy] * n_max
        others = rng.choice(n_pix, 60, replace=False)
        t += list(rng.uniform(k * step, (k + 1) * step, others.size))
        pix += others.tolist()
    order = np.argsort(t, kind="stable")
    t_cont = np.round(np.array(t)[order]).astype(np.int64)
    p_cont = np.array(pix, np.int32)[order]
    out = quantise_events(t_cont, p_cont, np.ones(t_cont.size, np.int8),
                          np.zeros(t_cont.size, np.uint8),
                          TimestampQuantisation(step_us=float(step)), 0, n_pix=n_pix)
    t_q = np.sort(out[0])
    assert np.mean(t_q % step == 0) < 0.05  # the step ends: what the grid test counted
    res = _scheme_fit(t_q, t_cont)
    assert isinstance(res, Fitted), res
    assert res.effect.step_us == step
    assert res.effect.scheme == "spread"
    assert res.detail["on_slots"] > 0.95
    # continuous times (a sensor, evcal's simulator) show no scheme
    assert isinstance(_scheme_fit(t_cont, t_cont), NoEvidence)


def test_a_stepped_dead_time_counts_blocked_crossings_in_the_slots() -> None:
    """v2e's refractory period (v2ecore/emulator.py, generate_events): the slots of a step
    come from the counts *before* the dead time is applied, an event passes at the first slot
    more than the period after the pixel's last stamp, and what is blocked stays pending."""
    q = TimestampQuantisation(step_us=100.0)
    t, pix = [10, 20, 30, 150], [0, 0, 0, 1]
    delay = _quantised(t, pix, q, refractory=Refractory(period_us=250.0, mode="delay"),
                       t_end_us=1000.0)
    # step 1: slots 33, 67, 100 -> pixel 0 fires at 33, two crossings wait; step 2: pixel 0
    # still counts 2, so pixel 1 takes the first of 2 slots (150), not the step's end;
    # pixel 0 fires at 300 (> 33 + 250) and 600 (> 300 + 250)
    assert delay == [(33, 0, 1), (150, 1, 1), (300, 0, 1), (600, 0, 1)]
    drop = _quantised(t, pix, q, refractory=Refractory(period_us=250.0, mode="drop"),
                      t_end_us=1000.0)
    assert drop == [(33, 0, 1), (200, 1, 1)]
    # shot noise resets the reference: nothing stays pending (without it: 50, 400)
    refr = Refractory(period_us=250.0, mode="delay")
    assert _quantised([10, 20], [0, 0], q, refractory=refr, t_end_us=1000.0) == [
        (50, 0, 1), (400, 0, 1)]
    assert _quantised([10, 20, 150], [0, 0, 0], q, lab=[0, 0, 2], refractory=refr,
                      t_end_us=1000.0) == [(50, 0, 1), (200, 0, 1)]
    # a dead time shorter than a slot is not applied (as in v2e)
    short = _quantised([10, 20], [0, 0], q, refractory=Refractory(period_us=40.0))
    assert [e[0] for e in short] == [50, 100]


# ------------------------------------------------------------------ interpolation


def test_held_back_events_give_the_dead_time_from_their_slots() -> None:
    """A pixel's first event of a step at a later slot (not the last) was held back by the
    dead time: the time since its previous event lies just above the period, while the
    pairs of events at short intervals need not be scarce. Without a dead time no event is
    held back; noise events at a step's last slot do not count."""
    rng = np.random.default_rng(5)
    n_pix, span_us = 400, 200_000
    t = np.sort(rng.integers(0, span_us, 60_000))  # about one crossing per 1.3 ms per pixel
    pix = rng.integers(0, n_pix, t.size).astype(np.int32)
    q = TimestampQuantisation(step_us=500.0)

    def stamped(refr: Refractory | None, lab: np.ndarray | None = None) -> SimpleNamespace:
        out = quantise_events(t, pix, np.ones(t.size, np.int8),
                              np.zeros(t.size, np.uint8) if lab is None else lab, q, 0,
                              n_pix=n_pix, t_end_us=float(span_us), refractory=refr)
        return SimpleNamespace(t_us=out[0], pix=out[1], frame_t_us=np.array([0]),
                               n_pixels=n_pix, extra={})

    for period in (800.0, 1000.0, 2000.0):
        held = late_slot_intervals(stamped(Refractory(period_us=period, mode="delay")), q)
        assert held.size > 200
        assert held.min() >= period - 1.0  # stamps are whole us
        assert np.percentile(held, 2.0) == pytest.approx(period, rel=0.1)
    assert late_slot_intervals(stamped(None), q).size == 0
    # shot noise, stamped at its step's end, is no held-back event
    noise = np.where(rng.random(t.size) < 0.1, 2, 0).astype(np.uint8)
    assert late_slot_intervals(stamped(None, noise), q).size == 0
    assert late_slot_intervals(stamped(None), TimestampQuantisation(step_us=500.0,
                                                                    scheme="end")).size == 0


def test_flow_interpolation_follows_the_motion_between_25_hz_frames() -> None:
    """Log-intensity error against the 1 kHz truth, inside the frame (the border sees new
    texture that neither frame holds), over the moving parts: at most 0.6x the linear
    blend's; at frame times the frames themselves."""
    for seed in (1, 2):
        cfg, src = scene(seed)
        ft = np.arange(0.0, 3.0001, 0.04)
        imgs = np.stack([src(t) for t in ft]).astype(np.float32)
        frames = Frames((ft * 1e6).astype(np.int64), imgs, np.zeros(ft.size, np.int64))
        flow = FlowInterpolator(frames)
        lin = FrameInterpolator(frames)
        tq = np.concatenate([np.arange(0.505, 1.245, 0.0037), np.arange(1.755, 2.995, 0.0037)])
        truth = np.stack([src(t) for t in tq])[:, 8:-8, 8:-8]

        def err(x: np.ndarray) -> float:
            return float(np.sqrt(np.mean((np.log(x[:, 8:-8, 8:-8] + 1)
                                          - np.log(truth + 1)) ** 2)))  # noqa: B023 - called at once

        e_flow, e_lin = err(flow.render_block(tq)), err(lin.render_block(tq))
        assert e_flow < 0.6 * e_lin, (seed, e_flow, e_lin)
        np.testing.assert_array_equal(flow.render_block(ft[3:6]), imgs[3:6])
        mask = trusted_windows(frames)
        assert mask.shape == (ft.size - 1, H * W)
        assert mask[:10].all()  # still at the start: every window is trusted


# ------------------------------------------------------------------ the loop at 25 Hz


@cache
def gap(key: str, seed: int):
    return run_gap(recording(key, seed).recording, GapConfig(max_effects=2, n_seeds=3, seed=1))


@pytest.mark.slow
@pytest.mark.parametrize("seed", [1, 2])
def test_nothing_hidden_at_25_hz_names_nothing(seed: int) -> None:
    res = gap("none", seed)
    assert res.named_effects == []
    assert res.final.gap < 3.0, res.final.disc.per_stat


@pytest.mark.slow
@pytest.mark.parametrize("seed", [1, 2])
def test_the_timestamp_scheme_is_named_as_its_own_item(seed: int) -> None:
    res = gap("quantised", seed)
    assert res.named_effects[0] == "timestamp_quantisation"
    q = res.steps[0].effect
    assert isinstance(q, TimestampQuantisation)
    assert q.step_us == pytest.approx(1000.0, rel=0.01)
    assert q.scheme == "spread"
    assert q.phase_us == pytest.approx(0.0, abs=2.0)
    assert "timestamp_jitter" not in res.named_effects
    assert res.final.gap < 0.25 * res.initial.gap


# ------------------------------------------------------------------ model correction


@pytest.mark.parametrize("seed", [1, 2])
def test_model_correction_removes_the_refractory_bias(seed: int) -> None:
    """Refractory 1 ms makes OffEI's c too large by ~0.07 (busy pixels lose events); the model
    correction takes the c RMSE to at most 0.4x the uncorrected one."""
    sim = recording("refractory", seed)
    truth = sim.truth["contrast"]
    oc = OffEIConfig(log_offset=1.0, window_frames=2)
    raw = offei(sim.recording, oc)
    cor = model_corrected(sim.recording, [Refractory(period_us=1000.0)], oc)
    r_raw = c_rmse(raw.contrast, raw.valid, truth)
    r_cor = c_rmse(cor.contrast, cor.valid, truth)
    assert r_raw > 0.05
    assert r_cor < 0.4 * r_raw, (r_raw, r_cor)
    np.testing.assert_array_equal(cor.valid, raw.valid)
    mc = cor.diagnostics.model_correction
    assert mc["effects"] == {"refractory": {"period_us": 1000.0, "mode": "drop"}}
    assert 1.1 < mc["gain_median"] < 1.6


def test_model_correction_leaves_an_unbiased_fit_alone() -> None:
    """Leak at 1 Hz barely biases c: the correction must not add error (within 10 %)."""
    sim = recording("leak", 1)
    truth = sim.truth["contrast"]
    oc = OffEIConfig(log_offset=1.0, window_frames=2)
    raw = offei(sim.recording, oc)
    cor = model_corrected(sim.recording, [Leak(rate_hz=1.0)], oc)
    assert c_rmse(cor.contrast, cor.valid, truth) < 1.1 * c_rmse(raw.contrast, raw.valid, truth)
    assert abs(cor.diagnostics.model_correction["gain_median"] - 1.0) < 0.02


def test_model_file_errors_name_the_problem(tmp_path) -> None:
    p = tmp_path / "report.json"
    with pytest.raises(ModelFileError, match="does not exist"):
        load_model_effects(p)
    p.write_text("{not json")
    with pytest.raises(ModelFileError, match="not readable JSON"):
        load_model_effects(p)
    p.write_text(json.dumps({"named_effects": []}))
    with pytest.raises(ModelFileError, match="neither 'steps'"):
        load_model_effects(p)
    p.write_text(json.dumps({"steps": [{"effect": "refractory",
                                        "parameters": {"period_us": -1}}]}))
    with pytest.raises(ModelFileError, match="effect 0 \\(refractory\\)"):
        load_model_effects(p)
    p.write_text(json.dumps({"steps": [{"effect": "wobble", "parameters": {}}]}))
    with pytest.raises(ModelFileError, match="unknown effect"):
        load_model_effects(p)
    p.write_text(json.dumps({"effects": [{"name": "leak", "parameters": {"rate_hz": 0.5}},
                                         {"name": "refractory",
                                          "parameters": {"period_us": 300.0}}]}))
    eff = load_model_effects(p)
    assert eff == {"leak": make_effect("leak", rate_hz=0.5),
                   "refractory": make_effect("refractory", period_us=300.0)}


def test_cli_calibrate_with_a_model_reports_the_correction(tmp_path, capsys) -> None:
    sim = recording("refractory", 1)
    rec_path = write_recording(sim.recording, tmp_path / "rec.npz")
    report = tmp_path / "report.json"
    report.write_text(json.dumps({"steps": [
        {"effect": "refractory", "parameters": {"period_us": 1000.0, "mode": "drop"}}]}))
    out = tmp_path / "cal.npz"
    rc = cli_main(["calibrate", str(rec_path), "--out", str(out), "--model", str(report),
                   "--log-offset", "1", "--window-frames", "2"])
    text = capsys.readouterr().out
    assert rc == 0, text
    assert "model         refractory(period_us=1000.0, mode=drop)" in text
    assert "correction    c / 1." in text
    cal = load_calibration(out)
    assert cal.diagnostics.model_correction["effects"]["refractory"]["period_us"] == 1000.0
    truth = sim.truth["contrast"]
    assert c_rmse(cal.contrast, cal.valid, truth) < 0.04
    rc = cli_main(["calibrate", str(rec_path), "--out", str(out), "--model", str(report),
                   "--method", "onei"])
    assert rc == 2
    assert "--model corrects OffEI" in capsys.readouterr().err


def test_refinement_stops_at_the_edge_of_a_parameter_range() -> None:
    """A moment estimate at the top of its range (threshold_noise sigma 1.0, seen on v2e's
    noisy preset) once crashed the loop: the search's next point, 1/0.7 of it, is not a valid
    effect. The moment estimate now stands."""
    from evcal.gap.finish import refine  # noqa: PLC0415
    from evcal.gap.model import fit_base  # noqa: PLC0415
    from evcal.gap.runner import Evaluator  # noqa: PLC0415
    from evcal.sim.effects import ThresholdNoise  # noqa: PLC0415

    rec = recording("none", 1).recording
    run = Evaluator(rec, GapConfig(n_seeds=3), lambda _what: None)
    base = fit_base(rec)
    edge = ThresholdNoise(sigma=1.0)
    best = run.evaluate(run.candidate_model(base, edge), "edge")
    eff, ev = refine(run, base, best, edge)
    assert eff == edge
    assert ev is best


def test_timing_statistics_leave_out_windows_with_a_clipped_frame() -> None:
    """A frame at full scale (255 DN) says only that the light was past the full well: the
    runner's trusted windows (those of the timing statistics) leave out every window with
    such a frame at the pixel, and keep the flow's verdict elsewhere."""
    from evcal.gap.flow import unclipped_windows
    from evcal.gap.runner import Evaluator
    from evcal.recording import Recording
    from evcal.sim.ideal import simulate_ideal

    rec = simulate_ideal(SimConfig(height=48, width=64, duration_s=1.0, seed=5)).recording
    images = rec.frames.images.astype(np.float32).copy()
    images[5:9, 10:20, 30:50] = 255.0  # a bright patch past the full well in frames 5-8
    frames = Frames(rec.frames.t_us, images, rec.frames.exposure_us)
    clipped_rec = Recording(rec.sensor, rec.events, frames)
    ok = unclipped_windows(frames)
    n_w, n_pix = len(frames) - 1, 48 * 64
    assert ok.shape == (n_w, n_pix)
    patch = np.zeros((48, 64), bool)
    patch[10:20, 30:50] = True
    patch = patch.ravel()
    # windows 4-8 have a clipped frame at the patch (4 ends at frame 5, 8 starts at frame 8)
    assert not ok[4:9][:, patch].any()
    assert ok[4:9][:, ~patch].all()
    assert ok[:4].all()
    assert ok[9:].all()
    run = Evaluator(clipped_rec, GapConfig(seed=0), lambda w: None)
    assert run.trusted is not None
    np.testing.assert_array_equal(run.trusted, trusted_windows(frames, max_px=np.inf) & ok)
    assert not run.meas.trusted[4:9][:, patch].any()


def test_the_exposure_blur_of_moving_frames_is_taken_out() -> None:
    """Frames of a textured scene panning at 300 px/s, each the mean over a 10 ms exposure
    (3 px of blur along the motion): deblurred along their flow they are closer to the
    sharp images than the blurred ones are, and a still scene is left as it is."""
    from evcal.gap.flow import deblurred

    rng = np.random.default_rng(3)
    h, w, k, speed_px_s, exposure_s = 48, 64, 8, 300.0, 0.010
    tex = cv2_blur(rng.uniform(0, 255, (h, 4 * w)).astype(np.float32), 3.0)
    t_us = np.arange(k, dtype=np.int64) * 40_000

    def view(x0: float) -> np.ndarray:
        xs = np.arange(w, dtype=np.float64) + x0
        i0 = np.floor(xs).astype(int)
        f = (xs - i0)[None, :]
        return ((1 - f) * tex[:, i0] + f * tex[:, i0 + 1]).astype(np.float32)

    sharp = np.stack([view(speed_px_s * t * 1e-6) for t in t_us])
    blurred = np.stack([np.mean([view(speed_px_s * (t * 1e-6 + u)) for u in
                                 np.linspace(-exposure_s / 2, exposure_s / 2, 21)], axis=0)
                        for t in t_us])
    out = deblurred(blurred, t_us, np.full(k, int(exposure_s * 1e6)))
    inner = (slice(None), slice(4, -4), slice(8, -8))
    err_blur = np.abs(blurred - sharp)[inner].mean()
    err_out = np.abs(out - sharp)[inner].mean()
    assert err_out < 0.6 * err_blur
    still = np.repeat(sharp[:1], k, axis=0)
    np.testing.assert_allclose(deblurred(still, t_us, np.full(k, 10_000)), still, atol=1e-3)
    # no exposure: nothing to take out
    np.testing.assert_array_equal(deblurred(blurred, t_us, np.zeros(k)), blurred)


def test_texture_the_blur_nearly_erased_is_not_turned_over() -> None:
    """A fine grating (period 2.2 px) on a smooth texture, panning at 300 px/s, 10 ms
    exposures: the 3 px box blur's response to the grating is negative (-0.22). Taking the
    blur out must not invert the grating and grow it (Van Cittert's iteration gave -0.55,
    frames further from the sharp ones than the blurred ones); what it cannot restore it
    leaves small, and the frames still come closer to the sharp ones."""
    from evcal.gap.flow import deblurred

    rng = np.random.default_rng(3)
    h, w, k, speed_px_s, exposure_s, period = 48, 96, 8, 300.0, 0.010, 2.2
    tex = cv2_blur(rng.uniform(0, 255, (h, 4 * w)).astype(np.float32), 3.0)
    t_us = np.arange(k, dtype=np.int64) * 40_000

    def view(x0: float, amp: float = 20.0) -> np.ndarray:
        xs = np.arange(w, dtype=np.float64) + x0
        i0 = np.floor(xs).astype(int)
        f = (xs - i0)[None, :]
        base = (1 - f) * tex[:, i0] + f * tex[:, i0 + 1]
        return (base + amp * np.sin(2 * np.pi * xs / period)[None, :]).astype(np.float32)

    def grating(img: np.ndarray, i: int) -> complex:
        xs = np.arange(w) + speed_px_s * t_us[i] * 1e-6
        ref = np.exp(-2j * np.pi * xs / period)[16:-16]
        return complex(np.mean(img[i, 8:-8, 16:-16] * ref[None, :]))

    shifts = [speed_px_s * t * 1e-6 for t in t_us]
    sharp = np.stack([view(x) for x in shifts])
    smooth = np.stack([view(x, 0.0) for x in shifts])
    blurred = np.stack([np.mean([view(x + speed_px_s * u) for u in
                                 np.linspace(-exposure_s / 2, exposure_s / 2, 41)], axis=0)
                        for x in shifts])
    out = deblurred(blurred, t_us, np.full(k, int(exposure_s * 1e6)))
    for i in range(1, k - 1):
        ref = grating(sharp - smooth, i)
        gain_blurred = grating(blurred - smooth, i) / ref
        gain_out = grating(out - smooth, i) / ref
        assert gain_blurred.real < -0.15  # the blur did turn it over
        assert abs(gain_out) <= abs(gain_blurred) + 0.02
    inner = (slice(None), slice(4, -4), slice(8, -8))
    assert np.abs(out - sharp)[inner].mean() < np.abs(blurred - sharp)[inner].mean()


def cv2_blur(img: np.ndarray, sigma: float) -> np.ndarray:
    import cv2

    out: np.ndarray = cv2.GaussianBlur(img, (0, 0), sigmaX=sigma)
    return out
