"""``evcal gap RECORDING --out DIR [--max-effects N] [--seed S]``: the model-gap workflow.

:func:`main` takes the arguments after the subcommand and returns the exit status.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path

from ..clihelp import HelpFormatter
from ..sim.effects import EFFECT_NAMES


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="evcal gap", formatter_class=HelpFormatter,
        description="Find where simulation and measurement disagree, name the missing sensor "
                    "effect, add it and show the gap shrink.",
        epilog="Candidates are fitted on the sensor's even rows and judged on its odd rows, "
               "held to what their fitters read on the model's own simulations (docs/GAP.md). "
               "Cost: about a minute for a 3 s 240x180 recording on 2 cores; a longer "
               "recording is cut to its busiest stretch within --max-events and "
               "--max-pixel-steps. Progress goes to stderr: a bar on a terminal, else a line "
               "every 10 s with the time left.")
    p.add_argument("recording", help="ECD folder, .aedat4, .mcap or .npz (needs frames)")
    p.add_argument("--out", required=True, help="output directory (report.json, report.md, "
                   "PNG plots, gap.rrd)")
    p.add_argument("--max-effects", type=int, default=3,
                   help="at most this many sensor effects named (the timestamp scheme of a "
                   "frame-driven simulator is named apart)")
    p.add_argument("--seed", type=int, default=0, help="seed of the simulations")
    p.add_argument("--n-seeds", type=int, default=3,
                   help="simulations per model (their spread; at least 3: the null calibration "
                        "takes one as a pseudo-measurement; default %(default)s)")
    p.add_argument("--internal-rate-hz", type=float, default=1000.0,
                   help="internal sample rate of the simulations")
    p.add_argument("--sensor", default=None, help="WxH, for recordings that do not store it")
    p.add_argument("--candidates", default=",".join(EFFECT_NAMES),
                   help="comma-separated effects to try (default: every effect)")
    p.add_argument("--interpolation", choices=("flow", "linear"), default="flow",
                   help="latent intensity between frames: motion-compensated (flow, default) "
                        "or a linear blend")
    p.add_argument("--no-subframe-motion", action="store_true",
                   help="drive the simulations by the flow's straight path between frames "
                        "(default: the image's shake between frames read from the events)")
    p.add_argument("--max-events", type=float, default=4e6,
                   help="analyse at most this many events: a longer recording is cut to its "
                        "busiest frames that hold them (default %(default).0e; 0: no limit)")
    p.add_argument("--max-pixel-steps", type=float, default=2.5e8,
                   help="analyse at most this many pixels x internal samples (a longer "
                        "recording is cut to its busiest contiguous frames; default 2.5e8: "
                        "2.7 s of 346x260 at 1 kHz)")
    p.add_argument("--workers", type=int, default=None,
                   help="simulations run at once (default: the usable cores)")
    p.add_argument("--no-screen", action="store_true",
                   help="evaluate every candidate on every seed (slower; default: one seed "
                        "each, the best confirmed on all)")
    p.add_argument("--no-plots", action="store_true", help="skip the PNG plots")
    p.add_argument("--no-rrd", action="store_true", help="skip gap.rrd")
    p.add_argument("-q", "--quiet", action="store_true",
                   help="no progress bar or notes on stderr (errors still)")
    p.add_argument("-v", "--verbose", action="count", default=0,
                   help="log the workflow's steps on stderr (-vv: debug)")
    return p


def run(args: argparse.Namespace) -> int:
    import logging  # noqa: PLC0415

    logging.basicConfig(
        level=logging.ERROR if args.quiet
        else (logging.WARNING, logging.INFO, logging.DEBUG)[min(args.verbose, 2)],
        stream=sys.stderr, format="evcal gap %(levelname)s %(name)s: %(message)s")
    from ..events import SensorSize  # noqa: PLC0415
    from ..io import open_recording  # noqa: PLC0415
    from ..recording import RecordingError  # noqa: PLC0415
    from .explain import summary  # noqa: PLC0415
    from .report import write_reports  # noqa: PLC0415
    from .stats import GapError  # noqa: PLC0415
    from .workflow import GapConfig, n_simulations, run_gap, working_window  # noqa: PLC0415

    try:
        cands = tuple(c.strip() for c in args.candidates.split(",") if c.strip())
        cfg = GapConfig(max_effects=args.max_effects, seed=args.seed, n_seeds=args.n_seeds,
                        interpolation=args.interpolation,
                        subframe_motion=not args.no_subframe_motion,
                        internal_rate_hz=args.internal_rate_hz, candidates=cands,
                        max_pixel_steps=int(args.max_pixel_steps), workers=args.workers,
                        max_events=int(args.max_events) or None,
                        screen=not args.no_screen)
        sensor = SensorSize.parse(args.sensor) if args.sensor else None
    except ValueError as exc:
        print(f"evcal gap: {exc}", file=sys.stderr)
        return 2
    missing = _missing_modules(flow=args.interpolation == "flow", plots=not args.no_plots,
                               rrd=not args.no_rrd)
    if missing:
        print(f"evcal gap: {', '.join(missing)} missing: pip install 'evcal[gap]' (or pass "
              "--interpolation linear, --no-plots, --no-rrd)", file=sys.stderr)
        return 1
    from ..mallocpolicy import trim_freed_memory  # noqa: PLC0415
    try:
        # cut at once: the whole recording (800 MB for 30 s of a busy DAVIS346) is not held
        # during the run
        rec, window = working_window(open_recording(args.recording, sensor=sensor),
                                     cfg.max_pixel_steps, cfg.internal_rate_hz,
                                     cfg.max_events)
    except (RecordingError, GapError) as exc:
        print(f"evcal gap: {args.recording}: {exc}", file=sys.stderr)
        return 1
    from ..progress import Progress  # noqa: PLC0415

    # the time left is the workflow's forecast, made at each round from the time the base
    # model took (the simulations' rate says little: fitters and statistics take much of a
    # round's time), unknown until the first round
    progress = Progress(n_simulations(cfg), "gap", unit="simulations planned",
                        quiet=args.quiet, decimals=1, skip_first=True, forecasts=True,
                        opening="fitting the base model (the time left is known once it is "
                                "fitted); the first simulation also renders the light "
                                "between the frames")
    try:
        result = run_gap(rec, cfg, progress=progress.update, plan=progress.plan, window=window,
                         released=trim_freed_memory, forecast=progress.forecast)
    except GapError as exc:
        print(f"evcal gap: {args.recording}: {exc}", file=sys.stderr)
        return 1
    finally:
        progress.close()
    result.recording_info["source"] = str(args.recording)
    paths = write_reports(result, Path(args.out), plots=not args.no_plots, rrd=not args.no_rrd)
    named = ", ".join(
        f"{s.effect.name} ({', '.join(f'{k}={v}' for k, v in s.effect.parameters().items())})"
        for s in result.steps) or "none"
    print(f"named effects: {named}")
    print(f"gap {result.initial.gap:.2f} -> {result.final.gap:.2f}; report in {paths['markdown']}")
    print("not explained:")
    for line in summary(result.final.disc):
        print(f"  {line}")
    return 0


def _missing_modules(*, flow: bool, plots: bool, rrd: bool) -> list[str]:
    """The optional modules (the ``gap`` extra) this run needs and cannot import: checked
    before the hour-long workflow, not when its report is written."""
    import importlib.util  # noqa: PLC0415

    needed = [("cv2 (opencv-python-headless)", "cv2", flow),
              ("matplotlib", "matplotlib", plots), ("rerun (rerun-sdk)", "rerun", rrd)]
    return [label for label, mod, used in needed
            if used and importlib.util.find_spec(mod) is None]


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``evcal gap`` (``argv`` excludes the subcommand)."""
    args = build_parser().parse_args(list(argv) if argv is not None else None)
    return run(args)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
