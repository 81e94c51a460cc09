"""jAER AEDAT 2.0 and libcaer/cAER AEDAT 3.1 files: polarity events and (3.1) APS frames.

AEDAT 2.0 (jAER; iniVation's "AEDAT file formats" page, and jAER's event extractors)
    ``#`` header lines (``#!AER-DAT2.0`` first; ``#End Of ASCII Header`` ends it where
    present), then 8-byte records: a big-endian uint32 address and a big-endian int32
    timestamp (µs). The address layout depends on the chip named by ``# AEChip:`` (or
    ``# HardwareInterface:``):

    - DAVIS (DAVIS240/346/640/208/128): bit 31 set is an APS or IMU sample (bit 11 then tells
      IMU from APS), bit 10 set a special event, else a polarity event with y in bits 22-30,
      x in bits 12-21 and polarity in bit 11 (1 = ON). jAER flips x on reading
      (``x = sizeX - 1 - raw``) and counts y from the bottom row, so the image coordinates
      are ``x = W - 1 - raw_x``, ``y = H - 1 - raw_y`` (v2e's ``AEDat2Output`` writes that
      inverse);
    - DVS128 (``DVS128``/``Tmpdiff128``): x bits 1-7, y bits 8-14, bit 0 = 0 is ON, bit 15
      a special (sync) event; image ``x = 127 - raw_x``, ``y = 127 - raw_y``.

    APS samples (reset and signal reads) are counted, not turned into frames
    (``metadata["aps_samples"]``); IMU samples and special events are counted too. The int32
    time wraps: a step back of more than 2^31 µs is taken as one wrap (+2^32 µs).
    Without a known chip the sensor must be given (``sensor=``); a 128x128 sensor is then
    read with the DVS128 layout, any other with the DAVIS layout.

AEDAT 3.1 (libcaer ``events/common.h``, ``polarity.h``, ``frame.h``)
    ``#`` header lines up to ``#!END-HEADER``, then packets: a 28-byte little-endian header
    (int16 eventType, int16 eventSource, int32 eventSize, eventTSOffset, eventTSOverflow,
    eventCapacity, eventNumber, eventValid) and ``eventCapacity * eventSize`` bytes of events.
    Polarity events (type 1, 8 bytes): uint32 data (bit 0 valid, bit 1 polarity = ON, y bits
    2-16, x bits 17-31, image coordinates) and int32 timestamp; the time is
    ``eventTSOverflow << 31 | timestamp``. Frame events (type 2): uint32 info (bit 0 valid,
    bits 1-3 colour channels), int32 start/end of frame readout and of exposure, lengthX,
    lengthY, positionX, positionY, then uint16 pixels row by row. A frame is taken at the
    middle of its exposure and converted to float32 on the 8-bit scale (value / 257);
    colour frames to luma (BT.601), partial (ROI) frames are skipped and counted. Other
    packet types are skipped and counted (``metadata["skipped_packets"]``). Only the first
    polarity source is read. The sensor size comes from the ``#Source`` chip name or the
    ``dvsSizeX``/``dvsSizeY`` header attributes, else the frames, else ``sensor=``.

Invalid events (3.1, valid bit clear) are skipped. Events are sorted by time (stable);
``metadata["reordered_events"]`` counts those that were out of order.
"""

from __future__ import annotations

import os
import re
import struct
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import ErrorReason
from ..events import SensorSize
from ..recording import Frames, Recording, RecordingError
from ._partial import (
    Cut,
    cut_in_header,
    header_only,
    nothing_whole,
    refuse_empty_file,
    report_cut,
    words_cut,
)
from ._util import check_sensor_arg, events_sorted

AEDAT2_MAGIC = b"#!AER-DAT2.0"
AEDAT31_MAGIC = b"#!AER-DAT3.1"

# chip names (jAER AEChip classes, libcaer/cAER source names) -> (sensor, layout)
_CHIPS: tuple[tuple[str, SensorSize, str], ...] = (
    ("dvs128", SensorSize(128, 128), "dvs128"),
    ("tmpdiff128", SensorSize(128, 128), "dvs128"),
    ("davis240", SensorSize(180, 240), "davis"),
    ("davis346", SensorSize(260, 346), "davis"),
    ("davi346", SensorSize(260, 346), "davis"),  # as aedat4to2 names it
    ("davis640", SensorSize(480, 640), "davis"),
    ("davis208", SensorSize(192, 208), "davis"),
    ("davis128", SensorSize(128, 128), "davis"),
)
_LUMA = np.array([0.299, 0.587, 0.114])
_PACKET_HEADER = struct.Struct("<hhiiiiii")


