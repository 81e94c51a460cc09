"""The ``.rrd`` file of a service run on disk, whole at every moment (no rerun import).

Rerun's file sink writes into a pipe; :class:`RrdFile` reads it and appends whole units of
rerun's framing to the file (the stream header, one message, or the end message with its
trailer), so that the file always ends on a message boundary and ``rerun rrd verify`` accepts
it once the end is written (rerun's own sink, writing to a full disk or past
``RLIMIT_FSIZE``, leaves the file cut mid-message and without its footer). The room the
recording still needs is held on the disk by an unlinked reserve file beside it.
:class:`~evcal.service.rrdlog.RrdLogger` decides what is logged and when to stop.
"""

from __future__ import annotations

import errno
import itertools
import logging
import os
import shutil
import struct
import tempfile
import threading
from enum import Enum
from importlib import metadata
from pathlib import Path
from typing import Any

log = logging.getLogger("evcal.service.rrdlog")

def _rerun_version() -> str:
    try:
        return metadata.version("rerun-sdk")
    except metadata.PackageNotFoundError:
        return "(unknown version)"


def free_path(path: Path) -> Path:
    """``path``, or the first of ``stem.1.rrd``, ``stem.2.rrd``... that does not exist: a
    restarted service never overwrites the previous run's recording."""
    if not path.exists():
        return path
    for i in itertools.count(1):
        p = path.with_name(f"{path.stem}.{i}{path.suffix}")
        if not p.exists():
            return p
    raise AssertionError("unreachable")


def disk_free(path: Path) -> int:
    """Bytes free on the file system holding ``path``."""
    return int(shutil.disk_usage(path).free)


class StopReason(str, Enum):
    """Why the recorder stopped (the ``reason`` of its state; stable strings)."""

    DISK_FULL = "disk_full"  # less than min_free_bytes would be left on the disk
    FILE_SIZE_LIMIT = "file_size_limit"  # the process's RLIMIT_FSIZE would be exceeded
    WRITE_ERROR = "write_error"  # the file could not be written (an I/O error)
    RERUN_ERROR = "rerun_error"  # rerun raised, timed out, or wrote what this cannot parse

    def __str__(self) -> str:
        return self.value


# rerun 0.41's .rrd framing (re_log_encoding): a 12-byte stream header starting "RRF2", then
# messages, each a 16-byte header (kind, payload length: u64 little-endian) and its payload;
# kind 0 ends the stream and carries the footer (the manifest of every chunk, with byte
# offsets into the stream), followed by a 32-byte trailer. A file is valid for `rerun rrd
# verify` only with that end: it is written after the last message or not at all.
_MAGIC = b"RRF2"
_STREAM_HEADER = 12
_MESSAGE_HEADER = struct.Struct("<QQ")
_END = 0
_TRAILER = 32
_MAX_MESSAGE = 1 << 40  # a longer message means the bytes are not that framing
_RESERVE_STEP = 1 << 20
_RESERVE_SLACK = 64 << 10  # file-system blocks beyond the bytes a write needs


def _reason_of(exc: OSError) -> StopReason:
    if exc.errno in (errno.ENOSPC, errno.EDQUOT):
        return StopReason.DISK_FULL
    if exc.errno == errno.EFBIG:
        return StopReason.FILE_SIZE_LIMIT
    return StopReason.WRITE_ERROR


def _preallocate(fd: int, size: int) -> None:
    """Make the file ``fd`` hold ``size`` bytes of disk (not sparse)."""
    if hasattr(os, "posix_fallocate"):
        os.posix_fallocate(fd, 0, size)
        return
    have = os.fstat(fd).st_size  # no posix_fallocate (macOS): zeros are as good
    zeros = bytes(1 << 20)
    while have < size:
        have += os.pwrite(fd, zeros[:size - have], have)


