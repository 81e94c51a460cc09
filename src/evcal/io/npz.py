"""Recordings as NumPy ``.npz`` archives.

Arrays::

    events             structured EVENTS_DTYPE (or the columns t_us, x, y, p instead)
    frame_t_us         int64 (n,)
    frame_images       (n, H, W), uint8 or float32
    frame_exposure_us  int64 (n,)
    sensor             int [height, width]
    metadata_json      0-d str, the recording's metadata as JSON

Files are read with ``allow_pickle=False``: an archive holding Python objects is refused.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

from ..events import EVENTS_DTYPE, SensorSize
from ..recording import Frames, Recording, RecordingError
from ._util import (
    check_sensor_arg,
    file_recording,
    load_npz_arrays,
    metadata_from_json,
    metadata_to_json,
)

_FRAME_KEYS = ("frame_t_us", "frame_images", "frame_exposure_us")


def write_npz(recording: Recording, path: str | os.PathLike[str], *,
              compress: bool = True) -> Path:
    """Write a recording as ``.npz`` (zip-deflated when ``compress``); return the path.

    The path is used as given (NumPy's habit of appending ``.npz`` is avoided).
    """
    path = Path(path)
    frames = recording.frames
    arrays: dict[str, Any] = {
        "events": recording.events,
        "frame_t_us": frames.t_us,
        "frame_images": frames.images,
        "frame_exposure_us": frames.exposure_us,
        "sensor": np.array(recording.sensor.shape, np.int64),
        "metadata_json": np.array(metadata_to_json(recording.metadata)),
    }
    save = np.savez_compressed if compress else np.savez
    with open(path, "wb") as f:
        save(f, **arrays)
    return path


def _events_from_columns(cols: dict[str, np.ndarray], where: str) -> np.ndarray:
    """EVENTS_DTYPE from integer columns, with range checks before any narrowing cast."""
    n = None
    for name in ("t_us", "x", "y", "p"):
        col = cols[name]
        if col.ndim != 1 or (n is not None and col.shape[0] != n):
            raise RecordingError(f"{where}: column {name} has shape {col.shape}, expected "
                                 f"({n if n is not None else 'n'},)")
        n = col.shape[0]
        if col.dtype.kind not in "iub":
            raise RecordingError(f"{where}: column {name} has dtype {col.dtype}, expected "
                                 "integers")
    x, y, p = (cols[k].astype(np.int64) for k in ("x", "y", "p"))
    for name, col in (("x", x), ("y", y)):
        bad = np.flatnonzero((col < 0) | (col > 65535))
        if bad.size:
            raise RecordingError(f"{where}: event {int(bad[0])} has {name}={int(col[bad[0]])}, "
                                 "not a pixel coordinate (0..65535)")
    values = set(np.unique(p).tolist())
    if not (values <= {-1, 1} or values <= {0, 1}):
        raise RecordingError(f"{where}: polarity values {sorted(values)}, expected {{-1, +1}} "
                             "or {0, 1}")
    ev = np.empty(x.shape[0], EVENTS_DTYPE)
    ev["t_us"] = cols["t_us"]
    ev["x"] = x
    ev["y"] = y
    ev["p"] = np.where(p > 0, 1, -1)
    return ev


def read_npz(path: str | os.PathLike[str], *, sensor: SensorSize | None = None) -> Recording:
    """Read a recording ``.npz`` (see the module docstring for the arrays).

    Raises
    ------
    RecordingError
        For a missing, truncated or foreign archive, missing arrays, or wrong dtypes/shapes.
    """
    path = Path(path)
    where = str(path)
    data = load_npz_arrays(path, RecordingError)
    if "sensor" not in data:
        raise RecordingError(f"{path}: no 'sensor' array ([height, width]); arrays: "
                             f"{sorted(data)}")
    s = data["sensor"]
    if s.shape != (2,) or s.dtype.kind not in "iu":
        raise RecordingError(f"{path}: 'sensor' is {s.dtype} {s.shape}, expected 2 integers "
                             "[height, width]")
    try:
        found = SensorSize(height=int(s[0]), width=int(s[1]))
    except ValueError as exc:
        raise RecordingError(f"{path}: {exc}") from None
    found = check_sensor_arg(found, sensor, where)

    if "events" in data:
        ev = data["events"]
        if ev.dtype == EVENTS_DTYPE and ev.ndim == 1:
            events = ev
        elif ev.dtype.names is not None and {"t_us", "x", "y", "p"} <= set(ev.dtype.names):
            events = _events_from_columns({k: ev[k] for k in ("t_us", "x", "y", "p")},
                                          f"{where} events")
        else:
            raise RecordingError(f"{path}: 'events' has dtype {ev.dtype} and shape {ev.shape}, "
                                 f"expected a 1-D array of {EVENTS_DTYPE}")
    elif {"t_us", "x", "y", "p"} <= set(data):
        events = _events_from_columns({k: data[k] for k in ("t_us", "x", "y", "p")}, where)
    else:
        raise RecordingError(f"{path}: no 'events' array and no t_us, x, y, p columns; "
                             f"arrays: {sorted(data)}")

    present = [k for k in _FRAME_KEYS if k in data]
    frames = None
    if present and len(present) != len(_FRAME_KEYS):
        missing = sorted(set(_FRAME_KEYS) - set(present))
        raise RecordingError(f"{path}: frame arrays incomplete, missing {missing}")
    if present:
        imgs = data["frame_images"]
        if imgs.dtype not in (np.uint8, np.float32):
            raise RecordingError(f"{path}: frame_images has dtype {imgs.dtype}, expected "
                                 "uint8 or float32")
        for key in ("frame_t_us", "frame_exposure_us"):
            if data[key].dtype.kind not in "iu":
                raise RecordingError(f"{path}: {key} has dtype {data[key].dtype}, expected "
                                     "integer µs")
        try:
            frames = Frames(t_us=data["frame_t_us"], images=imgs,
                            exposure_us=data["frame_exposure_us"])
        except RecordingError as exc:
            raise RecordingError(f"{path}: {exc}") from None
        if len(frames) == 0:
            frames = None
    meta_arr = data.get("metadata_json")
    metadata: dict[str, Any] = {}
    if meta_arr is not None:
        if meta_arr.shape != () or meta_arr.dtype.kind != "U":
            raise RecordingError(f"{path}: metadata_json is {meta_arr.dtype} {meta_arr.shape}, "
                                 "expected a 0-d string")
        metadata = metadata_from_json(str(meta_arr), where)
    metadata["format"] = "npz"
    metadata["source"] = str(path)
    return file_recording(path, found, events, frames, metadata)