def _split_header(data: bytes, end_line: bytes | None, where: str) -> tuple[list[str], int]:
    """The ``#`` lines and where the binary data starts."""
    pos = 0
    lines: list[str] = []
    while pos < len(data) and data[pos : pos + 1] == b"#":
        nl = data.find(b"\n", pos)
        if nl < 0:
            raise cut_in_header(where, len(data), f"line {len(lines) + 1} of the '#' header "
                                "has no end")
        line = data[pos:nl].rstrip(b"\r")
        lines.append(line.decode("latin-1"))
        pos = nl + 1
        if end_line is not None and line.strip().lower() == end_line.lower():
            return lines, pos
    if end_line is not None and end_line == b"#!END-HEADER":
        if pos == len(data):
            raise cut_in_header(where, len(data), "no '#!END-HEADER' line before the end")
        raise RecordingError(f"{where}: no '#!END-HEADER' line before the binary data (not "
                             "AEDAT 3.1?)", ErrorReason.MALFORMED)
    return lines, pos


def _chip(lines: list[str]) -> tuple[str | None, SensorSize | None, str | None]:
    """The chip named in the header, its sensor and address layout."""
    for line in lines:
        m = re.match(r"#\s*(?:-?Source\s+\d+|AEChip|HardwareInterface)\s*:\s*(.+)", line)
        if not m:
            continue
        name = m.group(1).strip()
        low = name.lower()
        for key, sensor, layout in _CHIPS:
            if key in low:
                return name, sensor, layout
    return None, None, None


def _check_inside(where: str, x: np.ndarray, y: np.ndarray, sensor: SensorSize,
                  layout: str) -> None:
    bad = np.flatnonzero((x < 0) | (y < 0) | (x >= sensor.width) | (y >= sensor.height))
    if bad.size:
        i = int(bad[0])
        raise RecordingError(
            f"{where}: polarity event {i} has raw address outside the {sensor} sensor "
            f"({bad.size} such events; wrong sensor= or not the {layout} address layout?)",
            ErrorReason.OUT_OF_SENSOR)


def _read_aedat2(data: bytes, where: str, sensor: SensorSize | None, strict: bool
                 ) -> Recording:
    lines, start = _split_header(data, b"#End Of ASCII Header", where)
    body = data[start:]
    if not body:
        raise header_only(where, start, "event records")
    # a file cut inside a record is read up to its last whole record
    cut = words_cut(where, len(data), start, len(body), 8, "record")
    if cut is not None and cut.whole_end == start:
        raise nothing_whole(cut)
    chip, chip_sensor, layout = _chip(lines)
    if chip_sensor is not None:
        found = check_sensor_arg(chip_sensor, sensor, where)
    elif sensor is not None:
        found = sensor
        layout = "dvs128" if sensor.shape == (128, 128) else "davis"
    else:
        raise RecordingError(
            f"{where}: the AEDAT 2.0 header names no chip evcal knows (no '# AEChip:' line "
            "with DVS128, DAVIS240, DAVIS346, ...); pass sensor= (e.g. --sensor-size 240x180) "
            "to read it with the DAVIS address layout (128x128: DVS128 layout)",
            ErrorReason.MALFORMED)
    truncated = None
    if cut is not None:
        truncated = report_cut(cut, strict=strict)
        body = body[: cut.whole_end - start]
    rec = np.frombuffer(body, dtype=[("a", ">u4"), ("t", ">u4")])
    addr = rec["a"].astype(np.int64)
    t32 = rec["t"].astype(np.int64)
    wraps = np.cumsum(np.concatenate([[0], np.diff(t32) < -(1 << 31)])) if t32.size else t32
    t = t32 + (wraps << 32)
    meta: dict[str, Any] = {"format": "aedat2", "chip": chip, "address_layout": layout,
                            "time_wraps": int(wraps[-1]) if wraps.size else 0}
    if layout == "dvs128":
        special = (addr >> 15) & 1 == 1
        pol = ~special
        x = (found.width - 1) - ((addr >> 1) & 0x7F)
        y = (found.height - 1) - ((addr >> 8) & 0x7F)
        on = (addr & 1) == 0
        meta.update(special_events=int(np.count_nonzero(special)), aps_samples=0,
                    imu_samples=0)
    else:
        sample = (addr >> 31) & 1 == 1
        imu = sample & ((addr >> 11) & 1 == 1)
        special = ~sample & ((addr >> 10) & 1 == 1)
        pol = ~sample & ~special
        x = (found.width - 1) - ((addr >> 12) & 0x3FF)
        y = (found.height - 1) - ((addr >> 22) & 0x1FF)
        on = (addr >> 11) & 1 == 1
        meta.update(special_events=int(np.count_nonzero(special)),
                    aps_samples=int(np.count_nonzero(sample & ~imu)),
                    imu_samples=int(np.count_nonzero(imu)))
    x, y, on, t = x[pol], y[pol], on[pol], t[pol]
    _check_inside(where, x, y, found, str(layout))
    events, reordered = events_sorted(t, x, y, on)
    meta.update(reordered_events=reordered, header=lines)
    if truncated is not None:
        meta["truncated"] = truncated
    return Recording(sensor=found, events=events, metadata=meta)


