"""``evcal replay``: publish a recording onto zenoh in the wire format.

Messages go to ``<prefix>/<camera>/events`` and ``<prefix>/<camera>/frames`` in time order:
each frame before the events that follow it, events cut at frame times into chunks of at
most ``--chunk-events`` events and ``--chunk-ms`` of sensor time. A chunk is sent when its
last event has happened (scaled by ``--speed``), a frame at its time; ``--max-rate`` sends as
fast as the link and the subscribers allow (publishers use congestion control BLOCK).
``--loop`` replays again with times shifted past the end, so time and sequence numbers keep
increasing.

Delivery is checked, not assumed: nothing is sent while no subscriber matches (exit code 3
after ``--wait-subscriber``); at the end the service's status says what it processed,
dropped and rejected of this run, and messages it never saw are reported (exit code 4, also
when the service dropped or rejected some, or when messages went out with nobody
subscribed). Publishers use congestion control BLOCK with ``--block-timeout`` (default 1 h)
instead of zenoh's 5 s before a stalled link is closed, so a ``--on-full block`` service is
lossless end to end across long stalls.
"""

from __future__ import annotations

import json
import sys
import threading
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from evcal.io import open_recording
from evcal.io.wire import encode_events, encode_frame
from evcal.recording import Recording
from evcal.service import keys
from evcal.service.cli import add_ros2_arguments, ros_domain
from evcal.service.transport import Transport, TransportError, options_from_args
from evcal.stream import frame_cuts

from .common import base_parser, camera_arg, fail


@dataclass
class ReplayStats:
    """What was sent, and what the service says it received (``delivered``)."""

    events: int = 0
    event_messages: int = 0
    frames: int = 0
    bytes: int = 0
    seconds: float = 0.0
    subscribed: bool = True  # a subscriber matched before sending
    unmatched_messages: int = 0  # sent while nobody subscribed (lost)
    service_gone: bool = False  # the service answered before the run and not after
    # the service's account of this run (status differences), None when no service answered
    delivered: dict[str, int] | None = None

    @property
    def messages(self) -> int:
        return self.event_messages + self.frames

    @property
    def missing_messages(self) -> int | None:
        """Messages the service never saw (neither processed, dropped nor rejected)."""
        if self.delivered is None:
            return None
        return self.messages - self.delivered["accounted_messages"]

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
    status_key = keys.camera_key(prefix, camera, "status")
    before = _status(t, status_key)
    stats = ReplayStats()
    if not (pub_ev.has_subscribers or pub_fr.has_subscribers):
        stats.subscribed = False
        return stats  # nobody listens: nothing is sent (the caller says so)
    images = rec.frames.images
    if images.dtype.kind == "f" and images.dtype != np.float32:
        images = images.astype(np.float32)
    t0, t1 = rec.t_range_us
    period = int(np.median(np.diff(rec.frames.t_us))) if len(rec.frames) > 1 else 1
    span = t1 - t0 + max(period, 1)
    plan = list(schedule(rec, chunk_events=chunk_events, chunk_us=chunk_us))
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
                stats.unmatched_messages += not pub_fr.has_subscribers
                seq_fr += 1
                stats.frames += 1
            else:
                ev = rec.events[i0:i1]
                if shift:
                    ev = ev.copy()
                    ev["t_us"] += shift
                msg = encode_events(ev, height=h, width=w, seq=seq_ev)
                pub_ev.put(msg)
                stats.unmatched_messages += not pub_ev.has_subscribers
                seq_ev += 1
                stats.events += i1 - i0
                stats.event_messages += 1
            stats.bytes += len(msg)
        loop_i += 1
        if not loop or (max_loops is not None and loop_i >= max_loops):
            break
    # confirm delivery through the service's status queryable before the session closes
    # (a busy service answers late: keep asking for up to 30 s; closing the session earlier
    # would drop what is still queued for sending)
    for _ in range(6 if before is not None else 1):  # no service: nobody to ask twice
        if t.flush(status_key, timeout_s=5.0, linger_s=0.0):
            break
    else:
        time.sleep(0.5)
    stats.seconds = time.monotonic() - wall0
    after = _status(t, status_key)
    if after is not None:
        stats.delivered = _delivered(t, status_key, before or {}, stats.messages)
    elif before is not None:
        stats.service_gone = True  # it answered before the run, not after: link lost?
    return stats


