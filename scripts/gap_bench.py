"""Larger hidden-effect runs of the gap workflow, printing the acceptance table.

For each effect of the library (and the none and two-effect cases) a recording is simulated
with the effect hidden, ``evcal.gap`` is run on it, and a row gives: the effects named, the gap
before and after, and the fitted against the true main parameter.

    PYTHONPATH=src python scripts/gap_bench.py [--size 64x96] [--duration 3] [--seed 101]
"""

from __future__ import annotations

import argparse
import sys
import time

from evcal.events import SensorSize
from evcal.gap.workflow import GapConfig, run_gap
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


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", default="96x64", help="WxH")
    ap.add_argument("--duration", type=float, default=3.0)
    ap.add_argument("--frame-rate", type=float, default=200.0)
    ap.add_argument("--seed", type=int, default=101)
    ap.add_argument("--n-seeds", type=int, default=3)
    ap.add_argument("--max-effects", type=int, default=3)
    ap.add_argument("--only", default="", help="comma-separated case names")
    args = ap.parse_args(argv)
    size = SensorSize.parse(args.size)
    print(f"| case | named | gap before | gap after | fitted vs true | time |")
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
