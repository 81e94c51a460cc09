"""OnEI's stated standard errors, calibrated (:func:`error_scales`).

A solve's own standard error (:func:`~evcal.solver.solve_pixels` with OnEI's ``overlap``) is
the plain least-squares one with the variance multiplied by the small buffers each event
lies in. That is far too much: the noise of an equation between frames ``j`` and ``k`` is
not a sum over its intervals but the sub-threshold residuals (and frame noise) at its two
end frames, ``r_k - r_j`` (OffEI's insight, :func:`~evcal.solver.overlap_standard_errors`).
OffEI's closed form needs windows of a constant number of frames (the noises then telescope
along the regressors' mean); OnEI's close on an event count, so a frame ends zero, one or
several of them. What holds for any windows is the sandwich over the frames' residuals:
with ``h_f`` the regressors of the equations ending at frame ``f`` less those starting
there, ``H = sum_f h_f h_f^T`` and ``G`` the normal matrix,
``Var(c, b) = kappa sigma_r^2 G^-1 H G^-1`` with ``sigma_r^2 = RSS / (2 n - tr(G^-1 H))``
(``n`` equations, two frame residuals each) and ``kappa`` for the residual that persists
from frame to frame (:func:`~evcal.solver.noise_overlap`, measured on the same pixels).

Computing ``H`` for every pixel costs a pass over every equation of the buffer, as a
rebuild does, and a live service reads the maps at every update. So the sandwich is
computed on a sample of the valid pixels (:data:`SAMPLE_PIXELS`, spread evenly over the
sensor), and its ratio to the solve's own variance on the same pixels and equations, one
factor each for ``c`` and ``b`` (the root of the mean ratio: std(z) over pixels is the root
of the mean of ``z^2``), scales every pixel's error. The spread of the per-pixel ratios is
what is given up.

The smoothed estimate averages overlapping solves: its variance, in the solves' own units,
is followed per pixel by the low-pass itself (:func:`~.estimate.low_pass`); the factors
scale it as they do one solve's.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..solver import OverlapNoise, log_intensity, noise_overlap, usable
from .kernels import jit

# pixels the sandwich is computed on (a pass over the buffer's frames each, at their values
# only): two factors to a few percent
SAMPLE_PIXELS = 2048
# of them, the pixels kappa is measured on
KAPPA_PIXELS = 512
# equations a sampled pixel needs in the buffer to enter the factors
MIN_EQUATIONS = 3


@dataclass(frozen=True)
class ErrorScale:
    """What multiplies the solves' own standard errors (and the smoothed estimate's, in
    their units): ``c`` and ``b``, with the figures behind them (``info``, for the
    diagnostics)."""

    c: float
    b: float
    info: dict[str, Any]


def identity(why: str) -> ErrorScale:
    """No calibration: the solves' own errors, and why."""
    return ErrorScale(1.0, 1.0, {"method": "per-solve", "why": why})