def _status(t: Transport, key: str) -> dict[str, Any] | None:
    """The camera's status from the service (None: no service answered)."""
    try:
        replies = [r for r in t.get(key, timeout_s=2.0) if r.ok]
        return json.loads(replies[0].payload) if replies else None
    except Exception:  # noqa: BLE001 - a diagnosis only
        return None


def _account(st: dict[str, Any], before: dict[str, Any]) -> dict[str, int]:
    def diff(name: str) -> int:
        v, b = st.get(name, 0), before.get(name, 0)
        if isinstance(v, dict):
            return int(sum(v.values()) - sum((b or {}).values()))
        return int(v - (b or 0))

    out = {"event_messages": diff("event_messages"), "events": diff("events"),
           "frames": diff("frames"), "dropped_messages": diff("dropped_messages"),
           "rejected_messages": diff("errors")}
    out["accounted_messages"] = (out["event_messages"] + out["frames"]
                                 + out["dropped_messages"] + out["rejected_messages"])
    return out


def _delivered(t: Transport, key: str, before: dict[str, Any], sent: int, *,
               timeout_s: float = 15.0) -> dict[str, int]:
    """What the service received of this run, once every sent message is accounted for (or
    its counters stop moving): processed, dropped by its queue, rejected."""
    deadline = time.monotonic() + timeout_s
    last: dict[str, int] = {"accounted_messages": -1}
    stable = 0
    while True:
        st = _status(t, key)
        acc = _account(st, before) if st is not None else last
        if acc["accounted_messages"] >= sent or time.monotonic() > deadline:
            return acc
        stable = stable + 1 if acc == last else 0
        if stable >= 10:  # 2 s without a change: the rest is not coming
            return acc
        last = acc
        time.sleep(0.2)


def build_parser():
    p = base_parser("evcal replay", "Publish a recording onto zenoh in evcal's wire format.")
    p.add_argument("recording", help="any recording evcal reads (.aedat4, .mcap, .npz, ECD "
                                     "folder)")
    p.add_argument("--camera", type=camera_arg,
                   help="camera id, one or more key chunks, e.g. lab/rig1/cam0 (required "
                        "but with --ros2)")
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
                   help="wait up to S seconds for a subscriber before sending (default 5); "
                        "with none, nothing is sent and the exit code is 3")
    p.add_argument("--block-timeout", type=float, default=3600.0, metavar="S",
                   help="how long a message may wait for a stalled receiver before zenoh "
                        "closes the link (default 3600; zenoh's own default is 5)")
    g = add_ros2_arguments(
        p, "RECORDING is a ROS 1 or 2 bag: publish its messages unchanged (CDR) on rmw_zenoh's "
           "keys with its liveliness tokens and attachments, as the camera's ROS 2 driver "
           "would (no --camera: `evcal serve --ros2` takes the camera from each topic's "
           "namespace)")
    g.add_argument("--topic", action="append", default=[], metavar="TOPIC",
                   help="with --ros2: publish only this topic (repeatable; default: all)")
    return p


def _replay_options(args: Any) -> Any:
    """The session options of the flags, with BLOCK publishers waiting ``--block-timeout``:
    a receiver stalled longer than zenoh's 5 s would see its link closed and the queued
    messages lost."""
    zopts = options_from_args(args)
    return replace(zopts, extra=(*zopts.extra, (
        "transport/link/tx/queue/congestion_control/block/wait_before_close",
        str(int(args.block_timeout * 1e6)))))


