"""Files cut short: the warning, the errors and the report of what was read (not public API;
the names are exported by :mod:`evcal.io`).

A recording file that ends inside a record (a copy stopped early, a recorder killed) is read
as far as its records are whole, as OpenEB does for RAW files: the readers call
:func:`report_cut`, which warns with :class:`TruncatedRecordingWarning` (naming the file, the
byte where the whole part ends, what was read and what was left out) or, with
``strict=True``, raises :class:`TruncatedRecordingError`. A file with nothing to read (0 bytes,
cut inside its header, a header and no data, no whole record) is an
:class:`EmptyRecordingError` with or without ``strict``.
"""

from __future__ import annotations

import sys
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ..errors import ErrorReason
from ..recording import RecordingError


class TruncatedRecordingWarning(UserWarning):
    """A recording file ends inside a record; what was whole before the cut was read."""


class TruncatedRecordingError(RecordingError):
    """A recording file that ends inside a record, refused because ``strict=True``."""

    default_reason = ErrorReason.TRUNCATED


class EmptyRecordingError(RecordingError):
    """A recording file with nothing to read: empty, cut inside its header, a header and no
    data, or no whole record before the cut."""

    default_reason = ErrorReason.TRUNCATED


@dataclass(frozen=True)
class Cut:
    """Where a file was cut and what was read of it.

    ``whole_end`` is the byte where the whole part ends (the partial record starts there);
    ``read`` says what was read before it ("2,345 whole 8-byte records"), ``partial`` what the
    file ends inside ("a 8-byte record (3 of its bytes present)") or, for a file cut at a
    record boundary (``whole_end == size``), what is missing after it; ``recovered`` what was
    still read from inside the partial record (a compressed chunk's whole messages).
    """

    path: str
    size: int
    whole_end: int
    read: str
    partial: str
    recovered: str = ""

    @property
    def cut_bytes(self) -> int:
        """Bytes from ``whole_end`` to the end of the file (the partial record's part)."""
        return self.size - self.whole_end

    def message(self) -> str:
        if not self.cut_bytes:  # cut at a record boundary, told by what is missing after it
            return (f"{self.path}: truncated file: it ends at byte {self.size:,}, before "
                    f"{self.partial}; read {self.read}")
        left = (f"; from it, {self.recovered}" if self.recovered else
                f"; the last {self.cut_bytes:,} bytes (from byte {self.whole_end:,}) were "
                "left out")
        return (f"{self.path}: truncated file: it ends at byte {self.size:,} inside "
                f"{self.partial}, which starts at byte {self.whole_end:,}; read {self.read} "
                f"before it{left}")

    def metadata(self) -> dict[str, Any]:
        """What ``metadata["truncated"]`` of the recording says."""
        return {"file_bytes": self.size, "whole_end_byte": self.whole_end,
                "cut_bytes": self.cut_bytes, "read": self.read, "partial": self.partial,
                "recovered": self.recovered}


def report_cut(cut: Cut, *, strict: bool) -> dict[str, Any]:
    """Warn about ``cut`` (or raise :class:`TruncatedRecordingError` when ``strict``);
    returns its metadata entry. The warning names the first caller outside ``evcal.io``."""
    if strict:
        raise TruncatedRecordingError(cut.message() + " (refused: strict; without strict the "
                                      "whole records before the cut are read)")
    level = 1
    frame = sys._getframe(0)
    while frame.f_back is not None and str(frame.f_globals.get("__name__", "")).startswith(
            "evcal.io"):
        frame = frame.f_back
        level += 1
    warnings.warn(cut.message(), TruncatedRecordingWarning, stacklevel=level)
    return cut.metadata()


def refuse_empty_file(path: Path) -> int:
    """The size of the file at ``path``; :class:`EmptyRecordingError` when it is 0 bytes."""
    try:
        size = path.stat().st_size
    except OSError as exc:
        raise RecordingError(f"{path}: cannot read: {exc}") from None
    if size == 0:
        raise EmptyRecordingError(f"{path}: empty file (0 bytes): no header and no data "
                                  "(a recording that never started, or a failed copy)")
    return size


def header_only(path: str, header_bytes: int, what: str) -> EmptyRecordingError:
    """The error for a file that ends right after its header."""
    return EmptyRecordingError(
        f"{path}: header only: the file ends after its {header_bytes:,}-byte header with no "
        f"{what} (truncated, or a recording stopped before it wrote any); nothing to read")


def cut_in_header(path: str, size: int, what: str) -> EmptyRecordingError:
    """The error for a file that ends inside its header."""
    return EmptyRecordingError(f"{path}: truncated inside its header ({what}; the file has "
                               f"{size:,} bytes): no data to read")


