"""Atomic per-camera snapshots in a state directory (``--state-dir``).

One file per camera, ``<quoted camera id>.npz`` (``lab/rig1/cam0`` -> ``lab%2Frig1%2Fcam0.npz``);
a quoted id longer than ``MAX_STEM`` characters is cut and given a hash suffix
(``<first 80 characters>~<16 hex digits of its SHA-256>.npz``), so any id has a valid, bounded
and distinct file name. The id itself is stored inside (``_camera_id``), an uncompressed
``.npz`` of plain arrays (``allow_pickle=False`` on load).

Atomicity: a snapshot is written to ``<name>.tmp-<host>-<pid>-<n>`` in the same directory, flushed
and ``fsync``-ed, then renamed over the final name with :func:`os.replace` (atomic on POSIX),
and the directory is ``fsync``-ed. A reader therefore sees the previous snapshot or the new
one, never a half-written file, whatever moment the process dies at (``kill -9``, power
loss). Temporary files left by a killed writer are ignored and removed
(:meth:`StateStore.sweep_temps`, at start-up and after every snapshot written): at once when
their writer was a process of this host that no longer runs (a killed worker's, which its
restart follows within seconds), else once older than ``TMP_MAX_AGE_S`` (another host's
writer, sharing the directory, may still be writing it).

Validation (:func:`read_snapshot`): a snapshot is checked completely before anything of it is
restored, and its sizes before its data is read. First the archive's directory and every
member's ``.npy`` header (dtype, shape, and that the header's size is the member's size);
then the few small text fields, which give the sensor: above the service's ``max_pixels``
the file is refused having read a few kilobytes (a 2000x2000 snapshot, 800 MB once loaded,
took `evcal serve`'s start-up to 831 MiB before it was refused; 117 MiB, as with no snapshot,
when refused from its headers). Then every field's dtype and shape
against the calibrator's own state layout for that sensor and configuration, and only then
the data; the stored calibration message must decode as a calibration of that sensor (one
of another dtype once restored and served bytes no client could decode). A refused file is
moved aside like a damaged one.
"""

from __future__ import annotations

import functools
import hashlib
import itertools
import json
import logging
import math
import os
import socket
import time
import zipfile
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any
from urllib.parse import quote, unquote

import numpy as np

from ..calibration import CALIBRATION_MAPS
from ..errors import ErrorReason, StateError
from ..events import SensorSize
from ..io._util import load_npz_arrays
from ..io.wire import FRAME_DTYPES, MAX_SIZE, WireError, decode_calibration
from ..offe import MARK_FIELDS, StreamingOffE
from ..online import STATE_FORMAT as ONEI_FORMAT
from ..online import OnEIConfig, OnlineCalibrator
from .camera import STATE_FORMAT as CAMERA_FORMAT

log = logging.getLogger("evcal.service.state")

SUFFIX = ".npz"
TMP_MAX_AGE_S = 30.0
MAX_STEM = 100  # characters of a snapshot's file name before ".npz" (file systems allow 255)
ID_KEY = "_camera_id"
_counter = itertools.count()

MSG_KEY = "calibration_msg"
META_KEY = "service_json"
EST = "est__"  # the calibrator's state (OnlineCalibrator.state_dict) under this prefix
# an events-only camera's streaming OffE state (StreamingOffE.state_dict), all or nothing
OFFE = "offe__"
# a camera's event-timing sums (serve --event-timing: StreamingOffE.state_dict), the same
# fields as the events-only ones, all or nothing
TIMING = "timing__"
OFFE_PREFIXES = (OFFE, TIMING)
OFFE_TEXTS = tuple(f"{p}scalars" for p in OFFE_PREFIXES)
# text read before the sensor is known, so bounded on its own: real ones are a few kB
TEXT_KEYS = (ID_KEY, META_KEY, f"{EST}format", f"{EST}scalars")
MAX_TEXT_BYTES = 1 << 20
# the stored calibration message: its maps' wire bytes per pixel, plus header and params
MSG_BYTES_PER_PIXEL = sum(m.wire.itemsize for m in CALIBRATION_MAPS)
# calibrator fields whose dtype follows the input (frames are uint8 or float32 on the wire)
EST_DTYPES = {"fr_images": frozenset(FRAME_DTYPES.values())}
# calibrator fields a snapshot may lack (OnlineCalibrator.from_state does without them:
# "track", the smoothed estimate's variance, is absent from snapshots written before the
# estimate kept it)
EST_OPTIONAL = frozenset({"hist_m", "hist_counts", "track"})


def _fsync_dir(path: Path) -> None:
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


_HOST = socket.gethostname().replace("/", "_") or "host"


