"""The ``evcal`` command: ``main(argv) -> int`` with one function per subcommand.

Subcommands: info, calibrate, evaluate, simulate, bench (core); gap (model-gap workflow);
serve, replay, query, record, demo (service and clients, need the ``service`` extra).
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from .clihelp import HelpFormatter
from .estimators import ERROR_SCALES, ESTIMATORS
from .events import SensorSize

if TYPE_CHECKING:
    from .calibration import Calibration
    from .progress import Progress
    from .recording import Recording

DESCRIPTION = """\
evcal: per-pixel calibration of event cameras.

An event pixel fires ON when its log intensity rose by c + b since its last event and OFF
when it fell by c - b. evcal estimates the contrast threshold c and the bias b of every
pixel from events and frames (offline or live), tells which pixels are hot, cold, warm or
cool, and measures how much better event-integrated images get."""

EPILOG = """\
examples:
  evcal info road.aedat4
  evcal calibrate road.aedat4 --out cal.npz             # OffEI, log offset estimated
  evcal evaluate road.aedat4 --calibration cal.npz      # reconstruction vs DI
  evcal simulate --out sim.mcap --duration-s 5          # a camera with known c, b
  evcal gap road.aedat4 --out gap/                      # what the sensor model lacks
  evcal demo                                            # service + simulated camera
  evcal serve --listen tcp/0.0.0.0:7447                 # the live calibration service
  evcal serve --workers auto --listen tcp/0.0.0.0:7447  # ... one process per core, cameras
                                                        #     split among them
  evcal serve --ros2 --connect tcp/localhost:7447       # ... also a ROS 2 node (rmw_zenoh)

environment:
  EVCAL_CONNECT, EVCAL_LISTEN, EVCAL_ZENOH_CONFIG, EVCAL_MODE
      defaults of --connect, --listen, --config and --mode of the service and clients
      (serve, replay, query, record, forget); a flag on the command line wins
  ROS_DOMAIN_ID
      the ROS 2 domain of --ros2 (serve, replay, record) when --ros-domain is not given

