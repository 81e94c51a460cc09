"""The msgpack envelopes of event chunks and frames (MCAP messages and network payloads).

One events message is a msgpack map::

    {"version": 1, "height": H, "width": W, "seq": n, "n": count,
     "t_us": <bin, count x little-endian int64>,
     "x": <bin, count x little-endian uint16>, "y": <bin, count x <u2>,
     "p": <bin, count x int8 in {-1, +1}>}

One frame message is a msgpack map::

    {"version": 1, "height": H, "width": W, "seq": n, "t_us": int, "exposure_us": int,
     "dtype": "uint8" | "float32", "data": <bin, H * W values, row-major [y, x], little-endian>}

Decoding is strict: every key must be present with the right type, no unknown keys, array
lengths must match ``n`` and the dtype, sizes must be in 1..65535, events must be sorted and
inside ``W x H`` with polarity +1/-1, float frames must be finite. Any violation raises
:class:`WireError` (a ``ValueError``) with a message naming the field; decoding never raises
another exception type. The arrays are read with ``np.frombuffer``: no Python loop over events.
"""

from __future__ import annotations

import json
import math
import struct
from collections.abc import Mapping
from typing import Any

import msgpack
import numpy as np

from ..calibration import CALIBRATION_MAPS, Calibration, check_map
from ..errors import ErrorReason, EvcalError, reraise_as
from ..events import EVENTS_DTYPE, EventError, SensorSize, validate_events
from ..jsonable import dumps

WIRE_VERSION = 1
MAX_SIZE = 65535  # largest height or width accepted (uint16 coordinates)
FRAME_DTYPES: dict[str, np.dtype[Any]] = {"uint8": np.dtype("u1"), "float32": np.dtype("<f4")}

_EVENT_KEYS = frozenset({"version", "height", "width", "seq", "n", "t_us", "x", "y", "p"})
_FRAME_KEYS = frozenset(
    {"version", "height", "width", "seq", "t_us", "exposure_us", "dtype", "data"}
)
# Bytes per event of each column, in the order of EVENTS_DTYPE.
_COLUMNS = (("t_us", np.dtype("<i8")), ("x", np.dtype("<u2")), ("y", np.dtype("<u2")),
            ("p", np.dtype("i1")))
_INT64_MIN, _INT64_MAX = -(2**63), 2**63 - 1


class WireError(EvcalError):
    """A message that is not a valid evcal envelope (or a value that cannot be encoded);
    ``reason`` (:class:`~evcal.errors.ErrorReason`) says what kind of problem."""


# ----------------------------------------------------------------------------- helpers


def _unpack(buf: Any, what: str) -> dict[str, Any]:
    if not isinstance(buf, (bytes, bytearray, memoryview)):
        raise WireError(f"{what}: expected bytes, got {type(buf).__name__}", ErrorReason.MALFORMED)
    if len(buf) == 0:
        raise WireError(f"{what}: empty message", ErrorReason.NOT_MSGPACK)
    try:
        obj = msgpack.unpackb(buf, raw=False, strict_map_key=True, use_list=True)
    except Exception as exc:  # msgpack raises several types (ExtraData, FormatError, ...)
        raise WireError(f"{what}: not a valid msgpack message ({exc or type(exc).__name__})",
                        ErrorReason.NOT_MSGPACK) \
            from None
    if not isinstance(obj, dict):
        raise WireError(f"{what}: expected a msgpack map, got {type(obj).__name__}",
                        ErrorReason.NOT_MSGPACK)
    return obj


def _check_keys(obj: dict[str, Any], expected: frozenset[str], what: str) -> None:
    keys = set(obj)
    missing = expected - keys
    if missing:
        raise WireError(f"{what}: missing field(s) {sorted(missing)}")
    extra = keys - expected
    if extra:
        raise WireError(f"{what}: unknown field(s) {sorted(map(str, extra))}")


