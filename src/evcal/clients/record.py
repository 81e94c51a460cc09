"""``evcal record``: record events, frames and calibrations from zenoh into MCAP files.

The file layout is evcal's own (:mod:`evcal.io.mcap_rec`): ``/events`` and ``/frames`` with
the wire envelopes, ``/calibration`` with the service's calibration messages, an ``evcal``
metadata record with the sensor. ``evcal replay`` and ``evcal calibrate`` read it back. One
file holds one camera: ``--camera`` naming a single camera writes ``--out`` as given;
otherwise ``--out`` must contain ``{camera}`` (replaced by the id with ``/`` -> ``_``).

Sequence numbers are renumbered from 0 per file (the reader requires contiguous numbers); the
messages lost on the way (gaps in the publishers' numbers) and the ones rejected as malformed
are counted in an ``evcal.record`` metadata record.
"""

from __future__ import annotations

import argparse
import json
import sys
import threading
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from evcal.errors import ConfigError, ErrorReason, EvcalError
from evcal.io.mcap_rec import McapWriter
from evcal.io.wire import (
    decode_calibration_maps,
    decode_events,
    decode_frame,
    encode_events,
    encode_frame,
)
from evcal.service import keys
from evcal.service.cli import add_ros2_arguments, ros_domain
from evcal.service.state import snapshot_name
from evcal.service.transport import Transport, TransportError, options_from_args
from evcal.signals import STOP_SIGNALS, SignalRelay
from evcal.stream import DuplicateMessage, LateMessage, StreamError, StreamGuard

from .common import base_parser, fail


class CameraWriter:
    """One camera's MCAP file (:class:`~evcal.io.mcap_rec.McapWriter`), fed through the
    stream's :class:`~evcal.stream.StreamGuard` with the service's semantics: a message for
    another sensor size, events going back in time or a frame not after the previous one are
    refused and counted (``rejected``), so is an exact copy of a recent message (a
    ``duplicate``); ``lost`` counts the messages missing in the publisher's sequence numbers
    that never arrived — one that arrived and was refused (also before its number could be
    read) is not lost, and a late one (after a later message) comes off ``lost`` whether it
    is placed or refused. One file holds one sensor: the new sensor of a publisher restart is
    refused (``sensor_changed``)."""

    def __init__(self, path: Path, camera: str) -> None:
        self.path = path
        self.camera = camera
        path.parent.mkdir(parents=True, exist_ok=True)
        self.out = McapWriter(path, library="evcal record", calibration=True)
        self.guard = StreamGuard()
        self.counts = {"messages": 0, "events": 0, "frames": 0, "calibrations": 0,
                       "lost": 0, "rejected": 0}
        self.errors: list[str] = []
        # per stream, since its last accepted message: messages refused before their
        # sequence number was read; a gap of that many is not loss (as the service's)
        self._not_lost = {"events": 0, "frames": 0}

    def _accept(self, kind: str, hd: dict[str, Any], t_first: int | None,
                t_last: int | None, what: str) -> None:
        """The stream checks of one message (raises :class:`~evcal.errors.EvcalError` for a
        refused one) and what they say about loss."""
        try:
            check = self.guard.accept(kind, t_first_us=t_first, t_last_us=t_last, what=what,
                                      seq=hd["seq"], size=(hd["height"], hd["width"]))
        except LateMessage as exc:
            # counted lost when the gap showed; it arrived (refused), so it is not lost
            self.counts["lost"] = max(0, self.counts["lost"] - exc.recovered)
            raise
        not_lost, self._not_lost[kind] = self._not_lost[kind], 0
        lost = self.counts["lost"] + max(0, check.lost - not_lost)
        self.counts["lost"] = max(0, lost - check.recovered)
        sensor = self.guard.sensor
        assert sensor is not None  # accept() fixed it
        if self.out.sensor is None:
            self.out.set_sensor(sensor, {"source": "evcal record", "camera": self.camera})
        elif sensor != self.out.sensor:
            raise StreamError(f"{what}: a {sensor} sensor after a publisher restart, but this "
                              f"file holds {self.out.sensor}: not recorded (one sensor per "
                              "file)", ErrorReason.SENSOR_CHANGED)

    def add(self, kind: str, payload: bytes) -> None:
        read = False  # the message's sequence number was read
        try:
            if kind == "events":
                ev, hd = decode_events(payload)
                read = True
                what = f"events message seq {hd['seq']}"
                t = ev["t_us"]
                self._accept(kind, hd, int(t[0]) if t.size else None,
                             int(t[-1]) if t.size else None, what)
                if ev.size == 0:
                    return  # its number counts (no gap), it records nothing
                self.out.add_events(int(t[0]), encode_events(ev, height=hd["height"],
                                                             width=hd["width"],
                                                             seq=self.out.counts["events"]))
                self.counts["events"] += int(ev.size)
            elif kind == "frames":
                t_us, exp, img, hd = decode_frame(payload)
                read = True
                self._accept(kind, hd, t_us, t_us, f"frame message seq {hd['seq']}")
                self.out.add_frame(t_us, encode_frame(t_us, img, exposure_us=exp,
                                                      seq=self.out.counts["frames"]))
                self.counts["frames"] += 1
            else:
                _, hd = decode_calibration_maps(payload)
                self.out.add_calibration(hd["t_us"], payload)
                self.counts["calibrations"] += 1
        except EvcalError as exc:
            if not read and kind in self._not_lost:
                self._not_lost[kind] += 1
            self.counts["rejected"] += 1
            reason = ErrorReason.DUPLICATE if isinstance(exc, DuplicateMessage) else exc.reason
            if len(self.errors) < 20:
                self.errors.append(f"{kind}: {reason}: {exc}")
            return
        self.counts["messages"] += 1

    def close(self) -> None:
        self.out.close({"evcal.record": {"camera": self.camera,
                                         "counts_json": json.dumps(self.counts),
                                         "errors_json": json.dumps(self.errors)}})