def _gray16(pixels: np.ndarray, channels: int) -> np.ndarray:
    """float32 ``[y, x]`` on the 8-bit scale from uint16 pixels (``(H, W, channels)``)."""
    scaled = pixels.astype(np.float64) / 257.0
    if channels >= 3:
        gray = scaled[:, :, :3] @ _LUMA
    else:
        gray = scaled[:, :, 0]
    return np.asarray(gray, np.float32)


def _read_aedat31(data: bytes, where: str, sensor: SensorSize | None, strict: bool
                  ) -> Recording:
    lines, pos = _split_header(data, b"#!END-HEADER", where)
    chip, chip_sensor, _ = _chip(lines)
    text = "\n".join(lines)
    sx = re.search(r"dvsSizeX\D{0,40}?(\d+)", text)
    sy = re.search(r"dvsSizeY\D{0,40}?(\d+)", text)
    if chip_sensor is None and sx and sy:
        chip_sensor = SensorSize(height=int(sy.group(1)), width=int(sx.group(1)))
    pol_chunks: list[tuple[np.ndarray, int]] = []
    frames: list[tuple[int, int, np.ndarray]] = []
    skipped: dict[str, int] = {}
    skipped_frames = 0
    source: int | None = None
    n = len(data)
    if pos == n:
        raise header_only(where, pos, "packets")
    k = 0
    cut: Cut | None = None  # a file cut inside a packet is read up to its last whole packet
    while pos < n:
        if n - pos < _PACKET_HEADER.size:
            cut = Cut(where, n, pos, f"{k:,} whole packets", f"the 28-byte header of packet "
                      f"{k} ({n - pos} bytes of it present)")
            break
        (ev_type, ev_source, ev_size, ts_offset, ts_overflow, capacity, number,
         _valid) = _PACKET_HEADER.unpack_from(data, pos)
        if ev_size <= 0 or capacity < 0 or not 0 <= number <= capacity or ev_type < 0:
            raise RecordingError(
                f"{where}: packet {k} at byte {pos} has an impossible header (type {ev_type}, "
                f"event size {ev_size}, capacity {capacity}, number {number}): corrupt file?",
                ErrorReason.MALFORMED)
        body_start = pos + _PACKET_HEADER.size
        end = body_start + capacity * ev_size
        if end > n:
            cut = Cut(where, n, pos, f"{k:,} whole packets",
                      f"packet {k} (type {ev_type}; {end - pos:,} bytes with its header, "
                      f"{n - pos:,} present)")
            break
        body = data[body_start : body_start + number * ev_size]
        if ev_type == 1 and (source is None or ev_source == source):
            if ev_size != 8 or ts_offset != 4:
                raise RecordingError(f"{where}: polarity packet {k} has event size {ev_size} "
                                     f"and timestamp offset {ts_offset}, expected 8 and 4",
                                     ErrorReason.MALFORMED)
            source = ev_source
            pol_chunks.append((np.frombuffer(body, dtype=[("d", "<u4"), ("t", "<i4")]),
                               ts_overflow))
        elif ev_type == 2:
            for i in range(number):  # frames: a loop over frames, never over pixels
                off = i * ev_size
                info, _sf, _ef, s_exp, e_exp, lx, ly, px, py = struct.unpack_from(
                    "<Iiiiiiiii", body, off)
                channels = (info >> 1) & 0x7
                if not info & 1:
                    continue
                if 36 + lx * ly * max(channels, 1) * 2 > ev_size or lx <= 0 or ly <= 0:
                    raise RecordingError(f"{where}: frame event {i} of packet {k} claims "
                                         f"{lx}x{ly}x{channels} pixels in {ev_size} bytes",
                                         ErrorReason.MALFORMED)
                if px or py:
                    skipped_frames += 1
                    continue
                pix = np.frombuffer(body, "<u2", lx * ly * max(channels, 1), off + 36)
                base = ts_overflow << 31
                frames.append((base + (s_exp + e_exp) // 2, e_exp - s_exp,
                               _gray16(pix.reshape(ly, lx, max(channels, 1)), channels)))
        else:
            name = {0: "special", 1: "polarity (other source)", 3: "IMU6", 4: "IMU9",
                    5: "sample"}.get(ev_type, f"type {ev_type}")
            skipped[name] = skipped.get(name, 0) + 1
        pos = end
        k += 1
    if chip_sensor is not None:
        found = check_sensor_arg(chip_sensor, sensor, where)
    elif frames:
        h, w = frames[0][2].shape
        found = check_sensor_arg(SensorSize(height=h, width=w), sensor, where)
    elif sensor is not None:
        found = sensor
    else:
        raise RecordingError(f"{where}: the AEDAT 3.1 header names no chip evcal knows and "
                             "there are no frames; pass sensor= (e.g. --sensor-size 346x260)",
                             ErrorReason.MALFORMED)
    truncated = None
    if cut is not None:
        if k == 0:
            raise nothing_whole(cut)
        truncated = report_cut(cut, strict=strict)
    if pol_chunks:
        d = np.concatenate([c["d"] for c, _ in pol_chunks]).astype(np.int64)
        ts = np.concatenate([c["t"].astype(np.int64) + (ov << 31) for c, ov in pol_chunks])
    else:
        d = ts = np.zeros(0, np.int64)
    valid = (d & 1) == 1
    d, ts = d[valid], ts[valid]
    x, y = (d >> 17) & 0x7FFF, (d >> 2) & 0x7FFF
    _check_inside(where, x, y, found, "libcaer polarity")
    events, reordered = events_sorted(ts, x, y, ((d >> 1) & 1) == 1)
    frame_obj = None
    if frames:
        frames.sort(key=lambda f: f[0])
        shapes = {f[2].shape for f in frames}
        if shapes != {found.shape}:
            raise RecordingError(f"{where}: frames of shapes {sorted(shapes)}, the sensor is "
                                 f"{found}", ErrorReason.MALFORMED)
        frame_obj = Frames(t_us=np.array([f[0] for f in frames], np.int64),
                           images=np.stack([f[2] for f in frames]),
                           exposure_us=np.array([f[1] for f in frames], np.int64))
    meta = {"format": "aedat3.1", "chip": chip, "packets": k, "skipped_packets": skipped,
            "skipped_frames": skipped_frames, "invalid_events": int(np.count_nonzero(~valid)),
            "polarity_source": source, "reordered_events": reordered, "header": lines}
    if truncated is not None:
        meta["truncated"] = truncated
    return Recording(sensor=found, events=events,
                     frames=frame_obj if frame_obj is not None else Frames.empty(*found.shape),
                     metadata=meta)


