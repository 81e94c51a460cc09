"""Readers and writers of recordings and calibration files.

=================================  ===========================  =====================
kind                               read                         write
=================================  ===========================  =====================
Event Camera Dataset folder        :func:`read_ecd`             :func:`write_ecd`
AEDAT4 (``.aedat4``)               :func:`read_aedat4`          --
evcal MCAP (``.mcap``)             :func:`read_mcap`            :func:`write_mcap`
NumPy archive (``.npz``)           :func:`read_npz`             :func:`write_npz`
ROS 1 / ROS 2 bag                  :func:`read_rosbag`          --
Prophesee RAW (EVT 2/2.1/3), DAT   :func:`read_prophesee`       --
HDF5: MVSEC, DSEC, v2e             :func:`read_hdf5`            --
jAER AEDAT 2.0, AEDAT 3.1          :func:`read_aedat2`          --
=================================  ===========================  =====================

:func:`open_recording` and :func:`write_recording` pick one by the path. Every reader raises
:class:`~evcal.recording.RecordingError` with the path and what was wrong.

Files cut short (RAW, DAT, AEDAT 2.0/3.1/4, evcal MCAP, ROS 1 bags, ROS 2 MCAP and sqlite3
files, ECD ``events.txt``) are read up to their last whole record with a
:class:`TruncatedRecordingWarning`; ``strict=True`` refuses them
(:class:`TruncatedRecordingError`); a cut ``.npz`` or HDF5 file cannot be read in part and is
refused (reason ``truncated``). An empty file, one cut inside its header, a
header without data or a cut file without a whole record is an :class:`EmptyRecordingError`.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

from ..events import SensorSize
from ..recording import Recording, RecordingError
from ._partial import (
    EmptyRecordingError,
    TruncatedRecordingError,
    TruncatedRecordingWarning,
    cut_in_header,
    refuse_empty_file,
)
from ._util import file_head
from .aedat2 import AEDAT2_MAGIC, AEDAT31_MAGIC, read_aedat2
from .aedat4 import read_aedat4
from .calibfile import CalibrationFileError, load_calibration, save_calibration, write_csv
from .ecd import read_ecd, write_ecd
from .hdf5 import HDF5_MAGIC, read_hdf5
from .mcap_rec import read_mcap, write_mcap
from .npz import read_npz, write_npz
from .prophesee import read_prophesee
from .rosbag import RosbagError, is_rosbag, read_rosbag
from .wire import WireError, decode_events, decode_frame, encode_events, encode_frame

__all__ = [
    "CalibrationFileError",
    "EmptyRecordingError",
    "RosbagError",
    "TruncatedRecordingError",
    "TruncatedRecordingWarning",
    "WireError",
    "decode_events",
    "decode_frame",
    "encode_events",
    "encode_frame",
    "load_calibration",
    "open_recording",
    "sniff",
    "read_aedat2",
    "read_aedat4",
    "read_ecd",
    "read_hdf5",
    "read_mcap",
    "read_npz",
    "read_prophesee",
    "read_rosbag",
    "save_calibration",
    "write_csv",
    "write_ecd",
    "write_mcap",
    "write_npz",
    "write_recording",
]

_KINDS = ("an Event Camera Dataset folder (events.txt, images.txt + images, calib.txt), "
          "AEDAT4 (.aedat4, DAVIS events and APS frames), jAER AEDAT 2.0 and AEDAT 3.1 "
          "(.aedat; DVS128/DAVIS events, 3.1 APS frames), Prophesee RAW (EVT 2.0, 2.1, 3.0) "
          "and DAT (.raw, .dat), HDF5 (.h5/.hdf5) of MVSEC, DSEC and v2e --dvs_h5, evcal's "
          "MCAP layout (.mcap), evcal's .npz, and ROS bags (a ROS 2 folder with metadata.yaml "
          "or its .mcap/.db3 file, a ROS 1 .bag) of event_camera_msgs/EventPacket "
          "(libcaer_cmp, libcaer, evt3, mono), dvs_msgs or prophesee_event_msgs EventArray "
          "and sensor_msgs/Image")
_MAGICS = ((b"#!AER-DAT4.0", "aedat4"), (AEDAT2_MAGIC, "aedat2"), (AEDAT31_MAGIC, "aedat3"),
           (b"\x89MCAP", "mcap"), (b"PK\x03\x04", "npz"), (HDF5_MAGIC, "hdf5"))
_SUFFIXES = {".aedat4": "aedat4", ".mcap": "mcap", ".npz": "npz", ".bag": "rosbag1",
             ".db3": "rosbag2", ".raw": "prophesee", ".dat": "prophesee", ".h5": "hdf5",
             ".hdf5": "hdf5", ".aedat": "aedat2"}
# keys of Prophesee '%' headers (RAW: OpenEB, faery; DAT: Metavision, faery)
_PROPHESEE_KEYS = re.compile(rb"^% (evt |format |geometry |Data file containing|Version |"
                             rb"Width |Height |serial_number |plugin_name |integrator_name |"
                             rb"camera_integrator_name |system_ID |end\b)", re.M)


def sniff(path: str | os.PathLike[str]) -> str | None:
    """The kind of recording at ``path`` from its content (``"ecd"``, ``"aedat4"``,
    ``"aedat2"``, ``"aedat3"``, ``"prophesee"``, ``"hdf5"``, ``"mcap"``, ``"npz"``,
    ``"rosbag1"``, ``"rosbag2"``), else from its suffix (any case: ``.raw``/``.dat``
    Prophesee, ``.h5``/``.hdf5``, ``.aedat`` jAER), else None.

    A folder with ``metadata.yaml`` (or that file) is a ROS 2 bag, any other folder an Event
    Camera Dataset one; ``#ROSBAG`` starts a ROS 1 bag, ``SQLite format 3`` a ROS 2 sqlite3
    bag; an MCAP file is a ROS 2 bag when its profile is ``ros2`` (or its schemas are
    ``ros2msg``/``ros2idl``, its channels ``cdr``), else evcal's own layout. ``#!AER-DAT2.0``
    / ``#!AER-DAT3.1`` start jAER / cAER files, the HDF5 signature an HDF5 file, and a
    ``% `` header with a Prophesee key (``% evt``, ``% format``, ``% Width``, ...) in its
    first 4 KiB a Prophesee RAW or DAT file.
    """
    path = Path(path)
    return _sniff_content(path) or _SUFFIXES.get(path.suffix.lower())


def _sniff_content(path: Path) -> str | None:
    """The kind from the content alone (see :func:`sniff`), None when it does not say."""
    ros = is_rosbag(path)
    if ros is not None:
        return ros
    if path.is_dir() or (path.is_file() and path.name in ("events.txt", "images.txt")):
        return "ecd"
    head = file_head(path)
    if head is None:
        return None
    for magic, kind in _MAGICS:
        if head.startswith(magic):
            return kind
    if head.startswith(b"#!AER-DAT"):
        return "aedat-other"
    if head.startswith(b"% "):
        longer = file_head(path, 4096) or b""
        if _PROPHESEE_KEYS.search(longer):
            return "prophesee"
    return None


def open_recording(path: str | os.PathLike[str], *, sensor: SensorSize | None = None,
                   events_topic: str | None = None, frames_topic: str | None = None,
                   camera: str | None = None, strict: bool = False) -> Recording:
    """Read a recording, choosing the reader by its content (then by its suffix).

    A directory (or its ``events.txt``) is an Event Camera Dataset folder, one with
    ``metadata.yaml`` a ROS 2 bag; files are recognised by their first bytes (AEDAT4's
    ``#!AER-DAT4.0``, ``#!AER-DAT2.0``, ``#!AER-DAT3.1``, a Prophesee ``%`` header, the HDF5
    signature, the MCAP magic and profile, a zip for ``.npz``, ``#ROSBAG``, SQLite's magic),
    so a misnamed file (``road.AEDAT``, ``rec.bin``) still opens. ``sensor`` is passed on
    (required for an ECD folder without frames or a recognisable ``calib.txt``, a Prophesee
    file whose header has no size, a jAER file naming no known chip, a v2e HDF5 file without
    frames); ``events_topic`` / ``frames_topic`` choose among a ROS bag's topics (see
    :func:`read_rosbag`) and ``camera`` an MVSEC camera (``left``/``right``, see
    :func:`read_hdf5`); they are refused for other kinds.

    A file cut short (a copy stopped early, a recorder killed) is read up to its last whole
    record (word, event, packet, message) with a :class:`TruncatedRecordingWarning` naming
    the file, the byte where the whole part ends and what was left out, and
    ``metadata["truncated"]`` saying the same; ``strict=True`` refuses it instead
    (:class:`TruncatedRecordingError`). So are RAW/DAT, AEDAT 2.0/3.1/4, evcal MCAP, ROS 1
    bags, ROS 2 MCAP and sqlite3 files and ECD ``events.txt``; a cut ``.npz`` or HDF5 file
    is refused (reason ``truncated``, whatever ``strict`` says): neither can be read in
    part.

    Raises
    ------
    RecordingError
        For a path that does not exist, an unknown kind (naming what evcal reads), or
        whatever the reader finds wrong; :class:`EmptyRecordingError` (reason ``truncated``)
        for an empty file, one cut inside its header, a header without data or a cut file
        without a whole record; :class:`TruncatedRecordingError` for a file cut short when
        ``strict``.
    """
    path = Path(path)
    if not path.exists():
        raise RecordingError(f"{path}: no such file or directory")
    if path.is_file() and path.suffix.lower() != ".txt":
        size = refuse_empty_file(path)
        head = file_head(path) or b""
        cut_magics = [kind for magic, kind in (*_MAGICS, (b"#ROSBAG V2.0\n", "rosbag1"))
                      if size < len(magic) and magic.startswith(head)]
        if cut_magics:  # a file shorter than the magic it starts
            raise cut_in_header(str(path), size, f"{head!r}, the start of the magic of "
                                f"{' or '.join(cut_magics)}")
    by_content = _sniff_content(path)
    kind = by_content or _SUFFIXES.get(path.suffix.lower())
    if by_content is None and kind in ("hdf5", "prophesee", "aedat2"):
        # only the suffix says: a reader's refusal means "not this format" as much as
        # "a damaged file of it", so name both
        try:
            return _open_kind(path, kind, sensor, events_topic, frames_topic, camera, strict)
        except RecordingError as exc:
            raise RecordingError(
                f"{path}: unknown recording format (its first bytes say nothing; by its suffix "
                f"{path.suffix!r} it would be {kind}, whose reader says: {exc}); evcal reads "
                f"{_KINDS}", exc.reason) from None
    return _open_kind(path, kind, sensor, events_topic, frames_topic, camera, strict)


def _open_kind(path: Path, kind: str | None, sensor: SensorSize | None,
               events_topic: str | None, frames_topic: str | None, camera: str | None,
               strict: bool) -> Recording:
    if kind in ("rosbag1", "rosbag2"):
        return read_rosbag(path, sensor=sensor, events_topic=events_topic,
                           frames_topic=frames_topic, strict=strict)
    if events_topic is not None or frames_topic is not None:
        what = f"a recording of kind {kind!r}" if kind else "not one"
        raise RecordingError(f"{path}: events_topic/frames_topic choose topics of ROS bags; "
                             f"this is {what}")
    if kind == "hdf5":
        return read_hdf5(path, sensor=sensor, camera=camera)
    if camera is not None:
        what = f"a recording of kind {kind!r}" if kind else "not one"
        raise RecordingError(f"{path}: camera chooses the camera of an MVSEC HDF5 file; this "
                             f"is {what}")
    if kind == "ecd":
        return read_ecd(path.parent if path.is_file() else path, sensor=sensor,
                        strict=strict)
    if kind == "aedat4":
        return read_aedat4(path, sensor=sensor, strict=strict)
    if kind == "mcap":
        return read_mcap(path, sensor=sensor, strict=strict)
    if kind == "npz":
        return read_npz(path, sensor=sensor)
    if kind in ("aedat2", "aedat3"):
        return read_aedat2(path, sensor=sensor, strict=strict)
    if kind == "prophesee":
        return read_prophesee(path, sensor=sensor, strict=strict)
    if kind == "aedat-other":
        raise RecordingError(f"{path}: an AEDAT file of another version than 2.0, 3.1 or 4.0 "
                             f"(the ones it reads); evcal reads {_KINDS}")
    raise RecordingError(f"{path}: unknown recording format (neither its first bytes nor its "
                         f"suffix {path.suffix or '(none)'!r} say); evcal reads {_KINDS}")


def write_recording(recording: Recording, path: str | os.PathLike[str]) -> Path:
    """Write a recording, choosing the writer by the path: ``.mcap``, ``.npz``, or a folder
    (an existing directory or a path without suffix) for the Event Camera Dataset layout.

    Raises
    ------
    RecordingError
        For a suffix no writer handles (``.aedat4`` is read-only).
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if path.is_dir() or (suffix == "" and not path.exists()):
        return write_ecd(recording, path)
    if suffix == ".mcap":
        return write_mcap(recording, path)
    if suffix == ".npz":
        return write_npz(recording, path)
    raise RecordingError(f"{path}: cannot write a recording of kind {suffix or '(no suffix)'!r}; "
                         "use .mcap, .npz or a folder (Event Camera Dataset layout)")
