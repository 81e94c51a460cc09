"""Readers and writers of recordings and calibration files.

=================================  ===========================  =====================
kind                               read                         write
=================================  ===========================  =====================
Event Camera Dataset folder        :func:`read_ecd`             :func:`write_ecd`
AEDAT4 (``.aedat4``)               :func:`read_aedat4`          --
evcal MCAP (``.mcap``)             :func:`read_mcap`            :func:`write_mcap`
NumPy archive (``.npz``)           :func:`read_npz`             :func:`write_npz`
=================================  ===========================  =====================

:func:`open_recording` and :func:`write_recording` pick one by the path. Every reader raises
:class:`~evcal.recording.RecordingError` with the path and what was wrong.
"""

from __future__ import annotations

import os
from pathlib import Path

from ..events import SensorSize
from ..recording import Recording, RecordingError
from .aedat4 import read_aedat4
from .calibfile import CalibrationFileError, load_calibration, save_calibration, write_csv
from .ecd import read_ecd, write_ecd
from .mcap_rec import is_ros2_event_mcap, read_mcap, write_mcap
from .npz import read_npz, write_npz
from .wire import WireError, decode_events, decode_frame, encode_events, encode_frame

__all__ = [
    "CalibrationFileError",
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
    "save_calibration",
    "write_csv",
    "write_ecd",
    "write_mcap",
    "write_npz",
    "write_recording",
]

_KINDS = ("an Event Camera Dataset folder (events.txt, images.txt + images, calib.txt), "
          "AEDAT4 (.aedat4, DAVIS events and APS frames), evcal's MCAP layout (.mcap) and "
          "evcal's .npz")
_MAGICS = ((b"#!AER-DAT4.0", "aedat4"), (b"\x89MCAP", "mcap"), (b"PK\x03\x04", "npz"))
_SUFFIXES = {".aedat4": "aedat4", ".mcap": "mcap", ".npz": "npz"}


def sniff(path: str | os.PathLike[str]) -> str | None:
    """The kind of recording at ``path`` from its content (``"ecd"``, ``"aedat4"``,
    ``"mcap"``, ``"npz"``), else from its suffix (any case), else None."""
    path = Path(path)
    if path.is_dir() or (path.is_file() and path.name in ("events.txt", "images.txt")):
        return "ecd"
    try:
        with open(path, "rb") as f:
            head = f.read(16)
    except OSError:
        return None
    for magic, kind in _MAGICS:
        if head.startswith(magic):
            return kind
    if head.startswith(b"#!AER-DAT"):
        return "aedat-other"
    return _SUFFIXES.get(path.suffix.lower())


def open_recording(path: str | os.PathLike[str], *, sensor: SensorSize | None = None
                   ) -> Recording:
    """Read a recording, choosing the reader by its content (then by its suffix).

    A directory (or its ``events.txt``) is an Event Camera Dataset folder; files are recognised
    by their first bytes (AEDAT4's ``#!AER-DAT4.0``, the MCAP magic, a zip for ``.npz``), so a
    misnamed file (``road.AEDAT``, ``rec.bin``) still opens. ``sensor`` is passed on (required
    for an ECD folder without frames or a recognisable ``calib.txt``).

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
    if kind == "ecd":
        return read_ecd(path.parent if path.is_file() else path, sensor=sensor)
    if kind == "aedat4":
        return read_aedat4(path, sensor=sensor)
    if kind == "mcap":
        if is_ros2_event_mcap(path):
            raise RecordingError(
                f"{path}: a ROS 2 bag of event_camera_msgs/msg/EventPacket; evcal reads its "
                "own MCAP layout only (convert the bag first)"
            )
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