def _int(obj: dict[str, Any], key: str, what: str, lo: int, hi: int) -> int:
    v = obj[key]
    # bool is an int subclass in Python: reject it explicitly.
    if not isinstance(v, int) or isinstance(v, bool):
        raise WireError(f"{what}: field {key!r} must be an integer, got {type(v).__name__}")
    if not lo <= v <= hi:
        raise WireError(f"{what}: field {key!r} = {v} is outside {lo}..{hi}",
                        ErrorReason.OUT_OF_RANGE)
    return v


def _bin(obj: dict[str, Any], key: str, what: str) -> bytes:
    v = obj[key]
    if not isinstance(v, bytes):
        raise WireError(f"{what}: field {key!r} must be binary (msgpack bin), got "
                        f"{type(v).__name__}")
    return v


def _check_version(obj: dict[str, Any], what: str) -> None:
    v = obj["version"]
    if not isinstance(v, int) or isinstance(v, bool) or v != WIRE_VERSION:
        raise WireError(f"{what}: unsupported version {v!r}, this reader knows version "
                        f"{WIRE_VERSION}", ErrorReason.VERSION)


def _envelope(buf: Any, kind: str, expected: frozenset[str]
              ) -> tuple[dict[str, Any], int, int, int, str]:
    """The checked common header of every envelope: ``(obj, height, width, seq, what)``,
    ``what`` naming the message in errors (``"frame message seq 12"``)."""
    obj = _unpack(buf, kind)
    _check_keys(obj, expected, kind)
    _check_version(obj, kind)
    h = _int(obj, "height", kind, 1, MAX_SIZE)
    w = _int(obj, "width", kind, 1, MAX_SIZE)
    seq = _int(obj, "seq", kind, 0, 2**64 - 1)
    return obj, h, w, seq, f"{kind} seq {seq}"


def _size_arg(value: int, name: str) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise WireError(f"cannot encode: {name} must be an integer, got {type(value).__name__}")
    if not 1 <= int(value) <= MAX_SIZE:
        raise WireError(f"cannot encode: {name}={int(value)} is outside 1..{MAX_SIZE}",
                        ErrorReason.OUT_OF_RANGE)
    return int(value)


def _seq_arg(seq: int) -> int:
    if isinstance(seq, bool) or not isinstance(seq, (int, np.integer)) or not 0 <= seq < 2**64:
        raise WireError(f"cannot encode: seq={seq!r} must be an integer in 0..2**64-1",
                        ErrorReason.OUT_OF_RANGE)
    return int(seq)


# ----------------------------------------------------------------------------- events


def encode_events(events: np.ndarray, *, height: int, width: int, seq: int) -> bytes:
    """Pack an event chunk into one msgpack message.

    Parameters
    ----------
    events : ndarray of EVENTS_DTYPE
        Sorted by ``t_us``, inside ``width x height``, polarity +1/-1 (checked). May be empty.
    height, width : int
        Sensor size in pixels, 1..65535.
    seq : int
        Message sequence number (0-based, lets a receiver detect loss).

    Raises
    ------
    WireError
        If the events or sizes break the invariants.
    """
    h, w = _size_arg(height, "height"), _size_arg(width, "width")
    seq = _seq_arg(seq)
    try:
        validate_events(events, SensorSize(height=h, width=w), where="cannot encode events")
    except EventError as exc:
        raise reraise_as(exc, WireError) from None
    msg: dict[str, Any] = {"version": WIRE_VERSION, "height": h, "width": w, "seq": seq,
                           "n": int(events.shape[0])}
    for name, dt in _COLUMNS:
        msg[name] = np.ascontiguousarray(events[name], dtype=dt).tobytes()
    result: bytes = msgpack.packb(msg, use_bin_type=True)
    return result


