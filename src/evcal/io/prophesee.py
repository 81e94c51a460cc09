"""Prophesee RAW (EVT 2.0, EVT 2.1, EVT 3.0) and DAT files: events.

evcal decodes these itself, with vectorised numpy (a loop over chunks of the file, none over
events). The maintained Python decoders were tried and not used: ``expelliarmus`` 1.1.12
reads EVT 3.0 wrongly where the sensor's TIME_LOW steps back (it adds 4096 µs to every later
event of that TIME_HIGH; seen on its own ``evt3_sample.raw``) and reads no EVT 2.1;
``faery`` 0.7.1 reads no EVT 2.1 either and clamps times that step back instead of keeping
them. The EVT 3.0 decoder is the one evcal uses for ``event_camera_msgs`` ``evt3`` packets
(:class:`evcal.io._evcodecs.Evt3Decoder`, checked there against the reference checksums).

Header
    Lines starting with ``%`` before the binary data; a ``% end`` line, where present, ends
    it. The encoding comes from ``% evt 2.0|2.1|3.0`` or ``% format EVT2|EVT21|EVT3[;...]``;
    the sensor size from ``% format ...;width=W;height=H``, ``% geometry WxH`` or
    ``% Width W`` / ``% Height H`` (DAT). A file that declares none needs ``sensor=``.

EVT 2.0 (Prophesee docs, ``encoding_formats/evt2``)
    32-bit little-endian words, type in bits 28-31: CD_OFF (0) and CD_ON (1) carry time bits
    0-5 (22-27), x (11-21) and y (0-10); EVT_TIME_HIGH (8) carries time bits 6-33 (0-27);
    EXT_TRIGGER (10) is counted; OTHERS (14) and CONTINUED (15) are skipped. Events before
    the first TIME_HIGH have no time and are skipped, as OpenEB does. A TIME_HIGH below the
    one before it is a wrap of the 34-bit time (+2^34 µs).
EVT 2.1 (``encoding_formats/evt21``)
    64-bit words: type (bits 60-63), time bits 0-5 (54-59), x base (43-53), y (32-42) and a
    32-bit validity mask (0-31): EVT_NEG (0) / EVT_POS (1) are events at x base + i for the
    set bits i. TIME_HIGH (8) carries time bits 6-33 in bits 32-59. ``endianness=legacy`` in
    the ``% format`` line (IMX636) stores the upper 32 bits first; otherwise the word is one
    little-endian 64-bit integer (GenX320).
EVT 3.0 (``encoding_formats/evt3``)
    see :mod:`evcal.io._evcodecs`; the 24-bit time is unwrapped (+2^24 µs).
DAT (``data/file_formats/dat``)
    After the header one byte of event type (0x0C CD, 0x00 2D) and one of event size (8);
    then 8-byte little-endian events: uint32 time (µs, unwrapped at 2^32), uint32 data.
    ``% Version 2`` (and later): x bits 0-13, y 14-27, polarity 28-31; ``% Version 1``
    (ATIS-era): x bits 0-8, y 9-16, polarity 17-20.

Polarity 1 is ON (+1), 0 is OFF (-1). Events are sorted by time (stable); how many were out
of order (sensor time glitches) is ``metadata["reordered_events"]``. Events outside the sensor
are dropped and counted (``metadata["dropped_events"]``, a ``RuntimeWarning``).
"""

from __future__ import annotations

import os
import re
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import ErrorReason
from ..events import EVENTS_DTYPE, SensorSize
from ..recording import Recording, RecordingError
from ._evcodecs import Evt3Decoder, PayloadError
from ._partial import (
    cut_in_header,
    header_only,
    nothing_whole,
    refuse_empty_file,
    report_cut,
    words_cut,
)
from ._util import check_sensor_arg

RAW_ENCODINGS = ("evt2", "evt21", "evt3")
# bytes decoded at once: bounds the temporary int64 arrays (tens of bytes a word) on big files
_CHUNK_BYTES = 1 << 22
_HEADER_MAX_BYTES = 1 << 20


@dataclass
class PropheseeHeader:
    """What a ``%`` header says: its lines, its length, encoding and sensor size."""

    lines: list[str]
    length: int
    encoding: str | None = None  # evt2, evt21, evt3 (RAW); None for DAT
    sensor: SensorSize | None = None
    legacy_evt21: bool = False
    dat_version: int | None = None
    fields: dict[str, str] = field(default_factory=dict)


