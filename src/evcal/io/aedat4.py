"""AEDAT4 files (iniVation DV) through the ``aedat`` decoder: events and APS frames.

Only the first event stream and the first frame stream are read; IMU and trigger streams are
skipped. The sensor size is the event stream's ``width x height``.

Real DAVIS recordings occasionally hold a few events out of time order across packets. They
are sorted (stable, so equal times keep their file order) and their number is recorded in
``metadata["reordered_events"]`` (0 for a file in order) instead of failing.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

from ..events import EVENTS_DTYPE, SensorSize
from ..recording import Frames, Recording, RecordingError
from ._util import check_sensor_arg

# ITU-R BT.601 luma, as Pillow's "L" conversion.
_LUMA = np.array([0.299, 0.587, 0.114])


def _gray(pixels: np.ndarray) -> np.ndarray:
    """A uint8 ``[y, x]`` image from ``(H, W)`` gray or ``(H, W, k)`` colour pixels."""
    if pixels.ndim == 2:
        return np.asarray(pixels, np.uint8)
    if pixels.ndim == 3 and pixels.shape[2] == 1:
        return np.asarray(pixels[:, :, 0], np.uint8)
    if pixels.ndim == 3 and pixels.shape[2] >= 3:
        luma = pixels[:, :, :3].astype(np.float64) @ _LUMA
        result: np.ndarray = np.clip(np.rint(luma), 0, 255).astype(np.uint8)
        return result
    if pixels.ndim == 3 and pixels.shape[2] == 2:  # gray + alpha
        return np.asarray(pixels[:, :, 0], np.uint8)
    raise ValueError(f"pixels of shape {pixels.shape} are not an image")


def _frame_time(frame: dict[str, Any]) -> tuple[int, int]:
    """``(t_us, exposure_us)``: the middle of the exposure when its stamps are present."""
    b, e = frame.get("exposure_begin_t"), frame.get("exposure_end_t")
    if b is not None and e is not None and int(e) >= int(b) > 0:
        return (int(b) + int(e)) // 2, int(e) - int(b)
    return int(frame["t"]), 0


def events_from_packets(chunks: list[np.ndarray]) -> tuple[np.ndarray, int]:
    """Concatenate the decoder's event packets (``t`` u8, ``x``, ``y``, ``on``) once.

    Returns the events as EVENTS_DTYPE sorted by time (stable) and the number of late events,
    those earlier than an event before them in the file (0 when the file is in order).
    """
    if not chunks:
        return np.zeros(0, EVENTS_DTYPE), 0
    raw = np.concatenate(chunks)
    events = np.empty(raw.shape[0], EVENTS_DTYPE)
    events["t_us"] = raw["t"].astype(np.int64)
    events["x"] = raw["x"]
    events["y"] = raw["y"]
    events["p"] = np.where(raw["on"], 1, -1)
    t = events["t_us"]
    if t.size > 1 and (t[1:] < t[:-1]).any():
        reordered = int(np.count_nonzero(t[1:] < np.maximum.accumulate(t)[:-1]))
        return events[np.argsort(t, kind="stable")], reordered
    return events, 0


def read_aedat4(path: str | os.PathLike[str], *, sensor: SensorSize | None = None) -> Recording:
    """Read events and frames of an AEDAT4 file.

    Parameters
    ----------
    path : path
        An ``.aedat4`` file.
    sensor : SensorSize, optional
        Checked against the size the file declares (an error when they differ); the file
        must declare one.

    Returns
    -------
    Recording
        Times are the camera's µs timestamps (usually µs since the Unix epoch). Frame times
        are the middle of the exposure, ``exposure_us = end - begin``. ``metadata`` holds
        ``format``, ``source``, ``reordered_events`` and ``streams``.

    Raises
    ------
    RecordingError
        For a missing, truncated or undecodable file (naming the path and the packet), a file
        without an event or frame stream, or frames of another size than the sensor.
    """
    path = Path(path)
    import aedat  # the Rust decoder; imported here so the rest of evcal works without it

    if not path.is_file():
        raise RecordingError(f"{path}: no such file")
    try:
        decoder = aedat.Decoder(str(path))
        streams = decoder.id_to_stream()
    except Exception as exc:  # the decoder raises RuntimeError with the OS/format message
        raise RecordingError(f"{path}: cannot open as AEDAT4: {exc}") from None
    event_ids = sorted(i for i, s in streams.items() if s.get("type") == "events")
    frame_ids = sorted(i for i, s in streams.items() if s.get("type") == "frame")
    if not event_ids and not frame_ids:
        kinds = sorted({str(s.get("type")) for s in streams.values()})
        raise RecordingError(f"{path}: no event or frame stream (streams: {kinds})")
    declared = streams[event_ids[0] if event_ids else frame_ids[0]]
    try:
        found = SensorSize(height=int(declared["height"]), width=int(declared["width"]))
    except (KeyError, TypeError, ValueError) as exc:
        raise RecordingError(f"{path}: the stream does not declare a valid sensor size "
                             f"({exc})") from None
    found = check_sensor_arg(found, sensor, str(path))
    ev_id = event_ids[0] if event_ids else None
    fr_id = frame_ids[0] if frame_ids else None

    chunks: list[np.ndarray] = []
    frame_t: list[int] = []
    frame_exp: list[int] = []
    images: list[np.ndarray] = []
    k = -1
    try:
        for k, packet in enumerate(decoder):  # noqa: B007 - k names the packet on error
            sid = packet.get("stream_id")
            if sid == ev_id and "events" in packet:
                if packet["events"].size:
                    chunks.append(packet["events"])
            elif sid == fr_id and "frame" in packet:
                frame = packet["frame"]
                image = _gray(np.asarray(frame["pixels"]))
                if image.shape != found.shape:
                    h, w = image.shape
                    raise RecordingError(
                        f"{path}: frame {len(images)} has shape ({h}, {w}) (a {w}x{h} image), "
                        f"the sensor is {found}"
                    )
                t_us, exp_us = _frame_time(frame)
                frame_t.append(t_us)
                frame_exp.append(exp_us)
                images.append(image)
    except RecordingError:
        raise
    except Exception as exc:
        raise RecordingError(f"{path}: decoding failed after {k + 1} packets "
                             f"(truncated or corrupt file?): {exc}") from None

    events, reordered = events_from_packets(chunks)
    frames = None
    if images:
        try:
            frames = Frames(t_us=np.array(frame_t, np.int64), images=np.stack(images),
                            exposure_us=np.array(frame_exp, np.int64))
        except RecordingError as exc:
            raise RecordingError(f"{path}: {exc}") from None
    metadata = {
        "format": "aedat4",
        "source": str(path),
        "reordered_events": reordered,
        "streams": {str(i): dict(s) for i, s in streams.items()},
    }
    try:
        return Recording(sensor=found, events=events,
                         frames=frames if frames is not None else Frames.empty(0, 0),
                         metadata=metadata)
    except RecordingError as exc:
        raise RecordingError(f"{path}: {exc}") from None