def decode_events(buf: bytes | bytearray | memoryview) -> tuple[np.ndarray, dict[str, Any]]:
    """Unpack one events message.

    Returns
    -------
    events : ndarray of EVENTS_DTYPE
        A new (writable) array, sorted, inside the sensor.
    header : dict
        ``version``, ``height``, ``width``, ``seq``, ``n``.

    Raises
    ------
    WireError
        With a message naming the first problem found.

    Examples
    --------
    >>> from evcal.events import make_events
    >>> ev = make_events([1, 2], [3, 4], [5, 6], [1, 0])
    >>> out, header = decode_events(encode_events(ev, height=10, width=20, seq=7))
    >>> bool((out == ev).all()), header["seq"], header["n"]
    (True, 7, 2)
    """
    obj, h, w, seq, what = _envelope(buf, "events message", _EVENT_KEYS)
    n = _int(obj, "n", what, 0, 2**62)
    columns = {}
    for name, dt in _COLUMNS:
        raw = _bin(obj, name, what)
        expected = n * dt.itemsize
        if len(raw) != expected:
            state = "truncated" if len(raw) < expected else "too long"
            raise WireError(
                f"{what}: field {name!r} is {state}: {len(raw)} bytes, expected {expected} "
                f"({n} events x {dt.itemsize} bytes of {dt.str})", ErrorReason.TRUNCATED)
        columns[name] = np.frombuffer(raw, dtype=dt)
    events = np.empty(n, dtype=EVENTS_DTYPE)
    for name, col in columns.items():
        events[name] = col
    try:
        validate_events(events, SensorSize(height=h, width=w), where=what)
    except EventError as exc:
        raise reraise_as(exc, WireError) from None
    header = {"version": WIRE_VERSION, "height": h, "width": w, "seq": seq, "n": n}
    return events, header


# ----------------------------------------------------------------------------- frames


def encode_frame(t_us: int, image: np.ndarray, *, exposure_us: int, seq: int) -> bytes:
    """Pack one intensity frame into one msgpack message.

    Parameters
    ----------
    t_us : int
        Time the frame represents, µs (int64).
    image : ndarray, shape (H, W), dtype uint8 or float32
        Indexed ``[y, x]``; float32 frames must be finite.
    exposure_us : int
        Exposure time in µs, 0 when unknown.
    seq : int
        Message sequence number.

    Raises
    ------
    WireError
        On a wrong dtype, shape or value.
    """
    seq = _seq_arg(seq)
    for name, v in (("t_us", t_us), ("exposure_us", exposure_us)):
        if isinstance(v, bool) or not isinstance(v, (int, np.integer)):
            raise WireError(f"cannot encode frame: {name} must be an integer, got "
                            f"{type(v).__name__}")
    if not _INT64_MIN <= int(t_us) <= _INT64_MAX:
        raise WireError(f"cannot encode frame: t_us={int(t_us)} does not fit int64",
                        ErrorReason.OUT_OF_RANGE)
    if not 0 <= int(exposure_us) <= _INT64_MAX:
        raise WireError(f"cannot encode frame: exposure_us={int(exposure_us)} must be >= 0",
                        ErrorReason.OUT_OF_RANGE)
    image = np.asarray(image)
    if image.ndim != 2:
        raise WireError(f"cannot encode frame: image has shape {image.shape}, expected (H, W)")
    h, w = image.shape
    _size_arg(h, "frame height")
    _size_arg(w, "frame width")
    names = {dt: name for name, dt in FRAME_DTYPES.items()}
    dt = image.dtype.newbyteorder("<") if image.dtype.kind == "f" else image.dtype
    if dt not in names:
        raise WireError(f"cannot encode frame: dtype {image.dtype} is not uint8 or float32")
    if image.dtype.kind == "f" and not np.isfinite(image).all():
        raise WireError("cannot encode frame: image contains NaN or infinite values",
                        ErrorReason.BAD_VALUES)
    msg = {
        "version": WIRE_VERSION, "height": h, "width": w, "seq": seq, "t_us": int(t_us),
        "exposure_us": int(exposure_us), "dtype": names[dt],
        "data": np.ascontiguousarray(image, dtype=dt).tobytes(),
    }
    result: bytes = msgpack.packb(msg, use_bin_type=True)
    return result