def temp_writer_gone(name: str) -> bool:
    """Whether the temp file ``name`` (``<name>.tmp-<host>-<pid>-<n>``) was written by a
    process of this host that no longer runs; False when that cannot be told (another host,
    an older name without the host, a live or foreign process)."""
    _, _, tail = name.rpartition(".tmp-")
    host, _, rest = tail.rpartition("-")  # rest = n
    host, _, pid_text = host.rpartition("-")
    if host != _HOST or not pid_text.isdigit() or not rest.isdigit():
        return False
    pid = int(pid_text)
    if pid == os.getpid():
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return True
    except OSError:  # another user's process: alive
        return False
    return False


def atomic_savez(path: Path, arrays: dict[str, np.ndarray]) -> Path:
    """Write ``arrays`` as an ``.npz`` at ``path`` atomically (temp file, fsync, rename)."""
    path = Path(path)
    tmp = path.with_name(f"{path.name}.tmp-{_HOST}-{os.getpid()}-{next(_counter)}")
    try:
        with open(tmp, "wb") as f:
            members: dict[str, Any] = dict(arrays)  # numpy's stubs: a key could be allow_pickle
            np.savez(f, **members)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    _fsync_dir(path.parent)
    return path


def load_npz(path: Path) -> dict[str, np.ndarray]:
    """Every array of an ``.npz`` file, unchecked (tests and tools; the service reads
    snapshots with :func:`read_snapshot`)."""
    return load_npz_arrays(path, StateError, "the snapshot")


@dataclass(frozen=True)
class _Member:
    """One array of the archive as its ``.npy`` header declares it (nothing read yet)."""

    info: zipfile.ZipInfo
    dtype: np.dtype[Any]
    shape: tuple[int, ...]

    @property
    def nbytes(self) -> int:
        return math.prod(self.shape) * self.dtype.itemsize


_HEADER_READERS = {(1, 0): np.lib.format.read_array_header_1_0,
                   (2, 0): np.lib.format.read_array_header_2_0}


def _members(zf: zipfile.ZipFile) -> dict[str, _Member]:
    """Every member's declared dtype and shape, from its header alone."""
    out: dict[str, _Member] = {}
    for info in zf.infolist():
        name = info.filename
        if not name.endswith(".npy") or name[:-4] in out:
            raise StateError(f"member {name!r} is not a distinct .npy array")
        with zf.open(info) as m:
            try:
                version = np.lib.format.read_magic(m)
                reader = _HEADER_READERS.get(version)
                if reader is None:
                    raise StateError(f"{name}: .npy format {version}, expected 1.0 or 2.0")
                shape, _, dtype = reader(m)
            except ValueError as exc:  # numpy's words for a damaged header
                if isinstance(exc, StateError):
                    raise
                raise StateError(f"{name}: not a .npy header ({exc})") from None
            header_bytes = m.tell()
        if dtype.hasobject:
            raise StateError(f"{name}: dtype {dtype} holds Python objects")
        mem = _Member(info, dtype, tuple(int(d) for d in shape))
        # numpy allocates what the header declares before reading: a header claiming more
        # than the member holds would allocate it, then fail
        if header_bytes + mem.nbytes != info.file_size:
            raise StateError(f"{name}: its header declares {mem.dtype} {mem.shape} "
                             f"({mem.nbytes} bytes), the archive holds "
                             f"{info.file_size - header_bytes} bytes", ErrorReason.TRUNCATED)
        out[name[:-4]] = mem
    return out


def _read(zf: zipfile.ZipFile, mem: _Member) -> np.ndarray:
    with zf.open(mem.info) as m:
        return np.lib.format.read_array(m, allow_pickle=False)


@functools.lru_cache(maxsize=16)
def _est_layout(config_json: str) -> dict[str, tuple[frozenset[np.dtype[Any]],
                                                     tuple[tuple[int, int] | None, ...]]]:
    """The calibrator's state fields for this configuration: their dtypes and dimensions,
    each ``(a, b)`` for ``a * n_pixels + b`` or None for a buffer's length (frames kept,
    events pending). Taken from two tiny calibrators, so that it follows
    :meth:`OnlineCalibrator.state_dict` without a second description of it."""
    config = OnEIConfig.from_json(config_json)
    n1, n2 = 7, 11
    s1 = OnlineCalibrator(SensorSize(1, n1), config).state_dict()
    s2 = OnlineCalibrator(SensorSize(1, n2), config).state_dict()
    layout = {}
    for k, a1 in s1.items():
        if a1.dtype.kind == "U":
            continue  # the text fields (format, scalars), checked on their own
        dims: list[tuple[int, int] | None] = []
        for d1, d2 in zip(a1.shape, s2[k].shape, strict=True):
            slope = (d2 - d1) // (n2 - n1)  # every per-pixel length is linear in n
            dims.append(None if d1 == d2 == 0 else (slope, d1 - slope * n1))
        layout[k] = (EST_DTYPES.get(k, frozenset({a1.dtype})), tuple(dims))
    return layout


