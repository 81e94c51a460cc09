"""OffEI: per-pixel least squares of event sums against frame log-intensity changes.

Between frames ``j`` and ``k`` a pixel obeys (Wang et al.'s model)::

    L_k - L_j = c * SP + b * SE + (r_k - r_j)

with ``SP`` the net polarity and ``SE`` the event count in between, ``L = log(I + offset)``
and ``r`` the sub-threshold residual (log intensity minus the pixel's reference level) at each
frame. A plain fit treats ``r_k - r_j`` as noise, but it is not: just after an ON event the
residual is positive (the intensity was rising), just after an OFF event negative, so it
correlates with the window's polarity and the plain slope over-estimates ``c`` by a few percent.

Residual correction (default ``"auto"``): if the most recent event before frame ``k`` had
polarity ``q_k`` (0 if none yet), the residual holds on average ``E[r_k] = lam (q_k c + |q_k| b)``
for some ``lam`` in [0, 1/2] (1/2 would be a residual uniform over the cell just crossed; in
textured motion the intensity tends to settle after a burst of events, so it is smaller).
Moving that expected part into the regressors gives::

    L_k - L_j = c * (SP + lam (q_k - q_j)) + b * (SE + lam (|q_k| - |q_j|)) + noise

``lam`` is estimated from the data: a plain fit first, then the part of its residuals still
explained by ``q_k - q_j`` (one step, :meth:`NormalEquations.residual_lambda`). All cross
products are accumulated in one pass, so this costs no second pass over the events.

Windows overlap (every pair ``(k - d, k)``), as in the paper; the standard errors account
for the overlap by counting ``n / d`` independent equations.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field

import numba
import numpy as np

from .accumulate import Snapshot, frame_snapshots
from .calibration import DEFAULT_BIAS, DEFAULT_CONTRAST, Calibration, Reason
from .recording import Recording, RecordingError


class CalibrationError(ValueError):
    """The data cannot support the requested calibration (too few frames, no events, ...)."""


# ----------------------------------------------------------------------------------------
# frames to log intensity


def log_intensity(image: np.ndarray, log_offset: float) -> np.ndarray:
    """``log(I + offset)`` as float64; uint8 frames go through a 256-entry table."""
    if image.dtype == np.uint8:
        lut = np.log(np.arange(256, dtype=np.float64) + log_offset)
        return lut[image]
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
        # one (16, n) block: a row per cross product, each row a flat map
        self.m = np.zeros((len(_TERMS), self.n_pixels), np.float64)
        for i, name in enumerate(_TERMS):
            setattr(self, name, self.m[i])

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
def _add_sparse(m, idx, p, e, q, a, dl, w, sign):  # pragma: no cover - compiled
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
def _pixel_fit(m, i, lam, min_decorrelation):  # pragma: no cover - compiled
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
def _solve_pixels(m, n_events, lam, overlap, min_events, min_equations, min_decorrelation,
                  min_contrast, max_contrast, max_bias_ratio, extra_reason
                  ):  # pragma: no cover - compiled
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
    """The per-pixel solve as flat maps (float64 ``c``, ``b`` and standard errors)."""

    contrast: np.ndarray
    bias: np.ndarray
    valid: np.ndarray
    reason: np.ndarray
    stderr_contrast: np.ndarray
    stderr_bias: np.ndarray


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
    params: dict | None = None,
    extra_reason: np.ndarray | None = None,
    residual_lambda: float = 0.0,
) -> Calibration:
    """Closed-form 2x2 solve at every pixel, with validity reasons and standard errors.

    ``overlap`` is how many equations share each piece of data (``d`` for overlapping windows);
    the residual degrees of freedom are divided by it.
    """
    sol = solve_pixels(ne, n_events, limits=limits, overlap=overlap,
                       extra_reason=extra_reason, residual_lambda=residual_lambda)
    from .special import classify  # noqa: PLC0415 - avoid an import cycle

    special = classify(sol.contrast, sol.bias, sol.stderr_contrast, sol.stderr_bias, sol.valid)
    return Calibration(
        contrast=sol.contrast.reshape(shape),
        bias=sol.bias.reshape(shape),
        valid=sol.valid.reshape(shape),
        reason=sol.reason.reshape(shape),
        stderr_contrast=sol.stderr_contrast.reshape(shape),
        stderr_bias=sol.stderr_bias.reshape(shape),
        special=special.reshape(shape),
        log_offset=float(log_offset),
        method=method,
        n_events=np.asarray(n_events, np.int64).reshape(shape),
        params=dict(params or {}),
    )


# ----------------------------------------------------------------------------------------
# OffEI


@dataclass(frozen=True, kw_only=True)
class OffEIConfig:
    """OffEI parameters.

    ``window_frames`` is ``d``: each equation spans ``d`` frame intervals (the paper used 40
    at 25 Hz). ``log_offset`` is a number or ``"auto"``.
    """

    window_frames: int = 5
    log_offset: float | str = "auto"
    residual_correction: str | float = "auto"
    saturation_dn: tuple[float, float] = (0.0, 255.0)
    limits: SolveLimits = field(default_factory=SolveLimits)
    offset_grid: tuple[float, float, int] = (1.0, 400.0, 21)
    offset_pixels: int = 10000
    seed: int = 0

    def __post_init__(self) -> None:
        if int(self.window_frames) < 1:
            raise ValueError(f"window_frames={self.window_frames} must be >= 1")
        rc = self.residual_correction
        if not (rc in ("auto", "off") or (isinstance(rc, (int, float)) and 0 <= rc <= 1)):
            raise ValueError(f"residual_correction={rc!r} must be 'auto', 'off' or in [0, 1]")
        if not (self.log_offset == "auto" or (isinstance(self.log_offset, (int, float))
                                              and self.log_offset >= 0)):
            raise ValueError(f"log_offset={self.log_offset!r} must be 'auto' or a number >= 0")


def _window_terms(s_j: Snapshot, s_k: Snapshot):
    """``(P, E, Q, A)`` of the window between two snapshots (float64 flat maps)."""
    on = (s_k.on - s_j.on).astype(np.float64)
    off = (s_k.off - s_j.off).astype(np.float64)
    qk = s_k.last_p.astype(np.float64)
    qj = s_j.last_p.astype(np.float64)
    return on - off, on + off, qk - qj, np.abs(qk) - np.abs(qj)


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _lambda_terms(m, n_events, min_events, min_decorrelation, min_contrast, max_contrast,
                  max_bias_ratio):  # pragma: no cover - compiled
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


def _check_frames(rec: Recording, d: int) -> None:
    assert rec.frames is not None
    n = len(rec.frames)
    if n < d + 1:
        raise CalibrationError(
            f"the recording has {n} frames, fewer than one window of {d} frame intervals needs "
            f"({d + 1}); use a smaller --window-frames"
        )
    if rec.n_events == 0:
        raise CalibrationError("the recording has no events")


def _frame_flags(rec: Recording, saturation_dn: tuple[float, float]) -> np.ndarray:
    """SATURATED where a pixel is clipped in most frames, CONSTANT where it never changes."""
    assert rec.frames is not None
    imgs = rec.frames.images
    n = imgs.shape[0]
    flags = np.zeros(imgs.shape[1] * imgs.shape[2], np.uint8)
    clipped = np.zeros(flags.size, np.int32)
    lo = np.full(flags.size, np.inf)
    hi = np.full(flags.size, -np.inf)
    for k in range(n):  # loop over frames, vectorised over pixels
        f = imgs[k].ravel()
        clipped += ~usable(f, saturation_dn)
        lo = np.minimum(lo, f)
        hi = np.maximum(hi, f)
    flags[hi == lo] = Reason.CONSTANT
    flags[clipped > n // 2] = Reason.SATURATED
    return flags


def offei(rec: Recording, config: OffEIConfig | None = None) -> Calibration:
    """Offline events + intensity calibration (OffEI) of every pixel of ``rec``."""
    cfg = config or OffEIConfig()
    d = int(cfg.window_frames)
    _check_frames(rec, d)
    if cfg.log_offset == "auto":
        offset, offset_info = estimate_log_offset(rec, cfg)
    else:
        offset, offset_info = float(cfg.log_offset), {"method": "given"}
    ne = NormalEquations(rec.sensor.n_pixels)
    ring: deque[tuple[Snapshot, np.ndarray, np.ndarray]] = deque(maxlen=d + 1)
    last: Snapshot | None = None
    for snap in frame_snapshots(rec):
        img = snap.image.ravel()
        ring.append((snap, log_intensity(img, offset), usable(img, cfg.saturation_dn)))
        last = snap
        if len(ring) == d + 1:
            s_j, l_j, u_j = ring[0]
            s_k, l_k, u_k = ring[-1]
            p, e, q, a = _window_terms(s_j, s_k)
            ne.add(p, e, q, a, l_k - l_j, (u_j & u_k).astype(np.float64))
    assert last is not None
    # Events used: those between the first and the last frame.
    first_t, last_t = int(rec.frames.t_us[0]), int(rec.frames.t_us[-1])  # type: ignore[union-attr]
    n_events = _events_per_pixel(rec, first_t, last_t)
    lam = correction_lambda(ne, cfg.residual_correction, cfg.limits, n_events)
    params = {
        "residual_lambda": lam,
        "window_frames": d,
        "residual_correction": cfg.residual_correction,
        "log_offset": offset,
        "log_offset_estimation": offset_info,
        "n_frames": len(rec.frames),  # type: ignore[arg-type]
    }
    return solve_normal_equations(
        ne, n_events, rec.sensor.shape, limits=cfg.limits, overlap=float(d), log_offset=offset,
        method="offei", params=params, extra_reason=_frame_flags(rec, cfg.saturation_dn),
        residual_lambda=lam,
    )


def _events_per_pixel(rec: Recording, t0_us: int, t1_us: int) -> np.ndarray:
    ev = rec.events_between(t0_us, t1_us)
    idx = ev["y"].astype(np.int64) * rec.sensor.width + ev["x"]
    return np.bincount(idx, minlength=rec.sensor.n_pixels)


# ----------------------------------------------------------------------------------------
# log offset


def _unexplained_fraction(sp: np.ndarray, se: np.ndarray, dl: np.ndarray, w: np.ndarray,
                          dq: np.ndarray) -> float:
    """Mean over pixels of RSS / TSS of the per-pixel fit ``dL ~ P + E + Q``.

    Columns are pixels. ``Q`` (change of last polarity) takes up the sub-threshold residual
    so that it does not pull the offset.
    """
    x = np.stack([sp, se, dq], axis=-1)  # windows, pixels, 3
    xw = x * w[..., None]
    ata = np.einsum("wpi,wpj->pij", xw, x)
    aty = np.einsum("wpi,wp->pi", xw, dl)
    yy = (w * dl * dl).sum(0)
    ata += np.eye(3) * 1e-9 * np.trace(ata, axis1=1, axis2=2)[:, None, None]
    ok = (np.linalg.cond(ata) < 1e8) & (yy > 0)
    sol = np.linalg.solve(np.where(ok[:, None, None], ata, np.eye(3)), np.where(ok[:, None], aty, 0.0)[..., None])[..., 0]
    rss = yy - (sol * aty).sum(-1)
    frac = np.where(ok, np.maximum(rss, 0.0) / np.where(ok, yy, 1.0), np.nan)
    return float(np.nanmean(frac))


def estimate_log_offset(rec: Recording, cfg: OffEIConfig) -> tuple[float, dict]:
    """The offset ``o`` for which ``log(I + o)`` is best explained by the events.

    For each candidate on a log-spaced grid the per-pixel OffEI fit is solved on a sample of
    the busiest pixels; the criterion is the mean unexplained fraction ``RSS / sum(dL^2)``,
    which does not depend on the overall scale of ``dL`` (a larger offset shrinks every
    ``dL``). The grid minimum is refined by a parabola through its neighbours in ``log o``.
    """
    d = int(cfg.window_frames)
    _check_frames(rec, d)
    n_all = _events_per_pixel(rec, int(rec.frames.t_us[0]), int(rec.frames.t_us[-1]))  # type: ignore[union-attr]
    busy = np.flatnonzero(n_all >= cfg.limits.min_events)
    if busy.size == 0:
        raise CalibrationError("no pixel has enough events to estimate the log offset")
    rng = np.random.default_rng(cfg.seed)
    pix = np.sort(rng.choice(busy, size=min(cfg.offset_pixels, busy.size), replace=False))
    sps, ses, dqs, f_j, f_k, ws = [], [], [], [], [], []
    ring: deque[Snapshot] = deque(maxlen=d + 1)
    for snap in frame_snapshots(rec):
        ring.append(snap)
        if len(ring) == d + 1:
            s_j, s_k = ring[0], ring[-1]
            sp, se, dq, _ = _window_terms(s_j, s_k)
            dqs.append(dq[pix])
            ij = s_j.image.ravel()[pix]
            ik = s_k.image.ravel()[pix]
            sps.append(sp[pix])
            ses.append(se[pix])
            f_j.append(ij)
            f_k.append(ik)
            ws.append((usable(ij, cfg.saturation_dn) & usable(ik, cfg.saturation_dn)))
    sp_a, se_a, dq_a = np.asarray(sps), np.asarray(ses), np.asarray(dqs)
    fj = np.asarray(f_j, np.float64)
    fk = np.asarray(f_k, np.float64)
    w = np.asarray(ws, np.float64)
    lo, hi, n = cfg.offset_grid
    grid = np.geomspace(lo, hi, int(n))

    def crit(o: float) -> float:
        dl = np.log(np.maximum(fk, 0) + o) - np.log(np.maximum(fj, 0) + o)
        return _unexplained_fraction(sp_a, se_a, dl, w, dq_a)

    vals = np.array([crit(o) for o in grid])
    i = int(np.nanargmin(vals))
    best = float(grid[i])
    if 0 < i < len(grid) - 1:
        x = np.log(grid[i - 1 : i + 2])
        y = vals[i - 1 : i + 2]
        denom = (x[0] - x[1]) * (x[0] - x[2]) * (x[1] - x[2])
        a = (x[2] * (y[1] - y[0]) + x[1] * (y[0] - y[2]) + x[0] * (y[2] - y[1])) / denom
        bq = (x[2] ** 2 * (y[0] - y[1]) + x[1] ** 2 * (y[2] - y[0]) + x[0] ** 2 * (y[1] - y[2])) / denom
        if a > 0:
            xv = -bq / (2 * a)
            if x[0] <= xv <= x[2]:
                best = float(np.exp(xv))
    at_edge = i in (0, len(grid) - 1)
    info = {
        "method": "auto",
        "criterion": "mean unexplained fraction of per-pixel OffEI fits",
        "pixels": int(pix.size),
        "windows": int(sp_a.shape[0]),
        "grid": grid.round(3).tolist(),
        "criterion_values": np.round(vals, 6).tolist(),
        "at_grid_edge": bool(at_edge),
    }
    if sp_a.shape[0] == 0:
        raise RecordingError("no windows to estimate the log offset from")
    return best, info
