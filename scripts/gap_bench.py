"""Larger hidden-effect runs of the gap workflow, printing the acceptance table; and its speed.

For each effect of the library (and the none and two-effect cases) a recording is simulated
with the effect hidden, ``evcal.gap`` is run on it, and a row gives: the effects named, the gap
before and after, and the fitted against the true main parameter.

    PYTHONPATH=src python scripts/gap_bench.py [--size 64x96] [--duration 3] [--seed 101]

``--speed`` runs the whole workflow instead on recordings of a user's size (each in a process
of its own, so that its peak memory is its own) and prints wall seconds, simulations, seconds
per million events and per megapixel-second of recording, and peak memory: a 3 s 240x180 and
a 30 s 346x260 recording simulated at 25 Hz frames (a pan over a photo with shot noise and a
dead time hidden), and the real DAVIS346 ``road.aedat4`` when ``../shared/data`` has it.

    python scripts/gap_bench.py --speed [--cases small,long,road]
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from typing import Any

from evcal.events import SensorSize
from evcal.gap.workflow import GapConfig, n_simulations, run_gap, working_window
from evcal.progress import Progress
from evcal.sim.effects import (
    Bandwidth,
    HotPixels,
    Leak,
    LogOffset,
    Refractory,
    ShotNoise,
    ThresholdNoise,
    TimestampJitter,
)
from evcal.sim.ideal import SimConfig
from evcal.sim.nonideal import simulate
from evcal.sim.scene import Trajectory
from evcal.sim.sources import MovingScene, SpeedProfile

CASES = {
    "none": [],
    "refractory": [Refractory(period_us=1300.0)],
    "refractory (delay)": [Refractory(period_us=1300.0, mode="delay")],
    "leak": [Leak(rate_hz=0.8)],
    "shot_noise": [ShotNoise(rate_hz=1.3)],
    "bandwidth": [Bandwidth(cutoff_hz=50.0)],
    "threshold_noise": [ThresholdNoise(sigma=0.22)],
    "hot_pixels": [HotPixels(fraction=0.003, rate_hz=100.0)],
    "log_offset": [LogOffset(dark_dn=40.0)],
    "timestamp_jitter": [TimestampJitter(sigma_us=400.0)],
    "two: shot_noise + log_offset": [ShotNoise(rate_hz=1.0), LogOffset(dark_dn=30.0)],
    "two: leak + refractory": [Leak(rate_hz=0.8), Refractory(period_us=1200.0)],
}


def build(size: SensorSize, duration_s: float, frame_rate_hz: float, seed: int, effects):
    traj = Trajectory(pan_px=30.0, seed=seed)
    cfg = SimConfig(height=size.height, width=size.width, duration_s=duration_s,
                    frame_rate_hz=frame_rate_hz, internal_rate_hz=1000.0, log_offset=1.0,
                    seed=seed, trajectory=traj)
    still = 0.25 * duration_s
    src = MovingScene(cfg.scene, size.shape, traj, speed=SpeedProfile(
        segments=((still, 0.0), (0.375 * duration_s, 1.0), (0.375 * duration_s, 2.5))))
    return simulate(cfg, effects, source=src).recording


SPEED_CASES = {
    # name: (W x H, seconds, frame rate) of a simulated recording, or a path
    "small": ("240x180", 3.0, 25.0),
    "long": ("346x260", 30.0, 25.0),
    "road": "davis346_road/road.aedat4",
}


SPEED_EFFECTS = [ShotNoise(rate_hz=0.5), Refractory(period_us=800.0)]  # hidden in the cases


def _build_case(name: str, path: str) -> None:
    """A simulated speed case written to ``path`` (in a process of its own: the simulator's
    memory is not the workflow's)."""
    from evcal.io import write_recording  # noqa: PLC0415

    size, dur, rate = SPEED_CASES[name]
    write_recording(build(SensorSize.parse(size), dur, rate, 7, SPEED_EFFECTS), path)


def _speed_case(name: str, path: str, out: Any) -> None:
    """One speed case read from ``path``, in a process of its own (its peak memory is the
    workflow's and the recording's): its figures put on ``out`` (a queue)."""
    import resource  # noqa: PLC0415

    from evcal.io import open_recording  # noqa: PLC0415
    from evcal.mallocpolicy import trim_freed_memory  # noqa: PLC0415
    cfg = GapConfig()
    t0 = time.perf_counter()
    # as `evcal gap` does: cut to the working window at once, the whole recording let go
    rec, window = working_window(open_recording(path), cfg.max_pixel_steps,
                                 cfg.internal_rate_hz, cfg.max_events)
    # the estimates of the whole run's duration that `evcal gap` would show: its first line
    # (10 s in) and at a quarter of the run (found afterwards from the samples)
    prog = Progress(n_simulations(cfg), "gap", unit="simulations", quiet=True, skip_first=True)
    samples: list[tuple[float, float]] = []  # (elapsed, estimated total)

    def tick(work: float) -> None:
        prog.update(work)
        first = prog._first  # noqa: SLF001 - the rate's start, as Progress.line takes it
        now = time.perf_counter() - t0
        if first is not None and prog.done > first[1] and prog.total is not None:
            rate = (prog.done - first[1]) / max(time.monotonic() - first[0], 1e-9)
            samples.append((now, now + (prog.total - prog.done) / rate))

    res = run_gap(rec, cfg, progress=tick, plan=prog.plan, window=window,
                  released=trim_freed_memory)  # as `evcal gap` does
    dt = time.perf_counter() - t0

    def estimate_at(at_s: float) -> float:
        return next((est for el, est in samples if el >= at_s), float("nan"))
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    h, w = rec.sensor.shape
    info = res.recording_info
    n_events, duration_s = info["n_events"], info["duration_s"]
    named = [f"{s.effect.name} {s.effect.primary}="
             f"{s.effect.parameters()[s.effect.primary]:.4g}" for s in res.steps]
    out.put({"case": name, "sensor": str(rec.sensor), "duration_s": duration_s,
             "events": n_events, "seconds": dt, "simulations": info["simulations"],
             "named": named, "gap": (res.initial.gap, res.final.gap), "peak_mib": peak,
             "s_per_mevent": dt / max(n_events / 1e6, 1e-9),
             "s_per_mpix_s": dt / (h * w / 1e6 * duration_s),
             "window_frames": f"{window['frames']}/{window['of_frames']} "
                              f"({window.get('events', n_events):,} events)",
             "eta_first_s": estimate_at(10.0), "eta_quarter_s": estimate_at(0.25 * dt)})


def speed(cases: list[str]) -> int:
    import multiprocessing as mp  # noqa: PLC0415

    ctx = mp.get_context("spawn")
    print(f"load average before: {os.getloadavg()[0]:.2f} (1 min), "
          f"{os.cpu_count()} cores; hidden in the simulated cases: "
          + ", ".join(f"{e.name} {e.primary}={e.parameters()[e.primary]:g}"
                      for e in SPEED_EFFECTS))
    print("| case | sensor | duration | events | analysed frames | simulations | wall | "
          "s / M events | s / megapixel-second | peak memory | named | gap | "
          "duration estimated at 10 s / at a quarter |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    import tempfile  # noqa: PLC0415
    from pathlib import Path  # noqa: PLC0415

    tmp = tempfile.TemporaryDirectory(prefix="gap_bench_")
    for name in cases:
        spec = SPEED_CASES[name]
        if isinstance(spec, str):
            base = Path(os.environ.get("EVCAL_SHARED_DATA", Path(__file__).resolve().parents[2]
                                       / "shared" / "data"))
            path = base / spec
            if not path.exists():
                print(f"| {name} | skipped: {spec} not found |")
                continue
        else:
            path = Path(tmp.name) / f"{name}.npz"
            b = ctx.Process(target=_build_case, args=(name, str(path)))
            b.start()
            b.join()
        q = ctx.Queue()
        p = ctx.Process(target=_speed_case, args=(name, str(path), q))
        p.start()
        r = q.get()
        p.join()
        print(f"| {name} | {r['sensor']} | {r['duration_s']:.1f} s | {r['events']:,} | "
              f"{r['window_frames']} | {r['simulations']} | {r['seconds']:.0f} s | "
              f"{r['s_per_mevent']:.1f} | {r['s_per_mpix_s']:.1f} | "
              f"{r['peak_mib']:.0f} MiB | {', '.join(r['named']) or 'none'} | "
              f"{r['gap'][0]:.1f} -> {r['gap'][1]:.1f} | {r['eta_first_s']:.0f} s / "
              f"{r['eta_quarter_s']:.0f} s |", flush=True)
    tmp.cleanup()
    return 0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--speed", action="store_true",
                    help="time the workflow on recordings of a user's size instead")
    ap.add_argument("--cases", default="small,long,road",
                    help="with --speed: which of " + ", ".join(SPEED_CASES))
    ap.add_argument("--size", default="96x64", help="WxH")
    ap.add_argument("--duration", type=float, default=3.0)
    ap.add_argument("--frame-rate", type=float, default=200.0)
    ap.add_argument("--seed", type=int, default=101)
    ap.add_argument("--n-seeds", type=int, default=3)
    ap.add_argument("--max-effects", type=int, default=3)
    ap.add_argument("--only", default="", help="comma-separated case names")
    args = ap.parse_args(argv)
    if args.speed:
        return speed([c for c in args.cases.split(",") if c])
    size = SensorSize.parse(args.size)
    print("| case | named | gap before | gap after | fitted vs true | time |")
    print("|---|---|---|---|---|---|")
    for k, (name, effects) in enumerate(CASES.items()):
        if args.only and name not in args.only.split(","):
            continue
        rec = build(size, args.duration, args.frame_rate, args.seed + k, effects)
        t0 = time.perf_counter()
        res = run_gap(rec, GapConfig(max_effects=args.max_effects, n_seeds=args.n_seeds,
                                     seed=args.seed))
        dt = time.perf_counter() - t0
        fits = []
        for e in effects:
            step = next((s for s in res.steps if s.effect.name == e.name), None)
            true = e.parameters()[e.primary]
            got = "not named" if step is None else f"{step.effect.parameters()[e.primary]:.4g}"
            fits.append(f"{e.name}.{e.primary}: {got} vs {true:g}")
        print(f"| {name} | {', '.join(res.named_effects) or 'none'} | {res.initial.gap:.2f} | "
              f"{res.final.gap:.2f} | {'; '.join(fits) or '-'} | {dt:.0f} s |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
