"""The per-pixel normal equations of the event-intensity model and their closed-form solve.

Between frames ``j`` and ``k`` a pixel obeys (Wang et al.'s model)::

    L_k - L_j = c * (SP + lam Q) + b * (SE + lam A) + noise

with ``SP`` the net polarity and ``SE`` the event count in between, ``L = log(I + offset)``,
and ``Q``, ``A`` the residual-correction regressors of :mod:`evcal.offline` (``lam = 0``: the
plain fit). :class:`NormalEquations` keeps every cross product per pixel, so an equation can be
added or removed exactly and ``lam`` chosen after the pass over the data;
:func:`solve_pixels` is the 2x2 solve with validity reasons and standard errors, one compiled
pass over the pixels. OffEI (:mod:`evcal.offline`), OnEI (:mod:`evcal.online`) and the gap
workflow's fits (:mod:`evcal.gap.stats`) all solve through here.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numba
import numpy as np

from .calibration import DEFAULT_BIAS, DEFAULT_CONTRAST, Calibration, Diagnostics, Reason
from .special import classify

# ----------------------------------------------------------------------------------------
# frames to log intensity


def log_intensity(image: np.ndarray, log_offset: float) -> np.ndarray:
    """``log(I + offset)`` as float64; uint8 frames go through a 256-entry table.

    With ``offset = 0`` a black pixel (0 DN) has ``-inf``: no signal there (estimators skip
    such pixels as clipped; a reconstruction from it stays black).
    """
    with np.errstate(divide="ignore"):
        if image.dtype == np.uint8:
            lut = np.log(np.arange(256, dtype=np.float64) + log_offset)
            result: np.ndarray = lut[image]
            return result
        img = np.asarray(image, np.float64)
        return np.log(np.maximum(img, 0.0) + log_offset)


def usable(image: np.ndarray, saturation_dn: tuple[float, float]) -> np.ndarray:
    """Pixels of a frame that are neither black-clipped nor saturated (bool, same shape)."""
    lo, hi = saturation_dn
    return (image > lo) & (image < hi)


# ----------------------------------------------------------------------------------------
# per-pixel normal equations


_TERMS = ("pp", "pe", "pq", "pa", "ee", "eq", "ea", "qq", "qa", "aa", "py", "ey", "qy", "ay",
          "yy", "n_eq")


@dataclass
class NormalEquations:
    """Running per-pixel cross products of ``[P, E, Q, A]`` and ``dL`` (flat maps).

    ``P``, ``E``: net polarity and event count of an equation; ``Q = q_end - q_start`` and
    ``A = |q_end| - |q_start|`` from the polarity of the last event before each end frame.
    Keeping all cross products lets the residual-correction factor ``lam`` be chosen after the
    pass over the data (:meth:`system`). ``add`` takes one equation per pixel (weight 0 leaves
    a pixel untouched) and ``sign=-1`` removes it exactly, so a sliding buffer can drop old
    equations.
    """

    n_pixels: int

    def __post_init__(self) -> None:
        # one (16, n) block: a row per cross product, each row a flat map (views)
        self.m = np.zeros((len(_TERMS), self.n_pixels), np.float64)
        (self.pp, self.pe, self.pq, self.pa, self.ee, self.eq, self.ea, self.qq, self.qa,
         self.aa, self.py, self.ey, self.qy, self.ay, self.yy, self.n_eq) = self.m

    def add(self, p: np.ndarray, e: np.ndarray, q: np.ndarray, a: np.ndarray, dl: np.ndarray,
            w: np.ndarray | float = 1.0, idx: np.ndarray | slice = slice(None),
            sign: float = 1.0) -> None:
        if not isinstance(idx, slice):
            # sparse: one compiled pass over the pixels (a numpy scatter per term is ~10x slower)
            n = len(idx)
            w_arr = np.broadcast_to(np.asarray(w, np.float64), (n,))
            _add_sparse(self.m, np.asarray(idx, np.int64), *(
                np.ascontiguousarray(np.broadcast_to(np.asarray(v, np.float64), (n,)))
                for v in (p, e, q, a, dl)), np.ascontiguousarray(w_arr), float(sign))
            return
        ws = sign * w
        wp, we, wq, wa = ws * p, ws * e, ws * q, ws * a
        self.pp[idx] += wp * p
        self.pe[idx] += wp * e
        self.pq[idx] += wp * q
        self.pa[idx] += wp * a
        self.ee[idx] += we * e
        self.eq[idx] += we * q
        self.ea[idx] += we * a
        self.qq[idx] += wq * q
        self.qa[idx] += wq * a
        self.aa[idx] += wa * a
        self.py[idx] += wp * dl
        self.ey[idx] += we * dl
        self.qy[idx] += wq * dl
        self.ay[idx] += wa * dl
        self.yy[idx] += ws * dl * dl
        self.n_eq[idx] += ws * np.ones_like(dl)

    def add_windows(self, ring: WindowRing, rows_j: np.ndarray, rows_k: np.ndarray) -> None:
        """:meth:`add` of the dense windows ``rows_j -> rows_k`` of ``ring``, weight 1 where
        both frames are usable (else 0): one compiled pass for the batch. The same sums as
        ``add(P, E, Q, A, dL, w)`` window by window, up to the order of the additions; the
        same pass adds the windows' ``P`` and ``E`` to ``ring.moments``."""
        _add_windows(self.m, ring.moments, ring.on, ring.off, ring.q, ring.lg, ring.ok,
                     np.ascontiguousarray(rows_j, np.int64),
                     np.ascontiguousarray(rows_k, np.int64))

    def system(self, lam: float) -> tuple[np.ndarray, ...]:
        """``(a11, a12, a22, r1, r2, yy)`` of ``dL = c (P + lam Q) + b (E + lam A)``."""
        a11 = self.pp + 2 * lam * self.pq + lam * lam * self.qq
        a12 = self.pe + lam * (self.pa + self.eq) + lam * lam * self.qa
        a22 = self.ee + 2 * lam * self.ea + lam * lam * self.aa
        r1 = self.py + lam * self.qy
        r2 = self.ey + lam * self.ay
        return a11, a12, a22, r1, r2, self.yy

    def residual_lambda(self, lam: float, c: np.ndarray, b: np.ndarray,
                        mask: np.ndarray) -> float:
        """One-step update of ``lam`` from the fit's residuals: ``lam + sum(res Q) / sum(c Q^2)``.

        The residual of the fit at ``lam`` still holds ``(lam_true - lam) c Q`` on average.
        """
        res_q = (self.qy - c * (self.pq + lam * self.qq) - b * (self.eq + lam * self.qa))
        cq = c * self.qq
        den = float(cq[mask].sum())
        if den <= 0:
            return lam
        return lam + float(res_q[mask].sum()) / den

    def arrays(self) -> dict[str, np.ndarray]:
        return {k: getattr(self, k) for k in _TERMS}

    @classmethod
    def from_arrays(cls, arrays: dict[str, np.ndarray]) -> NormalEquations:
        ne = cls(int(arrays["pp"].size))
        for k in _TERMS:
            getattr(ne, k)[:] = arrays[k]
        return ne


