"""Streaming OffEI over a recording larger than memory (figures, not a test).

    python scripts/bench_offei_stream.py [--minutes 60] [--rate 300e3] [--out DIR] [--keep]

Writes a synthetic 346x260 evcal MCAP of ``--minutes`` (25 Hz frames: a fixed scene with
per-frame noise; uniform random events at ``--rate`` events/s) message by message, so the
writer never holds it either, then runs ``evcal.offline.offei_file`` on it and prints the
file size, the time, events/s and the peak RSS of this process (``ru_maxrss``) beside the
in-memory size the recording would need. An hour at 300 k events/s is ~1.1 G events, 14 GB
of events and 8 GB of frames in memory; streamed, RSS stays at the window ring and sums.
"""

from __future__ import annotations

import argparse
import resource
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from evcal.events import EVENTS_DTYPE, SensorSize
from evcal.io.mcap_rec import McapWriter
from evcal.io.wire import encode_events, encode_frame
from evcal.offline import OffEIConfig, offei_file

SENSOR = SensorSize(260, 346)
FRAME_US = 40_000


def write(path: Path, minutes: float, rate: float, seed: int = 0) -> tuple[int, int]:
    rng = np.random.default_rng(seed)
    n_frames = int(minutes * 60 * 1e6 / FRAME_US)
    per_frame = int(rate * FRAME_US / 1e6)
    base = rng.integers(20, 230, SENSOR.shape).astype(np.int16)
    pool = [np.clip(base + rng.integers(-15, 16, SENSOR.shape), 1, 254).astype(np.uint8)
            for _ in range(16)]
    n_ev = 0
    with McapWriter(path) as out:
        out.set_sensor(SENSOR, {"source": "bench_offei_stream synthetic"})
        seq_ev = 0
        for k in range(n_frames):
            t0 = k * FRAME_US
            out.add_frame(t0, encode_frame(t0, pool[k % 16], exposure_us=0, seq=k))
            ev = np.empty(per_frame, EVENTS_DTYPE)
            ev["t_us"] = np.sort(rng.integers(t0, t0 + FRAME_US, per_frame))
            ev["x"] = rng.integers(0, SENSOR.width, per_frame)
            ev["y"] = rng.integers(0, SENSOR.height, per_frame)
            ev["p"] = rng.choice(np.array([-1, 1], np.int8), per_frame)
            out.add_events(int(ev["t_us"][0]), encode_events(ev, height=SENSOR.height,
                                                             width=SENSOR.width, seq=seq_ev))
            seq_ev += 1
            n_ev += per_frame
            if k % 1500 == 0:
                print(f"  writing: {k}/{n_frames} frames", file=sys.stderr, flush=True)
    return n_frames, n_ev


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=(__doc__ or "").split("\n")[0])
    p.add_argument("--minutes", type=float, default=60.0)
    p.add_argument("--rate", type=float, default=300e3, help="events/s")
    p.add_argument("--out", default=None, help="directory for the file (default: a temp dir)")
    p.add_argument("--keep", action="store_true", help="keep the file")
    args = p.parse_args(argv)
    d = Path(args.out or tempfile.mkdtemp(prefix="evcal-stream-"))
    path = d / "long.mcap"
    t0 = time.perf_counter()
    n_frames, n_ev = write(path, args.minutes, args.rate)
    t_write = time.perf_counter() - t0
    rss_before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    t0 = time.perf_counter()
    cal = offei_file(path, OffEIConfig(log_offset="auto"), prefix_frames=250)
    t_off = time.perf_counter() - t0
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    in_memory = (n_ev * EVENTS_DTYPE.itemsize + n_frames * SENSOR.n_pixels) / 2**20
    print(f"streaming OffEI, {SENSOR}, {args.minutes:g} min, {n_frames} frames, "
          f"{n_ev / 1e6:.1f} M events: file {path.stat().st_size / 2**20:.0f} MiB (written in "
          f"{t_write:.0f} s); offei_file {t_off:.1f} s ({n_ev / t_off / 1e6:.2f} M events/s, "
          f"{n_frames / t_off:.0f} frames/s); peak RSS {peak:.0f} MiB (before: "
          f"{rss_before:.0f} MiB) against {in_memory:.0f} MiB for the recording in memory; "
          f"log offset {cal.log_offset:.1f}, valid {cal.valid.mean() * 100:.1f} %", flush=True)
    if not args.keep:
        path.unlink()
    return 0


if __name__ == "__main__":
    sys.exit(main())