def error_scales(frames: Sequence[Any], base: int, se_c: np.ndarray, se_b: np.ndarray,
                 valid: np.ndarray, lam: float, log_offset: float,
                 saturation_dn: tuple[float, float], overlap: float,
                 sample_pixels: int = SAMPLE_PIXELS) -> ErrorScale:
    """The factors of the module's calibration from the large buffer's ``frames`` (absolute
    number of the first: ``base``; each with ``image``, ``last_p``, ``idx``, ``on``,
    ``off``, ``dense`` and ``closes_at`` as :class:`~.buffer.Frame`), on a sample of the
    pixels whose estimate is ``valid`` with finite stored errors ``se_c``, ``se_b``; ``lam``
    and ``overlap`` as the last solve used them. :func:`identity` (with the reason) where
    the buffer holds nothing to measure them on."""
    cand = np.flatnonzero(valid & np.isfinite(se_c) & np.isfinite(se_b) & (se_c > 0)
                          & (se_b > 0))
    n_f = len(frames)
    if cand.size == 0 or n_f < 3:
        return identity("nothing to sample")
    if cand.size > sample_pixels:
        cand = cand[np.linspace(0, cand.size - 1, sample_pixels).round().astype(np.int64)]
    s = cand.size
    # the sample's running counts, last polarities and log intensities at every frame
    # (the first frame's interval has left the buffer: counts start at 0 there)
    on = np.zeros((n_f, s), np.int64)
    off = np.zeros((n_f, s), np.int64)
    lastp = np.empty((n_f, s), np.int64)
    img = np.empty((n_f, s))
    slot = np.full(valid.size, -1, np.int64)  # each pixel's column in the sample, or -1
    slot[cand] = np.arange(s)
    for i, f in enumerate(frames):
        img[i] = np.asarray(f.image).reshape(-1)[cand]
        lastp[i] = f.last_p[cand]
        if i == 0 or not f.on.size:
            continue
        if f.dense:  # full maps
            on[i] = f.on[cand]
            off[i] = f.off[cand]
        else:
            _gather(f.idx, f.on, f.off, slot, on[i], off[i])
    _running(on)
    _running(off)
    ok = usable(img, saturation_dn)
    with np.errstate(divide="ignore", invalid="ignore"):
        lg = log_intensity(img, log_offset)
    eqs = [(j, f.closes_at - base) for j, f in enumerate(frames)
           if f.closes_at >= 0 and 0 < f.closes_at - base - j and f.closes_at - base < n_f]
    if not eqs:
        return identity("no equations")
    data = (on, off, lastp, lg, ok)
    full = _sandwich(_sweep(eqs, data, lam, n_f))
    use = full["use"]
    if not use.any():
        return identity("no sampled pixel has equations enough")
    d = int(np.median([k - j for j, k in eqs]))
    # kappa on part of the sample (a mean of correlations over pixels), with windows of the
    # buffer's median length
    sub = np.unique(np.linspace(0, s - 1, min(s, KAPPA_PIXELS)).round().astype(np.int64))
    noise = OverlapNoise(d, np.zeros((2, s)), sub, on[:, sub], off[:, sub], lastp[:, sub],
                         lg[:, sub], ok[:, sub])
    kappa = noise_overlap(noise, np.where(use, full["c"], 0.0), np.where(use, full["b"], 0.0),
                          use, float(lam))
    # the solve's own variances on the same equations (solve_pixels' formula)
    n_eq = full["n"]
    with np.errstate(divide="ignore", invalid="ignore"):
        n_eff = n_eq / max(overlap, 1.0)
        s2_own = full["rss"] / n_eq * n_eff / (n_eff - 2.0) * overlap
        own_c, own_b = s2_own * full["i11"], s2_own * full["i22"]
    use = use & (n_eff > 2.0) & (own_c > 0) & (own_b > 0)
    if not use.any():
        return identity("no sampled pixel has residual freedom")
    v_c, v_b = kappa * full["v_c"], kappa * full["v_b"]
    f_c = float(np.sqrt(np.mean(v_c[use] / own_c[use])))
    f_b = float(np.sqrt(np.mean(v_b[use] / own_b[use])))
    return ErrorScale(f_c, f_b, {
        "method": "sandwich", "sample_pixels": int(use.sum()), "kappa": round(kappa, 4),
        "window_frames_median": d, "factor_c": round(f_c, 4), "factor_b": round(f_b, 4)})


def _sweep(eqs: list[tuple[int, int]], data: tuple[np.ndarray, ...], lam: float,
           n_f: int) -> dict[str, np.ndarray]:
    """The sums over the equations ``eqs`` (frame pairs) of the sampled pixels: the normal
    matrix ``g``, its right side ``y``, ``yy``, the count ``n`` and ``h`` (the regressors of
    the equations ending at each frame less those starting there)."""
    on, off, lastp, lg, ok = data
    pairs = np.array(eqs, np.int64).reshape(-1, 2)
    sums = np.zeros((7, on.shape[1]))
    h = np.zeros((n_f, 2, on.shape[1]))
    _sweep_kernel(pairs, on, off, lastp, lg, ok, float(lam), sums, h)
    return {**dict(zip(("g11", "g12", "g22", "y1", "y2", "yy", "n"), sums, strict=True)),
            "h": h}


@jit(error_model="numpy")
def _gather(idx: np.ndarray, f_on: np.ndarray, f_off: np.ndarray, slot: np.ndarray,
            on: np.ndarray, off: np.ndarray) -> None:  # pragma: no cover - compiled
    """An interval's sparse counts (``idx`` each pixel once) of the sampled pixels (``slot``
    their columns, -1 for the others) into ``on``, ``off``."""
    for t in range(idx.size):
        col = slot[idx[t]]
        if col >= 0:
            on[col] = f_on[t]
            off[col] = f_off[t]


