"""Stated standard errors checked against the recording itself: the split-half scale.

An estimator's standard error is a model of its noise, and the model can be wrong for a
given recording (OnEI's counts the frames' residuals as noise; on frames without read noise,
such as a frame-driven simulator's, they are mostly not, and its errors come out about twice
the real ones). Without the true maps the errors can still be checked: calibrate the
recording's two halves in time apart (the frames split at the middle one, each half with the
events between its frames, both at the full run's log offset), and for every pixel valid and
normal in both, ``d = x1 - x2`` should spread as ``sqrt(s1^2 + s2^2)``. The halves' noises
are independent (they share one frame), so ``z = d / sqrt(s1^2 + s2^2)`` has unit variance
when the errors are right; its scale is read robustly as ``sqrt(median(z^2) / 0.4549)``
(the median of a chi-square with one degree of freedom), and the full run's errors are
multiplied by it, per map.

What this cannot see is an error both halves share: a bias of every pixel alike (a wrong
log offset, a response the model does not have) cancels in ``d``. The scale corrects the
errors' size, not their model; it is applied only with at least :data:`MIN_PIXELS` pixels
in both halves (fewer give a scale too noisy to trust) and kept within
:data:`SCALE_RANGE`. Pure numpy; the halves are calibrated by whoever calls
:func:`split_half_scale` (:func:`evcal.estimators.calibrate`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from .calibration import Calibration, Special
from .errors import CalibrationError
from .recording import Recording

# pixels valid and normal in both halves below which no scale is applied: the relative
# error of a median-of-chi-square scale at n pixels is about 1.2 / sqrt(n) (12 % at 100)
MIN_PIXELS = 100
# a scale outside this says the halves disagree for a reason other than noise
SCALE_RANGE = (0.2, 5.0)
# the median of a chi-square with one degree of freedom: a z-score's square with the right
# standard error has this median
CHI2_1_MEDIAN = 0.454936


@dataclass(frozen=True)
class SplitHalfScale:
    """The factors the full run's stated errors of ``c`` and ``b`` are multiplied by (1.0
    when not measured), the pixels they were read from, and why none was applied."""

    contrast: float = 1.0
    bias: float = 1.0
    pixels: int = 0
    reason: str = ""

    @property
    def applied(self) -> bool:
        return not self.reason

    def to_dict(self) -> dict[str, Any]:
        return {"method": "split-half", "contrast": self.contrast, "bias": self.bias,
                "pixels": self.pixels,
                "applied": self.applied, **({"reason": self.reason} if self.reason else {})}


def halves(rec: Recording) -> tuple[Recording, Recording]:
    """The recording's first and second half in time: its frames split at the middle frame
    (both halves hold it), each with the events between its first and last frame."""
    k = len(rec.frames)
    if k < 4:
        raise CalibrationError(f"{k} frames: two halves need at least 4")
    return rec.frame_window(0, k // 2), rec.frame_window(k // 2, k - 1)


def _scale(a: Calibration, b: Calibration, name: str, both: np.ndarray) -> tuple[float, int]:
    sa = getattr(a, f"stderr_{name}").astype(np.float64)
    sb = getattr(b, f"stderr_{name}").astype(np.float64)
    ok = both & np.isfinite(sa) & np.isfinite(sb) & (sa > 0) & (sb > 0)
    n = int(ok.sum())
    if n == 0:
        return float("nan"), 0
    d = getattr(a, name)[ok].astype(np.float64) - getattr(b, name)[ok].astype(np.float64)
    z2 = d * d / (sa[ok] ** 2 + sb[ok] ** 2)
    return float(np.sqrt(np.median(z2) / CHI2_1_MEDIAN)), n


def scale_of(first: Calibration, second: Calibration) -> SplitHalfScale:
    """The split-half scale of two calibrations of one sensor's two halves (see the module
    doc), or a scale of 1 with the reason it was not measured."""
    if first.shape != second.shape:
        raise CalibrationError(f"halves of different shapes: {first.shape}, {second.shape}")
    both = (first.valid & second.valid & (first.special == Special.NORMAL)
            & (second.special == Special.NORMAL))
    sc, n_c = _scale(first, second, "contrast", both)
    sb, n_b = _scale(first, second, "bias", both)
    n = min(n_c, n_b)
    if n < MIN_PIXELS:
        return SplitHalfScale(pixels=n, reason=f"{n} pixels valid with stated errors in both "
                              f"halves ({MIN_PIXELS} needed)")
    lo, hi = SCALE_RANGE
    if not (lo <= sc <= hi and lo <= sb <= hi):
        return SplitHalfScale(pixels=n, reason=f"the halves' scale (c {sc:.3g}, b {sb:.3g}) "
                              f"is outside {lo:g}-{hi:g}: they differ by more than noise")
    return SplitHalfScale(sc, sb, n)


def split_half_scale(rec: Recording, full: Calibration,
                     run: Callable[[Recording, float], Calibration]) -> SplitHalfScale:
    """The scale of ``full``'s stated errors, ``run(half, log_offset)`` calibrating each half
    of ``rec`` at ``full``'s log offset. A half the estimator cannot calibrate gives a scale
    of 1 with its reason."""
    try:
        first, second = (run(h, full.log_offset) for h in halves(rec))
    except CalibrationError as e:
        return SplitHalfScale(reason=f"a half could not be calibrated: {e}")
    return scale_of(first, second)


def with_scale(cal: Calibration, scale: SplitHalfScale) -> Calibration:
    """``cal`` with its stated errors multiplied by ``scale`` (unchanged when it was not
    applied) and the scale in ``diagnostics.extra["error_scale"]``."""
    diag = cal.diagnostics
    diag = replace(diag, extra={**diag.extra, "error_scale": scale.to_dict()})
    if not scale.applied:
        return cal.replace(diagnostics=diag)
    return cal.replace(
        stderr_contrast=(cal.stderr_contrast * np.float32(scale.contrast)).astype(np.float32),
        stderr_bias=(cal.stderr_bias * np.float32(scale.bias)).astype(np.float32),
        diagnostics=diag)