@numba.njit(cache=True, nogil=True)
def _add_sparse(m: np.ndarray, idx: np.ndarray, p: np.ndarray, e: np.ndarray, q: np.ndarray,
                a: np.ndarray, dl: np.ndarray, w: np.ndarray, sign: float) -> Any:
    for i in range(idx.size):
        k = idx[i]
        ws = sign * w[i]
        wp = ws * p[i]
        we = ws * e[i]
        wq = ws * q[i]
        wa = ws * a[i]
        m[0, k] += wp * p[i]
        m[1, k] += wp * e[i]
        m[2, k] += wp * q[i]
        m[3, k] += wp * a[i]
        m[4, k] += we * e[i]
        m[5, k] += we * q[i]
        m[6, k] += we * a[i]
        m[7, k] += wq * q[i]
        m[8, k] += wq * a[i]
        m[9, k] += wa * a[i]
        m[10, k] += wp * dl[i]
        m[11, k] += we * dl[i]
        m[12, k] += wq * dl[i]
        m[13, k] += wa * dl[i]
        m[14, k] += ws * dl[i] * dl[i]
        m[15, k] += ws


# pixels a block of the window ring holds (its rows contiguous): a block's rows and its 16
# running sums stay in the L2 cache while its windows are added, and the hardware prefetcher
# follows one contiguous stream instead of one per row and array (3x faster at 1280x720)
RING_BLOCK = 128


