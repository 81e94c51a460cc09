"""HDF5 recordings of three public layouts, read with ``h5py``: MVSEC, DSEC and v2e.

The layout is told from the datasets present (:func:`hdf5_layout`):

MVSEC (Zhu et al., RA-L 2018; ``*_data.hdf5``)
    ``davis/<camera>/events``: N x 4 float64 rows ``[x, y, t (s, Unix time), p (-1/+1)]``;
    ``davis/<camera>/image_raw``: n x 260 x 346 uint8 APS frames with ``image_raw_ts``
    (float64 s). Cameras ``left`` and ``right`` (``camera=``, default ``left``). The sensor
    is the DAVIS m346's 346x260 (or the frames' size). Times are rounded to µs.
DSEC (Gehrig et al., RA-L 2021; ``events.h5``)
    ``events/x``, ``events/y`` (uint16), ``events/t`` (uint32 µs from ``t_offset``),
    ``events/p`` (uint8 0/1), ``t_offset`` (int64 µs) and ``ms_to_idx``; the sensor is the
    Prophesee Gen3.1's 640x480. DSEC compresses with Blosc: ``hdf5plugin`` registers that
    filter. No frames.
v2e ``--dvs_h5`` (SensorsINI/v2e, ``v2ecore/emulator.py``)
    ``events``: N x 4 uint32 rows ``[t (µs), x, y, p (0/1)]``; when v2e also stored its
    input frames, ``frame`` (n x H x W uint8), ``frame_ts`` (uint32 µs) and ``frame_idx``.
    v2e converts its float32 seconds to µs (``float32(t) * 1e6``), so beyond 16.7 s its
    times are quantised by float32. The file declares no sensor size: it is the frames' size,
    else ``sensor=`` is required.

Events are sorted by time (stable); how many were out of order is
``metadata["reordered_events"]``. Frames have exposure 0 (unknown).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import ErrorReason
from ..events import SensorSize
from ..recording import Frames, Recording, RecordingError
from ._partial import hdf5_cut
from ._util import check_sensor_arg, events_sorted

HDF5_MAGIC = b"\x89HDF\r\n\x1a\n"
MVSEC_SENSOR = SensorSize(height=260, width=346)
DSEC_SENSOR = SensorSize(height=480, width=640)
_DSEC_KEYS = ("events/x", "events/y", "events/t", "events/p")


def _names(f: Any) -> list[str]:
    """Every dataset of the file with its shape, for error messages."""
    found: list[str] = []

    def visit(name: str, obj: Any) -> None:
        if hasattr(obj, "shape") and len(found) < 40:
            found.append(f"{name} {tuple(obj.shape)}")

    f.visititems(visit)
    return found


def _has(f: Any, name: str) -> bool:
    try:
        return name in f and hasattr(f[name], "shape")
    except (KeyError, ValueError):
        return False


def hdf5_layout(f: Any) -> str | None:
    """``"mvsec"``, ``"dsec"`` or ``"v2e"`` from the datasets of an open h5py file."""
    davis: Any = f["davis"] if "davis" in f else None
    if hasattr(davis, "keys") and any(_has(f, f"davis/{c}/events") for c in davis.keys()):
        return "mvsec"
    if all(_has(f, k) for k in _DSEC_KEYS):
        return "dsec"
    if _has(f, "events") and f["events"].ndim == 2 and f["events"].shape[1] == 4:
        return "v2e"
    return None


def _check_columns(where: str, **cols: np.ndarray) -> None:
    n = {k: v.shape for k, v in cols.items()}
    if len({s for s in n.values()}) != 1 or any(len(s) != 1 for s in n.values()):
        raise RecordingError(f"{where}: event columns of different shapes {n}",
                             ErrorReason.TRUNCATED)


def _coords(where: str, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Integer pixel coordinates (float columns must hold whole, non-negative numbers)."""
    out = []
    for name, col in (("x", x), ("y", y)):
        if col.dtype.kind == "f":
            bad = np.flatnonzero(~np.isfinite(col) | (col != np.round(col)) | (col < 0))
            if bad.size:
                i = int(bad[0])
                raise RecordingError(f"{where}: event {i} has {name}={col[i].item()}, not a "
                                     "pixel coordinate", ErrorReason.BAD_VALUES)
        out.append(col.astype(np.int64))
    return out[0], out[1]


