"""Decoders of ``event_camera_msgs/msg/EventPacket`` payloads (not public API).

One decoder object per stream (topic): it turns each message's ``events`` bytes into columns
and keeps what the encoding carries from one packet to the next (EVT3's time and address
state, libcaer_cmp's x address). ``libcaer`` / ``mono`` / ``evt3`` are vectorised numpy (a
loop per message, none per event); ``libcaer_cmp``, the live ROS 2 path's encoding, is one
compiled pass over the words (numba, the GIL released: 160 M events/s against 3.5 M for its
former numpy form on uniformly spread events, results identical).

The format facts come from the C++ reference decoders of ros-event-camera's
``event_camera_codecs`` (file paths below are in that repository), checked against the decoded
truth published with ``event_camera_py`` (``tests/test_1.py``, ``tests/test_2.py``):

- words are little-endian; ``is_bigendian`` payloads are not produced by the drivers;
- ``libcaer_cmp`` (``include/event_camera_codecs/libcaer_cmp_types.h``,
  ``libcaer_cmp_decoder.h``): 16-bit words, code in the top 4 bits. TIME_HIGH (0) holds time
  bits 12-23, TIME_LOW (1) bits 0-11 (both reset to 0 at the start of every packet); ADDR_X (2)
  sets x (11 bits) for the events that follow; ADDR_Y (3) is one event at (x, y = bits 0-10,
  polarity = bit 11); VECT_BASE_Y (4) sets a base y and a polarity, and each VECT_8 (5) is up
  to eight events at y = base + i for the set bits i of its low byte, after which the base
  moves up by 8. The time is ``time_base`` (ns, since ``event_camera_py`` 2025:
  ``include/event_camera_py/decoder.h`` sets a time multiplier of 1, which divides it by 1000)
  plus the 24-bit packet time in µs. x, the vector base and the vector polarity carry over
  to the next packet; events outside width x height are dropped.
- ``libcaer`` (``libcaer_decoder.h``): 8-byte records, a little-endian uint32 ``data``
  (polarity bit 1, y bits 2-16, x bits 17-31) and an int32 µs timestamp; the time is
  ``time_base`` (ns) + timestamp * 1000, and a timestamp smaller than the one before it in
  the same packet is a 31-bit overflow (+2^31 µs).
- ``mono`` (``mono_decoder.h``, ``mono_encoder.h``): 8-byte little-endian words, bits 0-31 a
  time offset added to ``time_base`` (both ns), x bits 32-47, y bits 48-62, polarity bit 63.
- ``evt3`` (``evt3_types.h``, ``evt3_decoder.h``): Prophesee EVT 3.0, 16-bit words, code in
  the top 4 bits. ADDR_Y (0) sets y; ADDR_X (2) is one event at (x = bits 0-10, y, polarity =
  bit 11); VECT_BASE_X (3) sets a base x and a polarity, VECT_12 (4) and VECT_8 (5) are events
  at x = base + i for the set bits i of their low 12 / 8 bits, after which the base moves up
  by 12 / 8; TIME_LOW (6) and TIME_HIGH (8) hold time bits 0-11 and 12-23 (µs of sensor time;
  ``time_base`` is not used). The 24-bit time wraps every 2^24 µs = 16.77 s: a TIME_HIGH more
  than 10 below the previous one is a wrap (smaller steps back are sensor bit errors, not
  wraps). Nothing is decoded before a TIME_HIGH followed by a TIME_LOW in the same packet.
  EXT_TRIGGER (10) is a trigger edge; OTHERS (14), CONTINUED_4 (7) and CONTINUED_12 (15) are
  skipped; other codes are refused. All state carries over to the next packet.

Polarity bit 1 is ON in every encoding.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol

import numba
import numpy as np

from ..errors import ErrorReason, EvcalError

ENCODINGS = ("libcaer_cmp", "libcaer", "evt3", "mono")


class PayloadError(EvcalError):
    """An event payload that does not decode (truncated, unknown code, impossible value)."""


@dataclass
class DecodedPacket:
    """One payload's events (in payload order, inside the sensor) and trigger times."""

    t_us: np.ndarray  # int64
    x: np.ndarray  # uint16
    y: np.ndarray  # uint16
    on: np.ndarray  # bool
    dropped: int = 0  # events outside width x height, dropped as the reference does
    trigger_t_us: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))