def decode_frame(
    buf: bytes | bytearray | memoryview,
) -> tuple[int, int, np.ndarray, dict[str, Any]]:
    """Unpack one frame message.

    Returns
    -------
    t_us : int
    exposure_us : int
    image : ndarray, shape (H, W), uint8 or float32
        A read-only view of the message bytes (copy it to modify it).
    header : dict
        ``version``, ``height``, ``width``, ``seq``, ``dtype``.

    Raises
    ------
    WireError
        With a message naming the first problem found.
    """
    obj, h, w, seq, what = _envelope(buf, "frame message", _FRAME_KEYS)
    t_us = _int(obj, "t_us", what, _INT64_MIN, _INT64_MAX)
    exposure_us = _int(obj, "exposure_us", what, 0, _INT64_MAX)
    name = obj["dtype"]
    if not isinstance(name, str) or name not in FRAME_DTYPES:
        raise WireError(f"{what}: dtype {name!r} is not one of {sorted(FRAME_DTYPES)}")
    dt = FRAME_DTYPES[name]
    data = _bin(obj, "data", what)
    expected = h * w * dt.itemsize
    if len(data) != expected:
        state = "truncated" if len(data) < expected else "too long"
        raise WireError(f"{what}: field 'data' is {state}: {len(data)} bytes, expected "
                        f"{expected} ({h}x{w} {name})", ErrorReason.TRUNCATED)
    image = np.frombuffer(data, dtype=dt).reshape(h, w)
    if dt.kind == "f":
        bad = ~np.isfinite(image)
        if bad.any():
            y, x = (int(v) for v in np.argwhere(bad)[0])
            raise WireError(f"{what}: float32 image has {int(bad.sum())} NaN or infinite "
                            f"values, the first at (x={x}, y={y})", ErrorReason.BAD_VALUES)
    header = {"version": WIRE_VERSION, "height": h, "width": w, "seq": seq, "dtype": name}
    return t_us, exposure_us, image, header


# ----------------------------------------------------------------------------- calibrations
#
# One calibration message is a msgpack map:
#
#     {"version": 1, "height": H, "width": W, "seq": n, "t_us": int, "n_events_used": int,
#      "method": str, "log_offset": float, "params_json": str,
#      "maps": {name: <bin, H * W values, row-major [y, x], little-endian>, ...}}
#
# ``maps`` holds any subset of CALIBRATION_MAP_DTYPES (a query may ask for some fields only),
# plus, beside them, the maps of EXTRA_MAP_DTYPES an estimate has that the schema has not
# (the events-only estimate's noise rate); each map's dtype is fixed by its name. A full
# message converts to a Calibration (the extra maps stay in decode_calibration_maps' dict).

# the wire dtypes of the calibration schema (evcal.calibration.CALIBRATION_MAPS)
CALIBRATION_MAP_DTYPES: dict[str, np.dtype[Any]] = {s.name: s.wire for s in CALIBRATION_MAPS}
# maps some estimates add (not in Calibration): finite values >= 0
EXTRA_MAP_DTYPES: dict[str, np.dtype[Any]] = {
    "noise_rate_hz": np.dtype("<f4"),  # events-only: per-pixel event rate, events/s
}
_CALIBRATION_KEYS = frozenset({"version", "height", "width", "seq", "t_us", "n_events_used",
                               "method", "log_offset", "params_json", "maps"})


