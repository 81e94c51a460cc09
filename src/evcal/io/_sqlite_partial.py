"""ROS 2 sqlite3 bag files (``.db3``) cut short, read as far as their messages are whole (not
public API).

SQLite's header (page 1, "Database File Format" of sqlite.org) records the page size (bytes
16-17, big-endian; 1 means 65536) and the database's size in pages (bytes 28-31, valid when
the "version-valid-for" number at bytes 92-95 equals the change counter at 24-27). A file
shorter than that, or not a whole number of pages, was cut. Such a file is opened through a
VFS whose reads fail past the file's end (SQLite would otherwise read the missing pages as
zeros: a message whose last overflow page is missing would come back with zeros for its
tail), and its ``messages`` table is walked in ``id`` order (the order rosbag2 wrote them)
up to the first message that needs a page the file does not have.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from ..errors import ErrorReason
from ..recording import RecordingError
from ._bag_partial import PartialBag
from ._partial import Cut, EmptyRecordingError, cut_in_header

if TYPE_CHECKING:
    import apsw

SQLITE_MAGIC = b"SQLite format 3\x00"
_HEADER_BYTES = 100
_vfs_names = itertools.count()


class PastTheCut(Exception):
    """A read of a page the cut file does not have (raised through SQLite)."""


@dataclass
class _SqliteBag(PartialBag):
    """A cut sqlite3 file's reader: its connection stays open until :meth:`close`."""

    closers: list[Callable[[], Any]] = field(default_factory=list)

    def close(self) -> None:
        for close in self.closers:
            close()
        self.closers = []


def sqlite_pages(path: Path) -> tuple[int, int | None] | None:
    """``(page size, pages its header counts or None)`` of a sqlite3 file cut short, or None
    when it is whole (or not SQLite)."""
    size = path.stat().st_size
    with open(path, "rb") as f:
        head = f.read(_HEADER_BYTES)
    if not head.startswith(SQLITE_MAGIC[: len(head)]) or not head:
        return None
    if len(head) < _HEADER_BYTES:
        raise cut_in_header(str(path), size, f"SQLite's {_HEADER_BYTES}-byte header, cut")
    page = int.from_bytes(head[16:18], "big")
    page = 65_536 if page == 1 else page
    if page < 512 or page & (page - 1):
        return None  # not a page size: a damaged header, for the whole-file reader to refuse
    counter, n_pages, valid_for = (int.from_bytes(head[a : a + 4], "big") for a in (24, 28, 92))
    counted = n_pages if n_pages and counter == valid_for else None
    if (counted is not None and size < page * counted) or size % page:
        return page, counted
    return None


def _cut_vfs(size: int, name: str) -> apsw.VFS:
    """A VFS over the default one whose reads past ``size`` bytes fail (an I/O error)."""
    import apsw

    class File(apsw.VFSFile):
        def xRead(self, amount: int, offset: int) -> bytes:  # noqa: N802 - apsw's name
            if offset + amount > size:
                raise PastTheCut(f"page at byte {offset} is past the cut at byte {size}")
            data: bytes = super().xRead(amount, offset)
            return data

    class Vfs(apsw.VFS):
        def __init__(self, name: str) -> None:
            super().__init__(name, "")

        def xOpen(self, name: Any, flags: list[int]) -> apsw.VFSFile:  # noqa: N802
            return File("", name, flags)

    return Vfs(name)


def scan_sqlite(path: Path, page: int, counted: int | None) -> PartialBag:
    """The whole messages of a sqlite3 bag file cut short (see the module docstring)."""
    import apsw
    from rosbags.interfaces import (
        Connection,
        ConnectionExtRosbag2,
        MessageDefinition,
        MessageDefinitionFormat,
    )

    where = str(path)
    size = path.stat().st_size
    whole_end = size - size % page
    name = f"evcal-cut-{next(_vfs_names)}"
    vfs = _cut_vfs(size, name)
    try:
        db = apsw.Connection(f"file:{path}?immutable=1", vfs=name,
                             flags=apsw.SQLITE_OPEN_READONLY | apsw.SQLITE_OPEN_URI)
    except apsw.Error as exc:
        vfs.unregister()
        raise RecordingError(f"{where}: cut short and cannot be opened as SQLite: {exc}",
                             ErrorReason.TRUNCATED) from None
    try:
        # a file smaller than its header says is "malformed" to SQLite unless the schema is
        # writable (this connection is read-only all the same): then it has the file's pages
        db.execute("PRAGMA writable_schema = ON")
        try:
            tables = {str(r[0]) for r in db.execute(
                "SELECT name FROM sqlite_master WHERE type = 'table'")}
            if not {"topics", "messages"} <= tables:
                raise RecordingError(f"{where}: an SQLite file without the topics and "
                                     "messages tables of a ROS 2 bag", ErrorReason.MALFORMED)
            topics = list(db.execute("SELECT id, name, type, serialization_format FROM topics "
                                     "ORDER BY id"))
            defs: dict[str, tuple[str, str]] = {}
            if "message_definitions" in tables:
                defs = {str(t): (str(e), str(d)) for t, e, d in db.execute(
                    "SELECT topic_type, encoding, encoded_message_definition "
                    "FROM message_definitions")}
        except (apsw.Error, PastTheCut) as exc:
            raise EmptyRecordingError(f"{where}: truncated before its list of topics is "
                                      f"whole ({exc}); nothing to read") from None
        # the messages whole before the cut, in id order: every page of each one was read
        counts: dict[int, int] = {}
        n = 0
        try:
            # (substr reads the whole message: every overflow page of its data)
            for topic_id, _last in db.execute("SELECT topic_id, substr(data, -1) FROM messages "
                                              "ORDER BY id"):
                counts[int(topic_id)] = counts.get(int(topic_id), 0) + 1
                n += 1
        except (apsw.Error, PastTheCut):
            pass  # the first message not whole
    except BaseException:
        db.close()
        vfs.unregister()
        raise
    pages = (f"the {counted:,} {page:,}-byte pages its header counts" if counted is not None
             else f"{page:,}-byte pages")
    cut = Cut(where, size, whole_end, f"{n:,} whole messages (in the order they were written)",
              f"page {whole_end // page + 1:,} of {pages}")
    bag = _SqliteBag(path, cut, message_count=n)
    bag.closers = [db.close, vfs.unregister]
    formats = {"ros2msg": MessageDefinitionFormat.MSG, "ros2idl": MessageDefinitionFormat.IDL}
    for cid, name, msgtype, fmt in topics:
        enc, text = defs.get(str(msgtype), ("", ""))
        bag.connections.append(Connection(
            int(cid), str(name), str(msgtype),
            MessageDefinition(formats.get(enc, MessageDefinitionFormat.NONE), text), "",
            counts.get(int(cid), 0), ConnectionExtRosbag2(str(fmt), []), bag))

    def messages() -> Iterator[tuple[int, int, bytes]]:
        rows = db.execute("SELECT topic_id, timestamp, data FROM messages ORDER BY id")
        for topic_id, t_ns, data in itertools.islice(rows, n):
            yield int(topic_id), int(t_ns), bytes(data)

    bag._messages = messages
    return bag