exit codes: 0 success, 1 failure (a bad file, a failed calibration), 2 bad usage.
Run 'evcal COMMAND -h' for a command's options; docs/ holds the formats, the service, the
wire layout and the model-gap workflow."""


class CliError(Exception):
    """A user error: printed without a traceback, exit code 2."""


def _progress(total: int | None, desc: str, quiet: bool, unit: str) -> Progress:
    from .progress import Progress  # noqa: PLC0415

    return Progress(total, desc, unit=unit, quiet=quiet)


def _sensor_arg(text: str | None) -> SensorSize | None:
    if text is None:
        return None
    try:
        return SensorSize.parse(text)
    except ValueError as exc:
        raise CliError(str(exc)) from None


def _open(path: str, sensor: str | None = None, args: argparse.Namespace | None = None
          ) -> Recording:
    from .io import open_recording  # noqa: PLC0415

    return open_recording(path, sensor=_sensor_arg(sensor),
                          events_topic=getattr(args, "events_topic", None),
                          frames_topic=getattr(args, "frames_topic", None),
                          camera=getattr(args, "camera", None),
                          strict=getattr(args, "strict", False))


def _offset_arg(text: str) -> float | str:
    if text == "auto":
        return "auto"
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"--log-offset {text!r}: expected 'auto' or a number") from None
    if v < 0:
        raise argparse.ArgumentTypeError(f"--log-offset {v} must be >= 0")
    return v


def _positive_int(text: str) -> int:
    try:
        v = int(float(text)) if "e" in text.lower() else int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: expected a whole number") from None
    if v < 1:
        raise argparse.ArgumentTypeError(f"{v} must be >= 1")
    return v


# -- info -------------------------------------------------------------------------------------


def cmd_info(args: argparse.Namespace) -> int:
    rec = _open(args.recording, args.sensor_size, args)
    n = rec.n_events
    dur = rec.duration_s
    info: dict[str, Any] = {
        "path": str(args.recording),
        "sensor": str(rec.sensor),
        "duration_s": round(dur, 6),
        "n_events": n,
        "n_frames": len(rec.frames),
        "event_rate_hz": round(n / dur, 1) if dur > 0 else 0.0,
        "on_fraction": round(float((rec.events["p"] > 0).mean()), 4) if n else None,
        "frame_rate_hz": round((len(rec.frames) - 1)
                               / ((rec.frames.t_us[-1] - rec.frames.t_us[0]) * 1e-6), 3)
        if len(rec.frames) > 1 else None,
        "frame_dtype": str(rec.frames.images.dtype),
    }
    if n:
        info["t_first_us"] = int(rec.events["t_us"][0])
        info["t_last_us"] = int(rec.events["t_us"][-1])
    if args.json:
        print(json.dumps(info, indent=2))
    else:
        width = max(len(k) for k in info)
        for k, v in info.items():
            print(f"{k:<{width}}  {v}")
    return 0


# -- calibrate --------------------------------------------------------------------------------


def cmd_calibrate(args: argparse.Namespace) -> int:
    from .io import save_calibration, write_csv  # noqa: PLC0415

    if args.stream:
        return _calibrate_stream(args)
    if args.c0 is not None and args.method != "offe":
        raise CliError("--c0 is OffE's scale: use it with --method offe (the frames give the "
                       "other methods theirs)")
    from .fusion import FUSABLE, with_event_timing  # noqa: PLC0415

    if args.event_timing and args.method not in FUSABLE:
        raise CliError(f"--event-timing fuses OffE into --method {' or '.join(FUSABLE)}")
    rec = _open(args.recording, args.sensor_size, args)
    from .estimators import calibrate  # noqa: PLC0415

    if args.model is not None:
        if args.method != "offei":
            print("evcal calibrate: --model corrects OffEI: use it with --method offei",
                  file=sys.stderr)
            return 2
        if args.event_timing:
            print("evcal calibrate: --event-timing is not fused with --model (OffE would need "
                  "the model's correction too)", file=sys.stderr)
            return 2
        if args.error_scale == "split-half":
            print("evcal calibrate: --error-scale split-half is not applied with --model (the "
                  "halves would each need the model's correction)", file=sys.stderr)
            return 2
        from .gap.correct import CorrectionConfig, load_model_effects, model_corrected  # noqa: PLC0415
        from .offline import OffEIConfig  # noqa: PLC0415

        effects = load_model_effects(args.model)
        okw: dict[str, Any] = {"log_offset": args.log_offset}
        if args.window_frames is not None:
            okw["window_frames"] = args.window_frames
        cal = model_corrected(rec, effects, OffEIConfig(**okw),
                              CorrectionConfig(seed=args.seed))
    else:
        cal = calibrate(rec, args.method, log_offset=args.log_offset,
                        window_frames=args.window_frames, n_small=args.n_small,
                        n_large=args.n_large, smoothing=args.smoothing, c0=args.c0,
                        error_scale=args.error_scale)
    if args.event_timing:
        cal = with_event_timing(rec, cal)
        fused = cal.diagnostics.extra["fusion"]
        if "reason" in fused:
            _note(args, "calibrate", f"--event-timing: {fused['reason']}")
    if args.posterior:
        from .posterior import POSTERIOR_METHODS, posterior_maps  # noqa: PLC0415

        if cal.method not in POSTERIOR_METHODS:
            raise CliError(f"--posterior is offered for --method "
                           f"{' or '.join(POSTERIOR_METHODS)} (calibrated errors and a pull "
                           f"that pays: docs/MEASUREMENTS.md)")
        cal = posterior_maps(cal)
    for warning in cal.warnings:
        _note(args, "calibrate", f"warning: {warning}")
    save_calibration(cal, args.out)
    if args.csv:
        write_csv(cal, args.csv)
    _review(args, "calibrate", rec, cal, reconstruct=False)
    s = cal.summary()
    if args.json is not None:
        _write_json(args.json, {
            "recording": str(args.recording), "out": str(args.out), "method": cal.method,
            "sensor": str(rec.sensor), "log_offset": cal.log_offset,
            "log_offset_estimated": args.log_offset == "auto" and args.method != "offe",
            "summary": s, "warnings": list(cal.warnings),
            "diagnostics": cal.diagnostics.to_dict()})
        if args.json == "-":
            return 0
    print(f"method        {cal.method}"
          + (" + event timing" if args.event_timing else "")
          + (" (posterior maps)" if args.posterior else ""))
    print(f"sensor        {rec.sensor}")
    print(f"log_offset    {cal.log_offset:.3f}"
          + (" (estimated)" if args.log_offset == "auto" and args.method != "offe" else ""))
    headline = low_valid_headline(cal)
    print(f"valid pixels  {s['valid_fraction'] * 100:.1f} %"
          + (f": {headline}" if headline else ""))
    why = invalid_reasons(cal)
    if why:
        print(f"invalid       {why}")
    if "contrast_median" in s:
        print(f"contrast      median {s['contrast_median']:.4f}  "
              f"[p5 {s['contrast_p05']:.4f}, p95 {s['contrast_p95']:.4f}]")
        print(f"bias          median {s['bias_median']:+.4f}  "
              f"[p5 {s['bias_p05']:+.4f}, p95 {s['bias_p95']:+.4f}]")
    print("special       " + ", ".join(f"{k} {v}" for k, v in s["special_counts"].items()))
    es = cal.diagnostics.extra.get("error_scale")
    if isinstance(es, dict):
        print("errors        " + (
            f"scaled by c {es['contrast']:.3f}, b {es['bias']:.3f} (the recording's two "
            f"halves, {es['pixels']} pixels)" if es.get("applied") else
            f"as the estimator states them (split-half check not applied: {es.get('reason')})"))
    mc = getattr(cal.diagnostics, "model_correction", None)
    if mc:
        names = ", ".join(f"{k}({', '.join(f'{p}={v}' for p, v in ps.items())})"
                          for k, ps in mc["effects"].items())
        print(f"model         {names}")
        print(f"correction    c / {mc['gain_median']:.4f} (median; "
              f"{mc['gain_range'][0]:.4f}..{mc['gain_range'][1]:.4f} over {mc['cells']} "
              f"cells), b shifted by {mc['bias_shift_median']:+.4f} (median)")
    print(f"wrote         {args.out}")
    return 0


def _calibrate_stream(args: argparse.Namespace) -> int:
    """``calibrate --stream``: OffEI of an evcal MCAP without loading it."""
    from .io import save_calibration, sniff, write_csv  # noqa: PLC0415
    from .offline import OffEIConfig, offei_file  # noqa: PLC0415

    if (args.method != "offei" or args.model or args.rrd or args.error_scale == "split-half"
            or args.event_timing):
        raise CliError("--stream is OffEI alone: no --method other than offei, no --model, "
                       "no --rrd, no --error-scale split-half, no --event-timing (the halves "
                       "need the recording in memory)")
    if sniff(args.recording) != "mcap":
        raise CliError(f"--stream reads evcal's .mcap recordings; {args.recording} is not one "
                       "(convert it with evcal simulate/record, or drop --stream)")
    okw: dict[str, Any] = {"log_offset": args.log_offset}
    if args.window_frames is not None:
        okw["window_frames"] = args.window_frames
    with _progress(None, "calibrate", args.quiet, "messages read") as bar:
        def tick(done: int, total: int) -> None:
            bar.set(done, total or None)

        cal = offei_file(args.recording, OffEIConfig(**okw), prefix_frames=args.prefix_frames,
                         progress=tick)
    if args.posterior:
        from .posterior import posterior_maps  # noqa: PLC0415

        cal = posterior_maps(cal)
    save_calibration(cal, args.out)
    if args.csv:
        write_csv(cal, args.csv)
    s = cal.summary()
    if args.json is not None:
        _write_json(args.json, {"recording": str(args.recording), "out": str(args.out),
                                "method": cal.method, "log_offset": cal.log_offset,
                                "summary": s, "diagnostics": cal.diagnostics.to_dict()})
        if args.json == "-":
            return 0
    print(f"method        {cal.method} (streamed)")
    print(f"log_offset    {cal.log_offset:.3f}")
    print(f"valid pixels  {s['valid_fraction'] * 100:.1f} %")
    print(f"wrote         {args.out}")
    return 0


def _min_events(cal: Calibration) -> int:
    """The events a pixel needed to be calibrated (the method's limits; 20 by default)."""
    config = getattr(cal.diagnostics, "config", None) or {}
    limits = config.get("limits") if isinstance(config, dict) else None
    return int((limits or {}).get("min_events", 20))


def low_valid_headline(cal: Calibration, below: float = 0.5) -> str:
    """A few words on why fewer than ``below`` of the pixels are valid, for the line that
    gives the valid share ("most pixels saw fewer than 20 events: ..."); "" otherwise."""
    from .calibration import Reason  # noqa: PLC0415

    if float(cal.valid.mean()) >= below:
        return ""
    counts = np.bincount(cal.reason.ravel(), minlength=len(Reason))
    if counts[Reason.NO_EVENTS] + counts[Reason.TOO_FEW_EVENTS] >= 0.5 * cal.reason.size:
        return (f"most pixels saw fewer than {_min_events(cal)} events (a still camera, a "
                "short recording or a dark scene; the others keep c = 0.1, b = 0)")
    if counts[Reason.CONSTANT] >= 0.5 * cal.reason.size:
        return "most pixels' frames never change (the camera or the scene must move)"
    return "see the reasons below"


def invalid_reasons(cal: Calibration, below: float = 0.5) -> str:
    """Why the pixels of a calibration whose valid share is below ``below`` are invalid:
    each reason's share of the sensor, largest first, with what to do about the commonest
    ones; "" when enough pixels are valid."""
    from .calibration import Reason  # noqa: PLC0415

    if float(cal.valid.mean()) >= below:
        return ""
    n = cal.reason.size
    counts = np.bincount(cal.reason.ravel(), minlength=len(Reason))
    parts = [f"{Reason(k).name.lower().replace('_', ' ')} {100 * counts[k] / n:.1f} %"
             for k in np.argsort(-counts) if k != Reason.VALID and counts[k] > 0]
    hint = ""
    quiet = counts[Reason.NO_EVENTS] + counts[Reason.TOO_FEW_EVENTS]
    if quiet >= 0.5 * n:
        hint = "; a longer recording with motion calibrates more of them"
    elif counts[Reason.CONSTANT] >= 0.5 * n:
        hint = "; most pixels' frames never change: the camera or the scene must move"
    return ", ".join(parts) + hint


# -- evaluate ---------------------------------------------------------------------------------


def cmd_evaluate(args: argparse.Namespace) -> int:
    from .io import load_calibration  # noqa: PLC0415
    from .reconstruct import evaluate  # noqa: PLC0415

    rec = _open(args.recording, args.sensor_size, args)
    cal = load_calibration(args.calibration)
    if cal.shape != rec.sensor.shape:
        raise CliError(f"calibration is {cal.shape[1]}x{cal.shape[0]}, the recording's sensor "
                       f"is {rec.sensor}")
    res = evaluate(rec, cal, events_per_image=args.events_per_image,
                   frames_per_image=args.frames_per_image, skip_s=args.skip_s)
    summary = res.summary()
    _review(args, "evaluate", rec, cal, reconstruct=True,
            frames_per_image=args.frames_per_image or 5)
    for note in (res.params.get("events_per_image_note"), res.log_offset_note):
        if note and note not in ("given", "from the calibration"):
            _note(args, "evaluate", f"note: {note}")
    n_invalid = int((~cal.valid).sum())
    if n_invalid and cal.valid.any():
        # the reconstruction integrates them with the valid pixels' median (with_invalid_filled)
        _note(args, "evaluate", f"note: {n_invalid} of {cal.valid.size} pixels "
              f"({100 * n_invalid / cal.valid.size:.1f} %) have no valid estimate and are "
              f"integrated with the valid pixels' median c = "
              f"{float(np.median(cal.contrast[cal.valid])):.4g}, b = "
              f"{float(np.median(cal.bias[cal.valid])):.4g}")
    if args.json == "-":
        _write_json("-", summary)
        return 0
    keys = ("rmse", "psnr", "ssim", "psnr_paper", "ssim_paper")
    print(f"images: {summary['n_images']}   (psnr, ssim: standard; *_paper: the reference "
          f"code's 20·log10(255²/MSE) and single-window SSIM)")
    print(f"{'':12}" + "".join(f"{k:>12}" for k in keys))
    for name in ("calibrated", "di"):
        print(f"{name:12}" + "".join(f"{summary[name][k]:>12.4f}" for k in keys))
    if args.json:
        _write_json(args.json, summary)
    return 0


# -- simulate ---------------------------------------------------------------------------------


def cmd_simulate(args: argparse.Namespace) -> int:
    from .io import write_recording  # noqa: PLC0415
    from .sim.ideal import SimConfig, simulate_ideal  # noqa: PLC0415
    from .sim.scene import Trajectory  # noqa: PLC0415

    sensor = _sensor_arg(args.sensor_size) or SensorSize(180, 240)
    cfg = SimConfig(
        height=sensor.height, width=sensor.width, duration_s=args.duration_s,
        frame_rate_hz=args.frame_rate_hz, internal_rate_hz=args.internal_rate_hz,
        contrast_mean=args.contrast_mean, contrast_std=args.contrast_std,
        bias_mean=args.bias_mean, bias_std=args.bias_std, log_offset=args.log_offset,
        scene=args.scene, trajectory=Trajectory(speed=args.speed, seed=args.seed),
        seed=args.seed,
    )
    n_steps = int(cfg.duration_s * cfg.internal_rate_hz)
    with _progress(n_steps, "simulate", args.quiet, "steps") as bar:
        res = simulate_ideal(cfg, progress=lambda k: bar.update(1))
    out = Path(args.out)
    write_recording(res.recording, out)
    truth_path = truth_path_for(out)
    np.savez(truth_path, contrast=res.truth["contrast"], bias=res.truth["bias"],
             log_offset=res.truth["log_offset"], seed=res.truth["seed"],
             config_json=json.dumps(cfg.to_dict()))
    rec = res.recording
    print(f"simulated {rec.n_events} events and {len(rec.frames)} frames "
          f"({rec.sensor}, {cfg.duration_s} s) -> {out}; truth -> {truth_path}")
    return 0


def truth_path_for(out: Path) -> Path:
    """Where ``evcal simulate`` writes the truth for a recording at ``out``."""
    out = Path(out)
    if out.suffix in (".mcap", ".npz", ".aedat4"):
        return out.with_name(out.stem + ".truth.npz")
    return out / "truth.npz"


# -- bench ------------------------------------------------------------------------------------


def cmd_bench(args: argparse.Namespace) -> int:
    from .bench import run_bench  # noqa: PLC0415

    figures = run_bench(quick=args.quick, progress=not args.quiet)
    for k, v in figures.items():
        print(f"{k:<44} {v}")
    if args.json:
        Path(args.json).write_text(json.dumps(figures, indent=2))
    return 0


def cmd_warmup(args: argparse.Namespace) -> int:
    import os  # noqa: PLC0415

    from .warmup import compile_kernels  # noqa: PLC0415

    def say(stage: str) -> None:
        _note(args, "warmup", f"{stage} ...")

    report = compile_kernels(None if args.quiet else say)
    where = os.environ.get("NUMBA_CACHE_DIR") or "__pycache__ beside the sources"
    print(f"compiled or loaded evcal's kernels in {report.total_s:.1f} s (cache: {where})")
    for stage, why in report.failed.items():
        print(f"  {stage} failed: {why}", file=sys.stderr)
    return 1 if report.failed else 0


# -- delegated subcommands --------------------------------------------------------------------


def _delegate(module: str, func: str = "main", extra: str = "service"
              ) -> Callable[[list[str]], int]:
    def run(argv: list[str]) -> int:
        import importlib  # noqa: PLC0415

        try:
            mod = importlib.import_module(module)
        except ModuleNotFoundError as exc:
            raise CliError(f"{module} needs the '{extra}' extra ({exc.name} is missing): "
                           f"pip install 'evcal[{extra}]'") from None
        return int(getattr(mod, func)(argv) or 0)

    return run


DELEGATED: dict[str, tuple[Callable[[list[str]], int], str]] = {
    "gap": (_delegate("evcal.gap.cli", extra="gap"),
            "find and name the effects a recording shows that the model lacks"),
    "serve": (_delegate("evcal.service.cli", "main_serve"), "run the live calibration service"),
    "replay": (_delegate("evcal.clients.replay"), "publish a recording onto Zenoh"),
    "query": (_delegate("evcal.clients.query"), "fetch a camera's current calibration"),
    "record": (_delegate("evcal.clients.record"), "record Zenoh traffic to MCAP"),
    "demo": (_delegate("evcal.clients.demo"), "end-to-end demo with an embedded Zenoh peer"),
    "keygen": (_delegate("evcal.clients.admin", "main_keygen"),
               "make an Ed25519 key pair to sign calibrations"),
    "forget": (_delegate("evcal.clients.admin", "main_forget"),
               "ask the service to drop a camera's state"),
}


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="evcal", description=DESCRIPTION, epilog=EPILOG,
                                formatter_class=HelpFormatter)
    from . import __version__  # noqa: PLC0415

    p.add_argument("--version", action="version", version=f"evcal {__version__}")
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")

    def add_parser(name: str, **kw: Any) -> argparse.ArgumentParser:
        return sub.add_parser(name, formatter_class=HelpFormatter, **kw)

    def common(sp: argparse.ArgumentParser, recording: bool = True) -> None:
        if recording:
            sp.add_argument("recording", help="an ECD folder, AEDAT 2.0/3.1/4, Prophesee RAW "
                                              "(EVT 2/2.1/3) or DAT, HDF5 (MVSEC, DSEC, v2e), "
                                              "a ROS 1/2 bag, evcal .mcap or .npz; detected "
                                              "by content (docs/FORMATS.md)")
            sp.add_argument("--sensor-size", metavar="WxH", help="sensor size, e.g. 240x180")
            sp.add_argument("--events-topic", metavar="TOPIC", default=None,
                            help="a bag's event topic, when it holds several")
            sp.add_argument("--frames-topic", metavar="TOPIC", default=None,
                            help="a bag's image topic, when it holds several")
            sp.add_argument("--camera", metavar="NAME", default=None,
                            help="which camera of a stereo HDF5 file (MVSEC: left or right)")
            sp.add_argument("--strict", action="store_true",
                            help="refuse a recording file cut short (default: read its whole "
                                 "records, with a warning naming where it was cut)")
        verbosity(sp)

    def review(sp: argparse.ArgumentParser, what: str) -> None:
        sp.add_argument("--rrd", metavar="OUT.rrd", default=None,
                        help=f"a Rerun recording to review: {what} (needs the service extra; "
                             "open with `rerun OUT.rrd`)")
        sp.add_argument("--truth", metavar="TRUTH.npz", default=None,
                        help="true c and b maps (contrast, bias), for error maps in --rrd "
                             "(default: the .truth.npz evcal simulate wrote beside the "
                             "recording, if any)")

    def verbosity(sp: argparse.ArgumentParser) -> None:
        sp.add_argument("-q", "--quiet", action="store_true",
                        help="no progress bars, notes or warnings on stderr (errors still)")
        sp.add_argument("-v", "--verbose", action="count", default=0,
                        help="log what is done on stderr (-vv: debug detail)")

    sp = add_parser("info", help="sensor size, duration, counts and event rate")
    common(sp)
    sp.add_argument("--json", action="store_true", help="print JSON")
    sp.set_defaults(func=cmd_info)

    sp = add_parser("calibrate", help="estimate per-pixel contrast and bias")
    common(sp)
    sp.add_argument("--method", choices=list(ESTIMATORS), default="offei",
                    help="; ".join(f"{e.name}: {e.summary}" for e in ESTIMATORS.values()))
    sp.add_argument("--out", required=True, help="calibration .npz to write")
    sp.add_argument("--log-offset", type=_offset_arg, default="auto",
                    help="'auto' (estimated) or a number added to frames before the log")
    sp.add_argument("--window-frames", type=int, default=None,
                    help="OffEI window d in frame intervals (default 5)")
    sp.add_argument("--n-small", type=_positive_int, default=None,
                    help="OnEI events per small buffer (default: 200 k scaled from 240x180 "
                         "to the sensor, at most an eighth of the recording's events)")
    sp.add_argument("--n-large", type=_positive_int, default=None,
                    help="OnEI events in the large buffer (default: 1.7 M, scaled likewise)")
    sp.add_argument("--smoothing", type=float, default=None,
                    help="OnEI low-pass factor in (0, 1] (default 0.1)")
    sp.add_argument("--c0", type=float, default=None,
                    help="OffE's scale, the population's median contrast (default 0.1: "
                         "without frames there is no absolute scale; give a known one)")
    sp.add_argument("--error-scale", choices=list(ERROR_SCALES), default="auto",
                    help="check the stated standard errors on the recording's two halves in "
                         "time and rescale them ('auto': OnEI only, about twice its time; "
                         "the scale is in the file's diagnostics)")
    sp.add_argument("--csv", metavar="DIR", help="also write scale.csv and bias.csv")
    sp.add_argument("--model", metavar="REPORT.json", default=None,
                    help="OffEI corrected for the bias of the effects named by 'evcal gap' "
                         "(its report.json): the recording is simulated under that model and "
                         "the fit's gain and offset removed (docs/GAP.md)")
    sp.add_argument("--seed", type=int, default=0, help="seed of --model's simulations")
    sp.add_argument("--posterior", action="store_true",
                    help="OffEI and OnEI: write posterior maps, each pixel pulled toward "
                         "the sensor's population by how little its own events say (special "
                         "pixels keep their own values; the file says it holds them; default: "
                         "the raw per-pixel estimate). Not always a gain: on simulated scenes "
                         "OffEI's error falls by 10-18 %%, OnEI's by 1-21 %% but its "
                         "reconstruction PSNR by up to 1 dB; on some v2e recordings OffEI's "
                         "error rises and its stated errors are too small; compare with "
                         "'evaluate'")
    sp.add_argument("--event-timing", action="store_true",
                    help="OffEI and OnEI: fuse each pixel's estimate with the events-only "
                         "one (OffE: when its events fall, against its neighbours'), weighted "
                         "by their errors; before --posterior. On simulated and v2e "
                         "recordings c's error falls by 0-27 %%, b's by 0-30 %% (the file's "
                         "diagnostics say how much was fused)")
    sp.add_argument("--stream", action="store_true",
                    help="OffEI of an evcal .mcap read message by message, for recordings "
                         "larger than memory (a progress bar on stderr; with --log-offset "
                         "auto the offset comes from the first --prefix-frames frames)")
    sp.add_argument("--prefix-frames", type=_positive_int, default=250,
                    help="--stream with --log-offset auto: frames the offset is estimated "
                         "on (default 250)")
    sp.add_argument("--json", nargs="?", const="-", metavar="OUT.json", default=None,
                    help="the summary and diagnostics as JSON: to OUT.json, or instead of the "
                         "table on stdout when no file is given")
    review(sp, "the maps, their masks, standard errors and histograms")
    sp.set_defaults(func=cmd_calibrate)

    sp = add_parser("evaluate", help="reconstruction quality against DI")
    common(sp)
    sp.add_argument("--calibration", required=True,
                    help="calibration .npz (evcal calibrate, evcal query or the service's)")
    sp.add_argument("--events-per-image", type=int, default=500_000,
                    help="integrate from a frame until this many events (default 500000, "
                         "lowered with a note when the recording holds fewer)")
    sp.add_argument("--frames-per-image", type=int, default=None,
                    help="integrate over this many frame intervals instead of an event count")
    sp.add_argument("--skip-s", type=float, default=0.0,
                    help="seconds at the start left out of the scoring (default 0)")
    sp.add_argument("--json", nargs="?", const="-", metavar="OUT.json", default=None,
                    help="the scores as JSON: to OUT.json, or instead of the table on stdout "
                         "when no file is given")
    review(sp, "the maps and every reconstruction beside DI's and the frame, PSNR over time, "
               "the events")
    sp.set_defaults(func=cmd_evaluate)

    sp = add_parser("simulate", help="ideal event camera simulation with known c, b")
    common(sp, recording=False)
    sp.add_argument("--out", required=True, help="recording to write (.mcap, .npz or folder)")
    sp.add_argument("--sensor-size", metavar="WxH", default="240x180",
                    help="sensor width x height (default 240x180)")
    sp.add_argument("--duration-s", type=float, default=10.0, help="seconds (default 10)")
    sp.add_argument("--frame-rate-hz", type=float, default=25.0,
                    help="APS frame rate (default 25)")
    sp.add_argument("--internal-rate-hz", type=float, default=1000.0,
                    help="rate of the simulator's intensity steps (default 1000)")
    sp.add_argument("--contrast-mean", type=float, default=0.2,
                    help="mean contrast threshold c over pixels (default 0.2)")
    sp.add_argument("--contrast-std", type=float, default=0.03,
                    help="pixel-to-pixel spread of c (default 0.03)")
    sp.add_argument("--bias-mean", type=float, default=0.02,
                    help="mean bias b (default 0.02; ON fires at c + b, OFF at c - b)")
    sp.add_argument("--bias-std", type=float, default=0.01,
                    help="pixel-to-pixel spread of b (default 0.01)")
    sp.add_argument("--log-offset", type=float, default=30.0,
                    help="the sensor sees log(I + offset), frames in DN (default 30)")
    sp.add_argument("--scene", default="astronaut", help="scikit-image photo name or image path")
    sp.add_argument("--speed", type=float, default=1.0, help="camera motion speed factor")
    sp.add_argument("--seed", type=int, default=0,
                    help="seed of the maps and the motion (default 0)")
    sp.set_defaults(func=cmd_simulate)

    sp = add_parser("bench", help="print speed and memory figures")
    sp.add_argument("--json", metavar="OUT.json", help="also write the figures as JSON")
    sp.add_argument("--quick", action="store_true", help="smaller sizes (for CI smoke runs)")
    verbosity(sp)
    sp.set_defaults(func=cmd_bench)

    sp = add_parser("warmup", help="compile the numba kernels into their disk cache now "
                                   "(an editable install does it already; for images and "
                                   "moved installs, with NUMBA_CACHE_DIR)")
    verbosity(sp)
    sp.set_defaults(func=cmd_warmup)

    for name, (_, helptext) in DELEGATED.items():
        add_parser(name, help=helptext, add_help=False)
    return p


