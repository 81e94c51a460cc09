"""``evcal replay``: publish a recording onto zenoh in the wire format.

Messages go to ``<prefix>/<camera>/events`` and ``<prefix>/<camera>/frames`` in time order:
each frame before the events that follow it, events cut at frame times into chunks of at
most ``--chunk-events`` events and ``--chunk-ms`` of sensor time. A chunk is sent when its
last event has happened (scaled by ``--speed``), a frame at its time; ``--max-rate`` sends as
fast as the link and the subscribers allow (publishers use congestion control BLOCK).
``--loop`` replays again with times shifted past the end, so time and sequence numbers keep
increasing.

Delivery is checked, not assumed. Nothing is sent while no subscriber matches. At the end
the camera's status is asked of the service until its account of this run is complete
(every message processed, dropped or refused, or nothing left in flight at the service) or
``--confirm-timeout`` (60 s) has passed: a busy service answers late, a camera new to it
appears once its first message is taken off the queue. A camera the service has no slot for
is answered with the refusal. Publishers use congestion control BLOCK with
``--block-timeout`` (default 1 h) instead of zenoh's 5 s before a stalled link is closed, so
a ``--on-full block`` service is lossless end to end across long stalls; the puts run on a
thread of their own, so SIGINT or SIGTERM stops the replay within a second or two even while
a put waits for a stalled service (a second signal skips the confirmation).

Exit codes, judged in this order (the first that applies names the cause; 0 when none does):

=====  ============  ==================================================================
code   outcome       meaning
=====  ============  ==================================================================
1      error         the zenoh session failed (or a put raised)
2      usage         bad arguments or an unreadable recording
3      nobody there  no subscriber after ``--wait-subscriber``: nothing was sent
5      refused       the service refused the camera (no slot: ``--max-cameras``, or its
                     probation slot given to another camera) or rejected messages
6      dropped       the service's queue dropped messages (``--on-full drop``)
4      lost          messages never reached the service: sent while nobody subscribed,
                     the service gone during the run, or missing from its account
7      unconfirmed   no service confirmed delivery within ``--confirm-timeout`` (only a
                     recorder listens, the service is too busy, or the replay was stopped
                     with a put still blocked)
0      all taken     the service confirmed it processed every message sent
=====  ============  ==================================================================
"""

from __future__ import annotations

import argparse
import queue
import sys
import threading
import time
from collections.abc import Iterator, Sequence
from dataclasses import replace
from typing import Any

import numpy as np

from evcal.io import open_recording
from evcal.io.wire import encode_events, encode_frame
from evcal.recording import Recording
from evcal.service import keys
from evcal.service.cli import add_ros2_arguments, add_ros_distro_argument, ros_domain
from evcal.service.transport import Publisher, Transport, TransportError, options_from_args
from evcal.stream import frame_cuts

from ..clihelp import HelpFormatter
from .common import base_parser, camera_arg, fail
from .delivery import (
    CONFIRM_TIMEOUT_S,
    EXIT_CODES,
    EXIT_DROPPED,
    EXIT_ERROR,
    EXIT_LOST,
    EXIT_NOBODY,
    EXIT_OK,
    EXIT_REFUSED,
    EXIT_UNCONFIRMED,
    EXIT_USAGE,
    STATUS_QUERY_S,
    STOPPED_CONFIRM_S,
    ReplayStats,
    confirm,
    exit_code,
    exit_code_table,
    print_account,
    print_outcome,
    probe_status,
)

# the names callers have imported from here (the code is in .delivery)
__all__ = ["CONFIRM_TIMEOUT_S", "EXIT_CODES", "EXIT_DROPPED", "EXIT_ERROR", "EXIT_LOST",
           "EXIT_NOBODY", "EXIT_OK", "EXIT_REFUSED", "EXIT_UNCONFIRMED", "EXIT_USAGE",
           "ReplayStats", "build_parser", "exit_code", "main", "replay", "report", "schedule"]

# sessions left open at a stop with a put still blocked (see main)
_LEFT_OPEN: list[Transport] = []


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