@jit(error_model="numpy")
def _running(a: np.ndarray) -> None:  # pragma: no cover - compiled
    """Cumulative sums down the frames, in place."""
    for i in range(1, a.shape[0]):
        for p in range(a.shape[1]):
            a[i, p] += a[i - 1, p]


@jit(error_model="numpy")
def _sweep_kernel(pairs: np.ndarray, on: np.ndarray, off: np.ndarray, lastp: np.ndarray,
                  lg: np.ndarray, ok: np.ndarray, lam: float, sums: np.ndarray,
                  h: np.ndarray) -> None:  # pragma: no cover - compiled
    """:func:`_sweep`'s sums (``sums``: g11, g12, g22, y1, y2, yy, n) and ``h``, equation by
    equation, weighed as the kernels weigh one (both frames usable, an event at least)."""
    for r in range(pairs.shape[0]):
        j, k = pairs[r, 0], pairs[r, 1]
        for p in range(on.shape[1]):
            n_on = on[k, p] - on[j, p]
            n_off = off[k, p] - off[j, p]
            e = n_on + n_off
            if not (ok[j, p] and ok[k, p] and e > 0):
                continue
            x1 = n_on - n_off + lam * (lastp[k, p] - lastp[j, p])
            x2 = e + lam * (abs(lastp[k, p]) - abs(lastp[j, p]))
            dl = lg[k, p] - lg[j, p]
            sums[0, p] += x1 * x1
            sums[1, p] += x1 * x2
            sums[2, p] += x2 * x2
            sums[3, p] += x1 * dl
            sums[4, p] += x2 * dl
            sums[5, p] += dl * dl
            sums[6, p] += 1.0
            h[k, 0, p] += x1
            h[k, 1, p] += x2
            h[j, 0, p] -= x1
            h[j, 1, p] -= x2


def _sandwich(t: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """The least-squares solution of :func:`_sweep`'s sums and its sandwich variances
    (without ``kappa``): ``c``, ``b``, ``v_c``, ``v_b``, ``rss``, ``i11``, ``i22`` (the
    normal matrix's inverse) and ``use`` (pixels where all are finite and positive)."""
    g11, g12, g22, n_eq, h = t["g11"], t["g12"], t["g22"], t["n"], t["h"]
    det = g11 * g22 - g12 * g12
    with np.errstate(divide="ignore", invalid="ignore"):
        i11, i12, i22 = g22 / det, -g12 / det, g11 / det
        c = i11 * t["y1"] + i12 * t["y2"]
        b = i12 * t["y1"] + i22 * t["y2"]
        rss = np.maximum(t["yy"] - c * t["y1"] - b * t["y2"], 0.0)
        h11 = np.einsum("fs,fs->s", h[:, 0], h[:, 0])
        h12 = np.einsum("fs,fs->s", h[:, 0], h[:, 1])
        h22 = np.einsum("fs,fs->s", h[:, 1], h[:, 1])
        # E[RSS] = sigma_r^2 (2 n - tr(G^-1 H)): each equation two frames' residuals
        dof = 2.0 * n_eq - (i11 * h11 + 2.0 * i12 * h12 + i22 * h22)
        s2 = rss / dof
        a11 = i11 * h11 + i12 * h12  # G^-1 H, then G^-1 H G^-1's diagonal
        a12 = i11 * h12 + i12 * h22
        a21 = i12 * h11 + i22 * h12
        a22 = i12 * h12 + i22 * h22
        v_c = s2 * (a11 * i11 + a12 * i12)
        v_b = s2 * (a21 * i12 + a22 * i22)
    use = ((n_eq >= MIN_EQUATIONS) & (det > 1e-9 * (g11 + g22) ** 2) & (dof > 0.5)
           & (v_c > 0) & (v_b > 0) & np.isfinite(v_c) & np.isfinite(v_b))
    return {"c": c, "b": b, "v_c": v_c, "v_b": v_b, "rss": rss, "i11": i11, "i22": i22,
            "n": n_eq, "use": use}