class Recorder:
    """Subscribes to cameras and writes one MCAP file per camera."""

    def __init__(self, out: str, cameras: list[str], prefix: str = "evcal", *,
                 max_cameras: int = 64):
        self.prefix = prefix.strip("/")
        self.cameras = cameras
        single = len(cameras) == 1 and not any(ch in cameras[0] for ch in "*$")
        if not single and "{camera}" not in out:
            raise ConfigError(f"--out {out!r}: several cameras may be recorded ({cameras}); put "
                              "{camera} in the path, e.g. --out 'rec-{camera}.mcap'")
        self.out = out
        self.single = single
        self.writers: dict[str, CameraWriter] = {}
        self.max_cameras = int(max_cameras)  # open files at once
        self.refused: dict[str, int] = {}  # messages of cameras not recorded
        self._lock = threading.Lock()

    def path_for(self, camera: str) -> Path:
        """The file of ``camera``: ``{camera}`` becomes its id percent-encoded (``/`` ->
        ``%2F``; injective, never a path separator or ``..``), cut with a hash suffix when
        long (the same names as the service's snapshots)."""
        if self.single:
            return Path(self.out)
        return Path(self.out.replace("{camera}", snapshot_name(camera)[: -len(".npz")]))

    def on_sample(self, key: str, payload: bytes, encoding: str) -> None:
        parsed = keys.split_camera_key(self.prefix, key)
        if parsed is None:
            return
        camera, kind = parsed
        if kind not in ("events", "frames", "calibration"):
            return
        with self._lock:
            w = self.writers.get(camera)
            if w is None:
                try:
                    keys.check_camera_id(camera)
                except ValueError as exc:
                    self._refuse(camera, str(exc))
                    return
                if len(self.writers) >= self.max_cameras:
                    self._refuse(camera, f"already recording {self.max_cameras} cameras "
                                         "(--max-cameras)")
                    return
                w = self.writers[camera] = CameraWriter(self.path_for(camera), camera)
            w.add(kind, payload)

    def _refuse(self, camera: str, why: str) -> None:
        self.refused[camera] = self.refused.get(camera, 0) + 1
        if self.refused[camera] == 1 and len(self.refused) <= 20:
            print(f"evcal record: not recording camera {camera[:80]!r}: {why}",
                  file=sys.stderr, flush=True)

    def subscribe(self, t: Transport) -> None:
        # calibrations with history: a recording started after the last update still
        # begins with each camera's last calibration (the service latches them)
        for cam in self.cameras:
            for kind in ("events", "frames", "calibration"):
                t.subscribe(f"{self.prefix}/{cam}/{kind}", self.on_sample,
                            history=kind == "calibration")

    def close(self) -> dict[str, dict[str, int]]:
        with self._lock:
            for w in self.writers.values():
                w.close()
            return {c: dict(w.counts) for c, w in self.writers.items()}