class PacketDecoder(Protocol):
    encoding: str

    def decode(self, payload: np.ndarray, *, time_base: int, width: int, height: int,
               stamp_ns: int) -> DecodedPacket:
        ...  # pragma: no cover


def _words(payload: np.ndarray, size: int, encoding: str) -> np.ndarray:
    """The payload as little-endian unsigned words of ``size`` bytes."""
    buf = np.ascontiguousarray(payload, dtype=np.uint8)
    if buf.size % size:
        raise PayloadError(
            f"{encoding} payload of {buf.size} bytes is not a whole number of {size}-byte "
            f"words ({buf.size % size} bytes left over: truncated?)", ErrorReason.TRUNCATED)
    dtype = {2: "<u2", 8: "<u8"}[size]
    return buf.view(dtype)


def _last_index(mask: np.ndarray) -> np.ndarray:
    """For every position, the index of the last True at or before it, else -1."""
    idx = np.where(mask, np.arange(mask.size), -1)
    result: np.ndarray = np.maximum.accumulate(idx) if idx.size else idx
    return result


def _bits(values: np.ndarray, n_bits: int) -> tuple[np.ndarray, np.ndarray]:
    """Rows and bit numbers (ascending within a row) of the set bits of ``values``."""
    as_bytes = values.astype("<u2").view(np.uint8).reshape(-1, 2)
    bits = np.unpackbits(as_bytes, axis=1, bitorder="little")[:, :n_bits]
    rows, cols = np.nonzero(bits)
    return rows, cols.astype(np.int64)


def _packet(t_us: np.ndarray, x: np.ndarray, y: np.ndarray, on: np.ndarray, key: np.ndarray,
            width: int, height: int, trigger_t_us: np.ndarray | None = None) -> DecodedPacket:
    """Events put in payload order (``key``) and cut to the sensor."""
    order = np.argsort(key, kind="stable")
    x, y = x[order], y[order]
    keep = (x < width) & (y < height)
    return DecodedPacket(
        t_us=np.asarray(t_us[order][keep], np.int64), x=x[keep].astype(np.uint16),
        y=y[keep].astype(np.uint16), on=np.asarray(on[order][keep], bool),
        dropped=int(keep.size - np.count_nonzero(keep)),
        trigger_t_us=(np.zeros(0, np.int64) if trigger_t_us is None
                      else np.asarray(trigger_t_us, np.int64)),
    )


def _unknown_codes(codes: np.ndarray, allowed: tuple[int, ...], encoding: str,
                   names: dict[int, str] | None = None) -> None:
    bad = np.flatnonzero(~np.isin(codes, allowed))
    if bad.size:
        i = int(bad[0])
        code = int(codes[i])
        what = (names or {}).get(code, "an unknown code")
        raise PayloadError(
            f"{encoding} word {i} has code {code} ({what}); expected one of "
            f"{sorted(allowed)} ({bad.size} such words)", ErrorReason.MALFORMED)


# Time stamps of this size (µs) can only be µs since the epoch, never ns.
_ONE_DAY_NS = 86_400 * 10**9


