"""Encoders of ``event_camera_msgs/msg/EventPacket`` payloads: what a ROS 2 driver would send.

The inverse of :mod:`evcal.io._evcodecs` for two encodings, vectorised (no loop per event):

- ``libcaer_cmp`` (what ``libcaer_driver`` sends for DAVIS cameras): 16-bit little-endian
  words, code in the top 4 bits. Each packet starts with TIME_HIGH (code 0, time bits 12-23)
  and TIME_LOW (code 1, bits 0-11) of its first event and ADDR_X (code 2) of its first x;
  after that a TIME_HIGH, TIME_LOW or ADDR_X word is written only where that value changes,
  and every event is one ADDR_Y word (code 3: y in bits 0-10, polarity in bit 11). The packet
  time is µs after ``time_base`` (ns), so a packet spans less than 2^24 µs (16.7 s); x and y
  must be below 2048. The compressed vector words (VECT_BASE_Y, VECT_8) are not written: a
  decoder reads the single-event form alike.
- ``mono`` (8-byte little-endian words): time offset after ``time_base`` in ns in bits 0-31
  (a packet spans less than 2^32 ns, 4.29 s), x bits 32-47, y bits 48-62, polarity bit 63.

These serve replays and tests (a simulated recording as a ROS 2 bag, round trips against the
decoders); ``time_base`` is the packet's first event time in ns, so every event decodes to its
exact µs.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from ..errors import ConfigError, ErrorReason
from ..stream import frame_cuts
from ._evcodecs import PayloadError

ENCODERS = ("libcaer_cmp", "mono")

_CMP_SPAN_US = 1 << 24  # libcaer_cmp packet time: 24 bits of µs
_MONO_SPAN_US = (1 << 32) // 1000  # mono packet time: 32 bits of ns
_CMP_MAX_ADDR = 2048  # 11-bit x and y of libcaer_cmp


@dataclass(frozen=True)
class EncodedPacket:
    """One EventPacket's ``events`` payload and the fields that go with it."""

    payload: bytes
    time_base_ns: int  # the packet's first event time (ns)
    i0: int  # the events it holds: ``events[i0:i1]``
    i1: int


def _check(events: np.ndarray, encoding: str, span_us: int) -> None:
    t = events["t_us"]
    if t.size and (np.diff(t) < 0).any():
        raise PayloadError(f"{encoding}: events must be sorted by time", ErrorReason.MALFORMED)
    if t.size and int(t[-1]) - int(t[0]) >= span_us:
        raise PayloadError(f"{encoding}: a packet spans {int(t[-1]) - int(t[0])} µs, at most "
                           f"{span_us - 1} fit", ErrorReason.OUT_OF_RANGE)
    if t.size and int(t[0]) < 0:
        raise PayloadError(f"{encoding}: negative time {int(t[0])} µs", ErrorReason.OUT_OF_RANGE)


def encode_libcaer_cmp(events: np.ndarray) -> bytes:
    """The ``libcaer_cmp`` payload of one packet of sorted events (``time_base`` = first event
    time in ns, see the module docstring)."""
    _check(events, "libcaer_cmp", _CMP_SPAN_US)
    n = events.size
    if n == 0:
        return b""
    x = events["x"].astype(np.uint16)
    y = events["y"].astype(np.uint16)
    if int(x.max()) >= _CMP_MAX_ADDR or int(y.max()) >= _CMP_MAX_ADDR:
        raise PayloadError("libcaer_cmp: x and y must be below 2048", ErrorReason.OUT_OF_RANGE)
    rel = (events["t_us"] - events["t_us"][0]).astype(np.uint32)
    high = (rel >> 12).astype(np.uint16)
    low = (rel & 0xFFF).astype(np.uint16)
    first = np.zeros(n, bool)
    first[0] = True
    # one row of up to four words per event: TIME_HIGH, TIME_LOW, ADDR_X, ADDR_Y
    words = np.empty((n, 4), np.uint16)
    words[:, 0] = (0 << 12) | high
    words[:, 1] = (1 << 12) | low
    words[:, 2] = (2 << 12) | x
    words[:, 3] = (3 << 12) | ((events["p"] > 0).astype(np.uint16) << 11) | y
    keep = np.empty((n, 4), bool)
    keep[:, 0] = first | np.concatenate([[False], high[1:] != high[:-1]])
    keep[:, 1] = first | np.concatenate([[False], rel[1:] != rel[:-1]])
    keep[:, 2] = first | np.concatenate([[False], x[1:] != x[:-1]])
    keep[:, 3] = True
    return words[keep].astype("<u2").tobytes()


def encode_mono(events: np.ndarray) -> bytes:
    """The ``mono`` payload of one packet of sorted events (``time_base`` = first event time
    in ns)."""
    _check(events, "mono", _MONO_SPAN_US)
    if events.size == 0:
        return b""
    dt_ns = (events["t_us"] - events["t_us"][0]).astype(np.uint64) * np.uint64(1000)
    words = (dt_ns
             | (events["x"].astype(np.uint64) << np.uint64(32))
             | ((events["y"].astype(np.uint64) & np.uint64(0x7FFF)) << np.uint64(48))
             | ((events["p"] > 0).astype(np.uint64) << np.uint64(63)))
    payload: bytes = words.astype("<u8").tobytes()
    return payload


_ENCODE = {"libcaer_cmp": encode_libcaer_cmp, "mono": encode_mono}


def encode_packet(events: np.ndarray, encoding: str) -> bytes:
    """One packet's payload in ``encoding`` (:data:`ENCODERS`)."""
    if encoding not in _ENCODE:
        raise PayloadError(f"evcal encodes EventPackets as {', '.join(ENCODERS)}, not "
                           f"{encoding!r}", ErrorReason.MALFORMED)
    payload: bytes = _ENCODE[encoding](events)
    return payload


def packets(events: np.ndarray, frame_t_us: np.ndarray | None = None, *,
            encoding: str = "libcaer_cmp", packet_us: int = 10_000,
            max_events: int = 100_000) -> Iterator[EncodedPacket]:
    """Cut sorted ``events`` into packets and encode them, as a driver would.

    A packet holds at most ``max_events`` events and ``packet_us`` µs of sensor time, and
    never spans a frame time (``frame_t_us``: events at a frame's time start the next packet,
    as :func:`~evcal.stream.frame_cuts` puts them after the frame), so a replay can send each
    frame after the events before it.
    """
    if packet_us < 1 or max_events < 1:
        raise ConfigError(f"packet_us={packet_us} and max_events={max_events} must be >= 1")
    t = events["t_us"]
    bounds = [0, t.size]
    if frame_t_us is not None and len(frame_t_us):
        bounds = [0, *frame_cuts(t, np.asarray(frame_t_us, np.int64)).tolist(), t.size]
    for a, b in zip(bounds[:-1], bounds[1:], strict=True):
        i = a
        while i < b:
            j = min(b, i + max_events)
            j = max(i + 1, min(j, i + int(np.searchsorted(t[i:j], int(t[i]) + packet_us))))
            chunk = events[i:j]
            yield EncodedPacket(encode_packet(chunk, encoding), int(t[i]) * 1000, i, j)
            i = j
