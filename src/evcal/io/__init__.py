"""Readers and writers of recordings and calibration files.

=================================  ===========================  =====================
kind                               read                         write
=================================  ===========================  =====================
Event Camera Dataset folder        :func:`read_ecd`             :func:`write_ecd`
AEDAT4 (``.aedat4``)               :func:`read_aedat4`          --
evcal MCAP (``.mcap``)             :func:`read_mcap`            :func:`write_mcap`
NumPy archive (``.npz``)           :func:`read_npz`             :func:`write_npz`
ROS 1 / ROS 2 bag                  :func:`read_rosbag`          --
=================================  ===========================  =====================

:func:`open_recording` and :func:`write_recording` pick one by the path. Every reader raises
:class:`~evcal.recording.RecordingError` with the path and what was wrong.
"""

from __future__ import annotations

import os
from pathlib import Path

from ..events import SensorSize
from ..recording import Recording, RecordingError
from ._util import file_head
from .aedat4 import read_aedat4
from .calibfile import CalibrationFileError, load_calibration, save_calibration, write_csv
from .ecd import read_ecd, write_ecd
from .mcap_rec import read_mcap, write_mcap
from .npz import read_npz, write_npz
from .rosbag import RosbagError, is_rosbag, read_rosbag
from .wire import WireError, decode_events, decode_frame, encode_events, encode_frame

__all__ = [
    "CalibrationFileError",
    "RosbagError",
    "WireError",
    "decode_events",
    "decode_frame",
    "encode_events",
    "encode_frame",
    "load_calibration",
    "open_recording",
    "sniff",
    "read_aedat4",
    "read_ecd",
    "read_mcap",
    "read_npz",
    "read_rosbag",
    "save_calibration",
    "write_csv",
    "write_ecd",
    "write_mcap",
    "write_npz",
    "write_recording",
]

_KINDS = ("an Event Camera Dataset folder (events.txt, images.txt + images, calib.txt), "
          "AEDAT4 (.aedat4, DAVIS events and APS frames), evcal's MCAP layout (.mcap), "
          "evcal's .npz, and ROS bags (a ROS 2 folder with metadata.yaml or its .mcap/.db3 "
          "file, a ROS 1 .bag) of event_camera_msgs/EventPacket (libcaer_cmp, libcaer, evt3, "
          "mono), dvs_msgs or prophesee_event_msgs EventArray and sensor_msgs/Image")
_MAGICS = ((b"#!AER-DAT4.0", "aedat4"), (b"\x89MCAP", "mcap"), (b"PK\x03\x04", "npz"))
_SUFFIXES = {".aedat4": "aedat4", ".mcap": "mcap", ".npz": "npz", ".bag": "rosbag1",
             ".db3": "rosbag2"}


def sniff(path: str | os.PathLike[str]) -> str | None:
    """The kind of recording at ``path`` from its content (``"ecd"``, ``"aedat4"``,
    ``"mcap"``, ``"npz"``, ``"rosbag1"``, ``"rosbag2"``), else from its suffix (any case),
    else None.

    A folder with ``metadata.yaml`` (or that file) is a ROS 2 bag, any other folder an Event
    Camera Dataset one; ``#ROSBAG`` starts a ROS 1 bag, ``SQLite format 3`` a ROS 2 sqlite3
    bag; an MCAP file is a ROS 2 bag when its profile is ``ros2`` (or its schemas are
    ``ros2msg``/``ros2idl``, its channels ``cdr``), else evcal's own layout.
    """
    path = Path(path)
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
    return _SUFFIXES.get(path.suffix.lower())


def open_recording(path: str | os.PathLike[str], *, sensor: SensorSize | None = None,
                   events_topic: str | None = None, frames_topic: str | None = None
                   ) -> Recording:
    """Read a recording, choosing the reader by its content (then by its suffix).

    A directory (or its ``events.txt``) is an Event Camera Dataset folder, one with
    ``metadata.yaml`` a ROS 2 bag; files are recognised by their first bytes (AEDAT4's
    ``#!AER-DAT4.0``, the MCAP magic and profile, a zip for ``.npz``, ``#ROSBAG``, SQLite's
    magic), so a misnamed file (``road.AEDAT``, ``rec.bin``) still opens. ``sensor`` is passed
    on (required for an ECD folder without frames or a recognisable ``calib.txt``);
    ``events_topic`` / ``frames_topic`` choose among a ROS bag's topics (see
    :func:`read_rosbag`) and are refused for other kinds.

    Raises
    ------
    RecordingError
        For a path that does not exist, an unknown kind (naming what evcal reads), or
        whatever the reader finds wrong.
    """
    path = Path(path)
    if not path.exists():
        raise RecordingError(f"{path}: no such file or directory")
    kind = sniff(path)
    if kind in ("rosbag1", "rosbag2"):
        return read_rosbag(path, sensor=sensor, events_topic=events_topic,
                           frames_topic=frames_topic)
    if events_topic is not None or frames_topic is not None:
        what = f"a recording of kind {kind!r}" if kind else "not one"
        raise RecordingError(f"{path}: events_topic/frames_topic choose topics of ROS bags; "
                             f"this is {what}")
    if kind == "ecd":
        return read_ecd(path.parent if path.is_file() else path, sensor=sensor)
    if kind == "aedat4":
        return read_aedat4(path, sensor=sensor)
    if kind == "mcap":
        return read_mcap(path, sensor=sensor)
    if kind == "npz":
        return read_npz(path, sensor=sensor)
    if kind == "aedat-other":
        raise RecordingError(f"{path}: an AEDAT file of another version than 4.0 (jAER AEDAT "
                             f"2/3); evcal reads {_KINDS}")
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
