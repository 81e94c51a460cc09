"""``evcal replay``: publish a recording onto zenoh in the wire format.

Messages go to ``<prefix>/<camera>/events`` and ``<prefix>/<camera>/frames`` in time order:
each frame before the events that follow it, events cut at frame times into chunks of at
most ``--chunk-events`` events and ``--chunk-ms`` of sensor time. A chunk is sent when its
last event has happened (scaled by ``--speed``), a frame at its time; ``--max-rate`` sends as
fast as the link and the subscribers allow (publishers use congestion control BLOCK).
``--loop`` replays again with times shifted past the end, so time and sequence numbers keep
increasing.
"""

from __future__ import annotations

import sys
import threading
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass

import numpy as np

from evcal.io import open_recording
from evcal.io.wire import encode_events, encode_frame
from evcal.recording import Recording
from evcal.service import keys
from evcal.service.transport import Transport, TransportError, options_from_args
from evcal.stream import frame_cuts

from .common import base_parser, camera_arg, fail


@dataclass
class ReplayStats:
    events: int = 0
    event_messages: int = 0
    frames: int = 0
    bytes: int = 0
    seconds: float = 0.0

    @property
    def events_per_s(self) -> float:
        return self.events / self.seconds if self.seconds > 0 else 0.0


def schedule(rec: Recording, *, chunk_events: int = 50_000, chunk_us: int = 10_000
             ) -> Iterator[tuple[str, int, int, int]]:
    """``(kind, t_send_us, i0, i1)`` in send order: ``kind`` "frame" (index ``i0``) or
    "events" (``rec.events[i0:i1]``). Events with ``t_us`` equal to a frame's time go after it.
    """
    t_ev = rec.events["t_us"]
    n = rec.n_events
    f_t = rec.frames.t_us
    bounds = frame_cuts(t_ev, f_t)
    starts = np.concatenate([[0], bounds])
    ends = np.concatenate([bounds, [n]])
    for seg in range(len(f_t) + 1):
        if seg > 0:
            yield "frame", int(f_t[seg - 1]), seg - 1, seg
        i, end = int(starts[seg]), int(ends[seg])
        while i < end:
            # at most chunk_events events and at most chunk_us of sensor time
            j = min(end, i + chunk_events)
            t_lim = int(t_ev[i]) + chunk_us
            j = min(j, int(np.searchsorted(t_ev[i:j], t_lim, side="left")) + i) if j > i else j
            j = max(j, i + 1)
            yield "events", int(t_ev[j - 1]), i, j
            i = j


def replay(t: Transport, rec: Recording, camera: str, *, prefix: str = "evcal",
           speed: float | None = 1.0, loop: bool = False, stop: threading.Event | None = None,
           chunk_events: int = 50_000, chunk_us: int = 10_000,
           wait_subscriber_s: float = 5.0, max_loops: int | None = None) -> ReplayStats:
    """Publish ``rec`` (``speed=None``: as fast as possible). Returns what was sent."""
    h, w = rec.sensor.shape
    pub_ev = t.publisher(keys.camera_key(prefix, camera, "events"), keys.ENC_EVENTS, block=True)
    pub_fr = t.publisher(keys.camera_key(prefix, camera, "frames"), keys.ENC_FRAME, block=True)
    stop = stop or threading.Event()
    deadline = time.monotonic() + wait_subscriber_s
    while not (pub_ev.has_subscribers and pub_fr.has_subscribers):
        if time.monotonic() > deadline or stop.is_set():
            break
        time.sleep(0.02)
    images = rec.frames.images
    if images.dtype.kind == "f" and images.dtype != np.float32:
        images = images.astype(np.float32)
    t0, t1 = rec.t_range_us
    period = int(np.median(np.diff(rec.frames.t_us))) if len(rec.frames) > 1 else 1
    span = t1 - t0 + max(period, 1)
    plan = list(schedule(rec, chunk_events=chunk_events, chunk_us=chunk_us))
    stats = ReplayStats()
    seq_ev = seq_fr = 0
    wall0 = time.monotonic()
    loop_i = 0
    while not stop.is_set():
        shift = loop_i * span
        for kind, t_send, i0, i1 in plan:
            if stop.is_set():
                break
            if speed:
                due = wall0 + (t_send + shift - t0) * 1e-6 / speed
                delay = due - time.monotonic()
                if delay > 0:
                    stop.wait(delay)
            if kind == "frame":
                msg = encode_frame(int(rec.frames.t_us[i0]) + shift, images[i0],
                                   exposure_us=int(rec.frames.exposure_us[i0]), seq=seq_fr)
                pub_fr.put(msg)
                seq_fr += 1
                stats.frames += 1
            else:
                ev = rec.events[i0:i1]
                if shift:
                    ev = ev.copy()
                    ev["t_us"] += shift
                msg = encode_events(ev, height=h, width=w, seq=seq_ev)
                pub_ev.put(msg)
                seq_ev += 1
                stats.events += i1 - i0
                stats.event_messages += 1
            stats.bytes += len(msg)
        loop_i += 1
        if not loop or (max_loops is not None and loop_i >= max_loops):
            break
    # confirm delivery through the service's status queryable before the session closes
    t.flush(keys.camera_key(prefix, camera, "status"))
    stats.seconds = time.monotonic() - wall0
    return stats


