"""``evcal record --ros2``: record the ROS 2 topics of a domain, heard over rmw_zenoh, into a
ROS 2 MCAP file (:class:`~evcal.io.ros2msg.Ros2McapWriter`: profile ``ros2``, ``ros2msg``
schemas, CDR messages unchanged) that ``ros2 bag``, Foxglove, ``rosbags`` and ``evcal info``
/ ``calibrate`` read.

Every topic on ``<domain>/<topic>/<dds type>/<hash>`` is recorded whose type evcal knows (the
ROS 2 standard types and the event camera messages: their definitions make the schemas); a
topic of another type, or whose RIHS01 hash differs from the definition evcal would write
(another version of the type), is skipped and named once. A message's log time is its
arrival (ns of wall time); its publish time the publisher's source timestamp when its
attachment carries one. With ``evcal serve --ros2`` in the same domain the calibration
images are recorded too.
"""

from __future__ import annotations

import json
import sys
import threading
import time
from pathlib import Path

from evcal.io.ros2msg import Ros2McapWriter, message_definition, type_hash
from evcal.service.ros2 import decode_attachment, parse_topic_key
from evcal.service.transport import Transport


class RosRecorder:
    """Writes what it hears on one ROS domain to one ROS 2 MCAP file (thread-safe)."""

    def __init__(self, out: str | Path, domain: int = 0) -> None:
        self.domain = int(domain)
        self.path = Path(out)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.writer = Ros2McapWriter(self.path, library="evcal record")
        self.counts: dict[str, int] = {}
        self.skipped: dict[str, str] = {}  # topic -> why
        self._lock = threading.Lock()

    def _skip(self, topic: str, why: str) -> None:
        if topic not in self.skipped:
            self.skipped[topic] = why
            print(f"evcal record: not recording {topic}: {why}", file=sys.stderr, flush=True)

    def on_sample(self, key: str, payload: bytes, encoding: str,
                  attachment: bytes | None) -> None:
        t_ns = time.time_ns()
        parsed = parse_topic_key(key)
        if parsed is None or parsed.domain != self.domain:
            return
        topic, msgtype = parsed.topic, parsed.msgtype
        with self._lock:
            if topic in self.skipped:
                return
            if topic not in self.counts:
                try:
                    message_definition(msgtype)
                except ValueError:
                    self._skip(topic, f"type {msgtype} is not known to evcal (no definition "
                                      "for the schema)")
                    return
                ours = type_hash(msgtype)
                if parsed.type_hash.startswith("RIHS01_") and parsed.type_hash != ours:
                    self._skip(topic, f"its {msgtype} has hash {parsed.type_hash}, the "
                                      f"definition evcal writes has {ours} (another version)")
                    return
                self.counts[topic] = 0
            att = decode_attachment(attachment)
            self.writer.add(topic, msgtype, t_ns, payload,
                            publish_time_ns=att.t_ns if att is not None else None)
            self.counts[topic] += 1

    def subscribe(self, t: Transport) -> None:
        t.subscribe(f"{self.domain}/**", self.on_sample, attachment=True)

    def close(self) -> dict[str, int]:
        """Finish the file; the messages recorded per topic."""
        with self._lock:
            self.writer.close({"evcal.record": {
                "ros_domain": str(self.domain), "counts_json": json.dumps(self.counts),
                "skipped_json": json.dumps(self.skipped)}})
            return dict(self.counts)
