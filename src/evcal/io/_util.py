"""Small helpers shared by the readers and writers (not public API)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import ErrorReason
from ..events import EVENTS_DTYPE, SensorSize
from ..jsonable import dumps
from ..recording import Frames, Recording, RecordingError
from ._partial import zip_cut


def file_head(path: Path, n: int = 16) -> bytes | None:
    """The first ``n`` bytes of a file (what content sniffing looks at); None if unreadable."""
    try:
        with open(path, "rb") as f:
            return f.read(n)
    except OSError:
        return None


def metadata_to_json(metadata: dict[str, Any]) -> str:
    """Serialise recording metadata; values JSON cannot hold become their ``repr``."""
    return dumps(metadata)


def metadata_from_json(text: str, where: str) -> dict[str, Any]:
    try:
        meta = json.loads(text) if text else {}
    except ValueError as exc:
        raise RecordingError(f"{where}: metadata is not valid JSON ({exc})") from None
    if not isinstance(meta, dict):
        raise RecordingError(f"{where}: metadata JSON is a {type(meta).__name__}, expected "
                             "an object")
    return meta


def check_sensor_arg(found: SensorSize, given: SensorSize | None, where: str) -> SensorSize:
    """The sensor a file declares, checked against the one the caller passed (if any)."""
    if given is not None and given != found:
        raise RecordingError(
            f"{where}: the file declares a {found} sensor, but sensor={given} was given"
        )
    return found


def file_recording(path: str | Path, sensor: SensorSize, events: np.ndarray,
                   frames: Frames | None, metadata: dict[str, Any]) -> Recording:
    """The :class:`Recording` a reader returns (no frames: an empty :class:`Frames`), a check
    it fails named after the file it was read from."""
    try:
        return Recording(sensor=sensor, events=events,
                         frames=frames if frames is not None else Frames.empty(0, 0),
                         metadata=metadata)
    except RecordingError as exc:
        raise RecordingError(f"{path}: {exc}") from None


def load_npz_arrays(path: str | Path, error: type[Exception], what: str = ""
                    ) -> dict[str, np.ndarray]:
    """Every array of the ``.npz`` archive at ``path`` (no pickles), or ``error`` naming the
    problem: no such file, a bare ``.npy``, a truncated or corrupt archive."""
    path = Path(path)
    if not path.is_file():
        raise error(f"{path}: no such file")
    try:
        # the file is ours to close: np.load leaks its own handle when the archive is damaged
        with open(path, "rb") as f:
            z = np.load(f, allow_pickle=False)
            if not hasattr(z, "files"):
                raise error(f"{path}: a single .npy array, not an .npz archive")
            with z:
                return {k: z[k] for k in z.files}
    except error:
        raise
    except Exception as exc:  # zipfile, zlib, OS and format errors of a damaged archive
        cut = zip_cut(path)
        if cut is not None:
            raise error(f"{path}: {cut}", ErrorReason.TRUNCATED) from None
        raise error(f"{path}: cannot read {what or 'as .npz'} (truncated or corrupt?): "
                    f"{type(exc).__name__}: {exc}") from None


def events_sorted(t: np.ndarray, x: np.ndarray, y: np.ndarray, on: np.ndarray
                  ) -> tuple[np.ndarray, int]:
    """Columns packed as evcal events (``on``: True for ON), sorted by time (stable) when
    they are not; with the number of events that were out of order (for the metadata)."""
    events = np.empty(t.shape[0], EVENTS_DTYPE)
    events["t_us"] = t
    events["x"] = x
    events["y"] = y
    events["p"] = np.where(on, 1, -1)
    tt = events["t_us"]
    if tt.size > 1 and (tt[1:] < tt[:-1]).any():
        reordered = int(np.count_nonzero(tt[1:] < np.maximum.accumulate(tt)[:-1]))
        return events[np.argsort(tt, kind="stable")], reordered
    return events, 0