def is_prophesee(head: bytes) -> str | None:
    """``"prophesee_raw"`` or ``"prophesee_dat"`` from a file's first bytes, else None."""
    if not head.startswith(b"% "):
        return None
    text = head.decode("latin-1")
    if "% Data file containing" in text or re.search(r"^% Version", text, re.M):
        return "prophesee_dat"
    return "prophesee_raw"


def read_header(data: bytes, where: str) -> PropheseeHeader:
    """Parse the ``%`` lines at the start of ``data``."""
    pos = 0
    lines: list[str] = []
    n = len(data)
    while pos < n and data[pos : pos + 1] == b"%":
        nl = data.find(b"\n", pos, pos + _HEADER_MAX_BYTES)
        if nl < 0 and n - pos < _HEADER_MAX_BYTES:
            raise cut_in_header(where, n, f"line {len(lines) + 1} of the '%' header has no "
                                "end")
        if nl < 0:
            raise RecordingError(f"{where}: a '%' header line longer than "
                                 f"{_HEADER_MAX_BYTES} bytes: not a Prophesee file?",
                                 ErrorReason.MALFORMED)
        line = data[pos:nl].decode("latin-1").rstrip("\r")
        pos = nl + 1
        lines.append(line)
        if line.strip() == "% end":
            break
    header = PropheseeHeader(lines=lines, length=pos)
    width = height = None
    for line in lines:
        words = line[1:].strip().split(None, 1)
        if len(words) < 2:
            continue
        key, value = words[0], words[1].strip()
        header.fields[key] = value
        low = key.lower()
        if low == "evt":
            header.encoding = {"2.0": "evt2", "2": "evt2", "2.1": "evt21", "3.0": "evt3",
                               "3": "evt3"}.get(value, f"evt {value}")
        elif low == "format":
            parts = [p.strip() for p in value.split(";")]
            name = parts[0].upper()
            header.encoding = {"EVT2": "evt2", "EVT21": "evt21", "EVT3": "evt3"}.get(
                name, f"format {parts[0]}")
            opts = dict(p.split("=", 1) for p in parts[1:] if "=" in p)
            if "width" in opts and "height" in opts:
                width, height = opts["width"], opts["height"]
            header.legacy_evt21 = opts.get("endianness", "").lower() == "legacy"
        elif low == "geometry":
            m = re.fullmatch(r"(\d+)\s*x\s*(\d+)", value)
            if m:
                width, height = m.group(1), m.group(2)
        elif low == "width":
            width = value
        elif low == "height":
            height = value
        elif low == "version":
            try:
                header.dat_version = int(float(value))
            except ValueError:
                pass
    if width is not None and height is not None:
        try:
            header.sensor = SensorSize(height=int(height), width=int(width))
        except (ValueError, TypeError) as exc:
            raise RecordingError(f"{where}: the header's sensor size {width}x{height} is not "
                                 f"valid ({exc})", ErrorReason.OUT_OF_RANGE) from None
    return header


def _sensor(header: PropheseeHeader, sensor: SensorSize | None, where: str) -> SensorSize:
    if header.sensor is not None:
        return check_sensor_arg(header.sensor, sensor, where)
    if sensor is None:
        raise RecordingError(
            f"{where}: the header declares no sensor size (no '% format ...;width=;height=', "
            "'% geometry WxH' or '% Width'/'% Height' line); pass sensor=, e.g. "
            "sensor=SensorSize(height=480, width=640) (--sensor-size 640x480)",
            ErrorReason.MALFORMED)
    return sensor


@dataclass
class _Columns:
    t: list[np.ndarray] = field(default_factory=list)
    x: list[np.ndarray] = field(default_factory=list)
    y: list[np.ndarray] = field(default_factory=list)
    on: list[np.ndarray] = field(default_factory=list)
    triggers: int = 0
    skipped: int = 0  # events before the first time word

    def add(self, t: np.ndarray, x: np.ndarray, y: np.ndarray, on: np.ndarray) -> None:
        self.t.append(np.asarray(t, np.int64))
        self.x.append(np.asarray(x, np.int64))
        self.y.append(np.asarray(y, np.int64))
        self.on.append(np.asarray(on, bool))


