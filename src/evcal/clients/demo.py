"""``evcal demo``: the whole live pipeline on one machine, with nothing else running.

1. Simulate a camera: a real photo (scikit-image's astronaut) moved by a camera, ideal DVS
   pixels whose ``c`` and ``b`` are drawn per pixel from known normal distributions.
2. Start the service in this process on an embedded zenoh peer (``tcp/127.0.0.1``, a free
   port, multicast scouting off), recording to ``demo.rrd``.
3. Replay the simulated recording onto it from a second zenoh session, as fast as the
   service takes it (blocking publishers, ``on_full=block``: lossless).
4. Query the live calibration like ``evcal query`` does, stop the service (the ``.rrd`` is
   complete), and print a table: contrast and bias errors against the truth, and the PSNR of
   event-integration reconstructions with direct integration (DI) and with the live
   calibration (offline OffEI on the same data for reference).
"""

from __future__ import annotations

import argparse
import sys
import threading
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from ..clihelp import HelpFormatter


def _say(msg: str) -> None:
    print(f"evcal demo: {msg}", file=sys.stderr, flush=True)


def error_row(name: str, cal: Any, truth: dict[str, np.ndarray], evaluation: Any
              ) -> dict[str, Any]:
    v = cal.valid
    c_err = np.abs(cal.contrast[v] - truth["contrast"][v])
    b_err = np.abs(cal.bias[v] - truth["bias"][v])
    s = evaluation.summary()
    return {"method": name, "valid_pct": 100.0 * float(v.mean()),
            "c_mae": float(c_err.mean()) if c_err.size else float("nan"),
            "c_rel_pct": 100.0 * float(np.median(c_err / truth["contrast"][v])) if c_err.size
            else float("nan"),
            "b_mae": float(b_err.mean()) if b_err.size else float("nan"),
            "psnr_db": s["calibrated"]["psnr"], "psnr_di_db": s["di"]["psnr"],
            "gain_db": s["gain_db"], "n_images": s["n_images"]}


TABLE_LEGEND = """
valid %    pixels the method calibrated (the others keep c = 0.1, b = 0)
c MAE      mean |c - true c| over valid pixels (log units)
c med rel  median |c - true c| / true c over valid pixels
b MAE      mean |b - true b| over valid pixels (log units)
PSNR dB    standard PSNR (peak 255) of intensity integrated from events over 5 frame
           intervals against the frame there, mean over {n} reconstructions
gain dB    PSNR - PSNR of DI
true maps  the simulation's own c, b: what a perfect calibration scores, the ceiling of the
           calibration itself (an estimate may land a little above it: fitted to the same
           events, it also absorbs some of the integration's own error)"""


def format_table(rows: list[dict[str, Any]]) -> str:
    head = (f"{'calibration':<26} {'valid %':>8} {'c MAE':>8} {'c med rel':>10} {'b MAE':>8} "
            f"{'PSNR dB':>8} {'gain dB':>8}")
    lines = [head, "-" * len(head)]
    for r in rows:
        lines.append(f"{r['method']:<26} {r['valid_pct']:>8.1f} {r['c_mae']:>8.4f} "
                     f"{r['c_rel_pct']:>9.1f}% {r['b_mae']:>8.4f} {r['psnr_db']:>8.2f} "
                     f"{r['gain_db']:>+8.2f}")
    return "\n".join(lines)


def warm_up(onei: Any) -> float:
    """Run OnEI (``onei``'s options, small buffers) over a tiny simulation so that numba
    compiles its kernels (or loads them from its cache) before the replay: otherwise a first
    run's latency is the compiler's (34 s of queueing, measured in a fresh checkout), not the
    service's. Returns the seconds it took."""
    from dataclasses import replace

    from evcal.online import onei as run_onei
    from evcal.sim.ideal import SimConfig, simulate_ideal

    t = time.monotonic()
    sim = simulate_ideal(SimConfig(height=24, width=32, duration_s=0.8, seed=0))
    run_onei(sim.recording, replace(onei, n_small=1000, n_large=100_000, eager=True))
    return time.monotonic() - t


