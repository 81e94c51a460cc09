"""``evcal serve``: argument parsing and signal handling around :func:`server.run`."""

from __future__ import annotations

import argparse
import faulthandler
import logging
import signal
import sys
import threading
from collections.abc import Sequence

from ..clihelp import HelpFormatter
from ..errors import ConfigError
from ..online import OnEIConfig
from ..signals import STOP_SIGNALS, SignalRelay
from . import keys
from .core import ON_FULL, ServiceConfig
from .ros2 import DISTRO_CHOICES, Ros2Options, TopicMap, default_domain
from .signing import SignatureError
from .transport import (
    TransportError,
    ZenohOptions,
    add_zenoh_arguments,
    check_key,
    options_from_args,
)


def build_parser(prog: str = "evcal serve") -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog=prog, formatter_class=HelpFormatter,
        description="Live per-pixel calibration service: subscribes to every camera's events "
                    "and frames on <prefix>/<camera>/events|frames, keeps an online (OnEI) "
                    "calibration per camera, publishes <prefix>/<camera>/calibration|status|"
                    "errors and answers queries on them. Deployments are kept apart by "
                    "their endpoints: give --listen (clients: --connect) and the service "
                    "sees only its own processes (see the end of this help).",
        epilog="Keeping deployments apart: a deployment is the processes that share an "
               "endpoint. With an endpoint given (--listen/--connect, or EVCAL_LISTEN/"
               "EVCAL_CONNECT) multicast scouting is off, so a service sees only the "
               "processes connected to it: two deployments on one host differ by port "
               "(evcal serve --listen tcp/127.0.0.1:7447, clients --connect the same). "
               "Without any endpoint zenoh's multicast scouting is on and the service "
               "ingests the cameras of every evcal process on the local network (it warns "
               "at start); --prefix NAME/evcal (the same on its clients) separates "
               "deployments that must share a network. --multicast-scouting turns "
               "scouting on with endpoints.",
    )
    add_zenoh_arguments(p)
    p.add_argument("--prefix", default="evcal", help="key prefix (default: evcal)")
    p.add_argument("--cameras", default="**", metavar="KEYEXPR",
                   help="camera ids this instance claims, a key expression relative to the "
                        "prefix, e.g. 'lab/rig1/**' (default: ** = all)")
    p.add_argument("--instance", default="", help="instance name in the liveliness token "
                                                  "(default: the zenoh session id)")
    p.add_argument("--workers", type=_workers_arg, default=1, metavar="N|auto",
                   help="worker processes (default 1: this process serves every camera). "
                        "N > 1: this process routes (a zenoh router on the endpoints given) "
                        "and supervises N workers, each serving the cameras whose id hashes "
                        "to it, so that several cameras use several cores; a worker that dies "
                        "is restarted from --state-dir. Each worker is instance NAME-w<i>, "
                        "writes its own --rrd file (PATH.w<i>.rrd) and has its own "
                        "--max-cameras and --queue-mb. auto: one per core")
    p.add_argument("--shard", type=_shard_arg, default=None, metavar="I/N",
                   help="serve only the cameras whose id hashes to I of N (BLAKE2b of the id "
                        "mod N): what worker I of --workers N does; also for N instances "
                        "on several hosts")
    p.add_argument("--supervised", type=int, default=None, metavar="PID",
                   help=argparse.SUPPRESS)  # a worker of --workers: stop when PID goes away
    p.add_argument("--rrd", metavar="PATH", help="write a Rerun recording of the run (with "
                                                 "--workers N: one per worker, PATH with "
                                                 ".w<i> before its suffix)")
    p.add_argument("--rrd-map-period", type=float, default=2.0, metavar="S",
                   help="log maps at most every S seconds of sensor time (default 2)")
    p.add_argument("--rrd-recon-period", type=float, default=2.0, metavar="S",
                   help="log a reconstruction at most every S seconds of sensor time")
    p.add_argument("--rerun-serve", type=int, default=None, metavar="PORT",
                   help="also serve the recording live on this gRPC port (with --rrd): "
                        "`rerun --connect rerun+http://HOST:PORT/proxy` shows it as it grows "
                        "(with --workers N: worker i on PORT + i)")
    p.add_argument("--rerun-connect", default=None, metavar="URL",
                   help="also stream the recording to a running viewer (with --rrd), e.g. "
                        "rerun+http://127.0.0.1:9876/proxy")
    p.add_argument("--rrd-max-mb", type=float, default=300.0,
                   help="stop logging images after this many MiB of them (default 300)")
    p.add_argument("--sign-key", metavar="FILE.key",
                   help="Ed25519 private key (PEM, from `evcal keygen`): sign every calibration "
                        "so that `evcal query --verify FILE.pub` detects spoofed answers")
    p.add_argument("--state-dir", metavar="DIR",
                   help="snapshot each camera's state here (atomically) and restore at start")
    p.add_argument("--snapshot-period", type=float, default=30.0, metavar="S",
                   help="seconds between snapshots of changed cameras (default 30)")
    p.add_argument("--status-period", type=float, default=1.0, metavar="S",
                   help="seconds between status publications (default 1)")
    p.add_argument("--on-full", choices=ON_FULL, default="drop",
                   help="when a camera's input queue is full: drop the message and count it "
                        "(default), or block the receive path (lossless with blocking "
                        "publishers)")
    p.add_argument("--queue-mb", type=float, default=64.0,
                   help="input queue size per camera in MiB (default 64)")
    p.add_argument("--max-cameras", type=int, default=64,
                   help="cameras served at once; a new camera takes the slot of one idle past "
                        "its probation, else it is refused and counted")
    p.add_argument("--max-pixels", type=int, default=1280 * 1024,
                   help="largest sensor accepted, in pixels (default 1280x1024)")
    p.add_argument("--max-message-mb", type=float, default=32.0,
                   help="largest events or frames message accepted (MB); a larger one is "
                        "refused and counted in the camera's errors")
    g = add_ros2_arguments(
        p, "also be a ROS 2 node over rmw_zenoh: take event_camera_msgs/EventPacket and "
           "sensor_msgs/Image topics as camera input (camera id = the topic's namespace) and "
           "publish each camera's calibration on /<camera>/calibration/{contrast,bias,special} "
           "(sensor_msgs/Image)")
    g.add_argument("--ros-topic-map", action="append", default=[], metavar="TOPIC=CAMERA",
                   help="feed camera CAMERA from TOPIC, or from every topic below a "
                        "namespace, e.g. /dvs/events=lab/rig1/cam0 or /dvs=lab/rig1/cam0 "
                        "(repeatable)")
    add_ros_distro_argument(g, "from the tokens and attachments seen on the domain")
    g = p.add_argument_group("OnEI estimator")
    g.add_argument("--n-small", type=int, default=None,
                   help="events per small buffer, a re-solve after each (default: an "
                        "eighth of the events the camera has sent, at least 1000, growing to "
                        "the paper's 200 k at 240x180 scaled to the sensor)")
    g.add_argument("--n-large", type=int, default=None,
                   help="events in the sliding buffer (default: scaled with the sensor)")
    g.add_argument("--smoothing", type=float, default=None,
                   help="weight of each new solution in the low-pass estimate (default 0.1)")
    g.add_argument("--window-frames", type=int, default=5,
                   help="frame intervals each equation spans, as OffEI's --window-frames "
                        "(default 5); 0 closes them by event count (n_small), as the OnEI "
                        "paper does")
    g.add_argument("--history", type=float, default=0.0,
                   help="time constant, in large buffers, of a forgotten history of the "
                        "equations that left the buffer, solved with it (default 0: none, "
                        "the paper's sliding buffer alone; 1 helps short recordings and "
                        "pixels whose events came early, at a second set of sums, 131 MiB "
                        "per megapixel, and 2 ms per update at 346x260)")
    g.add_argument("--threads", type=int, default=0,
                   help="threads of a re-solve (default 0: the cores this process may use, "
                        "at most 8; the result is the same with any number)")
    g.add_argument("--log-offset", type=_offset_arg, default="auto",
                   help="offset of log(I + offset) in frame units (DN), or 'auto' (default): "
                        "estimated per camera from its first frames and events with the "
                        "criterion of `evcal calibrate --log-offset auto`, re-checked as data "
                        "accumulate")
    g.add_argument("--posterior", action="store_true",
                   help="publish posterior maps: each pixel's c and b pulled toward the "
                        "sensor's population by how little its own events say (as `evcal "
                        "calibrate --posterior`); a query with estimate=raw (evcal query "
                        "--estimate raw) still gets each pixel's own estimate")
    g.add_argument("--posterior-refresh", type=float, default=1.0, metavar="S",
                   help="with --posterior: seconds of sensor time between two estimates of "
                        "the population's priors (default 1); every update is shrunk with "
                        "the latest")
    g.add_argument("--event-timing", action="store_true",
                   help="fuse each OnEI update with OffE's maps of the same events (when "
                        "they fall: as `evcal calibrate --event-timing`), OffE's maps taken "
                        "again every second of sensor time; keeps OffE's sums per camera "
                        "(144 bytes a pixel) and folds every event into them too")
    add_verbosity(p)
    return p


