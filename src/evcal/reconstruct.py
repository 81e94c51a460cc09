"""Frame reconstruction by event integration, and its evaluation against the next frames.

A calibration is judged by how well it turns events into intensity: starting from the log of
frame ``k``, every event at a pixel adds its threshold (Wang et al.'s model, as in
:mod:`evcal.solver`)::

    L(t_j) = L(t_k) + c * SP + b * SE        SP = ON - OFF,  SE = ON + OFF  in [t_k, t_j)

(an ON event adds ``c + b``, an OFF event ``-(c - b)``), with ``L = log(I + offset)``. The
reconstruction ``I = exp(L) - offset`` is compared with frame ``j``. Direct integration (DI),
the uncalibrated baseline, uses ``c = 0.1``, ``b = 0`` everywhere.

Events at ``t_us`` equal to a frame's time belong after that frame (``[t_k, t_j)``), as in
:func:`evcal.accumulate.frame_snapshots`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .calibration import DEFAULT_CONTRAST, Calibration
from .errors import ConfigError, ErrorReason, EvcalError
from .events import SensorSize, empty_events, validate_events
from .metrics import METRIC_NAMES, image_metrics, psnr
from .recording import Recording
from .solver import log_intensity
from .stream import frame_cuts

FALLBACK_LOG_OFFSET = 30.0  # DN; used when the calibration carries no usable offset
FULL_SCALE_DN = 255.0


class EvaluationError(EvcalError):
    """The recording cannot support the requested evaluation (no frames, too few events...)."""


# ----------------------------------------------------------------------------------------
# integration


def _sums(events: np.ndarray, height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
    """Per-pixel ``SP`` (net polarity) and ``SE`` (event count) maps ``[H, W]``, float64."""
    n_pix = height * width
    idx = events["y"].astype(np.int64) * width + events["x"].astype(np.int64)
    sp = np.bincount(idx, weights=events["p"].astype(np.float64), minlength=n_pix)
    se = np.bincount(idx, minlength=n_pix).astype(np.float64)
    return sp.reshape(height, width), se.reshape(height, width)


def _integrate(log_start: np.ndarray, events: np.ndarray, contrast: np.ndarray,
               bias: np.ndarray) -> np.ndarray:
    h, w = log_start.shape
    sp, se = _sums(events, h, w)
    result: np.ndarray = log_start + contrast.astype(np.float64) * sp + bias.astype(np.float64) * se
    return result


def integrate(log_start: np.ndarray, events: np.ndarray, cal: Calibration) -> np.ndarray:
    """Integrate events onto a log-intensity image: ``L = L_start + c * SP + b * SE``.

    Parameters
    ----------
    log_start : [H, W] float
        Log intensity ``log(I + offset)`` at the start (e.g. of a frame).
    events : EVENTS_DTYPE array
        The events to integrate (every one of them; select the time range beforehand).
        Coordinates must lie inside the ``H x W`` sensor.
    cal : Calibration
        Per-pixel contrast ``c`` and bias ``b`` maps of shape ``[H, W]``.

    Returns
    -------
    [H, W] float64 log intensity after the events.

    Examples
    --------
    >>> from evcal.events import make_events
    >>> cal = Calibration.uniform((1, 2), 0.2, 0.05)
    >>> ev = make_events([0, 1, 2], [0, 0, 1], [0, 0, 0], [1, 1, -1])
    >>> integrate(np.zeros((1, 2)), ev, cal).round(6).tolist()  # 2 (c + b), -(c - b)
    [[0.5, -0.15]]
    """
    log_start = np.asarray(log_start, np.float64)
    if log_start.shape != cal.shape:
        raise EvaluationError(
            f"log_start has shape {log_start.shape}, the calibration maps have {cal.shape}"
        )
    h, w = cal.shape
    validate_events(events, SensorSize(h, w), where="integrate")
    return _integrate(log_start, events, cal.contrast, cal.bias)


def to_intensity(L: np.ndarray, log_offset: float) -> np.ndarray:  # noqa: N803 - L is the model
    """Intensity in frame units: ``clip(exp(L) - offset, 0, 255)`` (float64, DN).

    The inverse of :func:`evcal.solver.log_intensity` on the 8-bit range. (The reference MATLAB
    code also rounds to uint8; we keep the float values.)
    """
    return np.clip(np.exp(np.asarray(L, np.float64)) - float(log_offset), 0.0, FULL_SCALE_DN)


# ----------------------------------------------------------------------------------------
# which frames to compare


def select_pairs(
    frames_t_us: np.ndarray,
    event_t_us: np.ndarray,
    *,
    events_per_image: int | None = 500_000,
    frames_per_image: int | None = None,
    skip_s: float = 0.0,
) -> list[tuple[int, int]]:
    """Frame pairs ``(k, j)``, ``j > k``: integrate the events of ``[t_k, t_j)`` from frame ``k``.

    - ``frames_per_image=n`` (takes precedence when given): ``j = k + n``.
    - otherwise ``events_per_image=N``: ``j`` is the first frame with at least ``N`` events in
      ``[t_k, t_j)``. The paper integrated 500k events per reconstruction; ending at a frame
      (instead of exactly at the N-th event) gives a reference image for the end time. A pair
      the recording has not enough events (or frames) left for is dropped.

    The first pair starts at the first frame at least ``skip_s`` seconds after frame 0; each
    next pair starts where the previous one ended (``k_next = j``), so pairs do not overlap and
    every event is integrated at most once.

    Parameters
    ----------
    frames_t_us : increasing int64 frame times (µs).
    event_t_us : non-decreasing int64 event times (µs).

    Examples
    --------
    >>> select_pairs(np.array([0, 10, 20, 30]), np.arange(30), events_per_image=15)
    [(0, 2)]
    >>> select_pairs(np.array([0, 10, 20, 30]), np.arange(30), frames_per_image=1, skip_s=1e-5)
    [(1, 2), (2, 3)]
    """
    ft = np.asarray(frames_t_us, np.int64)
    et = np.asarray(event_t_us, np.int64)
    if ft.ndim != 1 or et.ndim != 1:
        raise EvaluationError(f"frame times {ft.shape} and event times {et.shape} must be 1-D")
    if ft.size > 1 and (np.diff(ft) <= 0).any():
        raise EvaluationError("frame times must increase", ErrorReason.UNSORTED)
    if et.size > 1 and (np.diff(et) < 0).any():
        raise EvaluationError("event times must be sorted (non-decreasing)", ErrorReason.UNSORTED)
    if not (math.isfinite(skip_s) and skip_s >= 0):
        raise ConfigError(f"skip_s={skip_s!r} must be a number of seconds >= 0")
    if frames_per_image is None and events_per_image is None:
        raise ConfigError("give events_per_image or frames_per_image")
    if frames_per_image is not None and int(frames_per_image) < 1:
        raise ConfigError(f"frames_per_image={frames_per_image} must be >= 1")
    if frames_per_image is None and events_per_image is not None and int(events_per_image) < 1:
        raise ConfigError(f"events_per_image={events_per_image} must be >= 1")
    n = int(ft.size)
    if n < 2:
        return []
    k0 = int(np.searchsorted(ft, ft[0] + round(skip_s * 1e6), side="left"))
    if frames_per_image is not None:
        step = int(frames_per_image)
        ks = np.arange(k0, n - step, step)
        return [(int(k), int(k) + step) for k in ks]
    assert events_per_image is not None  # checked above
    need = int(events_per_image)
    # cum[i]: events before frame i; events in [t_k, t_j) = cum[j] - cum[k] (non-decreasing)
    cum = frame_cuts(et, ft)
    pairs: list[tuple[int, int]] = []
    k = k0
    while k < n - 1:
        j = int(np.searchsorted(cum, cum[k] + need, side="left"))  # > k since need >= 1
        if j >= n:
            break
        pairs.append((k, j))
        k = j
    return pairs


# ----------------------------------------------------------------------------------------
# evaluation


@dataclass(frozen=True)
class EvaluationResult:
    """Per-image metrics of a calibration and of the DI baseline on the same frame pairs.

    ``per_image[i]`` holds ``k``, ``j``, ``t_start_us``, ``t_end_us``, ``n_events`` and two
    metric dicts, ``"calibrated"`` and ``"di"`` (keys of :func:`evcal.metrics.image_metrics`).
    """

    n_images: int
    per_image: list[dict[str, Any]]
    log_offset: float
    log_offset_note: str
    params: dict[str, Any] = field(default_factory=dict)

    def summary(self) -> dict[str, Any]:
        """Means over the images; ``gain_db`` is the mean of ``psnr(calibrated) - psnr(di)``.

        A perfect reconstruction has infinite PSNR, which makes the mean infinite too.
        """
        out: dict[str, Any] = {"n_images": self.n_images}
        for method in ("calibrated", "di"):
            out[method] = {
                name: float(np.mean([im[method][name] for im in self.per_image]))
                for name in METRIC_NAMES
            }
        out["gain_db"] = float(np.mean(
            [im["calibrated"]["psnr"] - im["di"]["psnr"] for im in self.per_image]
        ))
        out["log_offset"] = self.log_offset
        return out


def _resolve_offset(log_offset: float | None, cal: Calibration) -> tuple[float, str]:
    """The offset to integrate with: given, else the calibration's, else (unknown: NaN) the
    fallback. 0 is an offset like any other (``log(DN)``), honoured everywhere."""
    if log_offset is not None:
        off = float(log_offset)
        if not (math.isfinite(off) and off >= 0):
            raise ConfigError(f"log_offset={log_offset!r} must be a finite number >= 0 (DN)")
        return off, "given"
    off = float(cal.log_offset)
    if math.isfinite(off) and off >= 0:
        return off, "from the calibration"
    return FALLBACK_LOG_OFFSET, (
        f"the calibration's log_offset is {cal.log_offset!r}; used {FALLBACK_LOG_OFFSET:g}"
    )


def evaluate(
    rec: Recording,
    cal: Calibration,
    *,
    events_per_image: int | None = 500_000,
    frames_per_image: int | None = None,
    skip_s: float = 0.0,
    log_offset: float | None = None,
    di_contrast: float = DEFAULT_CONTRAST,
    adapt_events_per_image: bool = True,
    fill_invalid: bool = True,
) -> EvaluationResult:
    """Reconstruct frames from events with ``cal`` and with DI; score both against the frames.

    For each pair ``(k, j)`` of :func:`select_pairs`: ``L = log(frame_k + offset)``
    (:func:`evcal.solver.log_intensity`), integrate the events of ``[t_k, t_j)``
    (:func:`integrate`), convert with :func:`to_intensity` and compare with frame ``j`` (as
    float) by :func:`evcal.metrics.image_metrics`. The DI baseline is
    ``Calibration.uniform(shape, di_contrast, 0.0)`` with the same offset and pairs.

    A recording too short for one image of ``events_per_image`` events gets about 4 images of
    fewer events instead (``adapt_events_per_image``; ``params["events_per_image_note"]`` says
    so).

    ``log_offset`` (DN) defaults to ``cal.log_offset``, 0 included; if that is unknown (NaN: a
    calibration that does not say, e.g. a uniform one or OffE's) :data:`FALLBACK_LOG_OFFSET`
    = 30 is used, and ``result.log_offset_note`` says so.

    Pixels the calibration marks invalid carry its defaults (c = 0.1, b = 0), a marker rather
    than an estimate: with ``fill_invalid`` they are integrated with the median ``c`` and
    ``b`` of its valid pixels instead (``params["filled_invalid_pixels"]`` counts them).

    Raises :class:`EvaluationError` when the recording has no frames or no pair can be formed.
    """
    frames = rec.frames
    n_filled = 0
    if fill_invalid:
        filled = cal.with_invalid_filled()
        n_filled = 0 if filled is cal else int((~cal.valid).sum())
        cal = filled
    if cal.shape != rec.sensor.shape:
        h, w = cal.shape
        raise EvaluationError(f"calibration is {w}x{h}, the recording's sensor is {rec.sensor}")
    if not (math.isfinite(di_contrast) and di_contrast > 0):
        raise ConfigError(f"di_contrast={di_contrast!r} must be a number > 0")
    if len(frames) == 0:
        raise EvaluationError(
            f"the recording has no frames ({rec.n_events} events): nothing to compare against"
        )
    offset, note = _resolve_offset(log_offset, cal)
    t_ev = rec.events["t_us"]
    pairs = select_pairs(frames.t_us, t_ev, events_per_image=events_per_image,
                         frames_per_image=frames_per_image, skip_s=skip_s)
    adapted = ""
    if not pairs and frames_per_image is None and events_per_image is not None \
            and adapt_events_per_image:
        # a short recording: fewer events per image, so that it gives about 4 images
        cuts = frame_cuts(t_ev, frames.t_us)
        k0 = int(np.searchsorted(frames.t_us, frames.t_us[0] + round(skip_s * 1e6)))
        available = int(cuts[-1] - cuts[min(k0, len(cuts) - 1)])
        if available >= 4:
            smaller = max(1, available // 4)
            pairs = select_pairs(frames.t_us, t_ev, events_per_image=smaller,
                                 frames_per_image=None, skip_s=skip_s)
            adapted = (f"the recording holds {available} events between its frames, fewer "
                       f"than events_per_image={events_per_image}: used {smaller} per image")
            events_per_image = smaller
    if not pairs:
        asked = (f"frames_per_image={frames_per_image}" if frames_per_image is not None
                 else f"events_per_image={events_per_image}")
        raise EvaluationError(
            f"no frame pair can be formed: the recording has {len(frames)} frames and "
            f"{rec.n_events} events over {rec.duration_s:.3f} s; asked {asked}, "
            f"skip_s={skip_s}"
        )
    di = Calibration.uniform(cal.shape, di_contrast, 0.0, log_offset=offset)
    bounds = frame_cuts(t_ev, frames.t_us)  # first event at or after each frame
    per_image: list[dict[str, Any]] = []
    for k, j in pairs:
        ev = rec.events[bounds[k]:bounds[j]]
        l0 = log_intensity(frames.images[k], offset)
        ref = np.asarray(frames.images[j], np.float64)
        # the event sums are shared by both reconstructions
        sp, se = _sums(ev, *cal.shape)
        item: dict[str, Any] = {
            "k": int(k),
            "j": int(j),
            "t_start_us": int(frames.t_us[k]),
            "t_end_us": int(frames.t_us[j]),
            "n_events": int(ev.size),
        }
        for name, c in (("calibrated", cal), ("di", di)):
            L = l0 + c.contrast.astype(np.float64) * sp + c.bias.astype(np.float64) * se  # noqa: N806
            item[name] = image_metrics(to_intensity(L, offset), ref)
        per_image.append(item)
    return EvaluationResult(
        n_images=len(per_image),
        per_image=per_image,
        log_offset=offset,
        log_offset_note=note,
        params={
            "events_per_image": events_per_image,
            "frames_per_image": frames_per_image,
            "skip_s": skip_s,
            "di_contrast": di_contrast,
            "method": cal.method,
            "events_per_image_note": adapted,
            "filled_invalid_pixels": n_filled,
        },
    )


# ----------------------------------------------------------------------------------------
# streaming evaluation (the live service's reconstructions)


@dataclass(frozen=True)
class Reconstruction:
    """One reconstruction of a live stream: both integrations and the reference frame (DN,
    float64 ``[H, W]``) with their PSNR (dB; ``inf`` for a perfect match)."""

    t_start_us: int
    t_end_us: int
    n_events: int
    calibrated: np.ndarray
    di: np.ndarray
    reference: np.ndarray
    psnr_calibrated_db: float
    psnr_di_db: float

    @property
    def psnr_gain_db(self) -> float:
        return self.psnr_calibrated_db - self.psnr_di_db


class StreamingEvaluator:
    """:func:`evaluate` for a stream: reconstructions from frames as they arrive.

    Feed it, in stream order, calibrations (:meth:`calibration`), event chunks
    (:meth:`events`) and frames (:meth:`frame`). Once a calibration is known, at most every
    ``period_us`` of sensor time a window opens at a frame; after ``window_frames`` more frames
    the events of ``[t_start, t_end)`` are integrated from the opening frame with the latest
    calibration and with DI (same offset) and both are scored against the closing frame:
    :meth:`frame` returns the :class:`Reconstruction`. A window holding more than
    ``max_events`` events is abandoned (bounded memory); :meth:`discard` abandons the open one
    (the caller lost part of the stream).
    """

    def __init__(self, shape: tuple[int, int], *, period_us: int = 2_000_000,
                 window_frames: int = 5, max_events: int = 5_000_000,
                 di_contrast: float = DEFAULT_CONTRAST) -> None:
        if window_frames < 1 or period_us < 0 or max_events < 1:
            raise ConfigError(f"window_frames={window_frames} must be >= 1, period_us="
                              f"{period_us} >= 0, max_events={max_events} >= 1")
        self.shape = (int(shape[0]), int(shape[1]))
        self.period_us = int(period_us)
        self.window_frames = int(window_frames)
        self.max_events = int(max_events)
        self.di_contrast = float(di_contrast)
        self._cal: Calibration | None = None
        self._start: np.ndarray | None = None  # log intensity of the opening frame
        self._t0_us = 0
        self._frames = 0
        self._events: list[np.ndarray] = []
        self._n = 0
        self.last_t_us: int | None = None  # end of the latest reconstruction
        self.abandoned = 0

    def calibration(self, cal: Calibration) -> None:
        if cal.shape != self.shape:
            raise EvaluationError(f"calibration is {cal.shape}, the stream is {self.shape}")
        self._cal = cal

    def events(self, events: np.ndarray) -> None:
        if self._start is None or events.size == 0:
            return
        if self._n + events.size > self.max_events:
            self.discard()  # too busy for a bounded window: skip this one
            return
        self._events.append(events)
        self._n += int(events.size)

    def discard(self) -> None:
        if self._start is not None:
            self.abandoned += 1
        self._start, self._events, self._n = None, [], 0

    def frame(self, t_us: int, image: np.ndarray) -> Reconstruction | None:
        cal = self._cal
        if cal is None:
            return None
        if self._start is not None:
            self._frames += 1
            if self._frames >= self.window_frames:
                return self._finish(int(t_us), image, cal)
            return None
        due = self.last_t_us is None or t_us - self.last_t_us >= self.period_us
        if due:
            self._start = log_intensity(np.asarray(image), cal.log_offset).reshape(self.shape)
            self._t0_us = int(t_us)
            self._frames = 0
            self._events, self._n = [], 0
        return None

    def _finish(self, t_us: int, image: np.ndarray, cal: Calibration) -> Reconstruction:
        assert self._start is not None
        ev = np.concatenate(self._events) if self._events else empty_events()
        ev = ev[(ev["t_us"] >= self._t0_us) & (ev["t_us"] < t_us)]
        start, t0 = self._start, self._t0_us
        self._start, self._events, self._n = None, [], 0
        self.last_t_us = t_us
        ref = np.asarray(image, np.float64)
        if np.asarray(image).dtype.kind == "f" and ref.size and ref.max() <= 1.0:
            ref = ref * FULL_SCALE_DN  # float frames in [0, 1]
        sp, se = _sums(ev, *self.shape)
        di = Calibration.uniform(self.shape, self.di_contrast, 0.0, log_offset=cal.log_offset)
        out = {}
        for name, c in (("calibrated", cal.with_invalid_filled()), ("di", di)):
            L = start + c.contrast.astype(np.float64) * sp + c.bias.astype(np.float64) * se  # noqa: N806
            out[name] = to_intensity(L, cal.log_offset)
        return Reconstruction(t0, t_us, int(ev.size), out["calibrated"], out["di"], ref,
                              psnr(out["calibrated"], ref, FULL_SCALE_DN),
                              psnr(out["di"], ref, FULL_SCALE_DN))


__all__ = [
    "EvaluationError",
    "EvaluationResult",
    "Reconstruction",
    "StreamingEvaluator",
    "evaluate",
    "integrate",
    "select_pairs",
    "to_intensity",
]
