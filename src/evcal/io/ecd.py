"""Event Camera Dataset (ECD) folders: ``events.txt``, ``images.txt`` + PNG frames, ``calib.txt``.

Layout (Mueggler et al., IJRR 2017)::

    events.txt   one event a line: ``t[s] x y p`` with p in {0, 1}
    images.txt   one frame a line: ``t[s] relative/path.png`` (optional)
    images/*.png 8-bit intensity frames (optional)
    calib.txt    ``fx fy cx cy k1 k2 p1 p2 k3`` pinhole intrinsics (optional; no image size)

The format does not store the sensor size. It comes from, in this order: the ``sensor``
argument, the frames' shape, or the principal point in ``calib.txt`` matched to a known sensor
(:func:`sensor_from_calib`). The largest coordinate seen is never used: a slice of a recording
rarely touches the last row and column.
"""

from __future__ import annotations

import io
import math
import os
import warnings
from collections.abc import Iterator, Sequence
from pathlib import Path

import numpy as np
from PIL import Image

from ..events import EVENTS_DTYPE, SensorSize
from ..recording import Frames, Recording, RecordingError, concat_events
from ._partial import Cut, nothing_whole, report_cut

KNOWN_SENSORS: tuple[SensorSize, ...] = (
    SensorSize(height=180, width=240),  # DAVIS240C
    SensorSize(height=260, width=346),  # DAVIS346
    SensorSize(height=480, width=640),  # VGA (DVXplorer, Prophesee Gen3.1)
    SensorSize(height=720, width=1280),  # Prophesee IMX636 / Gen4
)
# The principal point of a calibrated lens lies within this fraction of the image size from
# the image centre (per axis). The DAVIS240C of the ECD has (cx, cy) = (132.2, 110.7), i.e.
# 5 % and 11.5 % off the centre (120, 90), so 10 % would be too tight.
CALIB_CENTRE_TOLERANCE = 0.15
EVENTS_COLUMNS = "t[s] x y p"
_BLOCK_BYTES = 1 << 24  # about 700k ECD lines per parse


# ----------------------------------------------------------------------------- calibration


def read_calib(path: str | os.PathLike[str]) -> list[float]:
    """Read ``calib.txt``: ``fx fy cx cy`` and distortion coefficients (pixels).

    Raises
    ------
    RecordingError
        If the file holds fewer than four numbers, a non-number, or a focal length <= 0.
    """
    path = Path(path)
    tokens = path.read_text(encoding="utf-8", errors="replace").split()
    try:
        values = [float(tok) for tok in tokens]
    except ValueError:
        bad = next(t for t in tokens if not _is_float(t))
        raise RecordingError(f"{path}: {bad!r} is not a number (expected fx fy cx cy k1 ...)") \
            from None
    if len(values) < 4:
        raise RecordingError(f"{path}: {len(values)} numbers, expected at least 4 "
                             "(fx fy cx cy [k1 k2 p1 p2 k3])")
    if not all(math.isfinite(v) for v in values) or values[0] <= 0 or values[1] <= 0:
        raise RecordingError(f"{path}: fx={values[0]}, fy={values[1]} must be finite and > 0")
    return values


def sensor_from_calib(calib: Sequence[float]) -> SensorSize | None:
    """Guess the sensor from the principal point ``(cx, cy)`` of pinhole intrinsics.

    A known sensor (:data:`KNOWN_SENSORS`) fits when ``cx`` and ``cy`` lie within
    :data:`CALIB_CENTRE_TOLERANCE` of its width and height from its centre; among those that
    fit, the one whose centre is nearest (in pixels) wins. ``None`` when none fits.

    Examples
    --------
    >>> str(sensor_from_calib([199.1, 198.8, 132.2, 110.7]))
    '240x180'
    >>> sensor_from_calib([500.0, 500.0, 20.0, 20.0]) is None
    True
    """
    cx, cy = float(calib[2]), float(calib[3])
    best: tuple[float, SensorSize] | None = None
    for s in KNOWN_SENSORS:
        dx, dy = cx - s.width / 2, cy - s.height / 2
        if abs(dx) <= CALIB_CENTRE_TOLERANCE * s.width and \
                abs(dy) <= CALIB_CENTRE_TOLERANCE * s.height:
            d = math.hypot(dx, dy)
            if best is None or d < best[0]:
                best = (d, s)
    return None if best is None else best[1]