def build_parser():
    p = base_parser("evcal replay", "Publish a recording onto zenoh in evcal's wire format.")
    p.add_argument("recording", help="any recording evcal reads (.aedat4, .mcap, .npz, ECD "
                                     "folder)")
    p.add_argument("--camera", required=True, type=camera_arg,
                   help="camera id, one or more key chunks, e.g. lab/rig1/cam0")
    rate = p.add_mutually_exclusive_group()
    rate.add_argument("--speed", type=float, default=1.0,
                      help="real time scaled by this factor (default 1)")
    rate.add_argument("--max-rate", action="store_true",
                      help="as fast as the link and the subscribers allow")
    p.add_argument("--loop", action="store_true", help="replay again and again (until Ctrl-C)")
    p.add_argument("--chunk-events", type=int, default=50_000)
    p.add_argument("--chunk-ms", type=float, default=10.0)
    p.add_argument("--sensor", help="WxH, for recordings that do not tell it")
    p.add_argument("--wait-subscriber", type=float, default=5.0, metavar="S",
                   help="wait up to S seconds for a subscriber before sending (default 5)")
    return p


def main(argv: Sequence[str] | None = None) -> int:
    import signal

    from evcal.events import SensorSize
    from evcal.recording import RecordingError

    args = build_parser().parse_args(argv)
    prog = "evcal replay"
    if args.speed is not None and not args.speed > 0:
        return fail(prog, f"--speed {args.speed} must be > 0", 2)
    try:
        zopts = options_from_args(args)
        sensor = SensorSize.parse(args.sensor) if args.sensor else None
        rec = open_recording(args.recording, sensor=sensor)
    except (ValueError, RecordingError) as exc:
        return fail(prog, str(exc), 2)
    stop = threading.Event()
    old = {s: signal.signal(s, lambda *_: stop.set()) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        with Transport(zopts) as t:
            stats = replay(t, rec, args.camera, prefix=args.prefix,
                           speed=None if args.max_rate else args.speed, loop=args.loop,
                           stop=stop, chunk_events=args.chunk_events,
                           chunk_us=int(args.chunk_ms * 1000),
                           wait_subscriber_s=args.wait_subscriber)
    except TransportError as exc:
        return fail(prog, str(exc))
    finally:
        for s, h in old.items():
            signal.signal(s, h)
    print(f"{prog}: {stats.events} events in {stats.event_messages} messages, {stats.frames} "
          f"frames, {stats.bytes / 1e6:.1f} MB in {stats.seconds:.2f} s "
          f"({stats.events_per_s / 1e6:.2f} M events/s) to {args.prefix}/{args.camera}",
          file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