def _setup_logging(args: argparse.Namespace) -> None:
    """-v: INFO, -vv: DEBUG, -q: errors only, on stderr."""
    verbose, quiet = getattr(args, "verbose", 0), getattr(args, "quiet", False)
    level = (logging.ERROR if quiet else logging.WARNING if not verbose
             else logging.INFO if verbose == 1 else logging.DEBUG)
    logging.basicConfig(level=level, format="evcal %(levelname)s %(name)s: %(message)s",
                        stream=sys.stderr)
    logging.getLogger("evcal").setLevel(level)


def _note(args: argparse.Namespace, command: str, text: str) -> None:
    """A note or warning on stderr, unless -q."""
    if not getattr(args, "quiet", False):
        print(f"evcal {command}: {text}", file=sys.stderr)


def _write_json(target: str, data: Any) -> None:
    from .jsonable import to_jsonable  # noqa: PLC0415

    text = json.dumps(to_jsonable(data), indent=2)
    if target == "-":
        print(text)
    else:
        Path(target).write_text(text + "\n")


def _review(args: argparse.Namespace, command: str, rec: Any, cal: Any, *,
            reconstruct: bool, frames_per_image: int = 5) -> None:
    """``--rrd``: the offline review recording (service/rrdlog.py, rerun)."""
    if not args.rrd:
        return
    try:
        from .service.rrdlog import write_review  # noqa: PLC0415
    except ModuleNotFoundError as exc:
        raise CliError(f"--rrd needs the 'service' extra ({exc.name} is missing): "
                       "pip install 'evcal[service]'") from None
    truth_file = Path(args.truth) if args.truth else truth_path_for(Path(args.recording))
    truth = None
    if truth_file.is_file():
        with np.load(truth_file) as z:
            if "contrast" not in z or "bias" not in z:
                raise CliError(f"--truth {truth_file}: no contrast and bias arrays")
            truth = (z["contrast"], z["bias"])
        if truth[0].shape != cal.shape:
            raise CliError(f"--truth {truth_file}: maps of shape {truth[0].shape}, the "
                           f"calibration is {cal.shape}")
        if not args.truth:
            _note(args, command, f"note: error maps against the truth in {truth_file}")
    elif args.truth:
        raise CliError(f"--truth {truth_file}: no such file")
    path = write_review(args.rrd, rec, cal, camera=Path(args.recording).name or "recording",
                        truth=truth, reconstruct=reconstruct,
                        frames_per_image=frames_per_image)
    _note(args, command, f"review recording: {path} (rerun {path})")


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    try:
        if argv and argv[0] in DELEGATED:
            return DELEGATED[argv[0]][0](argv[1:])
        args = build_parser().parse_args(argv)
        _setup_logging(args)
        return int(args.func(args))
    except CliError as exc:
        print(f"evcal: error: {exc}", file=sys.stderr)
        return 2
    except (ValueError, OSError) as exc:
        # typed errors of the library (RecordingError, EventError, CalibrationError, ...)
        print(f"evcal: error: {type(exc).__name__}: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        return 130


def entry() -> None:
    sys.exit(main())


if __name__ == "__main__":
    entry()