def encode_calibration(cal: Calibration, *, t_us: int, seq: int, fields: Any = None,
                       extra_maps: Mapping[str, np.ndarray] | None = None) -> bytes:
    """Pack a :class:`~evcal.calibration.Calibration` (or the ``fields`` subset of its maps).

    ``t_us`` is the sensor time of the calibration (the last frame used), ``seq`` the
    message counter of the camera's calibration stream. ``extra_maps`` (names of
    :data:`EXTRA_MAP_DTYPES`, ``[H, W]``, finite and >= 0) go beside the calibration's maps.

    Raises
    ------
    WireError
        For an unknown field name or a value that cannot be encoded.
    """
    seq = _seq_arg(seq)
    try:
        maps_in = cal.maps(fields)
    except EvcalError as exc:
        raise WireError(f"cannot encode calibration: {exc}", exc.reason) from None
    h, w = cal.shape
    _size_arg(h, "height")
    _size_arg(w, "width")
    if isinstance(t_us, bool) or not isinstance(t_us, (int, np.integer)):
        raise WireError(f"cannot encode calibration: t_us must be an integer, got {t_us!r}")
    log_offset = float(cal.log_offset)  # finite: Calibration checks it
    # memoryviews: msgpack copies each map once into the message (no intermediate bytes)
    maps = {name: np.ascontiguousarray(a, dtype=CALIBRATION_MAP_DTYPES[name]).reshape(-1).data
            for name, a in maps_in.items()}
    for name, a in (extra_maps or {}).items():
        maps[name] = _check_extra_map(name, np.asarray(a), (h, w), "cannot encode calibration"
                                      ).reshape(-1).data
    msg = {
        "version": WIRE_VERSION, "height": int(h), "width": int(w), "seq": seq,
        "t_us": int(t_us), "n_events_used": int(np.asarray(cal.n_events).sum()),
        "method": str(cal.method), "log_offset": log_offset,
        "params_json": dumps(cal.diagnostics.to_dict()),
        "maps": maps,
    }
    return _packb_large_bins(msg)


def _check_extra_map(name: str, a: np.ndarray, shape: tuple[int, int], what: str
                     ) -> np.ndarray:
    """An extra map (:data:`EXTRA_MAP_DTYPES`) checked: known name, ``shape``, real numbers,
    finite and >= 0; returned in its wire dtype (contiguous)."""
    dt = EXTRA_MAP_DTYPES.get(name)
    if dt is None:
        raise WireError(f"{what}: unknown map {name!r}", ErrorReason.BAD_VALUES)
    if a.shape != shape:
        raise WireError(f"{what}: map {name!r} has shape {a.shape}, expected {shape}",
                        ErrorReason.BAD_VALUES)
    if a.dtype.kind not in "uif":
        raise WireError(f"{what}: map {name!r} has dtype {a.dtype}, expected {dt}",
                        ErrorReason.BAD_VALUES)
    out = np.ascontiguousarray(a, dtype=dt)
    if out.size and not (np.isfinite(out).all() and float(out.min()) >= 0):
        raise WireError(f"{what}: map {name!r} holds negative, NaN or infinite values",
                        ErrorReason.BAD_VALUES)
    return out


def _bin_header(n: int) -> bytes:
    """msgpack's header of a bin of ``n`` bytes (bin 8, 16 or 32, as msgpack picks)."""
    if n < 1 << 8:
        return struct.pack(">BB", 0xC4, n)
    if n < 1 << 16:
        return struct.pack(">BH", 0xC5, n)
    return struct.pack(">BI", 0xC6, n)


def _packb_large_bins(msg: dict[str, Any]) -> bytes:
    """``msgpack.packb(msg, use_bin_type=True)``, the same bytes, for a message whose
    ``"maps"`` value is a dict of buffers: the maps are copied once, straight into the
    result (``packb`` copies them into a buffer it grows by reallocation, then copies that
    buffer into the result: at 1280x720, 25 MB, twice the time and a worst case 20x its
    best on this machine)."""
    pk = msgpack.Packer(use_bin_type=True)
    chunks: list[Any] = [pk.pack_map_header(len(msg))]
    for key, value in msg.items():
        chunks.append(pk.pack(key))
        if key != "maps":
            chunks.append(pk.pack(value))
            continue
        chunks.append(pk.pack_map_header(len(value)))
        for name, buf in value.items():
            chunks += [pk.pack(name), _bin_header(memoryview(buf).nbytes), buf]
    return b"".join(chunks)