def _words(body: bytes, size: int, what: str, where: str) -> np.ndarray:
    if len(body) % size:
        raise RecordingError(
            f"{where}: {what} data of {len(body)} bytes is not a whole number of {size}-byte "
            f"words ({len(body) % size} bytes left over: truncated file?)",
            ErrorReason.TRUNCATED)
    return np.frombuffer(body, dtype={4: "<u4", 8: "<u8"}[size])


def _unknown(codes: np.ndarray, allowed: tuple[int, ...], what: str, where: str,
             offset: int) -> None:
    bad = np.flatnonzero(~np.isin(codes, allowed))
    if bad.size:
        i = int(bad[0])
        raise RecordingError(
            f"{where}: {what} word {offset + i} has type {int(codes[i])}, not one of "
            f"{sorted(allowed)} ({bad.size} such words in this chunk: not {what} data?)",
            ErrorReason.MALFORMED)


class _TimeHigh:
    """EVT 2.x TIME_HIGH state: the 28-bit value (time bits 6-33) and its wraps."""

    def __init__(self) -> None:
        self.last = -1  # no TIME_HIGH yet
        self.wraps = 0

    def at(self, is_th: np.ndarray, th_values: np.ndarray) -> np.ndarray:
        """For every word, the full high time (µs, bits 6+ with wraps), -1 before the first
        TIME_HIGH."""
        th = th_values[is_th].astype(np.int64)
        prev = np.concatenate([[self.last], th[:-1]]) if th.size else th
        wrap = (prev >= 0) & (th < prev)
        full = ((self.wraps + np.cumsum(wrap)) << 34) | (th << 6)
        idx = np.cumsum(is_th) - 1
        out = np.where(idx >= 0, full[np.maximum(idx, 0)] if th.size else 0,
                       -1 if self.last < 0 else (self.wraps << 34) | (self.last << 6))
        if th.size:
            self.last = int(th[-1])
            self.wraps += int(wrap.sum())
        return np.asarray(out, np.int64)


def _decode_evt2(body: bytes, where: str, cols: _Columns) -> None:
    words = _words(body, 4, "EVT 2.0", where)
    state = _TimeHigh()
    step = _CHUNK_BYTES // 4
    for start in range(0, words.size, step):
        w = words[start : start + step].astype(np.int64)
        code = w >> 28
        _unknown(code, (0, 1, 8, 10, 14, 15), "EVT 2.0", where, start)
        high = state.at(code == 8, w & 0xFFFFFFF)
        cd = (code <= 1)
        timed = cd & (high >= 0)
        cols.skipped += int(np.count_nonzero(cd & ~timed))
        cols.triggers += int(np.count_nonzero((code == 10) & (high >= 0)))
        ev = w[timed]
        cols.add(high[timed] | ((ev >> 22) & 0x3F), (ev >> 11) & 0x7FF, ev & 0x7FF,
                 (ev >> 28) == 1)


def _decode_evt21(body: bytes, legacy: bool, where: str, cols: _Columns) -> None:
    words = _words(body, 8, "EVT 2.1", where)
    state = _TimeHigh()
    step = _CHUNK_BYTES // 8
    for start in range(0, words.size, step):
        w = words[start : start + step]
        if legacy:  # the upper 32 bits come first in the file
            w = (w << np.uint64(32)) | (w >> np.uint64(32))
        upper = (w >> np.uint64(32)).astype(np.int64)
        mask = (w & np.uint64(0xFFFFFFFF)).astype(np.uint32)
        code = upper >> 28
        _unknown(code, (0, 1, 8, 10, 14, 15), "EVT 2.1", where, start)
        high = state.at(code == 8, upper & 0xFFFFFFF)
        cd = code <= 1
        timed = cd & (high >= 0)
        cols.skipped += int(np.count_nonzero(cd & ~timed))
        cols.triggers += int(np.count_nonzero((code == 10) & (high >= 0)))
        rows = np.flatnonzero(timed)
        bits = np.unpackbits(mask[rows].astype("<u4").view(np.uint8).reshape(-1, 4), axis=1,
                             bitorder="little")
        r, b = np.nonzero(bits)  # row-major: each word's events in ascending x
        u = upper[rows][r]
        cols.add(high[rows][r] | ((u >> 22) & 0x3F), ((u >> 11) & 0x7FF) + b, u & 0x7FF,
                 (u >> 28) == 1)