class _Sender:
    """Puts messages on a thread of its own.

    With congestion control BLOCK a put waits, up to ``--block-timeout``, while a stalled
    receiver holds the link, and zenoh 1.10 cannot cancel it: the main thread would neither
    see SIGINT (its handler runs only between bytecodes) nor could it undeclare the
    publisher or close the session (that times out after 10 s, the put still blocked). Here
    the main thread only hands messages over (at most ``depth`` ahead, which also lets it
    encode the next while this thread puts) and keeps answering ``stop``; what was handed
    over but not yet put when ``stop`` is set is never sent. ``stats`` counts messages once
    their put returned.
    """

    def __init__(self, stats: ReplayStats, stop: threading.Event, depth: int = 4) -> None:
        self.stats = stats
        self.stop = stop
        self.busy = False  # a put in progress
        self._queue: queue.Queue[tuple[Publisher, bytes, int] | None] = queue.Queue(depth)
        self.thread = threading.Thread(target=self._run, name="evcal-replay-put", daemon=True)
        self.thread.start()

    def send(self, pub: Publisher, msg: bytes, n_events: int) -> bool:
        """Hand one message over (``n_events`` -1 for a frame); False once stopped or
        failed."""
        while not (self.stop.is_set() or self.stats.send_error is not None):
            try:
                self._queue.put((pub, msg, n_events), timeout=0.1)
                return True
            except queue.Full:
                continue
        return False

    def _run(self) -> None:
        st = self.stats
        while (item := self._queue.get()) is not None:
            if self.stop.is_set() or st.send_error is not None:
                continue  # stopped: what is still queued is not sent
            pub, msg, n_events = item
            self.busy = True
            try:
                pub.put(msg)
            except Exception as exc:  # a closed or failed session: reported, not raised
                st.send_error = f"{type(exc).__name__}: {exc}"
                continue
            finally:
                self.busy = False
            if n_events < 0:
                st.frames += 1
            else:
                st.events += n_events
                st.event_messages += 1
            st.bytes += len(msg)
            st.unmatched_messages += not pub.has_subscribers

    def finish(self) -> bool:
        """Wait until every message handed over was put; False when ``stop`` came first
        with a put still blocked (the thread is left to the process's exit)."""
        while True:
            try:
                self._queue.put(None, timeout=0.1)
                break
            except queue.Full:
                if self.stop.is_set() and self._drain():
                    continue
        while self.thread.is_alive():
            self.thread.join(0.1)
            if self.stop.is_set() and self.busy:
                self.thread.join(0.2)  # a put about to return
                return not self.thread.is_alive()
        return True

    def _drain(self) -> bool:
        try:
            while True:
                self._queue.get_nowait()
        except queue.Empty:
            return True