def decode_calibration_maps(
    buf: bytes | bytearray | memoryview,
) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """Unpack a calibration message into its maps (any subset) and header.

    Returns ``(maps, header)``: maps are ``[H, W]`` arrays of the dtypes of
    :data:`CALIBRATION_MAP_DTYPES` (``valid`` as bool), and of :data:`EXTRA_MAP_DTYPES` for
    the extra maps the message has; the header holds ``version``,
    ``height``, ``width``, ``seq``, ``t_us``, ``n_events_used``, ``method``, ``log_offset``
    and ``params`` (a dict).

    Raises
    ------
    WireError
        Naming the first problem found.
    """
    obj, h, w, seq, what = _envelope(buf, "calibration message", _CALIBRATION_KEYS)
    t_us = _int(obj, "t_us", what, _INT64_MIN, _INT64_MAX)
    n_used = _int(obj, "n_events_used", what, 0, _INT64_MAX)
    method = obj["method"]
    if not isinstance(method, str):
        raise WireError(f"{what}: field 'method' must be a string")
    lo = obj["log_offset"]
    if isinstance(lo, bool) or not isinstance(lo, (int, float)) or not (
            math.isnan(lo) or (math.isfinite(lo) and lo >= 0)):
        raise WireError(f"{what}: field 'log_offset' must be a finite number, got {lo!r}")
    pj = obj["params_json"]
    try:
        params = json.loads(pj) if isinstance(pj, str) else None
    except ValueError:
        params = None
    if not isinstance(params, dict):
        raise WireError(f"{what}: field 'params_json' must be a JSON object string")
    raw_maps = obj["maps"]
    if not isinstance(raw_maps, dict):
        raise WireError(f"{what}: field 'maps' must be a map, got {type(raw_maps).__name__}")
    maps: dict[str, np.ndarray] = {}
    for name, raw in raw_maps.items():
        dt = CALIBRATION_MAP_DTYPES.get(name, EXTRA_MAP_DTYPES.get(name))
        if dt is None:
            raise WireError(f"{what}: unknown map {name!r}")
        if not isinstance(raw, bytes):
            raise WireError(f"{what}: map {name!r} must be binary (msgpack bin)")
        expected = h * w * dt.itemsize
        if len(raw) != expected:
            state = "truncated" if len(raw) < expected else "too long"
            raise WireError(f"{what}: map {name!r} is {state}: {len(raw)} bytes, expected "
                            f"{expected} ({w}x{h} {dt.str})", ErrorReason.TRUNCATED)
        values = np.frombuffer(raw, dtype=dt).reshape(h, w)
        if name in EXTRA_MAP_DTYPES:
            maps[name] = _check_extra_map(name, values, (h, w), what).copy()
            continue
        try:
            maps[name] = check_map(name, values).copy()
        except EvcalError as exc:
            raise WireError(f"{what}: {exc}", exc.reason) from None
    header = {"version": WIRE_VERSION, "height": h, "width": w, "seq": seq, "t_us": t_us,
              "n_events_used": n_used, "method": method, "log_offset": float(lo),
              "params": params}
    return maps, header


def decode_calibration(buf: bytes | bytearray | memoryview) -> tuple[Calibration, dict[str, Any]]:
    """Unpack a full calibration message into ``(Calibration, header)``.

    Raises
    ------
    WireError
        If the message is malformed or does not carry every map.
    """
    maps, header = decode_calibration_maps(buf)
    maps = {k: v for k, v in maps.items() if k in CALIBRATION_MAP_DTYPES}
    missing = sorted(set(CALIBRATION_MAP_DTYPES) - set(maps))
    if missing:
        raise WireError(f"calibration message seq {header['seq']}: map(s) {missing} missing "
                        "(a partial message: query without fields= to get all maps)")
    try:
        cal = Calibration.from_maps(maps, log_offset=header["log_offset"],
                                    method=header["method"], diagnostics=header["params"])
    except EvcalError as exc:
        raise WireError(f"calibration message seq {header['seq']}: {exc}", exc.reason) from None
    return cal, header