class LibcaerCmpDecoder:
    """``libcaer_cmp`` (iniVation cameras through libcaer_driver), see the module docstring.

    ``time_base`` is ns in event_camera_py's convention (the shared bag's truth); a stream
    whose first ``time_base`` is µs (within a day of the message stamp only when multiplied
    by 1000, as in event_camera_codecs' own 2023 test data) is read as µs:
    :attr:`time_base_unit` says which.
    """

    encoding = "libcaer_cmp"

    def __init__(self) -> None:
        self.x = 0
        self.base_y = 0
        self.pol = 0
        self.time_base_unit: str | None = None

    def _base_us(self, time_base: int, stamp_ns: int) -> int:
        if self.time_base_unit is None:
            as_us = stamp_ns > 0 and abs(time_base * 1000 - stamp_ns) < _ONE_DAY_NS \
                and abs(time_base - stamp_ns) >= _ONE_DAY_NS
            self.time_base_unit = "us" if as_us else "ns"
        return time_base if self.time_base_unit == "us" else time_base // 1000

    def decode(self, payload: np.ndarray, *, time_base: int, width: int, height: int,
               stamp_ns: int) -> DecodedPacket:
        w = _words(payload, 2, self.encoding)
        if w.size and int(w.max()) >> 12 > 5:
            _unknown_codes((w >> 12).astype(np.int64), (0, 1, 2, 3, 4, 5), self.encoding,
                           {6: "VECT_12, which libcaer_cmp encoders do not write"})
        base_us = self._base_us(int(time_base), stamp_ns)
        t, x, y, on, dropped, state = _cmp_kernel(
            w, np.int64(base_us), np.int64(self.x), np.int64(self.base_y), np.int64(self.pol),
            np.int64(width), np.int64(height))
        self.x, self.base_y, self.pol = (int(v) for v in state)
        return DecodedPacket(t_us=t, x=x, y=y, on=on, dropped=int(dropped))


def _cmp_loop(w: np.ndarray, base_us: np.int64, x: np.int64, base_y: np.int64,
              pol: np.int64, width: np.int64, height: np.int64
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, int, np.ndarray]:
    """libcaer_cmp words (codes 0-5 only) to events inside ``width x height`` in payload
    order, one pass to count them and one to write them; returns the columns, the number
    dropped outside the sensor and the carried state ``[x, base_y, pol]`` (see
    :class:`LibcaerCmpDecoder`; compiled by numba, the GIL released)."""
    n = 0
    for i in range(w.size):
        code = w[i] >> 12
        if code == 3:
            n += 1
        elif code == 5:
            v = w[i] & 0xFF
            while v:
                n += 1
                v &= v - 1
    t_out = np.empty(n, np.int64)
    x_out = np.empty(n, np.uint16)
    y_out = np.empty(n, np.uint16)
    on_out = np.empty(n, np.bool_)
    high = 0
    low = 0
    k = 0
    dropped = 0
    for i in range(w.size):
        code = w[i] >> 12
        rest = np.int64(w[i] & 0xFFF)
        if code == 0:
            high = rest
        elif code == 1:
            low = rest
        elif code == 2:
            x = rest & 0x7FF
        elif code == 3:
            y = rest & 0x7FF
            if x < width and y < height:
                t_out[k] = base_us + ((high << 12) | low)
                x_out[k] = x
                y_out[k] = y
                on_out[k] = ((rest >> 11) & 1) != 0
                k += 1
            else:
                dropped += 1
        elif code == 4:
            base_y = rest & 0x7FF
            pol = (rest >> 11) & 1
        else:  # VECT_8: events at base_y + bit for the set bits of the low byte
            bits = rest & 0xFF
            for b in range(8):
                if (bits >> b) & 1:
                    y = (base_y + b) & 0xFFFF
                    if x < width and y < height:
                        t_out[k] = base_us + ((high << 12) | low)
                        x_out[k] = x
                        y_out[k] = y
                        on_out[k] = pol != 0
                        k += 1
                    else:
                        dropped += 1
            base_y = (base_y + 8) & 0xFFFF
    state = np.empty(3, np.int64)
    state[0] = x
    state[1] = base_y
    state[2] = pol
    return t_out[:k], x_out[:k], y_out[:k], on_out[:k], dropped, state


_cmp_kernel = numba.njit(cache=True, nogil=True)(_cmp_loop)