def _decode_evt3(body: bytes, sensor: SensorSize, where: str, cols: _Columns) -> int:
    if len(body) % 2:
        raise RecordingError(f"{where}: EVT 3.0 data of {len(body)} bytes is not a whole "
                             "number of 16-bit words (truncated file?)", ErrorReason.TRUNCATED)
    decoder = Evt3Decoder()
    payload = np.frombuffer(body, np.uint8)
    dropped = 0
    for start in range(0, payload.size, _CHUNK_BYTES):
        try:
            packet = decoder.decode(payload[start : start + _CHUNK_BYTES], time_base=0,
                                    width=sensor.width, height=sensor.height, stamp_ns=0)
        except PayloadError as exc:
            raise RecordingError(f"{where}: EVT 3.0 data at byte {start} of the data: {exc}",
                                 exc.reason) from None
        cols.add(packet.t_us, packet.x, packet.y, packet.on)
        cols.triggers += int(packet.trigger_t_us.size)
        dropped += packet.dropped
    if not decoder.valid:
        cols.skipped = -1  # no TIME_HIGH + TIME_LOW anywhere
    return dropped


def _decode_dat(body: bytes, version: int, where: str, cols: _Columns) -> str:
    ev_type, ev_size = body[0], body[1]
    if ev_size != 8:
        raise RecordingError(f"{where}: DAT event size {ev_size}, expected 8",
                             ErrorReason.MALFORMED)
    if ev_type not in (0x00, 0x0C):
        what = {0x0E: "external trigger events"}.get(ev_type, f"event type 0x{ev_type:02x}")
        raise RecordingError(f"{where}: a DAT file of {what}; evcal reads CD (0x0C) and 2D "
                             "(0x00) events", ErrorReason.MALFORMED)
    w = _words(body[2:], 8, "DAT", where)
    t32 = (w & np.uint64(0xFFFFFFFF)).astype(np.int64)
    data = (w >> np.uint64(32)).astype(np.int64)
    # a 32-bit time that falls by more than half its range has wrapped (as faery reads it)
    wraps = np.cumsum(np.concatenate([[0], np.diff(t32) < -(1 << 31)]))
    if version >= 2:
        x, y, pol = data & 0x3FFF, (data >> 14) & 0x3FFF, (data >> 28) & 0xF
    else:
        x, y, pol = data & 0x1FF, (data >> 9) & 0xFF, (data >> 17) & 0xF
    cols.add(t32 + (wraps << 32), x, y, pol == 1)
    bad = np.flatnonzero(pol > 1)
    if bad.size:
        i = int(bad[0])
        raise RecordingError(f"{where}: DAT event {i} has polarity {int(pol[i])}, expected 0 "
                             f"or 1 ({bad.size} such events)", ErrorReason.BAD_POLARITY)
    return "cd" if ev_type == 0x0C else "2d"


def _finish(cols: _Columns, sensor: SensorSize, where: str) -> tuple[np.ndarray, int, int]:
    """Events (sorted, in the sensor), reordered count, dropped count."""
    if not cols.t:
        return np.zeros(0, EVENTS_DTYPE), 0, 0
    t = np.concatenate(cols.t)
    x = np.concatenate(cols.x)
    y = np.concatenate(cols.y)
    on = np.concatenate(cols.on)
    keep = (x < sensor.width) & (y < sensor.height) & (x >= 0)
    dropped = int(keep.size - np.count_nonzero(keep))
    events = np.empty(int(np.count_nonzero(keep)), EVENTS_DTYPE)
    events["t_us"] = t[keep]
    events["x"] = x[keep]
    events["y"] = y[keep]
    events["p"] = np.where(on[keep], 1, -1)
    reordered = 0
    tt = events["t_us"]
    if tt.size > 1 and (tt[1:] < tt[:-1]).any():
        reordered = int(np.count_nonzero(tt[1:] < np.maximum.accumulate(tt)[:-1]))
        events = events[np.argsort(tt, kind="stable")]
    return events, reordered, dropped