class RrdFile:
    """The ``.rrd`` on disk, fed by rerun's file sink through a pipe (``sink_path``).

    A thread reads the pipe and appends whole units of rerun's framing (the stream header, one
    message, or the end message with its trailer) to the file, so that the file always ends on
    a message boundary: a write that fails (disk full, file too large) is cut back to the last
    boundary, and from then on the pipe is read and discarded, so that rerun never blocks on
    it. ``reserve`` holds disk space in an unlinked file beside the ``.rrd``; a write finding
    the disk full takes its bytes from that reserve and tries again.
    """

    def __init__(self, path: Path) -> None:
        self.path = path
        # O_EXCL: free_path() chose an unused name; never truncate a file that appeared since
        self.fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL
                          | getattr(os, "O_CLOEXEC", 0), 0o644)
        self._read_fd, write_fd = os.pipe()
        self._write_fd: int | None = write_fd
        # rerun opens its own descriptor of the pipe by this name
        fds = "/dev/fd" if os.path.isdir("/dev/fd") else "/proc/self/fd"
        self.sink_path = f"{fds}/{write_fd}"
        self.received = 0  # bytes read from the pipe
        self.written = 0  # bytes in the file: whole units only
        self.messages = 0  # messages in the file (the footer grows with them)
        self.complete = False  # the end and trailer are written: `rerun rrd verify` accepts it
        self.failure: tuple[StopReason, str] | None = None
        self._buf = bytearray()
        self._unit: int | None = _STREAM_HEADER  # bytes of the next unit (None: not known yet)
        self._unit_is_end = False
        self._reserve_lock = threading.Lock()
        self._reserve: Any = None  # the unlinked reserve file, made on first use
        self.reserved = 0
        self._reserve_broken = False
        self._reading = True  # the read end is open
        self._done = threading.Event()
        self._thread = threading.Thread(target=self._run, name="evcal-rrd-writer", daemon=True)
        self._thread.start()

    def sink_opened(self) -> None:
        """Rerun holds its own descriptor of the pipe: the stream ends when rerun closes it."""
        if self._write_fd is not None:
            os.close(self._write_fd)
            self._write_fd = None

    # -- the writer thread -----------------------------------------------------------------

    def _run(self) -> None:
        try:
            while True:
                try:
                    data = os.read(self._read_fd, 1 << 20)
                except OSError as exc:
                    self._fail(StopReason.WRITE_ERROR, f"cannot read rerun's stream: {exc}")
                    return
                if not data:
                    return  # rerun closed the stream
                self.received += len(data)
                if self.failure is not None or self.complete:
                    continue  # read and dropped: rerun must never block on a full pipe
                try:
                    self._feed(data)
                except Exception as exc:  # noqa: BLE001 - the thread keeps draining the pipe
                    self._fail(StopReason.WRITE_ERROR,
                               f"writing {self.path} failed ({type(exc).__name__}: {exc})")
        finally:
            # a writer that gave up unblocks rerun too: its writes now fail with EPIPE
            self._reading = False
            os.close(self._read_fd)
            self._done.set()

    def _feed(self, data: bytes) -> None:
        buf = self._buf
        buf += data
        while True:
            if self._unit is None:
                if len(buf) < _MESSAGE_HEADER.size:
                    return
                kind, length = _MESSAGE_HEADER.unpack_from(buf)
                if length > _MAX_MESSAGE:
                    self._fail(StopReason.RERUN_ERROR, self._not_rrd(
                        f"a message header says {length} bytes"))
                    return
                self._unit_is_end = kind == _END
                self._unit = _MESSAGE_HEADER.size + length + (_TRAILER if kind == _END else 0)
            if len(buf) < self._unit:
                return
            if self.written == 0 and bytes(buf[:4]) != _MAGIC:
                self._fail(StopReason.RERUN_ERROR, self._not_rrd(
                    f"the stream starts with {bytes(buf[:4])!r}, not {_MAGIC!r}"))
                return
            unit, is_message = buf[:self._unit], self.written > 0
            del buf[:self._unit]
            self._unit = None
            if not self._append(unit):
                return
            if self._unit_is_end:
                self.complete = True
                return
            self.messages += is_message

    def _not_rrd(self, what: str) -> str:
        return (f"rerun-sdk {_rerun_version()} wrote a stream this recorder cannot frame ({what}; "
                "expected rerun 0.41's .rrd framing): recording stopped")

    def _append(self, unit: bytearray) -> bool:
        """Write ``unit`` at the end of the file; on failure cut the file back to where it
        was and record why."""
        start, done = self.written, 0
        while done < len(unit):
            try:
                done += os.pwrite(self.fd, unit[done:], start + done)
            except OSError as exc:
                if (exc.errno in (errno.ENOSPC, errno.EDQUOT)
                        and self._take_reserve(len(unit) - done)):
                    continue  # the reserve was kept for these bytes
                try:
                    os.ftruncate(self.fd, start)
                except OSError:  # noqa: S110 - nothing more to do; the failure says why
                    pass
                self._fail(_reason_of(exc), f"cannot write {self.path} ({exc.strerror}) at "
                           f"{start} bytes: the file ends at its last whole message, without "
                           "rerun's footer")
                return False
        self.written = start + len(unit)
        return True

    def _fail(self, reason: StopReason, message: str) -> None:
        if self.failure is None:
            self.failure = (reason, message)
            log.error("rerun recording: %s", message)

    # -- disk reserve ------------------------------------------------------------------------

    def reserve(self, nbytes: int) -> bool:
        """Hold ``nbytes`` of disk beside the file (in whole MiB, at most 2 MiB more): given to
        writes that find the disk full, and back to the disk at close; False when the disk
        has not that much."""
        step = -(-nbytes // _RESERVE_STEP) * _RESERVE_STEP
        with self._reserve_lock:
            if self._reserve_broken:
                return True
            if self._reserve is not None and step + _RESERVE_STEP < self.reserved:
                try:  # the promise shrank (rerun flushed): give the excess back
                    os.ftruncate(self._reserve.fileno(), step)
                    self.reserved = step
                except OSError:  # noqa: S110 - keeping more than needed is harmless
                    pass
            if nbytes <= self.reserved:
                return True
            try:
                if self._reserve is None:
                    self._reserve = tempfile.TemporaryFile(  # noqa: SIM115 - closed in close()
                        dir=self.path.parent, prefix=".evcal-rrd-reserve-")
                for size in (step, nbytes):
                    try:
                        _preallocate(self._reserve.fileno(), size)
                    except OSError as exc:
                        if exc.errno not in (errno.ENOSPC, errno.EDQUOT, errno.EFBIG):
                            raise
                        continue
                    self.reserved = size
                    return True
                return False
            except OSError as exc:
                # a file system that cannot preallocate: record on, without the reserve
                self._reserve_broken = True
                log.warning("rerun recording: cannot reserve disk space beside %s (%s): a "
                            "disk filled by another process may leave the file without its "
                            "footer", self.path, exc)
                return True

    def _take_reserve(self, nbytes: int) -> bool:
        """Give ``nbytes`` of the reserve back to the disk; False when it is empty."""
        with self._reserve_lock:
            if self._reserve is None or self.reserved == 0:
                return False
            self.reserved = max(0, self.reserved - nbytes - _RESERVE_SLACK)
            try:
                os.ftruncate(self._reserve.fileno(), self.reserved)
            except OSError:
                return False
            return True

    # -- end -------------------------------------------------------------------------------

    def pending(self) -> int:
        """Bytes rerun wrote into the pipe that this has not read yet."""
        if not self._reading:
            return 0
        try:
            import fcntl  # noqa: PLC0415 - Unix only, like the pipe
            import termios  # noqa: PLC0415

            n = bytearray(4)
            fcntl.ioctl(self._read_fd, termios.FIONREAD, n)
            return int.from_bytes(n, "little")
        except (OSError, ImportError):
            return 64 << 10  # a pipe's default capacity

    def wait(self, timeout_s: float) -> bool:
        """Wait until rerun closed the stream and all of it was handled."""
        return self._done.wait(max(0.0, timeout_s))

    def close(self) -> None:
        """Release the reserve and the descriptors. A writer thread still running (a disk
        that does not answer) keeps its descriptor: closing it under the thread could let a
        later write land in whatever file reuses the number."""
        self.sink_opened()
        with self._reserve_lock:
            if self._reserve is not None:
                self._reserve.close()
                self._reserve = None
                self.reserved = 0
        if self._done.is_set() and self.fd >= 0:
            os.close(self.fd)
            self.fd = -1