@numba.njit(cache=True, nogil=True)
def _add_windows(m: np.ndarray, mom: np.ndarray, on: np.ndarray, off: np.ndarray,
                 q: np.ndarray, lg: np.ndarray, ok: np.ndarray, rows_j: np.ndarray,
                 rows_k: np.ndarray) -> Any:  # pragma: no cover - compiled
    """The dense windows ``rows_j[w] -> rows_k[w]`` of ring buffers ``[block, row, pixel of
    the block]`` (running ON/OFF counts, last polarity, log intensity, usable), a block of
    pixels at a time: each pixel's 16 sums over all the windows are formed in a block-sized
    scratch and added to ``m`` once, so ``m`` (128 bytes a pixel) streams through memory once
    per batch, and the inner loop over a block's pixels is vectorised. The products are those
    of :meth:`NormalEquations.add` with weight 1 or 0 (unusable windows add exact zeros, so
    the sums equal the window-by-window ones bit for bit). Rows 16 and 17 of the scratch are
    the windows' ``P`` and ``E``, added to ``mom`` (:attr:`WindowRing.moments`)."""
    n = m.shape[1]
    n_w = rows_j.size
    size_b = on.shape[2]
    s = np.zeros((18, size_b))
    for blk in range(on.shape[0]):
        i0 = blk * size_b
        nb = min(size_b, n - i0)
        s[:, :nb] = 0.0
        for w in range(n_w):
            rj = rows_j[w]
            rk = rows_k[w]
            for t in range(nb):
                use = ok[blk, rk, t] & ok[blk, rj, t]
                non = np.float64(on[blk, rk, t] - on[blk, rj, t])
                noff = np.float64(off[blk, rk, t] - off[blk, rj, t])
                qk = np.float64(q[blk, rk, t])
                qj = np.float64(q[blk, rj, t])
                # selects, not a multiplication by the weight: dL is -inf at black pixels
                p = non - noff if use else 0.0
                e = non + noff if use else 0.0
                dq = qk - qj if use else 0.0
                a = abs(qk) - abs(qj) if use else 0.0
                dl = lg[blk, rk, t] - lg[blk, rj, t] if use else 0.0
                s[0, t] += p * p
                s[1, t] += p * e
                s[2, t] += p * dq
                s[3, t] += p * a
                s[4, t] += e * e
                s[5, t] += e * dq
                s[6, t] += e * a
                s[7, t] += dq * dq
                s[8, t] += dq * a
                s[9, t] += a * a
                s[10, t] += p * dl
                s[11, t] += e * dl
                s[12, t] += dq * dl
                s[13, t] += a * dl
                s[14, t] += dl * dl
                s[15, t] += 1.0 if use else 0.0
                s[16, t] += p
                s[17, t] += e
        for k in range(16):
            for t in range(nb):
                m[k, i0 + t] += s[k, t]
        for k in range(2):
            for t in range(nb):
                mom[k, i0 + t] += s[16 + k, t]