def replay(t: Transport, rec: Recording, camera: str, *, prefix: str = "evcal",
           speed: float | None = 1.0, loop: bool = False, stop: threading.Event | None = None,
           chunk_events: int = 50_000, chunk_us: int = 10_000,
           wait_subscriber_s: float = 5.0, max_loops: int | None = None,
           confirm_timeout_s: float = CONFIRM_TIMEOUT_S,
           stop_now: threading.Event | None = None) -> ReplayStats:
    """Publish ``rec`` (``speed=None``: as fast as possible), then ask the service for its
    account of the run (up to ``confirm_timeout_s``; 1 s once ``stop`` is set, none once
    ``stop_now`` is). Returns what was sent and delivered (:func:`exit_code` judges it)."""
    h, w = rec.sensor.shape
    pub_ev = t.publisher(keys.camera_key(prefix, camera, "events"), keys.ENC_EVENTS, block=True)
    pub_fr = t.publisher(keys.camera_key(prefix, camera, "frames"), keys.ENC_FRAME, block=True)
    stop = stop or threading.Event()
    stop_now = stop_now or threading.Event()
    deadline = time.monotonic() + wait_subscriber_s
    while not (pub_ev.has_subscribers and pub_fr.has_subscribers):
        if time.monotonic() > deadline or stop.is_set():
            break
        time.sleep(0.02)
    # a recorder started beside a service subscribes first (the service takes seconds to
    # start): wait for the service too, within the same deadline, or it misses the start
    while (pub_ev.has_subscribers and not stop.is_set() and time.monotonic() < deadline
           and not t.alive(keys.service_token_key(prefix), timeout_s=0.5)):
        time.sleep(0.1)
    stats = ReplayStats()
    if not (pub_ev.has_subscribers or pub_fr.has_subscribers):
        stats.subscribed = False
        return stats  # nobody listens: nothing is sent (the caller says so)
    status_key = keys.camera_key(prefix, camera, "status")
    before = probe_status(t, status_key, STATUS_QUERY_S)
    images = rec.frames.images
    if images.dtype.kind == "f" and images.dtype != np.float32:
        images = images.astype(np.float32)
    t0, t1 = rec.t_range_us
    period = int(np.median(np.diff(rec.frames.t_us))) if len(rec.frames) > 1 else 1
    span = t1 - t0 + max(period, 1)
    plan = list(schedule(rec, chunk_events=chunk_events, chunk_us=chunk_us))
    sender = _Sender(stats, stop)
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
                ok = sender.send(pub_fr, msg, -1)
                seq_fr += 1
            else:
                ev = rec.events[i0:i1]
                if shift:
                    ev = ev.copy()
                    ev["t_us"] += shift
                msg = encode_events(ev, height=h, width=w, seq=seq_ev)
                ok = sender.send(pub_ev, msg, i1 - i0)
                seq_ev += 1
            if not ok:
                break
        loop_i += 1
        if stats.send_error is not None or not loop or (
                max_loops is not None and loop_i >= max_loops):
            break
    stats.stuck_put = not sender.finish()
    stats.stopped = stop.is_set()
    stats.seconds = time.monotonic() - wall0
    if stats.send_error is not None:
        return stats
    if stats.stuck_put:
        # the link is held by a stalled receiver: a query would wait behind the blocked put
        stats.why_unconfirmed = ("stopped while a put waited for the service (stalled?): "
                                 "delivery of what was sent is unknown")
        return stats
    wait_s = STOPPED_CONFIRM_S if stats.stopped else confirm_timeout_s
    confirm(t, stats, status_key, before, prefix=prefix, since_s=wall0 - STATUS_QUERY_S,
            deadline=time.monotonic() + wait_s, stop_now=stop_now)
    return stats


def build_parser() -> argparse.ArgumentParser:
    p = base_parser("evcal replay", "Publish a recording onto zenoh in evcal's wire format.")
    p.epilog = exit_code_table()
    p.formatter_class = HelpFormatter
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
    p.add_argument("--chunk-events", type=int, default=50_000,
                   help="at most this many events per message")
    p.add_argument("--chunk-ms", type=float, default=10.0,
                   help="at most this many milliseconds of events per message")
    p.add_argument("--sensor", help="WxH, for recordings that do not tell it")
    p.add_argument("--wait-subscriber", type=float, default=5.0, metavar="S",
                   help="wait up to S seconds for a subscriber before sending (default 5); "
                        "with none, nothing is sent and the exit code is 3")
    p.add_argument("--confirm-timeout", type=float, default=CONFIRM_TIMEOUT_S, metavar="S",
                   help="after the run, ask the service for its account of it for up to S "
                        f"seconds (default {CONFIRM_TIMEOUT_S:g}; 1 after Ctrl-C, none "
                        "after a second Ctrl-C); unconfirmed delivery is exit code 7")
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
    add_ros_distro_argument(g, "Humble's wire when the domain's liveliness tokens are all "
                               "Humble's, else the current one (Jazzy 0.2.4+, Kilted, "
                               "Rolling); tokens do not tell jazzy-0.2.3, name it")
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
                               distro=args.ros_distro,
                               wait_subscriber_s=args.wait_subscriber,
                               confirm_timeout_s=args.confirm_timeout)
    except RecordingError as exc:
        return fail(prog, str(exc), 2)
    except TransportError as exc:
        return fail(prog, str(exc))
    finally:
        relay.close(ignore_after_stop=True)
    return report(prog, stats, args.wait_subscriber, domain)