def read_prophesee(path: str | os.PathLike[str], *, sensor: SensorSize | None = None,
                   strict: bool = False) -> Recording:
    """Read the events of a Prophesee RAW (EVT 2.0 / 2.1 / 3.0) or DAT file.

    Parameters
    ----------
    path : path
        A ``.raw`` or ``.dat`` file (told apart by the header: DAT headers have
        ``% Data file containing ...`` or ``% Version``).
    sensor : SensorSize, optional
        Required when the header declares no size; checked against it otherwise.
    strict : bool
        Refuse a file that ends inside a word (:class:`TruncatedRecordingError`) instead of
        reading its whole words with a :class:`TruncatedRecordingWarning`.

    Returns
    -------
    Recording
        Events only (no frames); times are the camera's µs. ``metadata`` holds ``format``
        (``"evt2"``, ``"evt21"``, ``"evt3"``, ``"dat"``), ``header`` (the ``%`` lines),
        ``trigger_events``, ``reordered_events``, ``dropped_events``, and ``truncated``
        (where the file was cut) for a file that ends inside a word.

    Raises
    ------
    RecordingError
        For a missing file, an unknown encoding, no sensor size, word types the encoding
        does not have (``malformed``); :class:`EmptyRecordingError` (``truncated``) for an
        empty file, one cut inside its header or one without a whole word after it;
        :class:`TruncatedRecordingError` for a file that ends inside a word when ``strict``.
    """
    path = Path(path)
    where = str(path)
    if not path.is_file():
        raise RecordingError(f"{where}: no such file")
    refuse_empty_file(path)
    data = path.read_bytes()
    if not data.startswith(b"%"):
        raise RecordingError(f"{where}: not a Prophesee RAW/DAT file (no '%' header)",
                             ErrorReason.MALFORMED)
    header = read_header(data, where)
    body = data[header.length :]
    kind = is_prophesee(data[: header.length]) or "prophesee_raw"
    cols = _Columns()
    dropped = 0
    meta: dict[str, Any] = {"source": where, "header": header.lines}
    dat = kind == "prophesee_dat" and header.encoding is None
    # the binary part: fixed-size words after the '%' lines (DAT: after two more bytes);
    # a file cut inside a word is read up to its last whole word
    start = header.length + (2 if dat else 0)
    if dat and len(body) == 1:
        raise cut_in_header(where, len(data), "one of the two event type and size bytes "
                            "after the '%' lines")
    if len(data) <= start:
        raise header_only(where, header.length, "event data")
    if not dat and header.encoding not in RAW_ENCODINGS:
        said = header.encoding or "nothing (no '% evt' or '% format' line)"
        raise RecordingError(
            f"{where}: the header gives the encoding as {said}; evcal reads EVT 2.0, "
            "EVT 2.1 and EVT 3.0 RAW files", ErrorReason.MALFORMED)
    found = _sensor(header, sensor, where)
    word, unit = (8, "event") if dat else {"evt2": (4, "EVT 2.0 word"),
                                          "evt21": (8, "EVT 2.1 word"),
                                          "evt3": (2, "EVT 3.0 word")}[str(header.encoding)]
    cut = words_cut(where, len(data), start, len(data) - start, word, unit)
    if cut is not None:
        if cut.whole_end == start:
            raise nothing_whole(cut)
        meta["truncated"] = report_cut(cut, strict=strict)
        body = body[: cut.whole_end - header.length]
    if dat:
        version = header.dat_version if header.dat_version is not None else 2
        meta["format"] = "dat"
        meta["dat_version"] = version
        meta["event_type"] = _decode_dat(body, version, where, cols)
    else:
        meta["format"] = header.encoding
        if header.encoding == "evt2":
            _decode_evt2(body, where, cols)
        elif header.encoding == "evt21":
            meta["evt21_legacy_endianness"] = header.legacy_evt21
            _decode_evt21(body, header.legacy_evt21, where, cols)
        else:
            dropped = _decode_evt3(body, found, where, cols)
    events, reordered, dropped_here = _finish(cols, found, where)
    dropped += dropped_here
    meta.update(trigger_events=cols.triggers, reordered_events=reordered,
                dropped_events=dropped, untimed_events=max(cols.skipped, 0))
    if dropped:
        warnings.warn(f"{where}: {dropped} events outside the {found} sensor were dropped",
                      RuntimeWarning, stacklevel=2)
    try:
        return Recording(sensor=found, events=events, metadata=meta)
    except RecordingError as exc:
        raise RecordingError(f"{where}: {exc}", exc.reason) from None
