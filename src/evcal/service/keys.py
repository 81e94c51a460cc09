"""Key expressions and payload encodings of the evcal network protocol (see docs/WIRE.md).

A camera id is one or more key chunks (``cam0``, ``lab/rig1/cam0``). Under a prefix
(default ``evcal``, may itself have several chunks) a camera has::

    <prefix>/<camera>/events        in:  event chunks        (msgpack, evcal.io.wire)
    <prefix>/<camera>/frames        in:  intensity frames    (msgpack, evcal.io.wire)
    <prefix>/<camera>/calibration   out: calibration maps    (msgpack; queryable: msgpack | npz)
    <prefix>/<camera>/status        out: counters and rates  (JSON; also a queryable)
    <prefix>/<camera>/errors        out: rejected inputs     (JSON, one per error, rate-limited)
    <prefix>/cameras                queryable: each service instance's cameras (JSON)
    <prefix>/@service/<instance>    liveliness token of a running service instance
"""

from __future__ import annotations

import hashlib

from ..errors import ConfigError, EvcalError

INPUT_KINDS = ("events", "frames")
OUTPUT_KINDS = ("calibration", "status", "errors")

ENC_EVENTS = "application/msgpack;evcal.events.v1"
ENC_FRAME = "application/msgpack;evcal.frame.v1"
ENC_CALIBRATION = "application/msgpack;evcal.calibration.v1"
ENC_CALIBRATION_NPZ = "application/x-npz;evcal.calibration.v1"
ENC_STATUS = "application/json;evcal.status.v1"
ENC_ERROR = "application/json;evcal.error.v1"
ENC_CAMERAS = "application/json;evcal.cameras.v1"

SERVICE_CHUNK = "@service"


def _strip(s: str) -> str:
    return s.strip("/")


def camera_key(prefix: str, camera: str, kind: str) -> str:
    """``<prefix>/<camera>/<kind>``."""
    return f"{_strip(prefix)}/{_strip(camera)}/{kind}"


def cameras_key(prefix: str) -> str:
    return f"{_strip(prefix)}/cameras"


def service_token_key(prefix: str, instance: str = "*") -> str:
    return f"{_strip(prefix)}/{SERVICE_CHUNK}/{instance}"


def split_camera_key(prefix: str, key: str) -> tuple[str, str] | None:
    """``(camera, kind)`` of a concrete key ``<prefix>/<camera>/<kind>``, else ``None``."""
    head = _strip(prefix) + "/"
    if not key.startswith(head):
        return None
    rest = key[len(head):]
    camera, sep, kind = rest.rpartition("/")
    if not sep or not camera:
        return None
    return camera, kind


MAX_CAMERA_ID = 200  # characters


class CameraIdError(EvcalError):
    """A camera id that cannot name a camera (too long, empty chunks, wildcards)."""


def check_camera_id(camera: str) -> str:
    """A camera id: at most :data:`MAX_CAMERA_ID` characters in non-empty ``/``-separated
    chunks of printable characters, no wildcards, no ``@`` chunk, no ``.`` or ``..`` chunk."""
    if len(camera) > MAX_CAMERA_ID:
        raise CameraIdError(f"camera id of {len(camera)} characters is longer than "
                            f"{MAX_CAMERA_ID}: {camera[:40]!r}...")
    chunks = camera.split("/")
    bad = (not camera or any(not c for c in chunks) or any(c.startswith("@") for c in chunks)
           or any(c in (".", "..") for c in chunks)
           or any(ch in camera for ch in "*$?#\\") or not camera.isprintable())
    if bad:
        raise CameraIdError(f"camera id {camera!r} is not valid: expected '/'-separated non-empty "
                            "chunks of printable characters without '*', '$', '?', '#', '\\', "
                            "a leading '@' or a '.'/'..' chunk, e.g. 'lab/rig1/cam0'")
    return camera


def matches(expr: str, key: str) -> bool:
    """Whether the concrete ``key`` is in the key expression ``expr`` (``*`` and ``**`` only).

    A pure-Python stand-in for zenoh's matching (used without a session, e.g. in tests);
    chunks starting with ``@`` are matched only literally, as zenoh does.
    """
    e, k = expr.strip("/").split("/"), key.strip("/").split("/")

    def rec(i: int, j: int) -> bool:
        if i == len(e):
            return j == len(k)
        if e[i] == "**":
            return rec(i + 1, j) or (j < len(k) and not k[j].startswith("@") and rec(i, j + 1))
        if j == len(k):
            return False
        if e[i] == "*":
            return not k[j].startswith("@") and rec(i + 1, j + 1)
        return e[i] == k[j] and rec(i + 1, j + 1)

    return rec(0, 0)


def shard_of(camera: str, n_shards: int) -> int:
    """The shard (``0 .. n_shards - 1``) that serves ``camera``: the first 8 bytes of the
    BLAKE2b hash of its UTF-8 id, big-endian, modulo ``n_shards``. Stable across processes,
    runs and machines (unlike ``hash()``), so a camera always has the same owner among the
    workers of ``evcal serve --workers N`` and among instances started with ``--shard i/N``.
    Not CRC-32: it is linear, and ids that differ in one character (``cam0`` .. ``cam3``)
    share their low bits, hence their shard."""
    if n_shards < 1:
        raise ConfigError(f"n_shards={n_shards} must be >= 1")
    digest = hashlib.blake2b(camera.encode("utf-8", "surrogatepass"), digest_size=8).digest()
    return int.from_bytes(digest, "big") % n_shards


def parse_shard(text: str) -> tuple[int, int]:
    """``"i/N"`` -> ``(i, N)`` with ``0 <= i < N``; ValueError otherwise."""
    index, sep, count = text.partition("/")
    try:
        i, n = int(index), int(count)
    except ValueError:
        i = n = -1
    if not sep or n < 1 or not 0 <= i < n:
        raise ConfigError(f"shard {text!r} is not I/N with 0 <= I < N, e.g. 0/2")
    return i, n