def report(prog: str, stats: ReplayStats, target: str) -> int:
    """Print what was sent and what the service says of it; returns :func:`exit_code`."""
    code = exit_code(stats)
    if stats.send_error is not None:
        print(f"{prog}: sending failed: {stats.send_error}", file=sys.stderr)
    print(f"{prog}: sent {stats.events} events in {stats.event_messages} messages and "
          f"{stats.frames} frames, {stats.bytes / 1e6:.1f} MB in {stats.seconds:.2f} s "
          f"({stats.events_per_s / 1e6:.2f} M events/s) to {target}"
          + (" (stopped)" if stats.stopped else ""), file=sys.stderr)
    if stats.unmatched_messages:
        print(f"{prog}: {stats.unmatched_messages} messages were sent while nobody subscribed "
              "(lost)", file=sys.stderr)
    print_account(prog, stats, target=target)
    return print_outcome(prog, code)


def main(argv: Sequence[str] | None = None) -> int:
    from evcal.events import SensorSize
    from evcal.recording import RecordingError
    from evcal.signals import STOP_SIGNALS, SignalRelay

    args = build_parser().parse_args(argv)
    prog = "evcal replay"
    if args.speed is not None and not args.speed > 0:
        return fail(prog, f"--speed {args.speed} must be > 0", EXIT_USAGE)
    if not args.confirm_timeout >= 0:
        return fail(prog, f"--confirm-timeout {args.confirm_timeout} must be >= 0", EXIT_USAGE)
    if args.ros2:
        return _main_ros2(args, prog)
    if args.camera is None:
        return fail(prog, "--camera is required (or --ros2 for a ROS bag)", EXIT_USAGE)
    if args.ros_domain is not None or args.topic:
        return fail(prog, "--ros-domain and --topic go with --ros2", EXIT_USAGE)
    try:
        zopts = _replay_options(args)
        sensor = SensorSize.parse(args.sensor) if args.sensor else None
        rec = open_recording(args.recording, sensor=sensor)
    except (ValueError, RecordingError) as exc:
        return fail(prog, str(exc), EXIT_USAGE)
    stop, stop_now = threading.Event(), threading.Event()

    def on_signal(_signum: int) -> None:
        # the first stops sending (and shortens the confirmation), the second skips it
        (stop_now if stop.is_set() else stop).set()

    relay = SignalRelay(STOP_SIGNALS, on_signal)
    t = Transport(zopts)
    stats: ReplayStats | None = None
    try:
        t.open()
        stats = replay(t, rec, args.camera, prefix=args.prefix,
                       speed=None if args.max_rate else args.speed, loop=args.loop,
                       stop=stop, chunk_events=args.chunk_events,
                       chunk_us=int(args.chunk_ms * 1000),
                       wait_subscriber_s=args.wait_subscriber,
                       confirm_timeout_s=args.confirm_timeout, stop_now=stop_now)
    except TransportError as exc:
        return fail(prog, str(exc), EXIT_ERROR)
    finally:
        relay.close(ignore_after_stop=True)
        # a put still blocked by a stalled receiver cannot be cancelled, and closing the
        # session would time out after 10 s with it still blocked (zenoh 1.10), as would
        # dropping the last reference to it: the session is kept open for the process's
        # exit, which ends it at once
        if stats is None or not stats.stuck_put:
            t.close()
        else:
            _LEFT_OPEN.append(t)
    target = f"{args.prefix}/{args.camera}"
    if not stats.subscribed:
        return fail(prog, f"nobody subscribes to {target}/events|frames after "
                          f"{args.wait_subscriber:g} s (is `evcal serve` or `evcal record` "
                          "running and reachable with these --connect/--mode settings?); "
                          "nothing was sent", EXIT_NOBODY)
    return report(prog, stats, target)


if __name__ == "__main__":
    sys.exit(main())