@functools.lru_cache(maxsize=1)
def _offe_layout() -> dict[str, tuple[np.dtype[Any], tuple[int, ...]]]:
    """The streaming OffE state's per-pixel fields: dtype and values per pixel (taken from
    a tiny estimator, so that it follows :meth:`StreamingOffE.state_dict`)."""
    st = StreamingOffE(SensorSize(1, 7)).state_dict()
    return {k: (a.dtype, a.shape[1:]) for k, a in st.items() if a.dtype.kind != "U"}


def _check_offe(members: dict[str, _Member], sensor: SensorSize, prefix: str) -> None:
    """A streaming OffE's fields under ``prefix`` (the events-only estimator's, the event
    timing's), when the snapshot has them: every one of them, each ``(n_pixels, ...)`` of
    its dtype."""
    have = {k[len(prefix):] for k in members if k.startswith(prefix)}
    if not have:
        return
    what = "events-only" if prefix == OFFE else "event-timing"
    layout = _offe_layout()
    want = {*layout, "scalars"}
    # a snapshot of before the mark (streaming OffE v1) has no mark arrays
    if have not in (want, want - set(MARK_FIELDS)):
        raise StateError(f"the snapshot's {what} state has {sorted(have)}, expected "
                         f"{sorted(want)}")
    for k, (dtype, tail) in layout.items():
        if k not in have:
            continue
        mem = members[prefix + k]
        shape = (sensor.n_pixels, *tail)
        if mem.dtype != dtype or tuple(mem.shape) != shape:
            raise StateError(f"{prefix}{k} is {mem.dtype} {mem.shape}, expected {dtype} "
                             f"{shape} for a {sensor} sensor")


def _sensor(scalars: str, max_pixels: int | None) -> tuple[SensorSize, str]:
    """The sensor and calibrator configuration (JSON) a snapshot declares, within limits."""
    try:
        s = json.loads(scalars)
        h, w = s["height"], s["width"]
        config = s["config"]
        OnEIConfig.from_json(config)
    except (ValueError, KeyError, TypeError) as exc:
        raise StateError(f"{EST}scalars: {type(exc).__name__}: {exc}") from None
    if not all(isinstance(v, int) and not isinstance(v, bool) for v in (h, w)) or not (
            0 < h <= MAX_SIZE and 0 < w <= MAX_SIZE):
        raise StateError(f"the snapshot's sensor is {w!r}x{h!r}, expected sizes in "
                         f"1..{MAX_SIZE}", ErrorReason.OUT_OF_RANGE)
    if max_pixels is not None and h * w > max_pixels:
        raise StateError(f"the snapshot's {w}x{h} sensor has {h * w} pixels, above this "
                         f"service's limit of {max_pixels} (--max-pixels); its data was not "
                         "read", ErrorReason.SENSOR_TOO_LARGE)
    return SensorSize(h, w), config


