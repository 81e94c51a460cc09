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

import json
import signal
import sys
import threading
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from evcal.io.mcap_rec import (
    CALIBRATION_TOPIC,
    EVENTS_SCHEMA,
    EVENTS_SCHEMA_NAME,
    EVENTS_TOPIC,
    FORMAT_VERSION,
    FRAME_SCHEMA,
    FRAME_SCHEMA_NAME,
    FRAMES_TOPIC,
    METADATA_NAME,
)
from evcal.io.wire import (
    WireError,
    decode_calibration_maps,
    decode_events,
    decode_frame,
    encode_events,
    encode_frame,
)
from evcal.service import keys
from evcal.service.transport import Transport, TransportError, options_from_args

from .common import base_parser, fail

CALIBRATION_SCHEMA_NAME = "evcal.Calibration"
CALIBRATION_SCHEMA: dict[str, Any] = {
    "title": CALIBRATION_SCHEMA_NAME,
    "description": "msgpack map, see docs/WIRE.md: header fields and 'maps' of raw "
                   "little-endian [y, x] arrays",
    "type": "object",
}


def _ns(t_us: int) -> int:
    return max(int(t_us), 0) * 1000


class CameraWriter:
    """One camera's MCAP file (opened at the first valid message)."""

    def __init__(self, path: Path, camera: str):
        from mcap.writer import CompressionType, Writer

        self.path = path
        self.camera = camera
        path.parent.mkdir(parents=True, exist_ok=True)
        self._f = open(path, "wb")
        self.w = Writer(self._f, compression=CompressionType.ZSTD)
        self.w.start(profile="", library="evcal record")
        ev_s = self.w.register_schema(EVENTS_SCHEMA_NAME, "jsonschema",
                                      json.dumps(EVENTS_SCHEMA).encode())
        fr_s = self.w.register_schema(FRAME_SCHEMA_NAME, "jsonschema",
                                      json.dumps(FRAME_SCHEMA).encode())
        ca_s = self.w.register_schema(CALIBRATION_SCHEMA_NAME, "jsonschema",
                                      json.dumps(CALIBRATION_SCHEMA).encode())
        self.ch = {"events": self.w.register_channel(EVENTS_TOPIC, "msgpack", ev_s),
                   "frames": self.w.register_channel(FRAMES_TOPIC, "msgpack", fr_s),
                   "calibration": self.w.register_channel(CALIBRATION_TOPIC, "msgpack", ca_s)}
        self.seq = {"events": 0, "frames": 0, "calibration": 0}
        self.src_next: dict[str, int | None] = {"events": None, "frames": None}
        self.sensor: tuple[int, int] | None = None
        self.last_t = {"events": None, "frames": None}
        self.counts = {"messages": 0, "events": 0, "frames": 0, "calibrations": 0,
                       "lost": 0, "rejected": 0}
        self.errors: list[str] = []

    def _sensor(self, h: int, w: int) -> None:
        if self.sensor is None:
            self.sensor = (h, w)
            self.w.add_metadata(METADATA_NAME, {
                "format_version": str(FORMAT_VERSION), "sensor": f"{w}x{h}", "height": str(h),
                "width": str(w),
                "metadata_json": json.dumps({"source": "evcal record", "camera": self.camera}),
            })
        elif self.sensor != (h, w):
            raise WireError(f"a {w}x{h} message, but the camera is {self.sensor[1]}x"
                            f"{self.sensor[0]}")

    def _gap(self, kind: str, seq: int) -> None:
        nxt = self.src_next[kind]
        if nxt is not None and seq > nxt:
            self.counts["lost"] += seq - nxt
        self.src_next[kind] = seq + 1

    def add(self, kind: str, payload: bytes) -> None:
        try:
            if kind == "events":
                ev, hd = decode_events(payload)
                self._sensor(hd["height"], hd["width"])
                if ev.size == 0:
                    return
                last = self.last_t["events"]
                if last is not None and int(ev["t_us"][0]) < last:
                    raise WireError("time goes backwards")
                self._gap(kind, hd["seq"])
                self.last_t["events"] = int(ev["t_us"][-1])
                t = int(ev["t_us"][0])
                data = encode_events(ev, height=hd["height"], width=hd["width"],
                                     seq=self.seq[kind])
                self.counts["events"] += int(ev.size)
            elif kind == "frames":
                t, exp, img, hd = decode_frame(payload)
                self._sensor(hd["height"], hd["width"])
                last = self.last_t["frames"]
                if last is not None and t <= last:
                    raise WireError("frame time goes backwards")
                self._gap(kind, hd["seq"])
                self.last_t["frames"] = t
                data = encode_frame(t, img, exposure_us=exp, seq=self.seq[kind])
                self.counts["frames"] += 1
            else:
                _, hd = decode_calibration_maps(payload)
                t, data = hd["t_us"], payload
                self.counts["calibrations"] += 1
        except WireError as exc:
            self.counts["rejected"] += 1
            if len(self.errors) < 20:
                self.errors.append(f"{kind}: {exc}")
            return
        self.w.add_message(self.ch[kind], log_time=_ns(t), publish_time=_ns(t),
                           sequence=self.seq[kind] & 0xFFFFFFFF, data=data)
        self.seq[kind] += 1
        self.counts["messages"] += 1

    def close(self) -> None:
        self.w.add_metadata("evcal.record", {
            "camera": self.camera, "counts_json": json.dumps(self.counts),
            "errors_json": json.dumps(self.errors)})
        self.w.finish()
        self._f.close()