def _polarity(where: str, p: np.ndarray, values: tuple[int, int]) -> np.ndarray:
    bad = np.flatnonzero((p != values[0]) & (p != values[1]))
    if bad.size:
        i = int(bad[0])
        raise RecordingError(f"{where}: event {i} has polarity {p[i].item()}, expected "
                             f"{values[0]} or {values[1]} ({bad.size} such events)",
                             ErrorReason.BAD_POLARITY)
    result: np.ndarray = p == values[1]
    return result


def _seconds_to_us(where: str, t: np.ndarray) -> np.ndarray:
    if t.size and not np.isfinite(t).all():
        i = int(np.flatnonzero(~np.isfinite(t))[0])
        raise RecordingError(f"{where}: time {i} is {t[i].item()}", ErrorReason.BAD_VALUES)
    result: np.ndarray = np.rint(np.asarray(t, np.float64) * 1e6).astype(np.int64)
    return result


def _read_mvsec(f: Any, where: str, camera: str | None, sensor: SensorSize | None
                ) -> tuple[SensorSize, np.ndarray, int, Frames | None, dict[str, Any]]:
    cams = sorted(c for c in f["davis"] if _has(f, f"davis/{c}/events"))
    cam = camera if camera is not None else ("left" if "left" in cams else cams[0])
    if cam not in cams:
        raise RecordingError(f"{where}: no camera {cam!r} in this MVSEC file (it has "
                             f"{', '.join(cams)})", ErrorReason.MALFORMED)
    g = f[f"davis/{cam}"]
    raw = np.asarray(g["events"][()])
    if raw.ndim != 2 or raw.shape[1] != 4:
        raise RecordingError(f"{where}: davis/{cam}/events has shape {raw.shape}, expected "
                             "(N, 4) rows [x, y, t, p]", ErrorReason.MALFORMED)
    x, y = _coords(where, raw[:, 0], raw[:, 1])
    on = _polarity(where, raw[:, 3], (-1, 1))
    events, reordered = events_sorted(_seconds_to_us(where, raw[:, 2]), x, y, on)
    frames = None
    found = MVSEC_SENSOR
    if _has(g, "image_raw"):
        images = np.asarray(g["image_raw"][()])
        if not _has(g, "image_raw_ts"):
            raise RecordingError(f"{where}: davis/{cam}/image_raw without image_raw_ts",
                                 ErrorReason.MALFORMED)
        ts = _seconds_to_us(where, np.asarray(g["image_raw_ts"][()], np.float64))
        if images.ndim != 3 or ts.shape != (images.shape[0],):
            raise RecordingError(f"{where}: davis/{cam}/image_raw has shape {images.shape} "
                                 f"and image_raw_ts {ts.shape}", ErrorReason.MALFORMED)
        found = SensorSize(height=images.shape[1], width=images.shape[2])
        frames = Frames(t_us=ts, images=images, exposure_us=np.zeros_like(ts))
    meta = {"camera": cam, "cameras": cams}
    return check_sensor_arg(found, sensor, where), events, reordered, frames, meta


def _read_dsec(f: Any, where: str, sensor: SensorSize | None
               ) -> tuple[SensorSize, np.ndarray, int, Frames | None, dict[str, Any]]:
    x = np.asarray(f["events/x"][()])
    y = np.asarray(f["events/y"][()])
    t = np.asarray(f["events/t"][()])
    p = np.asarray(f["events/p"][()])
    _check_columns(where, x=x, y=y, t=t, p=p)
    offset = int(np.asarray(f["t_offset"][()])) if _has(f, "t_offset") else 0
    xi, yi = _coords(where, x, y)
    events, reordered = events_sorted(t.astype(np.int64) + offset, xi, yi,
                                _polarity(where, p, (0, 1)))
    meta = {"t_offset_us": offset, "has_ms_to_idx": _has(f, "ms_to_idx")}
    return check_sensor_arg(DSEC_SENSOR, sensor, where), events, reordered, None, meta


