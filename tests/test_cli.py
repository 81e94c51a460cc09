"""The ``evcal`` command line, end to end, on simulated and real recordings."""

from __future__ import annotations

import json

import numpy as np
import pytest

from evcal.cli import main
from evcal.io import load_calibration, save_calibration


@pytest.fixture(scope="module")
def small_sim(tmp_path_factory):
    out = tmp_path_factory.mktemp("sim") / "sim.mcap"
    rc = main(["simulate", "--out", str(out), "--sensor-size", "64x48", "--duration-s", "4",
               "--internal-rate-hz", "500", "--seed", "3", "--quiet"])
    assert rc == 0
    return out


def test_simulate_writes_recording_and_truth(small_sim):
    truth = np.load(small_sim.with_name("sim.truth.npz"))
    assert truth["contrast"].shape == (48, 64)
    assert float(truth["log_offset"]) == 30.0
    assert int(truth["seed"]) == 3


def test_info_json(small_sim, capsys):
    assert main(["info", str(small_sim), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["sensor"] == "64x48"
    assert info["n_frames"] == 101
    assert info["n_events"] > 10_000
    assert info["event_rate_hz"] > 0


@pytest.mark.parametrize("method", ["offei", "onei", "offe", "brandli", "di"])
def test_calibrate_every_method_writes_the_npz_layout(small_sim, tmp_path, method):
    out = tmp_path / "cal.npz"
    rc = main(["calibrate", str(small_sim), "--method", method, "--out", str(out),
               "--log-offset", "30", "--csv", str(tmp_path / "csv"), "--quiet"])
    assert rc == 0
    with np.load(out) as z:
        for key, dtype in (("contrast", np.float32), ("bias", np.float32), ("valid", bool),
                           ("stderr_contrast", np.float32), ("stderr_bias", np.float32),
                           ("special", np.uint8)):
            assert z[key].shape == (48, 64)
            assert z[key].dtype == dtype
        # OffE (events only) cannot know the offset: NaN, never a made-up 0
        lo = float(z["log_offset"])
        assert np.isnan(lo) if method == "offe" else lo >= 0
    scale = np.loadtxt(tmp_path / "csv" / "scale.csv", delimiter=",")
    assert scale.shape == (48, 64)


def test_calibrate_offei_then_evaluate_beats_di(small_sim, tmp_path, capsys):
    cal_path = tmp_path / "cal.npz"
    assert main(["calibrate", str(small_sim), "--out", str(cal_path), "--quiet"]) == 0
    cal = load_calibration(cal_path)
    truth = np.load(small_sim.with_name("sim.truth.npz"))
    v = cal.valid
    assert v.mean() > 0.8
    assert np.sqrt(np.mean((cal.contrast[v] - truth["contrast"][v]) ** 2)) < 0.03
    assert abs(cal.log_offset - 30.0) < 10  # estimated ('auto' is the default)
    js = tmp_path / "eval.json"
    rc = main(["evaluate", str(small_sim), "--calibration", str(cal_path),
               "--frames-per-image", "10", "--json", str(js)])
    assert rc == 0
    summary = json.loads(js.read_text())
    assert summary["n_images"] >= 5
    for key in ("rmse", "psnr", "ssim", "psnr_paper", "ssim_paper"):
        assert key in summary["calibrated"]
        assert key in summary["di"]
    assert summary["calibrated"]["psnr"] > summary["di"]["psnr"] + 1.0
    assert "psnr_paper" in capsys.readouterr().out
    # pixels without an estimate: integrated with the valid pixels' median, and counted
    valid = v.copy()
    valid[:10] = False
    holed = cal.replace(valid=valid, reason=np.where(valid, cal.reason, 2).astype(np.uint8),
                        contrast=np.where(valid, cal.contrast, 0.1).astype(cal.contrast.dtype),
                        bias=np.where(valid, cal.bias, 0.0).astype(cal.bias.dtype))
    save_calibration(holed, tmp_path / "holed.npz")
    assert main(["evaluate", str(small_sim), "--calibration", str(tmp_path / "holed.npz"),
                 "--frames-per-image", "10"]) == 0
    n = int((~valid).sum())
    assert f"{n} of {valid.size} pixels ({100 * n / valid.size:.1f} %) have no valid " \
           "estimate" in capsys.readouterr().err


def test_errors_are_reported_not_raised(tmp_path, capsys):
    assert main(["info", str(tmp_path / "missing.aedat4")]) != 0
    assert "missing.aedat4" in capsys.readouterr().err
    bad = tmp_path / "ecd"
    bad.mkdir()
    (bad / "events.txt").write_text("0.1 1 2 1\n0.05 1 2 0\n")
    assert main(["info", str(bad), "--sensor-size", "10x10"]) != 0
    assert "sorted" in capsys.readouterr().err
    assert main(["calibrate", str(bad), "--sensor-size", "10x10", "--out",
                 str(tmp_path / "x.npz")]) != 0
    assert main(["info", str(bad), "--sensor-size", "10by10"]) == 2
    assert "WxH" in capsys.readouterr().err


def test_too_few_frames_for_a_window(small_sim, tmp_path, capsys):
    rc = main(["calibrate", str(small_sim), "--out", str(tmp_path / "c.npz"), "--log-offset",
               "30", "--window-frames", "500"])
    assert rc == 1
    assert "fewer than one window" in capsys.readouterr().err


def test_real_davis346_end_to_end(shared_data, tmp_path, capsys):
    road = shared_data / "davis346_road" / "road.aedat4"
    if not road.exists():
        pytest.skip(f"{road} is absent")
    assert main(["info", str(road), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert (info["sensor"], info["n_events"], info["n_frames"]) == ("346x260", 78830, 59)
    for method in ("offei", "onei", "offe", "brandli", "di"):
        out = tmp_path / f"{method}.npz"
        assert main(["calibrate", str(road), "--method", method, "--out", str(out)]) == 0
    # 79 k events: the paper's OnEI buffers (416 k at 346x260) would never fill; the small
    # buffer is fitted to the recording, and it says so
    out = capsys.readouterr()
    assert "small buffer fitted to the recording: 9,853 events" in out.err
    assert "valid pixels  1.4 %: most pixels saw fewer than 20 events" in out.out
    assert load_calibration(tmp_path / "onei.npz").valid.sum() > 500
    # sizes given are kept: the paper's never fill, and it says why
    assert main(["calibrate", str(road), "--method", "onei", "--n-small", "416481",
                 "--out", str(tmp_path / "onei_paper.npz")]) == 0
    assert ("OnEI made no update: 416,481 events needed per small buffer"
            in capsys.readouterr().err)
    assert not load_calibration(tmp_path / "onei_paper.npz").valid.any()
    # default options on a recording holding fewer events than events_per_image: adapted,
    # and said
    capsys.readouterr()
    assert main(["evaluate", str(road), "--calibration", str(tmp_path / "offei.npz")]) == 0
    assert "fewer than events_per_image" in capsys.readouterr().err
    js = tmp_path / "e.json"
    assert main(["evaluate", str(road), "--calibration", str(tmp_path / "offei.npz"),
                 "--frames-per-image", "5", "--json", str(js)]) == 0
    summary = json.loads(js.read_text())
    assert summary["n_images"] >= 10
    cal = load_calibration(tmp_path / "offei.npz")
    assert 20 < cal.log_offset < 200  # DAVIS frames: the paper hand-tuned 40-100
    assert summary["calibrated"]["rmse"] <= summary["di"]["rmse"]


def test_gap_says_which_extra_is_missing_before_it_runs(small_sim, tmp_path, capsys,
                                                        monkeypatch):
    """On an install without the ``gap`` extra, ``evcal gap`` names the missing modules and
    the extra at once (it used to fail with ``No module named 'matplotlib'`` after the
    workflow, when writing its plots)."""
    import importlib.util

    real = importlib.util.find_spec

    def find_spec(name, *args, **kwargs):
        return None if name in ("matplotlib", "cv2") else real(name, *args, **kwargs)

    monkeypatch.setattr(importlib.util, "find_spec", find_spec)
    assert main(["gap", str(small_sim), "--out", str(tmp_path / "g")]) == 1
    err = capsys.readouterr().err
    assert "cv2 (opencv-python-headless), matplotlib missing" in err
    assert "pip install 'evcal[gap]'" in err
    assert not (tmp_path / "g").exists()


def test_calibrate_and_evaluate_json_on_stdout(small_sim, tmp_path, capsys):
    """--json with no file prints JSON instead of the table (machine-readable stdout);
    with a file it writes it beside the table."""
    cal_path = tmp_path / "cal.npz"
    assert main(["calibrate", str(small_sim), "--out", str(cal_path), "--json", "-q"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["method"] == "offei"
    assert out["sensor"] == "64x48"
    assert out["log_offset_estimated"] is True
    assert 0.5 < out["summary"]["valid_fraction"] <= 1.0
    assert out["diagnostics"]["window_frames"] == 5
    assert main(["evaluate", str(small_sim), "--calibration", str(cal_path),
                 "--frames-per-image", "5", "--json"]) == 0
    scores = json.loads(capsys.readouterr().out)
    assert scores["calibrated"]["psnr"] > scores["di"]["psnr"]
    assert main(["evaluate", str(small_sim), "--calibration", str(cal_path),
                 "--frames-per-image", "5", "--json", str(tmp_path / "s.json")]) == 0
    assert "psnr" in capsys.readouterr().out
    assert json.loads((tmp_path / "s.json").read_text())["n_images"] == scores["n_images"]


def test_every_option_of_the_core_commands_has_help():
    from evcal.cli import build_parser

    parser = build_parser()
    sub = next(a for a in parser._actions if a.dest == "command")
    for name in ("info", "calibrate", "evaluate", "simulate", "bench"):
        sp = sub.choices[name]
        dests = {a.dest for a in sp._actions}
        assert {"quiet", "verbose"} <= dests, name
        for action in sp._actions:
            assert action.help, f"evcal {name} {action.option_strings or action.dest}"


def test_every_command_takes_q_and_v():
    """-q and -v on every command, core and delegated (each parses them)."""
    import contextlib
    import io

    from evcal.cli import DELEGATED

    for name in ("info", "calibrate", "evaluate", "simulate", "bench", *DELEGATED):
        out = io.StringIO()
        with contextlib.redirect_stdout(out), pytest.raises(SystemExit) as exc:
            main([name, "--help"])
        assert exc.value.code == 0, name
        text = out.getvalue()
        assert "-q, --quiet" in text, name
        assert "-v, --verbose" in text, name


def test_a_low_valid_share_is_explained() -> None:
    import numpy as np

    from evcal.calibration import Calibration, Reason
    from evcal.cli import invalid_reasons, low_valid_headline

    cal = Calibration.uniform((10, 10))
    reason = np.full((10, 10), Reason.NO_EVENTS, np.uint8)
    reason[0, :5] = Reason.VALID
    reason[1] = Reason.TOO_FEW_EVENTS
    valid = reason == Reason.VALID
    low = cal.replace(valid=valid, reason=reason)
    text = invalid_reasons(low)
    assert text.startswith("no events 85.0 %, too few events 10.0 %")
    assert text.endswith("a longer recording with motion calibrates more of them")
    assert low_valid_headline(low) == ("most pixels saw fewer than 20 events (a still camera, "
                                       "a short recording or a dark scene; the others keep "
                                       "c = 0.1, b = 0)")
    assert invalid_reasons(cal) == low_valid_headline(cal) == ""  # all valid: nothing to say


def test_calibrate_offe_takes_its_scale(small_sim, tmp_path):
    """--c0 sets OffE's median contrast (no frames, no absolute scale); other methods
    refuse it rather than ignore it."""
    out = tmp_path / "cal.npz"
    assert main(["calibrate", str(small_sim), "--method", "offe", "--c0", "0.2", "--out",
                 str(out), "--quiet"]) == 0
    cal = load_calibration(out)
    assert abs(float(np.median(cal.contrast[cal.valid])) - 0.2) < 1e-6
    assert main(["calibrate", str(small_sim), "--method", "offei", "--c0", "0.2", "--out",
                 str(out), "--quiet"]) == 2
