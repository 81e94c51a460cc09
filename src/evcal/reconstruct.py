"""Frame reconstruction by event integration, and its evaluation against the next frames.

A calibration is judged by how well it turns events into intensity: starting from the log of
frame ``k``, every event at a pixel adds its threshold (Wang et al.'s model, as in
:mod:`evcal.lsq`)::

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
from .events import SensorSize, validate_events
from .lsq import log_intensity
from .metrics import METRIC_NAMES, image_metrics
from .recording import Recording

FALLBACK_LOG_OFFSET = 30.0  # DN; used when the calibration carries no usable offset
FULL_SCALE_DN = 255.0


class EvaluationError(ValueError):
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
    return log_start + contrast.astype(np.float64) * sp + bias.astype(np.float64) * se


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
        raise ValueError(
            f"log_start has shape {log_start.shape}, the calibration maps have {cal.shape}"
        )
    h, w = cal.shape
    validate_events(events, SensorSize(h, w), where="integrate")
    return _integrate(log_start, events, cal.contrast, cal.bias)


def to_intensity(L: np.ndarray, log_offset: float) -> np.ndarray:  # noqa: N803 - L is the model
    """Intensity in frame units: ``clip(exp(L) - offset, 0, 255)`` (float64, DN).

    The inverse of :func:`evcal.lsq.log_intensity` on the 8-bit range. (The reference MATLAB
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
        raise ValueError(f"frame times {ft.shape} and event times {et.shape} must be 1-D")
    if ft.size > 1 and (np.diff(ft) <= 0).any():
        raise ValueError("frame times must increase")
    if et.size > 1 and (np.diff(et) < 0).any():
        raise ValueError("event times must be sorted (non-decreasing)")
    if not (math.isfinite(skip_s) and skip_s >= 0):
        raise ValueError(f"skip_s={skip_s!r} must be a number of seconds >= 0")
    if frames_per_image is None and events_per_image is None:
        raise ValueError("give events_per_image or frames_per_image")
    if frames_per_image is not None and int(frames_per_image) < 1:
        raise ValueError(f"frames_per_image={frames_per_image} must be >= 1")
    if frames_per_image is None and int(events_per_image) < 1:  # type: ignore[arg-type]
        raise ValueError(f"events_per_image={events_per_image} must be >= 1")
    n = int(ft.size)
    if n < 2:
        return []
    k0 = int(np.searchsorted(ft, ft[0] + round(skip_s * 1e6), side="left"))
    if frames_per_image is not None:
        step = int(frames_per_image)
        ks = np.arange(k0, n - step, step)
        return [(int(k), int(k) + step) for k in ks]
    need = int(events_per_image)  # type: ignore[arg-type]
    # cum[i]: events before frame i; events in [t_k, t_j) = cum[j] - cum[k] (non-decreasing)
    cum = np.searchsorted(et, ft, side="left")
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
    if log_offset is not None:
        off = float(log_offset)
        if not (math.isfinite(off) and off > 0):
            raise ValueError(f"log_offset={log_offset!r} must be a finite number > 0 (DN)")
        return off, "given"
    off = float(cal.log_offset)
    if math.isfinite(off) and off > 0:
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
) -> EvaluationResult:
    """Reconstruct frames from events with ``cal`` and with DI; score both against the frames.

    For each pair ``(k, j)`` of :func:`select_pairs`: ``L = log(frame_k + offset)``
    (:func:`evcal.lsq.log_intensity`), integrate the events of ``[t_k, t_j)``
    (:func:`integrate`), convert with :func:`to_intensity` and compare with frame ``j`` (as
    float) by :func:`evcal.metrics.image_metrics`. The DI baseline is
    ``Calibration.uniform(shape, di_contrast, 0.0)`` with the same offset and pairs.

    ``log_offset`` (DN) defaults to ``cal.log_offset``; if that is 0 or NaN (a calibration that
    did not estimate it, e.g. a uniform one) :data:`FALLBACK_LOG_OFFSET` = 30 is used, and
    ``result.log_offset_note`` says so.

    Raises :class:`EvaluationError` when the recording has no frames or no pair can be formed.
    """
    assert rec.frames is not None
    frames = rec.frames
    if cal.shape != rec.sensor.shape:
        h, w = cal.shape
        raise EvaluationError(f"calibration is {w}x{h}, the recording's sensor is {rec.sensor}")
    if not (math.isfinite(di_contrast) and di_contrast > 0):
        raise ValueError(f"di_contrast={di_contrast!r} must be a number > 0")
    if len(frames) == 0:
        raise EvaluationError(
            f"the recording has no frames ({rec.n_events} events): nothing to compare against"
        )
    offset, note = _resolve_offset(log_offset, cal)
    t_ev = rec.events["t_us"]
    pairs = select_pairs(frames.t_us, t_ev, events_per_image=events_per_image,
                         frames_per_image=frames_per_image, skip_s=skip_s)
    if not pairs:
        asked = (f"frames_per_image={frames_per_image}" if frames_per_image is not None
                 else f"events_per_image={events_per_image}")
        raise EvaluationError(
            f"no frame pair can be formed: the recording has {len(frames)} frames and "
            f"{rec.n_events} events over {rec.duration_s:.3f} s; asked {asked}, "
            f"skip_s={skip_s}"
        )
    di = Calibration.uniform(cal.shape, di_contrast, 0.0, log_offset=offset)
    bounds = np.searchsorted(t_ev, frames.t_us, side="left")  # first event at or after frame
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
        },
    )


__all__ = [
    "EvaluationError",
    "EvaluationResult",
    "evaluate",
    "integrate",
    "select_pairs",
    "to_intensity",
]