class WindowRing:
    """The last ``size`` frames' running counts, last polarities, log intensities and usable
    masks as ring buffers, and the windows waiting to be added: OffEI adds its windows in
    batches through :meth:`NormalEquations.add_windows` (one pass over the sums per batch).

    Layout ``[block, row, pixel of the block]`` (:data:`RING_BLOCK` pixels a block, the last
    block padded): a block's rows are contiguous, so a batch reads the ring as one stream.
    """

    def __init__(self, n_pixels: int, window_frames: int, batch: int = 16):
        self.d = int(window_frames)
        self.size = self.d + int(batch)
        self.batch = int(batch)
        self.n_pixels = int(n_pixels)
        shape = (-(-self.n_pixels // RING_BLOCK), self.size, RING_BLOCK)
        self.on = np.zeros(shape, np.int32)
        self.off = np.zeros(shape, np.int32)
        self.q = np.zeros(shape, np.int8)
        self.lg = np.zeros(shape, np.float64)
        self.ok = np.zeros(shape, np.bool_)
        self.n = 0  # frames pushed
        self.pending: list[int] = []  # frame numbers k whose window (k - d, k) is pending
        # sums over the added windows of w P and w E (flat maps): the regressors' means that
        # the standard errors need (:class:`OverlapNoise`)
        self.moments = np.zeros((2, self.n_pixels), np.float64)

    def push(self, on: np.ndarray, off: np.ndarray, last_p: np.ndarray, lg: np.ndarray,
             ok: np.ndarray) -> bool:
        """Store frame ``n`` (flat per-pixel maps); True when a batch of windows is due (call
        ``flush``)."""
        r = self.n % self.size
        full = self.n_pixels // RING_BLOCK  # whole blocks; the last one may be partial
        cut = full * RING_BLOCK
        for dst, src in ((self.on, on), (self.off, off), (self.q, last_p), (self.lg, lg),
                         (self.ok, ok)):
            # numpy's strided copies: 4x faster here than one compiled loop over the five
            dst[:full, r, :] = src[:cut].reshape(full, RING_BLOCK)
            if cut < self.n_pixels:
                dst[full, r, : self.n_pixels - cut] = src[cut:]
        if self.n >= self.d:
            self.pending.append(self.n)
        self.n += 1
        return len(self.pending) >= self.batch

    def counts(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        """The running ON and OFF counts (flat int32 maps, copies) stored for frame ``k``,
        one of the last ``size`` frames pushed."""
        if not (self.n - self.size <= k < self.n and k >= 0):
            raise IndexError(f"frame {k} is not in the ring (frames {max(self.n - self.size, 0)}"
                             f" to {self.n - 1})")
        r = k % self.size
        return (self.on[:, r, :].reshape(-1)[: self.n_pixels].copy(),
                self.off[:, r, :].reshape(-1)[: self.n_pixels].copy())

    def flush(self, ne: NormalEquations) -> None:
        if not self.pending:
            return
        k = np.asarray(self.pending, np.int64)
        ne.add_windows(self, (k - self.d) % self.size, k % self.size)
        self.pending.clear()


# Reason codes as plain ints for the compiled kernels
_VALID = int(Reason.VALID)
_NO_EVENTS = int(Reason.NO_EVENTS)
_TOO_FEW_EVENTS = int(Reason.TOO_FEW_EVENTS)
_RANK_DEFICIENT = int(Reason.RANK_DEFICIENT)
_OUT_OF_RANGE = int(Reason.OUT_OF_RANGE)


@dataclass(frozen=True, kw_only=True)
class SolveLimits:
    """When a pixel's solution is trusted."""

    min_events: int = 20
    min_equations: float = 3.0
    min_decorrelation: float = 1e-3  # 1 - corr(P, E)^2 below this: rank deficient
    min_contrast: float = 0.01
    max_contrast: float = 2.0
    max_bias_ratio: float = 0.95  # |b| < ratio * c keeps both thresholds positive


@numba.njit(inline="always")
def _pixel_fit(m: np.ndarray, i: int, lam: float, min_decorrelation: float) -> Any:
    """``(a11, a12, a22, r1, r2, c, b, ok, safe_det)`` of pixel ``i``: the system of
    :meth:`NormalEquations.system` and its 2x2 solve (defaults where rank deficient)."""
    l2 = 2 * lam
    ll = lam * lam
    a11 = m[0, i] + l2 * m[2, i] + ll * m[7, i]
    a12 = m[1, i] + lam * (m[3, i] + m[5, i]) + ll * m[8, i]
    a22 = m[4, i] + l2 * m[6, i] + ll * m[9, i]
    r1 = m[10, i] + lam * m[12, i]
    r2 = m[11, i] + lam * m[13, i]
    det = a11 * a22 - a12 * a12
    scale = a11 * a22
    ok = (scale > 0) & (det > min_decorrelation * scale)
    safe = det if ok else 1.0
    c = (a22 * r1 - a12 * r2) / safe if ok else DEFAULT_CONTRAST
    b = (a11 * r2 - a12 * r1) / safe if ok else DEFAULT_BIAS
    return a11, a12, a22, r1, r2, c, b, ok, safe


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _solve_pixels(m: np.ndarray, n_events: np.ndarray, lam: float, overlap: float,
                  min_events: int, min_equations: float, min_decorrelation: float,
                  min_contrast: float, max_contrast: float, max_bias_ratio: float,
                  extra_reason: np.ndarray) -> Any:  # pragma: no cover - compiled
    """One pass of :func:`solve_normal_equations` over the pixels: the same operations in the
    same order as the numpy formulas it replaced, so bit-identical results; written with
    selects rather than branches so that it vectorises."""
    n = m.shape[1]
    c_out = np.empty(n, np.float64)
    b_out = np.empty(n, np.float64)
    se_c_out = np.empty(n, np.float64)
    se_b_out = np.empty(n, np.float64)
    reason = np.empty(n, np.uint8)
    ov1 = overlap if overlap >= 1.0 else 1.0
    yy, n_eq = m[14], m[15]
    for i in range(n):
        a11, a12, a22, r1, r2, c, b, ok, safe = _pixel_fit(m, i, lam, min_decorrelation)
        # residual variance (np.maximum semantics: NaN propagates) and standard errors
        rss = yy[i] - 2 * (c * r1 + b * r2) + c * c * a11 + 2 * c * b * a12 + b * b * a22
        rss = 0.0 if rss < 0.0 else rss
        neq = n_eq[i]
        n_eff = neq / ov1
        neq_1 = neq if (neq >= 1e-9) | (neq != neq) else 1e-9
        dof = n_eff - 2.0
        dof_1 = dof if (dof >= 1e-9) | (dof != dof) else 1e-9
        sigma2 = rss / neq_1 * n_eff / dof_1 if n_eff > 2.0 else np.inf
        se_c = np.sqrt(sigma2 * overlap * (a22 / safe if ok else np.inf))
        se_b = np.sqrt(sigma2 * overlap * (a11 / safe if ok else np.inf))
        # reasons, later ones take precedence
        in_range = (c > min_contrast) & (c < max_contrast) & (abs(b) < max_bias_ratio * c)
        r = _VALID if ok else _RANK_DEFICIENT
        r = _OUT_OF_RANGE if ok & (not in_range) else r
        ne_i = n_events[i]
        r = _TOO_FEW_EVENTS if (ne_i < min_events) | (neq < min_equations) else r
        ex = extra_reason[i]
        r = ex if ex != _VALID else r
        r = _NO_EVENTS if ne_i == 0 else r
        reason[i] = r
        valid = r == _VALID
        c_out[i] = c if valid else DEFAULT_CONTRAST
        b_out[i] = b if valid else DEFAULT_BIAS
        se_c_out[i] = se_c if valid & np.isfinite(se_c) else np.inf
        se_b_out[i] = se_b if valid & np.isfinite(se_b) else np.inf
    return c_out, b_out, reason, se_c_out, se_b_out


@dataclass(frozen=True)
class PixelSolution:
    """The per-pixel solve as flat float64 maps: ``c``, ``b``, their standard errors
    ``se_c``, ``se_b`` (inf where invalid), ``reason`` codes and ``valid`` (reason 0); the
    calibration maps are built from it by :func:`solve_normal_equations`."""

    c: np.ndarray
    b: np.ndarray
    valid: np.ndarray
    reason: np.ndarray
    se_c: np.ndarray
    se_b: np.ndarray


def solve_pixels(
    ne: NormalEquations,
    n_events: np.ndarray,
    *,
    limits: SolveLimits,
    overlap: float = 1.0,
    extra_reason: np.ndarray | None = None,
    residual_lambda: float = 0.0,
) -> PixelSolution:
    """The closed-form 2x2 solve of :func:`solve_normal_equations` without building a
    :class:`Calibration` (no special-pixel classification): one compiled pass over the
    pixels. Invalid pixels hold the defaults and ``inf`` standard errors."""
    n = ne.n_pixels
    n_ev = np.ascontiguousarray(np.broadcast_to(np.asarray(n_events, np.int64).ravel(), (n,)))
    extra = (np.zeros(n, np.uint8) if extra_reason is None
             else np.ascontiguousarray(np.asarray(extra_reason).ravel(), np.uint8))
    c, b, reason, se_c, se_b = _solve_pixels(
        ne.m, n_ev, float(residual_lambda), float(overlap), int(limits.min_events),
        float(limits.min_equations), float(limits.min_decorrelation),
        float(limits.min_contrast), float(limits.max_contrast), float(limits.max_bias_ratio),
        extra)
    return PixelSolution(c, b, reason == _VALID, reason, se_c, se_b)


def solve_normal_equations(
    ne: NormalEquations,
    n_events: np.ndarray,
    shape: tuple[int, int],
    *,
    limits: SolveLimits,
    overlap: float = 1.0,
    log_offset: float,
    method: str,
    diagnostics: Diagnostics | None = None,
    extra_reason: np.ndarray | None = None,
    residual_lambda: float = 0.0,
) -> Calibration:
    """Closed-form 2x2 solve at every pixel, with validity reasons and standard errors.

    ``overlap`` is how many equations share each piece of data (``d`` for overlapping windows);
    the residual degrees of freedom are divided by it.
    """
    sol = solve_pixels(ne, n_events, limits=limits, overlap=overlap,
                       extra_reason=extra_reason, residual_lambda=residual_lambda)
    return calibration_from_solution(sol, n_events, shape, log_offset=log_offset,
                                     method=method, diagnostics=diagnostics)


def calibration_from_solution(sol: PixelSolution, n_events: np.ndarray,
                              shape: tuple[int, int], *, log_offset: float, method: str,
                              diagnostics: Diagnostics | None = None) -> Calibration:
    """The :class:`Calibration` of a per-pixel solve: its maps, special pixels classified."""
    special = classify(sol.c, sol.b, sol.se_c, sol.se_b, sol.valid)
    return Calibration(
        contrast=sol.c.reshape(shape),
        bias=sol.b.reshape(shape),
        valid=sol.valid.reshape(shape),
        reason=sol.reason.reshape(shape),
        stderr_contrast=sol.se_c.reshape(shape),
        stderr_bias=sol.se_b.reshape(shape),
        special=special.reshape(shape),
        log_offset=float(log_offset),
        method=method,
        n_events=np.asarray(n_events, np.int64).reshape(shape),
        diagnostics=diagnostics if diagnostics is not None else Diagnostics(),
    )


# ----------------------------------------------------------------------------------------
# standard errors of overlapping windows


@dataclass(frozen=True)
class OverlapNoise:
    """What the standard errors of overlapping windows need besides the normal equations.

    ``moments``: (2, n) sums over the equations of ``w P`` and ``w E``
    (:attr:`WindowRing.moments`). ``sample``: flat indices of a pixel sample; ``on``, ``off``,
    ``last_p``, ``lg``, ``ok``: their running ON and OFF counts, last polarities, log
    intensities and usable masks at consecutive frames (``[frame, sample pixel]``), from which
    the correlation of overlapping windows' noise is measured. ``window_frames``: ``d``.
    """

    window_frames: int
    moments: np.ndarray
    sample: np.ndarray
    on: np.ndarray
    off: np.ndarray
    last_p: np.ndarray
    lg: np.ndarray
    ok: np.ndarray


def noise_overlap(noise: OverlapNoise, c: np.ndarray, b: np.ndarray, valid: np.ndarray,
                  lam: float) -> float:
    """``kappa = 1 + 2 sum_{l<d} rho(l) (1 - l/d)``: how many windows' worth of noise the
    ``d`` windows overlapping one interval share.

    ``rho(l)`` is the correlation of the residuals of two windows ``l`` frames apart, the
    mean over the valid pixels of the sample of each pixel's own (so that each pixel counts
    alike, as in a spread of z-scores over pixels); ``1 - l/d`` is how much two such windows'
    regressors share (sums over ``d`` intervals, ``d - l`` of them common). ``d`` when there is
    nothing to measure it on (the bound: noise shared whole by the ``d`` windows); clipped to
    ``[1, d]``.
    """
    d = int(noise.window_frames)
    keep = valid[noise.sample]
    n_w = noise.on.shape[0] - d
    if d <= 1 or n_w <= d or not keep.any():
        return float(d)
    pix = noise.sample[keep]
    on = noise.on[:, keep]
    off = noise.off[:, keep]
    q = noise.last_p[:, keep].astype(np.float64)
    lg, ok = noise.lg[:, keep], noise.ok[:, keep]
    # [window, sample pixel]
    n_on = (on[d:] - on[:-d]).astype(np.float64)
    n_off = (off[d:] - off[:-d]).astype(np.float64)
    x1 = n_on - n_off + lam * (q[d:] - q[:-d])
    x2 = n_on + n_off + lam * (np.abs(q[d:]) - np.abs(q[:-d]))
    with np.errstate(invalid="ignore"):  # -inf - -inf at black pixels (unusable)
        res = np.where(ok[d:] & ok[:-d], lg[d:] - lg[:-d] - c[pix] * x1 - b[pix] * x2, 0.0)
    g0 = np.einsum("ij,ij->j", res, res)
    res, g0 = res[:, g0 > 0], g0[g0 > 0]
    if not g0.size:
        return float(d)
    kappa = 1.0
    for lag in range(1, d):
        rho = np.einsum("ij,ij->j", res[lag:], res[:-lag]) / g0
        kappa += 2.0 * float(rho.mean()) * (1.0 - lag / d)
    return float(np.clip(kappa, 1.0, d))


def overlap_standard_errors(ne: NormalEquations, sol: PixelSolution, lam: float,
                            noise: OverlapNoise
                            ) -> tuple[np.ndarray, np.ndarray, np.ndarray, float, float]:
    """``(se_c, se_b, rho, kappa, tau)`` of OffEI's overlapping windows (``inf`` where
    invalid; ``rho`` the correlation of the errors of ``c`` and ``b``, NaN there).

    The noise of the equation between frames ``j`` and ``k`` is ``r_k - r_j``: the
    sub-threshold residuals (and frame noise) at its two frames, not a sum over its intervals.
    So (1) two overlapping windows share no frame, their noises correlate only as far as a
    residual persists from frame to frame: ``kappa`` (:func:`noise_overlap`) replaces the
    ``d`` of "every interval is in ``d`` equations"; (2) along the mean of the regressors
    (``E`` is about ``d`` times the event rate in every window) the noises telescope, ``sum_w
    (r_k - r_j)`` keeps only the residuals of the first and last ``d`` frames, so only the
    regressors' spread about their mean, ``S = G - n m m^T``, carries noise (``G`` the
    regressors' cross products, ``m`` their mean); (3) the residual correction uses one
    ``lam`` for every pixel, the pixels' own factors spread about it with variance ``tau^2``
    (the variance over pixels of their one-pixel estimates less the part their noise
    explains), which moves ``(c, b)`` by ``(lam_pixel - lam) u``, ``u = G^-1 sum_w x_w (c Q_w
    + b A_w)``. Hence::

        Var(c, b) = kappa sigma^2 G^-1 S G^-1 + tau^2 u u^T

    with ``sigma^2 = RSS / n * n_eff / (n_eff - 2)``, ``n_eff = n / kappa``. The estimates
    are those of ``sol``, unchanged. ``rho`` is that matrix's correlation: near +1 or -1 for
    a pixel whose events are nearly all of one polarity (``P`` and ``E`` then move together,
    and only that polarity's threshold, ``c + b`` or ``c - b``, is measured well).
    """
    kappa = noise_overlap(noise, sol.c, sol.b, sol.valid, lam)
    var_c, var_b, cov_cb, u1, u2, lam_dev, lam_noise = _overlap_terms(
        ne.m, np.ascontiguousarray(noise.moments[0]), np.ascontiguousarray(noise.moments[1]),
        sol.c, sol.b, float(lam), float(kappa))
    use = sol.valid & np.isfinite(lam_dev) & np.isfinite(lam_noise)
    tau2 = (max(float(np.var(lam_dev[use])) - float(np.mean(lam_noise[use])), 0.0)
            if int(use.sum()) > 1 else 0.0)
    se_c, se_b, rho = _overlap_errors(var_c, var_b, cov_cb, u1, u2, sol.valid, tau2)
    return se_c, se_b, rho, kappa, float(np.sqrt(tau2))


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _overlap_terms(m: np.ndarray, m_p: np.ndarray, m_e: np.ndarray, c: np.ndarray,
                   b: np.ndarray, lam: float, kappa: float) -> Any:  # pragma: no cover
    """Per pixel, the terms of :func:`overlap_standard_errors`: the noise variances of ``c``
    and ``b`` and their covariance (``kappa sigma^2 G^-1 S G^-1``), ``u`` and the one-pixel
    estimate of the residual-correction factor's deviation with its noise variance (NaN where
    it has none)."""
    n_px = m.shape[1]
    var_c = np.empty(n_px)
    var_b = np.empty(n_px)
    cov_cb = np.empty(n_px)
    u1_out = np.empty(n_px)
    u2_out = np.empty(n_px)
    dev = np.empty(n_px)
    dev_noise = np.empty(n_px)
    for i in range(n_px):
        a11, a12, a22, r1, r2, _, _, _, _ = _pixel_fit(m, i, lam, 0.0)
        ci, bi, n = c[i], b[i], m[15, i]
        pq, pa, eq, ea, qq, qa, aa, qy, ay = (m[2, i], m[3, i], m[5, i], m[6, i], m[7, i],
                                                m[8, i], m[9, i], m[12, i], m[13, i])
        det = a11 * a22 - a12 * a12
        i11 = a22 / det
        i12 = -a12 / det
        i22 = a11 / det
        rss = (m[14, i] - 2 * (ci * r1 + bi * r2) + ci * ci * a11 + 2 * ci * bi * a12
               + bi * bi * a22)
        rss = 0.0 if rss < 0.0 else rss
        n_eff = n / kappa
        sigma2 = rss / n * n_eff / (n_eff - 2.0) if n_eff > 2.0 else np.inf
        # the regressors' spread about their mean (weights 0 or 1: positive semi-definite);
        # Q and A telescope (their sums over the windows are those of the last d frames less
        # the first d, at most 2 d), so P + lam Q and E + lam A have the means of P and E
        mean1 = m_p[i] / n
        mean2 = m_e[i] / n
        s11 = a11 - n * mean1 * mean1
        s12 = a12 - n * mean1 * mean2
        s22 = a22 - n * mean2 * mean2
        var_c[i] = kappa * sigma2 * (i11 * (i11 * s11 + i12 * s12)
                                     + i12 * (i11 * s12 + i12 * s22))
        var_b[i] = kappa * sigma2 * (i12 * (i12 * s11 + i22 * s12)
                                     + i22 * (i12 * s12 + i22 * s22))
        cov_cb[i] = kappa * sigma2 * (i11 * (i12 * s11 + i22 * s12)
                                      + i12 * (i12 * s12 + i22 * s22))
        # the residual correction's factor, one per pixel: u and the one-pixel estimate
        t1 = ci * (pq + lam * qq) + bi * (pa + lam * qa)
        t2 = ci * (eq + lam * qa) + bi * (ea + lam * aa)
        u1 = i11 * t1 + i12 * t2
        u2 = i12 * t1 + i22 * t2
        u1_out[i] = u1
        u2_out[i] = u2
        den = ci * ci * qq + 2 * ci * bi * qa + bi * bi * aa - (t1 * u1 + t2 * u2)
        z_res = (ci * (qy - ci * (pq + lam * qq) - bi * (eq + lam * qa))
                 + bi * (ay - ci * (pa + lam * qa) - bi * (ea + lam * aa)))
        ok = den > 0.0
        dev[i] = z_res / den if ok else np.nan
        dev_noise[i] = kappa * sigma2 / den if ok else np.nan
    return var_c, var_b, cov_cb, u1_out, u2_out, dev, dev_noise


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _overlap_errors(var_c: np.ndarray, var_b: np.ndarray, cov_cb: np.ndarray, u1: np.ndarray,
                    u2: np.ndarray, valid: np.ndarray, tau2: float) -> Any:  # pragma: no cover
    """``sqrt(noise variance + tau^2 u^2)`` of ``c`` and ``b`` (``inf`` where not valid or
    not finite) and the correlation of their errors (NaN there)."""
    n = var_c.size
    se_c = np.empty(n)
    se_b = np.empty(n)
    rho = np.empty(n)
    for i in range(n):
        vc = var_c[i] + tau2 * u1[i] * u1[i]
        vb = var_b[i] + tau2 * u2[i] * u2[i]
        ok_c = valid[i] & np.isfinite(vc) & (vc >= 0.0)
        ok_b = valid[i] & np.isfinite(vb) & (vb >= 0.0)
        se_c[i] = np.sqrt(vc) if ok_c else np.inf
        se_b[i] = np.sqrt(vb) if ok_b else np.inf
        cv = cov_cb[i] + tau2 * u1[i] * u2[i]
        r = cv / np.sqrt(vc * vb) if ok_c & ok_b & (vc > 0.0) & (vb > 0.0) else np.nan
        rho[i] = min(1.0, max(-1.0, r)) if np.isfinite(r) else np.nan
    return se_c, se_b, rho


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _lambda_terms(m: np.ndarray, n_events: np.ndarray, min_events: int,
                  min_decorrelation: float, min_contrast: float, max_contrast: float,
                  max_bias_ratio: float) -> Any:  # pragma: no cover - compiled
    """Per pixel, the plain fit (``lam = 0``) of :func:`correction_lambda`: the trust mask,
    the residual's ``Q`` cross product and ``c Q^2`` of :meth:`NormalEquations.
    residual_lambda` (the same operations in the same order as the numpy version)."""
    n = m.shape[1]
    mask = np.empty(n, np.bool_)
    res_q = np.empty(n, np.float64)
    cq = np.empty(n, np.float64)
    lam = 0.0
    pq, eq, qq, qa, qy = m[2], m[5], m[7], m[8], m[12]
    for i in range(n):
        _, _, _, _, _, c, b, ok, _ = _pixel_fit(m, i, lam, min_decorrelation)
        mask[i] = (ok & (n_events[i] >= min_events) & (c > min_contrast) & (c < max_contrast)
                   & (abs(b) < max_bias_ratio * c))
        res_q[i] = qy[i] - c * (pq[i] + lam * qq[i]) - b * (eq[i] + lam * qa[i])
        cq[i] = c * qq[i]
    return mask, res_q, cq


def correction_lambda(ne: NormalEquations, setting: str | float, limits: SolveLimits,
                      n_events: np.ndarray) -> float:
    """The residual-correction factor: 0 for ``"off"``, a given number, or estimated.

    ``"auto"``: fit with no correction, then one step of :meth:`NormalEquations.
    residual_lambda` over the pixels with a trusted fit; clipped to [0, 0.5] (0.5 is a residual
    uniform over the whole threshold cell).
    """
    if setting == "off":
        return 0.0
    if setting != "auto":
        return float(setting)
    n_ev = np.ascontiguousarray(np.broadcast_to(np.asarray(n_events, np.int64).ravel(),
                                                (ne.n_pixels,)))
    # one compiled pass; the sums stay numpy's (pairwise) so lam is bit-identical
    mask, res_q, cq = _lambda_terms(ne.m, n_ev, int(limits.min_events),
                                    float(limits.min_decorrelation), float(limits.min_contrast),
                                    float(limits.max_contrast), float(limits.max_bias_ratio))
    if not mask.any():
        return 0.0
    den = float(cq[mask].sum())
    lam = 0.0 if den <= 0 else 0.0 + float(res_q[mask].sum()) / den
    return float(np.clip(lam, 0.0, 0.5))
