"""Image-quality metrics for reconstructed frames (8-bit range: float arrays in ``[0, 255]``).

Two families, labelled so that numbers are never mixed up:

- standard metrics: :func:`rmse`, :func:`psnr` (``10 log10(R^2 / MSE)`` dB) and :func:`ssim`
  (scikit-image's windowed SSIM);
- the conventions of the reference MATLAB evaluation (``Evaluation.m`` of Wang et al.'s
  Event-Camera-Calibration code), which the paper's tables use: :func:`psnr_paper`
  (``20 log10(255^2 / MSE)``, exactly twice the standard PSNR) and :func:`ssim_paper` (one
  global window over the whole image).

Compare a paper's table only with the ``*_paper`` values; report the standard ones elsewhere.
Only :func:`ssim` needs scikit-image, and imports it when called.
"""

from __future__ import annotations

import math

import numpy as np

from .errors import ConfigError, ErrorReason, EvcalError

PAPER_DATA_RANGE = 255.0
SSIM_K1 = 0.01
SSIM_K2 = 0.03
SSIM_WIN_SIZE = 7  # scikit-image's default window side (uniform, not Gaussian)


class ImageError(EvcalError):
    """Two images that cannot be compared (shapes differ, empty, NaN or infinite values)."""


def _pair(a: np.ndarray, b: np.ndarray, what: str) -> tuple[np.ndarray, np.ndarray]:
    """Both images as float64, after checking equal shapes and finite values."""
    a = np.asarray(a, np.float64)
    b = np.asarray(b, np.float64)
    if a.shape != b.shape:
        raise ImageError(f"{what}: images have shapes {a.shape} and {b.shape}, expected equal")
    if a.size == 0:
        raise ImageError(f"{what}: images are empty (shape {a.shape})")
    for name, img in (("first", a), ("second", b)):
        bad = ~np.isfinite(img)
        if bad.any():
            raise ImageError(
                f"{what}: the {name} image has {int(bad.sum())} NaN or infinite values, "
                "expected finite intensities", ErrorReason.BAD_VALUES)
    return a, b


def _check_range(data_range: float, what: str) -> float:
    r = float(data_range)
    if not (math.isfinite(r) and r > 0):
        raise ConfigError(f"{what}: data_range={data_range!r} must be a finite number > 0")
    return r


def _mse(a: np.ndarray, b: np.ndarray) -> float:
    d = a - b
    return float(np.mean(d * d))


def rmse(a: np.ndarray, b: np.ndarray) -> float:
    """Root mean squared error ``sqrt(mean((a - b)^2))``, in the images' units (DN).

    Examples
    --------
    >>> rmse(np.zeros((2, 2)), np.full((2, 2), 3.0))
    3.0
    """
    a, b = _pair(a, b, "rmse")
    return math.sqrt(_mse(a, b))


def psnr(a: np.ndarray, b: np.ndarray, data_range: float = 255.0) -> float:
    """Standard peak signal-to-noise ratio ``10 log10(R^2 / MSE)`` in dB.

    ``R`` is ``data_range`` (255 for 8-bit images). Identical images (``MSE = 0``) give
    ``float('inf')``.

    Examples
    --------
    >>> round(psnr(np.zeros((2, 2)), np.full((2, 2), 2.55)), 6)  # MSE = 2.55^2 = R^2 / 1e4
    40.0
    """
    a, b = _pair(a, b, "psnr")
    r = _check_range(data_range, "psnr")
    mse = _mse(a, b)
    if mse == 0.0:
        return float("inf")
    return 10.0 * math.log10(r * r / mse)


def ssim(a: np.ndarray, b: np.ndarray, data_range: float = 255.0) -> float:
    """Mean structural similarity of two 2-D images (``skimage.metrics.structural_similarity``).

    scikit-image's defaults are kept: a 7x7 *uniform* (not Gaussian) sliding window, sample
    covariances (``N - 1``), ``K1 = 0.01``, ``K2 = 0.03``, and the mean over the windows that
    fit inside the image. Images must be at least 7x7. Identical images give 1.0.
    """
    a, b = _pair(a, b, "ssim")
    r = _check_range(data_range, "ssim")
    if a.ndim != 2 or min(a.shape) < SSIM_WIN_SIZE:
        raise ImageError(
            f"ssim: images have shape {a.shape}, expected 2-D images of at least "
            f"{SSIM_WIN_SIZE}x{SSIM_WIN_SIZE} (the SSIM window)"
        )
    from skimage.metrics import structural_similarity  # noqa: PLC0415 - heavy import

    return float(structural_similarity(a, b, data_range=r))


def psnr_paper(a: np.ndarray, b: np.ndarray) -> float:
    """PSNR as the reference MATLAB code computes it: ``20 log10(255^2 / MSE)`` in "dB".

    This squares the ratio twice over, so it is exactly ``2 * psnr(a, b, 255)`` (computed as
    that product, so the equality holds bit for bit). Only for comparison with the paper's
    tables. Identical images give ``float('inf')``.
    """
    return 2.0 * psnr(a, b, PAPER_DATA_RANGE)


def ssim_paper(a: np.ndarray, b: np.ndarray) -> float:
    """Single-window (global) SSIM, the reference MATLAB code's ``computeSSIM``.

    With means ``mu``, variances ``s_aa``, ``s_bb`` and covariance ``s_ab`` over the whole
    image (sample estimates with ``N - 1``, as MATLAB's ``cov``)::

        SSIM = (2 mu_a mu_b + C1) (2 s_ab + C2) / ((mu_a^2 + mu_b^2 + C1) (s_aa + s_bb + C2))

    with ``C1 = (0.01 * 255)^2`` and ``C2 = (0.03 * 255)^2``. (The MATLAB code calls ``mean`` on
    the matrix, which gives column means, and then divides the row vectors with ``/``; we
    implement the global-mean formula the code intends.) A one-pixel image has no sample
    variance: it raises.
    """
    a, b = _pair(a, b, "ssim_paper")
    n = a.size
    if n < 2:
        raise ImageError("ssim_paper: images have 1 pixel, a sample variance needs at least 2")
    c1 = (SSIM_K1 * PAPER_DATA_RANGE) ** 2
    c2 = (SSIM_K2 * PAPER_DATA_RANGE) ** 2
    mu_a = float(a.mean())
    mu_b = float(b.mean())
    da = a - mu_a
    db = b - mu_b
    s_aa = float((da * da).sum()) / (n - 1)
    s_bb = float((db * db).sum()) / (n - 1)
    s_ab = float((da * db).sum()) / (n - 1)
    return ((2 * mu_a * mu_b + c1) * (2 * s_ab + c2)) / (
        (mu_a * mu_a + mu_b * mu_b + c1) * (s_aa + s_bb + c2)
    )


METRIC_NAMES = ("rmse", "psnr", "ssim", "psnr_paper", "ssim_paper")


def image_metrics(recon: np.ndarray, ref: np.ndarray) -> dict[str, float]:
    """All metrics of a reconstruction against its reference frame (8-bit range, R = 255).

    Returns ``{"rmse", "psnr", "ssim", "psnr_paper", "ssim_paper"}`` as floats.
    """
    recon, ref = _pair(recon, ref, "image_metrics")
    p = psnr(recon, ref, 255.0)
    return {
        "rmse": rmse(recon, ref),
        "psnr": p,
        "ssim": ssim(recon, ref, 255.0),
        "psnr_paper": 2.0 * p,
        "ssim_paper": ssim_paper(recon, ref),
    }