def _read_v2e(f: Any, where: str, sensor: SensorSize | None
              ) -> tuple[SensorSize, np.ndarray, int, Frames | None, dict[str, Any]]:
    raw = np.asarray(f["events"][()])
    xi, yi = _coords(where, raw[:, 1], raw[:, 2])
    t = raw[:, 0]
    if t.dtype.kind == "f":
        t = np.rint(t)
    events, reordered = events_sorted(t.astype(np.int64), xi, yi,
                                      _polarity(where, raw[:, 3], (0, 1)))
    frames = None
    found = None
    if _has(f, "frame"):
        images = np.asarray(f["frame"][()])
        if images.ndim != 3:
            raise RecordingError(f"{where}: 'frame' has shape {images.shape}, expected "
                                 "(n, H, W)", ErrorReason.MALFORMED)
        found = SensorSize(height=images.shape[1], width=images.shape[2])
        if images.shape[0]:
            if not _has(f, "frame_ts") or f["frame_ts"].shape != (images.shape[0],):
                raise RecordingError(f"{where}: 'frame' ({images.shape[0]} images) without "
                                     "a 'frame_ts' of that length", ErrorReason.MALFORMED)
            ts = np.asarray(f["frame_ts"][()]).astype(np.int64)
            frames = Frames(t_us=ts, images=images, exposure_us=np.zeros_like(ts))
    if found is None:
        if sensor is None:
            raise RecordingError(f"{where}: a v2e events file without frames declares no "
                                 "sensor size; pass sensor= (e.g. --sensor-size 346x260)",
                                 ErrorReason.MALFORMED)
        found = sensor
    return check_sensor_arg(found, sensor, where), events, reordered, frames, {}


def read_hdf5(path: str | os.PathLike[str], *, sensor: SensorSize | None = None,
              camera: str | None = None) -> Recording:
    """Read an MVSEC, DSEC or v2e HDF5 recording (see the module docstring).

    Parameters
    ----------
    path : path
        An HDF5 file.
    sensor : SensorSize, optional
        Checked against the size the layout implies; required for a v2e file without frames.
    camera : str, optional
        The MVSEC camera (``"left"``, the default, or ``"right"``); refused for the others.

    Raises
    ------
    RecordingError
        For a file that is not HDF5 or is damaged, a layout evcal does not know (listing the
        datasets found), missing or inconsistent datasets, bad polarities or coordinates.
    """
    path = Path(path)
    where = str(path)
    import h5py

    try:
        import hdf5plugin  # noqa: F401 - registers Blosc and other filters DSEC files use
    except ImportError:  # pragma: no cover - a core dependency; reading Blosc data fails
        pass
    if not path.is_file():
        raise RecordingError(f"{where}: no such file")
    cut = hdf5_cut(path)
    if cut is not None:
        raise RecordingError(f"{where}: {cut}", ErrorReason.TRUNCATED)
    try:
        f = h5py.File(path, "r")
    except OSError as exc:
        raise RecordingError(f"{where}: cannot open as HDF5 (truncated or corrupt?): {exc}",
                             ErrorReason.TRUNCATED) from None
    with f:
        layout = hdf5_layout(f)
        if camera is not None and layout != "mvsec":
            raise RecordingError(f"{where}: camera= chooses an MVSEC camera; this file is "
                                 f"{layout or 'no known layout'}", ErrorReason.MALFORMED)
        try:
            if layout == "mvsec":
                found, events, reordered, frames, meta = _read_mvsec(f, where, camera, sensor)
            elif layout == "dsec":
                found, events, reordered, frames, meta = _read_dsec(f, where, sensor)
            elif layout == "v2e":
                found, events, reordered, frames, meta = _read_v2e(f, where, sensor)
            else:
                names = _names(f)
                raise RecordingError(
                    f"{where}: an HDF5 file of no layout evcal knows; it has "
                    f"{', '.join(names) if names else 'no datasets'}. evcal reads MVSEC "
                    "(davis/<camera>/events), DSEC (events/x, y, t, p) and v2e --dvs_h5 "
                    "(events N x 4)", ErrorReason.MALFORMED)
        except (OSError, KeyError) as exc:  # a damaged dataset or a missing filter
            hint = (" (install hdf5plugin for Blosc-compressed files such as DSEC)"
                    if "filter" in str(exc).lower() else " (truncated or corrupt?)")
            raise RecordingError(f"{where}: cannot read the {layout} datasets{hint}: {exc}",
                                 ErrorReason.TRUNCATED) from None
    metadata = {"format": f"hdf5-{layout}", "source": where, "reordered_events": reordered,
                **meta}
    try:
        return Recording(sensor=found, events=events,
                         frames=frames if frames is not None else Frames.empty(*found.shape),
                         metadata=metadata)
    except RecordingError as exc:
        raise RecordingError(f"{where}: {exc}", exc.reason) from None