def read_aedat2(path: str | os.PathLike[str], *, sensor: SensorSize | None = None,
                strict: bool = False) -> Recording:
    """Read a jAER AEDAT 2.0 or an AEDAT 3.1 file (see the module docstring).

    A file that ends inside a record (2.0) or packet (3.1) is read up to its last whole one,
    with a :class:`TruncatedRecordingWarning` and ``metadata["truncated"]``; ``strict=True``
    refuses it instead (:class:`TruncatedRecordingError`).

    Raises
    ------
    RecordingError
        For a missing file, another AEDAT version, an impossible packet header, no known
        sensor size, or events outside the sensor; :class:`EmptyRecordingError`
        (``truncated``) for an empty file, one cut inside its header, a header without
        records or packets, or no whole one.
    """
    path = Path(path)
    where = str(path)
    if not path.is_file():
        raise RecordingError(f"{where}: no such file")
    refuse_empty_file(path)
    data = path.read_bytes()
    try:
        if data.startswith(AEDAT2_MAGIC):
            rec = _read_aedat2(data, where, sensor, strict)
        elif data.startswith(AEDAT31_MAGIC):
            rec = _read_aedat31(data, where, sensor, strict)
        else:
            first = data[:40].split(b"\n", 1)[0].decode("latin-1", "replace").strip()
            raise RecordingError(f"{where}: starts with {first!r}; evcal reads AEDAT 2.0 "
                                 "('#!AER-DAT2.0'), 3.1 ('#!AER-DAT3.1') and 4.0 files",
                                 ErrorReason.VERSION)
    except RecordingError as exc:
        if str(exc).startswith(where):
            raise
        raise RecordingError(f"{where}: {exc}", exc.reason) from None
    rec.metadata["source"] = where
    return rec