def _workers_arg(text: str) -> int:
    if text == "auto":
        from ..online import usable_cores

        return usable_cores()
    try:
        n = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number or 'auto'") from None
    if n < 1:
        raise argparse.ArgumentTypeError(f"{text!r} must be >= 1")
    return n


def _shard_arg(text: str) -> tuple[int, int]:
    try:
        return keys.parse_shard(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def _offset_arg(text: str) -> float | str:
    if text == "auto":
        return text
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not 'auto' or a number") from None
    if not v >= 0:
        raise argparse.ArgumentTypeError(f"{text!r} must be >= 0")
    return v


def config_from_args(args: argparse.Namespace) -> ServiceConfig:
    check_key(f"{args.prefix.strip('/')}/{args.cameras}", "--prefix/--cameras")
    onei = {k: getattr(args, k) for k in ("n_small", "n_large", "smoothing", "log_offset")
            if getattr(args, k) is not None}
    if args.window_frames < 0:
        raise ConfigError(f"--window-frames {args.window_frames} must be >= 0")
    onei["window_frames"] = args.window_frames or None
    if not args.history >= 0:
        raise ConfigError(f"--history {args.history} must be >= 0")
    onei["history"] = args.history
    if args.threads < 0:
        raise ConfigError(f"--threads {args.threads} must be >= 0")
    onei["threads"] = args.threads
    onei["eager"] = True  # a service's update frames wait on the least (OnEIConfig.eager)
    return ServiceConfig(
        prefix=args.prefix, cameras=args.cameras, instance=args.instance, shard=args.shard,
        queue_bytes=int(args.queue_mb * (1 << 20)), on_full=args.on_full,
        max_cameras=args.max_cameras, max_pixels=args.max_pixels,
        max_message_bytes=int(args.max_message_mb * (1 << 20)),
        status_period_s=args.status_period, snapshot_period_s=args.snapshot_period,
        onei=OnEIConfig(**onei),
        posterior=bool(args.posterior),
        posterior_refresh_us=_refresh_us(args.posterior_refresh),
        event_timing=bool(args.event_timing),
    )


def _refresh_us(seconds: float) -> int:
    if not seconds >= 0:
        raise ConfigError(f"--posterior-refresh {seconds} must be >= 0 seconds")
    return int(round(seconds * 1e6))


def add_ros2_arguments(p: argparse.ArgumentParser, ros2_help: str
                       ) -> argparse._ArgumentGroup:
    """``--ros2`` (what it does: ``ros2_help``) and ``--ros-domain``, the same on every
    command; returns the group for the command's own ROS options."""
    g = p.add_argument_group("ROS 2 (rmw_zenoh)")
    g.add_argument("--ros2", action="store_true", help=ros2_help)
    g.add_argument("--ros-domain", type=int, default=None, metavar="N",
                   help="ROS domain id (default: $ROS_DOMAIN_ID, else 0)")
    return g


def add_ros_distro_argument(g: argparse._ArgumentGroup, auto: str) -> None:
    """``--ros-distro`` (:data:`~evcal.service.ros2.DISTROS`, or ``auto``: ``auto`` says
    how), the same on every command that speaks rmw_zenoh's wire."""
    g.add_argument("--ros-distro", choices=DISTRO_CHOICES, default="auto",
                   help="the rmw_zenoh to speak to: humble (rmw_zenoh 0.1.2+), humble-0.1.1, "
                        "jazzy (0.2.4+), jazzy-0.2.3 (0.2.0-0.2.3), kilted, rolling; auto "
                        f"(default): {auto}")


def ros_domain(args: argparse.Namespace) -> int:
    """``--ros-domain``, else ``$ROS_DOMAIN_ID``, else 0 (ValueError for a bad variable)."""
    return int(args.ros_domain) if args.ros_domain is not None else default_domain()


def ros2_from_args(args: argparse.Namespace) -> Ros2Options | None:
    """The ROS 2 options of ``--ros2`` (None without it; ValueError for bad values)."""
    if not args.ros2:
        if args.ros_domain is not None or args.ros_topic_map:
            raise ValueError("--ros-domain and --ros-topic-map go with --ros2")
        return None
    return Ros2Options(domain=ros_domain(args), topic_map=TopicMap.parse(args.ros_topic_map),
                       distro=args.ros_distro)


def setup_logging(verbose: int, quiet: bool = False, *, tag: str = "") -> None:
    """stderr logging: evcal's INFO by default (the service's own account), -v INFO for all,
    -vv DEBUG, -q errors only; ``tag`` after each logger's name (a worker's ``w0``)."""
    level = (logging.ERROR if quiet else logging.WARNING if verbose <= 0
             else logging.INFO if verbose == 1 else logging.DEBUG)
    logging.basicConfig(level=level, stream=sys.stderr,
                        format="%(asctime)s %(levelname)s %(name)s"
                               + (f"[{tag}]" if tag else "") + ": %(message)s")
    logging.getLogger("evcal").setLevel(level if quiet else min(level, logging.INFO))


def add_verbosity(p: argparse.ArgumentParser) -> None:
    """-v / -q, the same on every command."""
    p.add_argument("-v", "--verbose", action="count", default=0,
                   help="more detail on stderr (-vv: debug)")
    p.add_argument("-q", "--quiet", action="store_true",
                   help="errors only on stderr (no notes, progress or info lines)")


def warn_if_scouting(zopts: ZenohOptions, prefix: str) -> bool:
    """Warn, on stderr, that multicast scouting will join this service to every evcal
    process of the local network (no endpoint given); True when it did."""
    try:
        on = bool(zopts.to_config().get_json("scouting/multicast/enabled").strip() != "false")
    except Exception:  # noqa: BLE001 - an unreadable value: zenoh's default (on)
        on = True
    if on:
        logging.getLogger("evcal.service").warning(
            "multicast scouting is on (no --listen/--connect endpoint given): this service "
            "will ingest the cameras of every evcal process on the local network under "
            "prefix %r. Keep deployments apart with an endpoint (--listen "
            "tcp/127.0.0.1:7447, clients --connect it) or a --prefix of their own", prefix)
    return on


SWITCH_INTERVAL_S = 0.001


def main_serve(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    setup_logging(args.verbose, args.quiet,
                  tag=f"w{args.shard[0]}" if args.supervised is not None and args.shard else "")
    try:
        if (args.rerun_serve is not None or args.rerun_connect) and not args.rrd:
            raise ValueError("--rerun-serve and --rerun-connect go with --rrd PATH (the live "
                             "view is of the recording the file keeps)")
        if args.workers > 1 and args.shard is not None:
            raise ValueError(f"--shard goes with one worker: --workers {args.workers} gives "
                             "each of its workers its shard")
        zopts = options_from_args(args)
        config = config_from_args(args)
        ros2 = ros2_from_args(args)
    except ValueError as exc:
        print(f"evcal serve: {exc}", file=sys.stderr)
        return 2
    warn_if_scouting(zopts, config.prefix)
    from ..mallocpolicy import keep_freed_memory
    from .server import run

    malloc = keep_freed_memory()  # freed maps and messages reused: no page faults per update
    # the GIL changes hands every 1 ms, not 5: the frame path's short Python steps between
    # compiled kernels wait less behind the decoder and transport threads
    sys.setswitchinterval(SWITCH_INTERVAL_S)
    logging.getLogger("evcal.service").info("allocator: %s", malloc)
    # `kill -USR1 <pid>` dumps every thread's stack to stderr (diagnosing a stuck service)
    faulthandler.register(signal.SIGUSR1, all_threads=True)
    stop = threading.Event()

    def on_signal(signum: int) -> None:  # on the relay's thread, not in the handler
        logging.getLogger("evcal.service").info("signal %d: stopping", signum)
        stop.set()

    relay = SignalRelay(STOP_SIGNALS, on_signal)
    if args.workers > 1:
        from .workers import serve_workers

        try:
            return serve_workers(parser, args, zenoh=zopts, prefix=config.prefix,
                                 instance=config.instance, claims=config.cameras, stop=stop)
        finally:
            relay.close(ignore_after_stop=True)
    parent_gone = None
    if args.supervised is not None:
        from .workers import watch_parent

        parent_gone = watch_parent(args.supervised, stop)
    try:
        service = run(zopts, config, stop=stop, state_dir=args.state_dir, rrd=args.rrd,
                      rrd_options={"map_period_s": args.rrd_map_period,
                                   "recon_period_s": args.rrd_recon_period,
                                   "max_image_bytes": int(args.rrd_max_mb * (1 << 20)),
                                   "serve_port": args.rerun_serve,
                                   "connect_url": args.rerun_connect},
                      ready=lambda s: print(f"evcal serve: ready ({s.instance})",
                                            file=sys.stderr, flush=True),
                      sign_key=args.sign_key, ros2=ros2)
    except (TransportError, SignatureError) as exc:
        print(f"evcal serve: {exc}", file=sys.stderr)
        return 1
    finally:
        relay.close(ignore_after_stop=True)
    if parent_gone is not None and parent_gone.is_set():
        from .workers import remove_orphaned_socket

        remove_orphaned_socket(zopts.connect)
    n = len(service.cameras)
    errors = sum(c.counters.errors_total for c in service.cameras.values())
    print(f"evcal serve: stopped; {n} camera(s), {errors} rejected input(s)", file=sys.stderr)
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    return main_serve(argv)