def _main_ros2(args: Any, prog: str) -> int:
    """``evcal replay BAG --ros2`` (see :mod:`evcal.clients.rosreplay`)."""
    from evcal.recording import RecordingError
    from evcal.signals import STOP_SIGNALS, SignalRelay

    from .rosreplay import replay_bag, report

    if args.camera is not None or args.loop or args.sensor:
        return fail(prog, "--camera, --loop and --sensor do not go with --ros2 (a bag is "
                          "replayed unchanged, once; its topics name the cameras)", 2)
    try:
        zopts = _replay_options(args)
        domain = ros_domain(args)
    except ValueError as exc:
        return fail(prog, str(exc), 2)
    stop = threading.Event()
    relay = SignalRelay(STOP_SIGNALS, lambda _s: stop.set())
    try:
        with Transport(zopts) as t:
            stats = replay_bag(t, args.recording, domain=domain,
                               speed=None if args.max_rate else args.speed,
                               topics=set(args.topic) or None, stop=stop, prefix=args.prefix,
                               wait_subscriber_s=args.wait_subscriber)
    except RecordingError as exc:
        return fail(prog, str(exc), 2)
    except TransportError as exc:
        return fail(prog, str(exc))
    finally:
        relay.close()
    return report(prog, stats, args.wait_subscriber, domain)


def main(argv: Sequence[str] | None = None) -> int:
    from evcal.events import SensorSize
    from evcal.recording import RecordingError
    from evcal.signals import STOP_SIGNALS, SignalRelay

    args = build_parser().parse_args(argv)
    prog = "evcal replay"
    if args.speed is not None and not args.speed > 0:
        return fail(prog, f"--speed {args.speed} must be > 0", 2)
    if args.ros2:
        return _main_ros2(args, prog)
    if args.camera is None:
        return fail(prog, "--camera is required (or --ros2 for a ROS bag)", 2)
    if args.ros_domain is not None or args.topic:
        return fail(prog, "--ros-domain and --topic go with --ros2", 2)
    try:
        zopts = _replay_options(args)
        sensor = SensorSize.parse(args.sensor) if args.sensor else None
        rec = open_recording(args.recording, sensor=sensor)
    except (ValueError, RecordingError) as exc:
        return fail(prog, str(exc), 2)
    stop = threading.Event()
    relay = SignalRelay(STOP_SIGNALS, lambda _s: stop.set())
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
        relay.close()
    target = f"{args.prefix}/{args.camera}"
    if not stats.subscribed:
        return fail(prog, f"nobody subscribes to {target}/events|frames after "
                          f"{args.wait_subscriber:g} s (is `evcal serve` or `evcal record` "
                          "running and reachable with these --connect/--mode settings?); "
                          "nothing was sent", 3)
    print(f"{prog}: sent {stats.events} events in {stats.event_messages} messages and "
          f"{stats.frames} frames, {stats.bytes / 1e6:.1f} MB in {stats.seconds:.2f} s "
          f"({stats.events_per_s / 1e6:.2f} M events/s) to {target}", file=sys.stderr)
    code = 0
    if stats.unmatched_messages:
        print(f"{prog}: {stats.unmatched_messages} messages were sent while nobody subscribed "
              "(lost)", file=sys.stderr)
        code = 4
    d = stats.delivered
    if stats.service_gone:
        print(f"{prog}: the service answered on {target}/status before the run but not "
              "after it: the link was lost (a stall longer than --block-timeout?) and "
              "messages may be lost", file=sys.stderr)
        code = 4
    elif d is None:
        print(f"{prog}: delivery not confirmed (no evcal service answered on "
              f"{target}/status)", file=sys.stderr)
    else:
        print(f"{prog}: the service processed {d['event_messages']} event messages "
              f"({d['events']} events) and {d['frames']} frames, dropped "
              f"{d['dropped_messages']} and rejected {d['rejected_messages']} messages",
              file=sys.stderr)
        missing = stats.missing_messages or 0
        if missing > 0:
            print(f"{prog}: {missing} of {stats.messages} messages never reached the service",
                  file=sys.stderr)
            code = 4
        elif d["dropped_messages"] or d["rejected_messages"]:
            code = 4
    return code


if __name__ == "__main__":
    sys.exit(main())