def build_parser() -> argparse.ArgumentParser:
    from .common import add_verbosity
    p = argparse.ArgumentParser(prog="evcal demo", description=__doc__.split("\n")[0],
                                formatter_class=HelpFormatter)
    p.add_argument("--out", default="demo.rrd", help="Rerun recording to write")
    p.add_argument("--size", default="240x180", help="simulated sensor WxH (default 240x180)")
    p.add_argument("--duration", type=float, default=6.0, help="seconds of simulated data")
    p.add_argument("--seed", type=int, default=1,
                   help="seed of the simulated sensor's maps and motion")
    p.add_argument("--camera", default="demo/cam0",
                   help="camera id the recording is replayed under")
    p.add_argument("--n-small", type=int, default=100_000,
                   help="OnEI events per small buffer (default 100000: ~30 updates)")
    p.add_argument("--n-large", type=int, default=5_000_000,
                   help="OnEI sliding buffer in events (default 5M: the whole demo)")
    p.add_argument("--timeout", type=float, default=100.0,
                   help="give up after this many seconds of streaming")
    p.add_argument("--max-rate", action="store_true",
                   help="replay as fast as the link takes it instead of in real time (the "
                        "latency then includes the backlog the burst builds)")
    add_verbosity(p)
    return p


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    t_start = time.monotonic()
    from evcal.events import SensorSize
    from evcal.offline import OffEIConfig, offei
    from evcal.online import OnEIConfig
    from evcal.reconstruct import evaluate
    from evcal.service.cli import setup_logging
    from evcal.service.core import ServiceConfig
    from evcal.service.server import run
    from evcal.service.transport import Transport, ZenohOptions
    from evcal.sim.ideal import SimConfig, simulate_ideal
    from evcal.testing import endpoint, free_port, wait_for

    from .query import fetch_calibration, fetch_json
    from .replay import replay

    setup_logging(args.verbose, args.quiet)
    try:
        sensor = SensorSize.parse(args.size)
        cfg = SimConfig(height=sensor.height, width=sensor.width, duration_s=args.duration,
                        seed=args.seed)
    except ValueError as exc:
        print(f"evcal demo: {exc}", file=sys.stderr)
        return 2
    _say(f"simulating {sensor} for {args.duration:g} s (c ~ N({cfg.contrast_mean}, "
         f"{cfg.contrast_std}), b ~ N({cfg.bias_mean}, {cfg.bias_std}), scene "
         f"{cfg.scene!r})")
    sim = simulate_ideal(cfg)
    rec, truth = sim.recording, sim.truth
    _say(f"{rec.n_events} events, {len(rec.frames)} frames")

    ep = endpoint(free_port())
    # the service is not told the offset: it estimates it per camera, as it would live
    onei_cfg = OnEIConfig(n_small=args.n_small, n_large=args.n_large, log_offset="auto")
    warm_s = warm_up(onei_cfg)
    if warm_s > 2.0:
        _say(f"compiled evcal's kernels in {warm_s:.0f} s (once: they are cached for later "
             "runs)")
    config = ServiceConfig(on_full="block", onei=onei_cfg, status_period_s=0.2)
    stop = threading.Event()
    ready = threading.Event()
    failure: list[BaseException] = []
    out = Path(args.out)

    def serve() -> None:
        try:
            run(ZenohOptions.loopback(listen=[ep]), config, stop=stop, rrd=out,
                rrd_options={"map_period_s": 0.25, "recon_period_s": 0.25,
                             "scalar_period_s": 0.04,
                             # the simulation's truth: error maps and the c MAE curve
                             "truth": {args.camera: (truth["contrast"], truth["bias"])}},
                ready=lambda s: ready.set())
        except BaseException as exc:  # reported by the main thread
            failure.append(exc)
            ready.set()

    server = threading.Thread(target=serve, name="evcal-demo-service")
    server.start()
    try:
        if not ready.wait(30) or failure:
            # said like the failures below, not as a traceback (the finally stops it)
            print(f"evcal demo: the service did not start: "
                  f"{failure[0] if failure else 'not ready within 30 s'}", file=sys.stderr)
            return 1
        _say(f"service up on {ep}; replaying onto {config.prefix}/{args.camera}")
        with Transport(ZenohOptions.loopback(connect=[ep])) as t:
            st = replay(t, rec, args.camera, speed=None if args.max_rate else 1.0)
            _say(f"sent {st.events} events, {st.frames} frames in {st.seconds:.2f} s")
            status_key = f"{config.prefix}/{args.camera}/status"

            def done() -> bool:
                got = fetch_json(t, status_key, timeout_s=2.0)
                return bool(got) and got[0]["frames"] >= len(rec.frames)

            wait_for(done, timeout_s=args.timeout, what="the service processing every frame")
            status = fetch_json(t, status_key)[0]
            live = fetch_calibration(t, args.camera, prefix=config.prefix)
    finally:
        stop.set()
        server.join(60)
    if failure:
        print(f"evcal demo: the service failed: {failure[0]}", file=sys.stderr)
        return 1
    pace = ("replayed at maximum rate: the latency includes the backlog the burst builds"
            if args.max_rate else "replayed in real time")
    _say(f"live calibration after {status['updates']} updates; {latency_line(status)} "
         f"({pace}); log "
         f"offset estimated online {live.log_offset:.1f} (true {cfg.log_offset:g}); computing "
         "the offline reference")

    from evcal.calibration import Calibration

    offline = offei(rec, OffEIConfig(log_offset=float(cfg.log_offset)))
    di = Calibration.uniform(sensor.shape, log_offset=float(cfg.log_offset))
    true_maps = di.replace(contrast=truth["contrast"].astype(np.float32),
                           bias=truth["bias"].astype(np.float32), method="truth")
    rows = []
    for name, cal in (("DI (c=0.1, b=0)", di), ("live OnEI (service)", live),
                      ("offline OffEI (reference)", offline),
                      ("true maps (perfect c, b)", true_maps)):
        ev = evaluate(rec, cal, frames_per_image=5, log_offset=float(cfg.log_offset))
        rows.append(error_row(name, cal, truth, ev))
    print()
    print(f"evcal demo: {sensor} simulated camera, {rec.n_events} events, {len(rec.frames)} "
          f"frames, true c = {cfg.contrast_mean} +- {cfg.contrast_std}, "
          f"b = {cfg.bias_mean} +- {cfg.bias_std}")
    print(format_table(rows))
    print(TABLE_LEGEND.format(n=rows[0]["n_images"]))
    print(f"Rerun recording: {out} (open with `rerun {out}`); "
          f"{time.monotonic() - t_start:.1f} s in all.")
    return 0


def latency_line(status: dict[str, Any]) -> str:
    """What the latency figures of a camera's status mean, in one line: frame received to
    calibration published (median, p95), and how much of it was waiting in the queue."""
    lat = status.get("latency_ms") or {}
    if lat.get("median") is None:
        return "no calibration published yet"
    parts = lat.get("parts_median") or {}
    queue = parts.get("queue")
    line = (f"frame received -> calibration published: median {lat['median']:.1f} ms, "
            f"p95 {lat['p95']:.1f} ms")
    if queue is not None:
        line += f" (median {queue:.1f} ms of it queued behind earlier messages)"
    return line


if __name__ == "__main__":
    sys.exit(main())