class LibcaerDecoder:
    """``libcaer`` (uncompressed libcaer polarity events), see the module docstring."""

    encoding = "libcaer"
    _DTYPE = np.dtype([("data", "<u4"), ("ts", "<i4")])

    def decode(self, payload: np.ndarray, *, time_base: int, width: int, height: int,
               stamp_ns: int) -> DecodedPacket:
        words = _words(payload, 8, self.encoding)
        rec = words.view(self._DTYPE)
        ts = rec["ts"].astype(np.int64)
        neg = np.flatnonzero(ts < 0)
        if neg.size:
            i = int(neg[0])
            raise PayloadError(f"libcaer event {i} has a negative timestamp {int(ts[i])} "
                               "(libcaer timestamps are 31-bit)", ErrorReason.MALFORMED)
        wraps = np.concatenate([[0], np.cumsum(ts[1:] < ts[:-1])]) if ts.size else ts
        # time_base + ts * 1000 ns, floored to µs: time_base // 1000 + ts exactly
        t = int(time_base) // 1000 + ts + (wraps.astype(np.int64) << 31)
        data = rec["data"].astype(np.int64)
        return _packet(t_us=t, x=(data >> 17) & 0x7FFF, y=(data >> 2) & 0x7FFF,
                       on=((data >> 1) & 1).astype(bool), key=np.arange(t.size),
                       width=width, height=height)


class MonoDecoder:
    """``mono`` (legacy 8-byte events), see the module docstring."""

    encoding = "mono"

    def decode(self, payload: np.ndarray, *, time_base: int, width: int, height: int,
               stamp_ns: int) -> DecodedPacket:
        w = _words(payload, 8, self.encoding)
        dt = (w & 0xFFFFFFFF).astype(np.int64)
        tb = int(time_base)
        t = tb // 1000 + (tb % 1000 + dt) // 1000  # floor((time_base + dt) / 1000) exactly
        return _packet(t_us=t, x=((w >> 32) & 0xFFFF).astype(np.int64),
                       y=((w >> 48) & 0x7FFF).astype(np.int64), on=(w >> 63).astype(bool),
                       key=np.arange(t.size), width=width, height=height)


_EVT3_NAMES = {1: "no EVT3 meaning", 9: "no EVT3 meaning", 11: "no EVT3 meaning",
               12: "no EVT3 meaning", 13: "no EVT3 meaning"}
# A TIME_HIGH this much below the previous one is a wrap of the 24-bit time; a smaller step
# back is a sensor bit error (evt3_decoder.h, update_high_time).
_EVT3_WRAP_MIN_STEP = 10