def build_parser() -> argparse.ArgumentParser:
    p = base_parser("evcal record", "Record events, frames and calibrations from zenoh to MCAP.")
    p.add_argument("--out", required=True, metavar="FILE.mcap",
                   help="output file; with several cameras include {camera}")
    p.add_argument("--camera", "--cameras", dest="cameras", action="append", default=[],
                   metavar="ID_OR_KEYEXPR", help="camera(s) to record (default: **)")
    p.add_argument("--duration", type=float, default=None, metavar="S",
                   help="stop after S seconds (default: until Ctrl-C)")
    p.add_argument("--max-cameras", type=int, default=64,
                   help="record at most this many cameras (open files) at once (default 64)")
    add_ros2_arguments(
        p, "record the ROS 2 topics of a domain heard over rmw_zenoh (drivers' EventPackets "
           "and Images, `evcal serve --ros2`'s calibration images, any standard type) into "
           "one ROS 2 MCAP file (ros2msg schemas, CDR) that Foxglove, ros2 bag and evcal read")
    return p


def _record(prog: str, zopts: Any, recorder: Any, duration: float | None, what: str
            ) -> tuple[Any, int | None]:
    """Subscribe ``recorder`` and record until SIGINT/SIGTERM or ``duration`` s; returns what
    its ``close()`` returns and None, or an exit code when the session failed."""
    stop = threading.Event()
    relay = SignalRelay(STOP_SIGNALS, lambda _s: stop.set())
    code = None
    try:
        with Transport(zopts) as t:
            recorder.subscribe(t)
            print(f"{prog}: recording {what}", file=sys.stderr, flush=True)
            stop.wait(duration)
    except TransportError as exc:
        code = fail(prog, str(exc))
    finally:
        counts = recorder.close()
        relay.close(ignore_after_stop=True)
    return counts, code


def _main_ros2(args: Any, prog: str) -> int:
    """``evcal record --ros2`` (see :mod:`evcal.clients.rosrecord`)."""
    from .rosrecord import RosRecorder

    if args.cameras or "{camera}" in args.out:
        return fail(prog, "--camera and {camera} do not go with --ros2 (one file holds every "
                          "topic of the domain)", 2)
    try:
        zopts = options_from_args(args)
        domain = ros_domain(args)
        rec = RosRecorder(args.out, domain)
    except (ValueError, OSError) as exc:
        return fail(prog, str(exc), 2)
    t0 = time.monotonic()
    counts, code = _record(prog, zopts, rec, args.duration,
                           f"ROS 2 domain {domain} to {rec.path}")
    if code is not None:
        return code
    for topic, n in sorted(counts.items()):
        print(f"{prog}: {topic}: {n} messages", file=sys.stderr)
    if not counts:
        return fail(prog, f"nothing recorded in {time.monotonic() - t0:.1f} s (is a ROS 2 node "
                          f"publishing in domain {domain}, reachable with these --connect/"
                          "--mode settings?)", 3)
    print(f"{prog}: {sum(counts.values())} messages -> {rec.path}", file=sys.stderr)
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    prog = "evcal record"
    if args.ros2:
        return _main_ros2(args, prog)
    if args.ros_domain is not None:
        return fail(prog, "--ros-domain goes with --ros2", 2)
    cameras = [c.strip("/") for c in args.cameras] or ["**"]
    try:
        zopts = options_from_args(args)
        rec = Recorder(args.out, cameras, args.prefix, max_cameras=args.max_cameras)
    except ValueError as exc:
        return fail(prog, str(exc), 2)
    t0 = time.monotonic()
    counts, code = _record(prog, zopts, rec, args.duration,
                           f"{', '.join(cameras)} under {args.prefix}")
    if code is not None:
        return code
    for cam, c in counts.items():
        print(f"{prog}: {cam}: {c['events']} events, {c['frames']} frames, "
              f"{c['calibrations']} calibrations, {c['lost']} lost, {c['rejected']} rejected "
              f"-> {rec.path_for(cam)}", file=sys.stderr)
    if rec.refused:
        print(f"{prog}: {sum(rec.refused.values())} messages of {len(rec.refused)} camera(s) "
              "not recorded (see above)", file=sys.stderr)
    if not counts:
        return fail(prog, f"nothing received in {time.monotonic() - t0:.1f} s (is anything "
                          f"publishing under {args.prefix}, reachable with these --connect/"
                          "--mode settings?)", 3)
    return 0


if __name__ == "__main__":
    sys.exit(main())