def _is_float(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


# ----------------------------------------------------------------------------- frames


def _read_images_txt(path: Path) -> list[tuple[int, float, str]]:
    """``(line number, t[s], relative path)`` of every frame listed in ``images.txt``."""
    entries = []
    text = path.read_text(encoding="utf-8", errors="replace")
    for k, line in enumerate(text.splitlines(), start=1):  # one line a frame: few
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        parts = line.split(None, 1)
        if len(parts) != 2:
            raise RecordingError(f"{path} line {k}: expected 't[s] relative/path.png', got "
                                 f"{line[:80]!r}")
        try:
            t_s = float(parts[0])
        except ValueError:
            raise RecordingError(f"{path} line {k}: time {parts[0]!r} is not a number") from None
        if not math.isfinite(t_s):
            raise RecordingError(f"{path} line {k}: time {parts[0]!r} is not finite")
        entries.append((k, t_s, parts[1].strip()))
    return entries


def _load_gray(file: Path) -> np.ndarray:
    """A PNG as a uint8 ``[y, x]`` image (colour converted to luma, 16 bit scaled by 1/257)."""
    with Image.open(file) as im:
        if im.mode == "L":
            return np.asarray(im, dtype=np.uint8)
        if im.mode in ("I;16", "I;16B", "I;16L", "I"):
            a = np.asarray(im).astype(np.float64) / 257.0
            return np.clip(np.rint(a), 0, 255).astype(np.uint8)
        return np.asarray(im.convert("L"), dtype=np.uint8)


def _read_frames(folder: Path, sensor: SensorSize | None
                 ) -> tuple[Frames, SensorSize | None] | None:
    images_txt = folder / "images.txt"
    if not images_txt.is_file():
        return None
    entries = _read_images_txt(images_txt)
    files = [folder / rel for _, _, rel in entries]
    missing = [i for i, f in enumerate(files) if not f.is_file()]
    if missing:
        k, _, rel = entries[missing[0]]
        raise RecordingError(
            f"{images_txt} line {k}: frame file {rel!r} is missing (looked for "
            f"{files[missing[0]]}); {len(missing)} of {len(files)} frame files are missing"
        )
    if not entries:
        return None
    images = []
    ref = "the sensor is"  # what a frame's size is compared with, for the error message
    for i, ((k, _, rel), file) in enumerate(zip(entries, files, strict=False)):
        try:
            img = _load_gray(file)
        except (OSError, ValueError) as exc:
            raise RecordingError(f"frame {i} ({rel}, {images_txt.name} line {k}) cannot be "
                                 f"read as an image: {exc}") from None
        if sensor is None:
            sensor = SensorSize(height=img.shape[0], width=img.shape[1])
            ref = f"frame 0 ({rel}) is"
        elif img.shape != sensor.shape:
            h, w = img.shape
            raise RecordingError(
                f"frame {i} ({rel}, {images_txt.name} line {k}) has shape ({h}, {w}) "
                f"(a {w}x{h} image), {ref} {sensor}"
            )
        images.append(img)
    t_us = np.rint(np.array([t for _, t, _ in entries]) * 1e6).astype(np.int64)
    try:
        frames = Frames(t_us=t_us, images=np.stack(images),
                        exposure_us=np.zeros(len(images), np.int64))
    except RecordingError as exc:
        raise RecordingError(f"{images_txt}: {exc}") from None
    return frames, sensor


# ----------------------------------------------------------------------------- events


def _iter_blocks(path: Path, block_bytes: int) -> Iterator[tuple[bytes, int]]:
    """Whole-line blocks of a text file with the 1-based number of their first line."""
    line_no = 1
    rest = b""
    with open(path, "rb") as f:
        while True:
            data = f.read(block_bytes)
            if not data:
                if rest:
                    yield rest, line_no
                return
            data = rest + data
            cut = data.rfind(b"\n")
            if cut < 0:
                rest = data
                continue
            block, rest = data[: cut + 1], data[cut + 1 :]
            yield block, line_no
            line_no += block.count(b"\n")


def _data_lines(block: bytes, first_line: int) -> Iterator[tuple[int, bytes, bool]]:
    """``(line number, content, is last and unterminated)`` of non-blank lines (error path)."""
    lines = block.split(b"\n")
    for k, raw in enumerate(lines):
        content = raw.split(b"#", 1)[0].strip()
        if content:
            yield first_line + k, content, k == len(lines) - 1


def _diagnose(block: bytes, first_line: int, path: Path, cause: str) -> RecordingError:
    """Find the first malformed line of a block that did not parse (error path only)."""
    for n, content, unterminated in _data_lines(block, first_line):
        tokens = content.split()
        if len(tokens) != 4:
            hint = "; the last line is incomplete, the file looks truncated" \
                if unterminated else ""
            return RecordingError(
                f"{path} line {n}: {len(tokens)} columns, expected 4 ({EVENTS_COLUMNS}): "
                f"{content[:80].decode(errors='replace')!r}{hint}"
            )
        for name, tok in zip(("t", "x", "y", "p"), tokens, strict=False):
            if not _is_float(tok.decode(errors="replace")):
                return RecordingError(f"{path} line {n}: column {name} is not a number: "
                                      f"{tok[:40].decode(errors='replace')!r}")
    return RecordingError(f"{path}: lines {first_line}.. cannot be parsed: {cause}")


def _row_line(block: bytes, first_line: int, row: int) -> int:
    """Line number of data row ``row`` of a block (error path only)."""
    for i, (n, _, _) in enumerate(_data_lines(block, first_line)):
        if i == row:
            return n
    return first_line + row


def _parse_block(
    block: bytes,
    first_line: int,
    path: Path,
    sensor: SensorSize,
    sensor_source: str,
    prev_t_us: int | None,
) -> np.ndarray:
    """Events of one whole-line block, validated (sorted, in range, p in {0, 1})."""
    if not block.strip():
        return np.zeros(0, EVENTS_DTYPE)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # loadtxt warns on a block of comments only
            arr = np.loadtxt(io.BytesIO(block), dtype=np.float64, ndmin=2, comments="#")
    except ValueError as exc:
        raise _diagnose(block, first_line, path, str(exc)) from None
    if arr.size == 0:
        return np.zeros(0, EVENTS_DTYPE)
    if arr.shape[1] != 4:
        raise _diagnose(block, first_line, path, f"{arr.shape[1]} columns")

    def fail(row: int, text: str) -> RecordingError:
        return RecordingError(f"{path} line {_row_line(block, first_line, row)}: {text}")

    bad = np.flatnonzero(~np.isfinite(arr).all(axis=1))
    if bad.size:
        raise fail(int(bad[0]), f"non-finite value in {arr[bad[0]].tolist()}")
    t_s, x, y, p = arr.T
    for name, col in (("x", x), ("y", y)):
        bad = np.flatnonzero((col != np.floor(col)) | (col < 0) | (col > 65535))
        if bad.size:
            raise fail(int(bad[0]), f"{name}={col[bad[0]]:g} is not a pixel coordinate "
                                    "(an integer in 0..65535)")
    bad = np.flatnonzero((p != 0) & (p != 1))
    if bad.size:
        raise fail(int(bad[0]), f"polarity p={p[bad[0]]:g}, expected 0 or 1")
    h, w = sensor.shape
    bad = np.flatnonzero((x >= w) | (y >= h))
    if bad.size:
        i = int(bad[0])
        raise fail(i, f"event at (x={int(x[i])}, y={int(y[i])}) is outside the {sensor} sensor "
                      f"(size from {sensor_source}; {bad.size} such events in this block); "
                      "give the right size with sensor=SensorSize(...) / --sensor-size WxH")
    # float64 holds ECD times (< 1e6 s with 9 decimals) to well below 1 µs.
    t_us = np.rint(t_s * 1e6).astype(np.int64)
    back = np.flatnonzero(t_us[1:] < t_us[:-1])
    if back.size:
        i = int(back[0]) + 1
        raise fail(i, f"timestamps are not sorted: t={t_s[i]:.9f} s comes after "
                      f"t={t_s[i - 1]:.9f} s")
    if prev_t_us is not None and t_us[0] < prev_t_us:
        raise fail(0, f"timestamps are not sorted: t={t_s[0]:.9f} s comes after "
                      f"t={prev_t_us * 1e-6:.9f} s on the previous line")
    ev = np.empty(t_us.shape[0], EVENTS_DTYPE)
    ev["t_us"] = t_us
    ev["x"] = x
    ev["y"] = y
    ev["p"] = np.where(p > 0, 1, -1)
    return ev


def read_events_txt(
    path: str | os.PathLike[str],
    sensor: SensorSize,
    *,
    sensor_source: str = "the sensor argument",
    block_bytes: int = _BLOCK_BYTES,
    strict: bool = False,
) -> np.ndarray:
    """Read an ECD ``events.txt`` (``t[s] x y p`` a line, p in {0, 1}) into EVENTS_DTYPE.

    The file is parsed in blocks of about ``block_bytes`` (C parser, no Python loop over lines)
    and ``t_us = rint(t * 1e6)``. Blank lines and ``#`` comments are skipped. A file cut
    inside its last line (no end of line, not four columns) is read up to that line, with a
    :class:`~evcal.io.TruncatedRecordingWarning` (``strict``: refused).

    Raises
    ------
    RecordingError
        Naming the line of the first malformed, out-of-order or out-of-sensor event.
    """
    events, cut = _events_txt(Path(path), sensor, sensor_source, block_bytes)
    if cut is not None:
        if not events.size:
            raise nothing_whole(cut)
        report_cut(cut, strict=strict)
    return events


def _events_txt(path: Path, sensor: SensorSize, sensor_source: str, block_bytes: int
                ) -> tuple[np.ndarray, Cut | None]:
    """The events of ``events.txt`` and, for a file cut inside its last line, the cut."""
    chunks: list[np.ndarray] = []
    prev: int | None = None
    whole_end = 0  # bytes of the whole lines so far
    lines = 0
    for block, first_line in _iter_blocks(path, block_bytes):
        try:
            ev = _parse_block(block, first_line, path, sensor, sensor_source, prev)
        except RecordingError:
            cut = _cut_line(path, block, first_line, whole_end, lines, chunks)
            if cut is None:
                raise
            return concat_events(chunks), cut
        whole_end += len(block)
        lines += block.count(b"\n")
        if ev.size:
            chunks.append(ev)
            prev = int(ev["t_us"][-1])
    return concat_events(chunks), None


def _cut_line(path: Path, block: bytes, first_line: int, whole_end: int, lines: int,
              chunks: list[np.ndarray]) -> Cut | None:
    """The cut, when ``block`` (which did not parse) is the file's last line, unterminated
    and short of its four columns (a copy stopped inside it); None for a malformed line."""
    if block.endswith(b"\n") or len(block.split(b"#", 1)[0].split()) >= 4:
        return None
    n = sum(c.size for c in chunks)
    text = block[:40].decode(errors="replace")
    return Cut(str(path), whole_end + len(block), whole_end,
               f"{lines:,} whole lines ({n:,} events)",
               f"line {first_line} ({text!r}: {len(block)} bytes, no end of line, fewer "
               f"than the 4 columns {EVENTS_COLUMNS})")


# ----------------------------------------------------------------------------- reader


def read_ecd(folder: str | os.PathLike[str], *, sensor: SensorSize | None = None,
             strict: bool = False) -> Recording:
    """Read an Event Camera Dataset folder.

    Parameters
    ----------
    folder : path
        Holds ``events.txt`` and/or ``images.txt`` (with its PNG frames), optionally
        ``calib.txt``.
    sensor : SensorSize, optional
        The sensor size; by default taken from the frames or guessed from ``calib.txt``.
    strict : bool
        Refuse an ``events.txt`` cut inside its last line
        (:class:`~evcal.io.TruncatedRecordingError`) instead of reading the lines before it
        with a :class:`~evcal.io.TruncatedRecordingWarning` (``metadata["truncated"]``).

    Returns
    -------
    Recording
        ``metadata`` holds ``format`` ("ecd"), ``source``, ``sensor_source`` and, with a
        ``calib.txt``, ``calib`` (``[fx, fy, cx, cy, k1, ...]``). Frames have
        ``exposure_us = 0`` (the format does not record it).

    Raises
    ------
    RecordingError
        For a missing or malformed file, a frame of the wrong size, events out of order or
        outside the sensor, or when the sensor size cannot be determined.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise RecordingError(f"{folder}: not a directory (expected an Event Camera Dataset "
                             "folder with events.txt)")
    events_txt, images_txt, calib_txt = (folder / n for n in
                                         ("events.txt", "images.txt", "calib.txt"))
    if not events_txt.is_file() and not images_txt.is_file():
        raise RecordingError(f"{folder}: no events.txt or images.txt, not an Event Camera "
                             "Dataset folder")
    metadata: dict[str, object] = {"format": "ecd", "source": str(folder)}
    calib = read_calib(calib_txt) if calib_txt.is_file() else None
    if calib is not None:
        metadata["calib"] = calib
    source = "the sensor argument"
    got = _read_frames(folder, sensor)
    frames = None
    if got is not None:
        frames, found = got
        if sensor is None:
            sensor, source = found, "the frames"
    if sensor is None and calib is not None:
        sensor = sensor_from_calib(calib)
        source = f"the principal point of {calib_txt.name}"
    if sensor is None:
        why = ("calib.txt's principal point matches none of "
               + ", ".join(map(str, KNOWN_SENSORS))) if calib is not None else "no calib.txt"
        raise RecordingError(
            f"{folder}: cannot tell the sensor size (no frames; {why}); give it with "
            "sensor=SensorSize(height=..., width=...) or on the command line --sensor-size WxH"
        )
    metadata["sensor_source"] = source
    events, cut = ((np.zeros(0, EVENTS_DTYPE), None) if not events_txt.is_file() else
                   _events_txt(events_txt, sensor, source, _BLOCK_BYTES))
    if cut is not None:
        if not events.size and frames is None:
            raise nothing_whole(cut)
        metadata["truncated"] = report_cut(cut, strict=strict)
    return Recording(sensor=sensor, events=events,
                         frames=frames if frames is not None else Frames.empty(0, 0),
                         metadata=metadata)


# ----------------------------------------------------------------------------- writer


def _digits(values: np.ndarray, *, width: int | None = None, strip: bool = True) -> np.ndarray:
    """ASCII decimal digits of non-negative integers as an ``(n, width)`` uint8 matrix.

    With ``strip`` the leading zeros are set to 0 (a byte the caller drops).
    """
    v = values.astype(np.uint64)
    if width is None:
        width = len(str(int(v.max()))) if v.size else 1
    pow10 = np.uint64(10) ** np.arange(width - 1, -1, -1, dtype=np.uint64)
    d = (v[:, None] // pow10) % np.uint64(10)
    chars = (d + np.uint64(48)).astype(np.uint8)
    if strip:
        lead = np.cumsum(d != 0, axis=1) == 0
        lead[:, -1] = False  # 0 is written "0"
        chars[lead] = 0
    result: np.ndarray = chars
    return result


def _col(n: int, text: str) -> np.ndarray:
    return np.broadcast_to(np.frombuffer(text.encode(), np.uint8), (n, len(text)))


def format_events_txt(events: np.ndarray) -> bytes:
    """ECD text of events: ``t[s] x y p`` with 9 decimals and p in {0, 1} (vectorised).

    Examples
    --------
    >>> from evcal.events import make_events
    >>> format_events_txt(make_events([13582596, 5], [190, 0], [82, 7], [1, -1]))
    b'13.582596000 190 82 1\\n0.000005000 0 7 0\\n'
    """
    n = events.shape[0]
    if n == 0:
        return b""
    t = events["t_us"].astype(np.int64)
    a = np.abs(t)
    sign = np.where(t < 0, ord("-"), 0).astype(np.uint8)[:, None]
    parts = [
        sign, _digits(a // 1_000_000), _col(n, "."), _digits(a % 1_000_000, width=6, strip=False),
        _col(n, "000 "), _digits(events["x"]), _col(n, " "), _digits(events["y"]), _col(n, " "),
        np.where(events["p"] > 0, ord("1"), ord("0")).astype(np.uint8)[:, None], _col(n, "\n"),
    ]
    mat = np.concatenate(parts, axis=1)
    result: bytes = mat[mat != 0].tobytes()
    return result


def _seconds_text(t_us: int) -> str:
    sign = "-" if t_us < 0 else ""
    s, us = divmod(abs(int(t_us)), 1_000_000)
    return f"{sign}{s}.{us:06d}000"


def _to_uint8(image: np.ndarray) -> np.ndarray:
    if image.dtype == np.uint8:
        return image
    # Float frames use 8-bit full scale 255 (see Frames); the PNG keeps 8 bits.
    return np.clip(np.rint(image.astype(np.float64)), 0, 255).astype(np.uint8)


def write_ecd(
    recording: Recording,
    folder: str | os.PathLike[str],
    *,
    chunk_events: int = 500_000,
) -> Path:
    """Write a recording as an Event Camera Dataset folder; return the folder.

    Writes ``events.txt`` (9 decimals, p in {0, 1}), and with frames ``images.txt`` and
    ``images/frame_%08d.png`` (8-bit; float frames are rounded and clipped to 0..255), and
    ``calib.txt`` when ``recording.metadata["calib"]`` holds intrinsics. Existing files of
    those names are replaced. The sensor size is not stored (the format has no place for it):
    read the folder back with ``sensor=`` unless frames or a calib.txt tell it.
    """
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    with open(folder / "events.txt", "wb") as f:
        for chunk in recording.iter_events(chunk_events):
            f.write(format_events_txt(chunk))
    frames = recording.frames
    if len(frames):
        (folder / "images").mkdir(exist_ok=True)
        lines = []
        for k in range(len(frames)):  # one iteration a frame
            rel = f"images/frame_{k:08d}.png"
            Image.fromarray(_to_uint8(frames.images[k])).save(folder / rel)
            lines.append(f"{_seconds_text(int(frames.t_us[k]))} {rel}\n")
        (folder / "images.txt").write_text("".join(lines), encoding="utf-8")
    calib = recording.metadata.get("calib")
    if isinstance(calib, (list, tuple)) and len(calib) >= 4:
        text = " ".join(repr(float(v)) for v in calib)
        (folder / "calib.txt").write_text(text + "\n", encoding="utf-8")
    return folder