def nothing_whole(cut: Cut) -> EmptyRecordingError:
    """The error for a file cut before its first whole record."""
    where = (f"before {cut.partial}" if not cut.cut_bytes else
             f"inside {cut.partial}, which starts at byte {cut.whole_end:,}")
    return EmptyRecordingError(f"{cut.path}: truncated before its first whole record: it ends "
                               f"at byte {cut.size:,}, {where}; nothing to read")


def words_cut(path: str, size: int, body_start: int, body_bytes: int, word: int, unit: str
              ) -> Cut | None:
    """The cut of a body of fixed-size ``word``-byte records starting at ``body_start``, or
    None when it is a whole number of them."""
    extra = body_bytes % word
    if not extra:
        return None
    n = body_bytes // word
    return Cut(path, size, body_start + n * word, f"{n:,} whole {unit}s",
               f"a {word}-byte {unit} ({extra} of its bytes present)")


# ------------------------------------------------------------------ formats not read in part

_ZIP_LOCAL = b"PK\x03\x04"
_ZIP_END = b"PK\x05\x06"


def zip_cut(path: Path) -> str | None:
    """What is wrong with a zip archive (an ``.npz``) cut short, or None when it is not one.

    A zip's directory is at its end, so a cut archive has none; the members whole before the
    cut are told from their local headers (numpy writes each member's sizes there, in a
    ZIP64 extra field)."""
    try:
        with open(path, "rb") as f:
            data = f.read()
    except OSError:
        return None
    end_at = data.rfind(_ZIP_END, max(0, len(data) - 65_536 - 22))
    if not data.startswith(_ZIP_LOCAL) or (end_at >= 0 and end_at + 22 <= len(data)):
        return None  # not a zip, or one with its end record: damaged, not cut
    whole: list[str] = []
    pos = 0
    partial = f"a member's header, which starts at byte {pos:,}"
    while data.startswith(_ZIP_LOCAL, pos) and pos + 30 <= len(data):
        flags, csize, usize, nlen, elen = (int.from_bytes(data[pos + a : pos + b], "little")
                                           for a, b in ((6, 8), (18, 22), (22, 26), (26, 28),
                                                        (28, 30)))
        name = data[pos + 30 : pos + 30 + nlen].decode("utf-8", "replace")
        extra = data[pos + 30 + nlen : pos + 30 + nlen + elen]
        k = 0
        while k + 4 <= len(extra):  # ZIP64: the sizes that did not fit the header's fields
            tag, n = int.from_bytes(extra[k : k + 2], "little"), int.from_bytes(
                extra[k + 2 : k + 4], "little")
            if tag == 1 and n >= 16 and 0xFFFFFFFF in (usize, csize):
                usize = int.from_bytes(extra[k + 4 : k + 12], "little")
                csize = int.from_bytes(extra[k + 12 : k + 20], "little")
            k += 4 + n
        end = pos + 30 + nlen + elen + csize
        if flags & 0x08 or end > len(data) or pos + 30 + nlen + elen > len(data):
            partial = f"member {name!r}, which starts at byte {pos:,}"
            break
        whole.append(name)
        pos = end
        partial = (f"its directory, which starts at byte {pos:,}"
                   if data.startswith(b"PK\x01\x02", pos) else
                   f"a member's header, which starts at byte {pos:,}")
    return (f"truncated zip archive: it ends at byte {len(data):,} inside {partial}, without "
            f"the directory a zip keeps at its end ({len(whole)} member(s) whole before the "
            f"cut{': ' + ', '.join(whole) if whole else ''}). An .npz is not read in part: its "
            "arrays are whole or missing; copy the file again whole")


def hdf5_cut(path: Path) -> str | None:
    """What is wrong with an HDF5 file shorter than the end-of-file address its superblock
    records, or None when it is not one (HDF5 "File Format Specification", superblock
    versions 0-3; the signature at byte 0, 512, 1024, ...)."""
    try:
        size = path.stat().st_size
        with open(path, "rb") as f:
            for base in (0, 512, 1024, 2048, 4096, 8192):
                f.seek(base)
                head = f.read(120)
                if head.startswith(b"\x89HDF\r\n\x1a\n"):
                    break
            else:
                return None
    except OSError:
        return None
    version = head[8] if len(head) > 8 else -1
    if version in (0, 1):
        o = head[13] if len(head) > 13 else 0
        at = 24 + (4 if version == 1 else 0) + 2 * o  # base, free-space, then end of file
    elif version in (2, 3):
        o = head[9] if len(head) > 9 else 0
        at = 12 + 2 * o  # base, superblock extension, then end of file
    else:
        return None
    if o not in (2, 4, 8) or len(head) < at + o:
        return None
    eof = base + int.from_bytes(head[at : at + o], "little")
    if size >= eof:
        return None
    return (f"truncated HDF5 file: it has {size:,} bytes, its superblock says {eof:,} "
            f"({eof - size:,} missing). HDF5 keeps its index (object headers, chunk B-trees) "
            "anywhere in the file, often at its end, so a cut HDF5 file is not read in part; "
            "copy the file again whole")