class Evt3Decoder:
    """Prophesee EVT 3.0 (metavision_driver), see the module docstring. Times are the
    sensor's µs since the camera started, unwrapped across packets."""

    encoding = "evt3"

    def __init__(self) -> None:
        self.y = 0
        self.base_x = 0
        self.pol = 0
        self.low = 0
        self.high = 0  # wraps << 24 | TIME_HIGH << 12
        self.valid = False

    def decode(self, payload: np.ndarray, *, time_base: int, width: int, height: int,
               stamp_ns: int) -> DecodedPacket:
        w = _words(payload, 2, self.encoding)
        code = (w >> 12).astype(np.int64)
        rest = (w & 0xFFF).astype(np.int64)
        n = code.size
        pos = np.arange(n)
        is_th = code == 8
        is_tl = code == 6
        start = 0
        if not self.valid:
            # decoding starts after the first TIME_LOW that follows a TIME_HIGH in this packet
            th_first = np.flatnonzero(is_th)
            tl_after = np.flatnonzero(is_tl & (pos > th_first[0])) if th_first.size else th_first
            start = int(tl_after[0]) + 1 if tl_after.size else n
            self.valid = bool(tl_after.size)
        live = pos >= start
        _unknown_codes(code[live], (0, 2, 3, 4, 5, 6, 7, 8, 10, 14, 15), self.encoding,
                       _EVT3_NAMES)
        # TIME_HIGH with wraps: compared with the TIME_HIGH before it (also across packets)
        th_idx = np.flatnonzero(is_th)
        th = rest[th_idx]
        prev = np.concatenate([[(self.high >> 12) & 0xFFF], th[:-1]])
        wrap = (th < prev) & (prev - th > _EVT3_WRAP_MIN_STEP)
        high_vals = ((self.high >> 24) + np.cumsum(wrap)) << 24 | (th << 12)
        th_pos = np.cumsum(is_th) - 1
        high_at = np.where(th_pos >= 0, high_vals[np.maximum(th_pos, 0)] if th.size else 0,
                           self.high)
        tl_last = _last_index(is_tl)
        low_at = np.where(tl_last >= 0, rest[np.maximum(tl_last, 0)], self.low)
        t = high_at | low_at
        # addresses, only from the start of decoding on
        is_y = (code == 0) & live
        ya = _last_index(is_y)
        y_at = np.where(ya >= 0, rest[np.maximum(ya, 0)] & 0x7FF, self.y)
        a = np.flatnonzero((code == 2) & live)
        is_vb = (code == 3) & live
        is_v12 = (code == 4) & live
        is_v8 = (code == 5) & live
        step = 12 * is_v12 + 8 * is_v8
        before = np.cumsum(step) - step
        vb = _last_index(is_vb)
        v = np.flatnonzero(is_v12 | is_v8)
        vbv = vb[v]
        has_base = vbv >= 0
        base = np.where(has_base, rest[np.maximum(vbv, 0)] & 0x7FF, self.base_x)
        offset = np.where(has_base, before[v] - before[np.maximum(vbv, 0)], before[v])
        pol = np.where(has_base, (rest[np.maximum(vbv, 0)] >> 11) & 1, self.pol)
        valid_bits = np.where(is_v12[v], rest[v] & 0xFFF, rest[v] & 0xFF)
        rows, b = _bits(valid_bits, 12)
        trig = np.flatnonzero((code == 10) & live)
        packet = _packet(
            t_us=np.concatenate([t[a], t[v][rows]]),
            x=np.concatenate([rest[a] & 0x7FF, (base[rows] + offset[rows] + b) & 0xFFFF]),
            y=np.concatenate([y_at[a], y_at[v][rows]]),
            on=np.concatenate([(rest[a] >> 11) & 1, pol[rows]]).astype(bool),
            key=np.concatenate([a * 16, v[rows] * 16 + b]),
            width=width, height=height, trigger_t_us=t[trig])
        # state for the next packet
        if th.size:
            self.high = int(high_vals[-1])
        if tl_last.size and tl_last[-1] >= 0:
            self.low = int(rest[tl_last[-1]])
        if ya.size and ya[-1] >= 0:
            self.y = int(rest[ya[-1]] & 0x7FF)
        if vb.size and vb[-1] >= 0:
            last = int(vb[-1])
            self.pol = int((rest[last] >> 11) & 1)
            self.base_x = (int(rest[last] & 0x7FF) + int(step[last:].sum())) & 0xFFFF
        else:
            self.base_x = (self.base_x + int(step.sum())) & 0xFFFF
        return packet


def make_decoder(encoding: str) -> PacketDecoder:
    """A fresh decoder for ``encoding``; :class:`PayloadError` for one evcal does not read."""
    decoders: dict[str, type[PacketDecoder]] = {
        "libcaer_cmp": LibcaerCmpDecoder, "libcaer": LibcaerDecoder, "evt3": Evt3Decoder,
        "mono": MonoDecoder,
    }
    if encoding not in decoders:
        raise PayloadError(f"EventPacket encoding {encoding!r} is not one evcal decodes "
                           f"(it reads {', '.join(ENCODINGS)})", ErrorReason.MALFORMED)
    return decoders[encoding]()