class Recorder:
    """Subscribes to cameras and writes one MCAP file per camera."""

    def __init__(self, out: str, cameras: list[str], prefix: str = "evcal"):
        self.prefix = prefix.strip("/")
        self.cameras = cameras
        single = len(cameras) == 1 and not any(ch in cameras[0] for ch in "*$")
        if not single and "{camera}" not in out:
            raise ValueError(f"--out {out!r}: several cameras may be recorded ({cameras}); put "
                             "{camera} in the path, e.g. --out 'rec-{camera}.mcap'")
        self.out = out
        self.single = single
        self.writers: dict[str, CameraWriter] = {}
        self._lock = threading.Lock()

    def path_for(self, camera: str) -> Path:
        if self.single:
            return Path(self.out)
        return Path(self.out.replace("{camera}", camera.replace("/", "_")))

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
                w = self.writers[camera] = CameraWriter(self.path_for(camera), camera)
            w.add(kind, payload)

    def subscribe(self, t: Transport) -> None:
        for cam in self.cameras:
            for kind in ("events", "frames", "calibration"):
                t.subscribe(f"{self.prefix}/{cam}/{kind}", self.on_sample)

    def close(self) -> dict[str, dict[str, int]]:
        with self._lock:
            for w in self.writers.values():
                w.close()
            return {c: dict(w.counts) for c, w in self.writers.items()}


def build_parser():
    p = base_parser("evcal record", "Record events, frames and calibrations from zenoh to MCAP.")
    p.add_argument("--out", required=True, metavar="FILE.mcap",
                   help="output file; with several cameras include {camera}")
    p.add_argument("--camera", "--cameras", dest="cameras", action="append", default=[],
                   metavar="ID_OR_KEYEXPR", help="camera(s) to record (default: **)")
    p.add_argument("--duration", type=float, default=None, metavar="S",
                   help="stop after S seconds (default: until Ctrl-C)")
    return p


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    prog = "evcal record"
    cameras = [c.strip("/") for c in args.cameras] or ["**"]
    try:
        zopts = options_from_args(args)
        rec = Recorder(args.out, cameras, args.prefix)
    except ValueError as exc:
        return fail(prog, str(exc), 2)
    stop = threading.Event()
    old = {s: signal.signal(s, lambda *_: stop.set()) for s in (signal.SIGINT, signal.SIGTERM)}
    t0 = time.monotonic()
    try:
        with Transport(zopts) as t:
            rec.subscribe(t)
            print(f"{prog}: recording {', '.join(cameras)} under {args.prefix}", file=sys.stderr,
                  flush=True)
            stop.wait(args.duration)
    except TransportError as exc:
        return fail(prog, str(exc))
    finally:
        counts = rec.close()
        for s, h in old.items():
            signal.signal(s, h)
    for cam, c in counts.items():
        print(f"{prog}: {cam}: {c['events']} events, {c['frames']} frames, "
              f"{c['calibrations']} calibrations, {c['lost']} lost, {c['rejected']} rejected "
              f"-> {rec.path_for(cam)}", file=sys.stderr)
    if not counts:
        print(f"{prog}: nothing received in {time.monotonic() - t0:.1f} s", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