def _check_layout(members: dict[str, _Member], sensor: SensorSize, config: str,
                  file_bytes: int) -> None:
    """Every field's dtype and shape for ``sensor``; buffers no larger than the file."""
    n = sensor.n_pixels
    layout = _est_layout(config)
    known = {*TEXT_KEYS, MSG_KEY, *(EST + k for k in layout),
             *(p + k for p in OFFE_PREFIXES for k in (*_offe_layout(), "scalars"))}
    unknown = sorted(set(members) - known)
    if unknown:
        raise StateError(f"unknown field(s) {unknown}: not a snapshot of this version")
    missing = sorted(set(layout) - {k[len(EST):] for k in members} - EST_OPTIONAL)
    if missing:
        raise StateError(f"the snapshot lacks {[EST + k for k in missing]}")
    for prefix in OFFE_PREFIXES:
        _check_offe(members, sensor, prefix)
    buffered = 0
    for k, (dtypes, dims) in layout.items():
        mem = members.get(EST + k)
        if mem is None:
            continue
        if mem.dtype not in dtypes:
            raise StateError(f"{EST}{k} has dtype {mem.dtype}, expected "
                             f"{' or '.join(sorted(str(d) for d in dtypes))}")
        want = tuple(None if d is None else d[0] * n + d[1] for d in dims)
        if len(mem.shape) != len(want) or any(e is not None and s != e
                                              for s, e in zip(mem.shape, want, strict=False)):
            shown = ", ".join("any" if e is None else str(e) for e in want)
            shown = f"({shown},)" if len(want) == 1 else f"({shown})"
            raise StateError(f"{EST}{k} has shape {mem.shape}, expected {shown} for a "
                             f"{sensor} sensor")
        if None in want:
            buffered += mem.nbytes
    # the per-pixel fields are bounded by the sensor; the buffers' lengths by nothing but
    # the file: written uncompressed, they cannot declare more than it holds
    if buffered > file_bytes:
        raise StateError(f"the snapshot's buffers declare {buffered} bytes, more than its "
                         f"{file_bytes}-byte file holds", ErrorReason.TOO_LARGE)
    for k in TEXT_KEYS:
        if k != ID_KEY and k not in members:
            raise StateError(f"the snapshot lacks {k!r}")
    msg = members.get(MSG_KEY)
    if msg is None:
        raise StateError(f"the snapshot lacks {MSG_KEY!r}")
    limit = n * MSG_BYTES_PER_PIXEL + MAX_TEXT_BYTES
    if msg.dtype != np.dtype(np.uint8) or len(msg.shape) != 1:
        raise StateError(f"{MSG_KEY} is {msg.dtype} {msg.shape}, expected uint8 bytes (n,)")
    if msg.nbytes > limit:
        raise StateError(f"{MSG_KEY} has {msg.nbytes} bytes, more than a {sensor} "
                         f"calibration's {limit}", ErrorReason.TOO_LARGE)


def read_snapshot(f: IO[bytes], *, max_pixels: int | None = None) -> dict[str, np.ndarray]:
    """The arrays of the snapshot open as ``f``, checked completely (:class:`StateError`
    saying what is wrong): headers and text first, then dtypes and shapes against the
    declared sensor (refused above ``max_pixels``), then the data, then the calibration
    message. Nothing large is read before its size is known to be right."""
    file_bytes = os.fstat(f.fileno()).st_size
    with zipfile.ZipFile(f) as zf:
        members = _members(zf)
        arrays: dict[str, np.ndarray] = {}
        for k in (*TEXT_KEYS, *OFFE_TEXTS):
            mem = members.get(k)
            if mem is None:
                continue  # missing fields are named below, the id may be (older files)
            if mem.dtype.kind != "U" or mem.shape != () or mem.nbytes > MAX_TEXT_BYTES:
                raise StateError(f"{k} is {mem.dtype} {mem.shape}, expected a string of at "
                                 f"most {MAX_TEXT_BYTES // 4} characters")
            arrays[k] = _read(zf, mem)
        if f"{EST}scalars" not in arrays or f"{EST}format" not in arrays:
            raise StateError(f"the snapshot lacks {EST}scalars or {EST}format")
        if str(arrays[f"{EST}format"]) != ONEI_FORMAT:
            raise StateError(f"calibrator state format {str(arrays[f'{EST}format'])!r}, "
                             f"this version reads {ONEI_FORMAT!r}", ErrorReason.VERSION)
        sensor, config = _sensor(str(arrays[f"{EST}scalars"]), max_pixels)
        _check_layout(members, sensor, config, file_bytes)
        try:
            meta = json.loads(str(arrays[META_KEY]))
        except ValueError as exc:
            raise StateError(f"{META_KEY} is not JSON ({exc})") from None
        if not isinstance(meta, dict) or meta.get("format") != CAMERA_FORMAT:
            raise StateError(f"{META_KEY} is not a camera state of format {CAMERA_FORMAT!r}",
                             ErrorReason.VERSION)
        for k, mem in members.items():
            if k not in arrays:
                arrays[k] = _read(zf, mem)
    msg = arrays[MSG_KEY]
    if msg.size:
        try:
            cal, _ = decode_calibration(msg.data)
        except WireError as exc:
            raise StateError(f"{MSG_KEY} is not a calibration message: {exc}",
                             exc.reason) from None
        if cal.shape != sensor.shape:
            raise StateError(f"{MSG_KEY} is a {cal.shape[1]}x{cal.shape[0]} calibration, "
                             f"the snapshot's sensor is {sensor}")
    return arrays


def snapshot_name(camera: str) -> str:
    """The file name of ``camera``'s snapshot: its quoted id, or a cut one with a hash."""
    stem = quote(camera, safe="")
    if len(stem) > MAX_STEM:
        digest = hashlib.sha256(camera.encode()).hexdigest()[:16]
        stem = f"{stem[:80]}~{digest}"
    return stem + SUFFIX


@dataclass(frozen=True)
class Snapshot:
    """One readable snapshot: the camera id it holds, its file, its arrays."""

    camera: str
    path: Path
    arrays: dict[str, np.ndarray]


class StateStore:
    """The snapshots of one service instance (or of several, behind a shared volume).

    Every failure to read one snapshot moves that file aside (``.bad``) with the reason
    logged and counted in ``bad``: a damaged file never stops a start. Snapshots of sensors
    above ``max_pixels`` (the service's ``--max-pixels``; None: only the wire's 65535x65535)
    are refused before their data is read (:func:`read_snapshot`).
    """

    def __init__(self, directory: str | os.PathLike[str], *, max_pixels: int | None = None):
        self.dir = Path(directory)
        self.dir.mkdir(parents=True, exist_ok=True)
        self.max_pixels = max_pixels
        self.bad = 0

    def path(self, camera: str) -> Path:
        return self.dir / snapshot_name(camera)

    def save(self, camera: str, arrays: dict[str, np.ndarray]) -> Path:
        out = atomic_savez(self.path(camera), {**arrays, ID_KEY: np.array(camera)})
        self.sweep_temps()
        return out

    def sweep_temps(self) -> int:
        """Remove the temp files of writers that died (see the module docstring); returns
        how many were removed. Never raises: a file that vanished or resists is left."""
        removed = 0
        try:
            names = [p for p in self.dir.iterdir() if ".tmp-" in p.name]
        except OSError:
            return 0
        now = time.time()
        for p in names:
            try:
                if temp_writer_gone(p.name) or now - p.stat().st_mtime > TMP_MAX_AGE_S:
                    p.unlink(missing_ok=True)
                    removed += 1
                    log.info("removed %s, a snapshot its writer never finished", p.name)
            except OSError:
                pass
        return removed

    def remove(self, camera: str) -> bool:
        """Delete ``camera``'s snapshot; True if there was one."""
        try:
            self.path(camera).unlink()
            return True
        except FileNotFoundError:
            return False

    def quarantine(self, path: Path, reason: str) -> None:
        """Move an unusable snapshot aside as ``<name>.bad`` (never deleted: evidence)."""
        self.bad += 1
        log.error("snapshot %s cannot be used (%s); moved aside to %s.bad", path.name, reason,
                  path.name)
        try:
            os.replace(path, path.with_name(path.name + ".bad"))
        except OSError as exc:
            log.error("cannot move %s aside: %s", path, exc)

    def load(self, camera: str) -> Snapshot | None:
        """``camera``'s snapshot, or None (none, or unreadable: moved aside)."""
        p = self.path(camera)
        if not p.is_file():
            return None
        snap = self._read(p)
        return snap if snap is not None and snap.camera == camera else None

    def _read(self, p: Path) -> Snapshot | None:
        try:
            # one open file for the checks and the data: a writer sharing the directory
            # may replace the file meanwhile, and the data read must be what was checked
            with open(p, "rb") as f:
                arrays = read_snapshot(f, max_pixels=self.max_pixels)
            ident = arrays.pop(ID_KEY, None)
            if ident is None:  # written before ids were stored inside
                camera = unquote(p.name[: -len(SUFFIX)])
            elif ident.shape != () or ident.dtype.kind != "U":
                raise StateError(f"{ID_KEY} is {ident.dtype} {ident.shape}, expected a string")
            else:
                camera = str(ident)
        except Exception as exc:  # noqa: BLE001 - any damage: aside, never fatal
            self.quarantine(p, f"{type(exc).__name__}: {exc}")
            return None
        return Snapshot(camera, p, arrays)

    def snapshots(self, want: Callable[[str], bool] | None = None) -> list[Snapshot]:
        """Every readable snapshot (with ``want``, of the cameras it accepts); removes stale
        temp files, moves unreadable ones aside. A file whose name gives its camera id and
        ``want`` refuses is not read at all (another shard's, sharing the directory)."""
        out: list[Snapshot] = []
        self.sweep_temps()
        for p in sorted(self.dir.iterdir()):
            if ".tmp-" in p.name:  # a live writer's (sweep_temps removed the dead ones')
                continue
            if not p.name.endswith(SUFFIX):
                continue
            if want is not None:
                named = unquote(p.name[: -len(SUFFIX)])
                if snapshot_name(named) == p.name and not want(named):
                    continue
            snap = self._read(p)
            if snap is not None and (want is None or want(snap.camera)):
                out.append(snap)
        return out

    def load_all(self) -> dict[str, dict[str, np.ndarray]]:
        """Every readable snapshot's arrays by camera id."""
        return {s.camera: s.arrays for s in self.snapshots()}
