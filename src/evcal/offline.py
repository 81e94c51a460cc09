"""OffEI: offline per-pixel least squares of event sums against frame log-intensity changes.

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

Windows overlap (every pair ``(k - d, k)``), as in the paper. The noise of an equation is the
difference of the residuals at its two frames, so overlapping windows share it only as far as
a residual persists from frame to frame, and it telescopes along the regressors' mean; the
standard errors say so (:func:`~evcal.solver.overlap_standard_errors`).
"""

from __future__ import annotations

import os
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Any

import numba
import numpy as np

from .accumulate import Accumulator, Snapshot, frame_snapshots
from .calibration import Calibration, OffEIDiagnostics, Reason
from .errors import CalibrationError, ConfigError
from .events import SensorSize
from .recording import Frames, Recording, RecordingError, concat_events
from .solver import (
    NormalEquations,
    OverlapNoise,
    SolveLimits,
    WindowRing,
    calibration_from_solution,
    correction_lambda,
    log_intensity,
    overlap_standard_errors,
    solve_pixels,
    usable,
)
from .stream import frame_cut, frame_intervals

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
            raise ConfigError(f"window_frames={self.window_frames} must be >= 1")
        rc = self.residual_correction
        if not (rc in ("auto", "off") or (isinstance(rc, (int, float)) and 0 <= rc <= 1)):
            raise ConfigError(f"residual_correction={rc!r} must be 'auto', 'off' or in [0, 1]")
        if not (self.log_offset == "auto" or (isinstance(self.log_offset, (int, float))
                                              and self.log_offset >= 0)):
            raise ConfigError(f"log_offset={self.log_offset!r} must be 'auto' or a number >= 0")


def _window_terms(s_j: Snapshot, s_k: Snapshot
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``(P, E, Q, A)`` of the window between two snapshots (float64 flat maps)."""
    on = (s_k.on - s_j.on).astype(np.float64)
    off = (s_k.off - s_j.off).astype(np.float64)
    qk = s_k.last_p.astype(np.float64)
    qj = s_j.last_p.astype(np.float64)
    return on - off, on + off, qk - qj, np.abs(qk) - np.abs(qj)


def _check_frames(rec: Recording, d: int) -> None:
    n = len(rec.frames)
    if n < d + 1:
        raise CalibrationError(
            f"the recording has {n} frames, fewer than one window of {d} frame intervals needs "
            f"({d + 1}); use a smaller --window-frames"
        )
    if rec.n_events == 0:
        raise CalibrationError("the recording has no events")


def offei(rec: Recording, config: OffEIConfig | None = None) -> Calibration:
    """Offline events + intensity calibration (OffEI) of every pixel of ``rec``."""
    cfg = config or OffEIConfig()
    _check_frames(rec, int(cfg.window_frames))
    if cfg.log_offset == "auto":
        offset, offset_info = estimate_log_offset(rec, cfg)
    else:
        offset, offset_info = float(cfg.log_offset), {"method": "given"}
    acc = OffEIStream(rec.sensor, cfg, offset, offset_info)
    for k, chunk in frame_intervals(rec.events, rec.frames.t_us):
        acc.events(chunk)
        acc.frame(int(rec.frames.t_us[k]), rec.frames.images[k])
    return acc.result()


# the pixels and consecutive windows on which the correlation of overlapping windows' noise is
# measured (:func:`evcal.solver.noise_overlap`): about 10 MB whatever the recording's length
NOISE_SAMPLE_PIXELS = 2048
NOISE_SAMPLE_WINDOWS = 256


class OffEIStream:
    """OffEI fed in time order, for recordings that do not fit in memory: :meth:`events`
    (validated chunks, each before the next frame), :meth:`frame`, then :meth:`result`.

    Memory is bounded whatever the length: the running counts, the window ring of the last
    ``window_frames + 16`` frames (:class:`~evcal.solver.WindowRing`), the sums, and the
    per-pixel frame statistics of the SATURATED / CONSTANT flags. The log offset must be known
    (``offset``): :func:`offei_file` estimates it on a prefix. :func:`offei` is this fed
    from memory, so both give the same maps.
    """

    def __init__(self, sensor: SensorSize, config: OffEIConfig, offset: float,
                 offset_info: dict[str, Any] | None = None):
        self.sensor = sensor
        self.cfg = config
        self.offset = float(offset)
        self.offset_info = offset_info or {"method": "given"}
        n = sensor.n_pixels
        self._acc = Accumulator(sensor)
        self._ne = NormalEquations(n)
        self._ring = WindowRing(n, int(config.window_frames))
        self._count_first: np.ndarray | None = None  # events per pixel before frame 0
        self._clipped = np.zeros(n, np.int32)
        self._lo = np.full(n, np.inf)
        self._hi = np.full(n, -np.inf)
        self.n_frames = 0
        self.n_events = 0
        # the first frames of a sample of pixels, evenly spread over the sensor
        self._sample = np.unique(np.linspace(0, n - 1, min(n, NOISE_SAMPLE_PIXELS))
                                 .astype(np.int64))
        self._sample_frames: list[tuple[np.ndarray, ...]] = []

    def events(self, chunk: np.ndarray) -> None:
        """Events before the next frame (``t_us`` below it), validated and in time order."""
        self._acc.add(chunk)
        self.n_events += int(chunk.size)

    def frame(self, t_us: int, image: np.ndarray) -> None:
        img = np.asarray(image)
        if img.shape != self.sensor.shape:
            raise CalibrationError(f"frame at t_us={t_us} has shape {img.shape}, the sensor "
                                   f"is {self.sensor}")
        flat = np.ascontiguousarray(img.ravel())
        if self._count_first is None:
            self._count_first = (self._acc.on + self._acc.off).astype(np.int64)
        lo_dn, hi_dn = self.cfg.saturation_dn
        if flat.dtype == np.uint8:  # log through the 256-entry table of log_intensity
            lut = log_intensity(np.arange(256, dtype=np.uint8), self.offset)
        else:
            lut = np.empty(0)
        lg = np.empty(flat.size, np.float64)
        ok = np.empty(flat.size, np.bool_)
        _frame_maps(flat, float(lo_dn), float(hi_dn), self.offset, lut, self._clipped,
                    self._lo, self._hi, lg, ok)
        if len(self._sample_frames) < NOISE_SAMPLE_WINDOWS + int(self.cfg.window_frames):
            i = self._sample
            self._sample_frames.append((self._acc.on[i], self._acc.off[i], self._acc.last_p[i],
                                        lg[i], ok[i]))
        if self._ring.push(self._acc.on, self._acc.off, self._acc.last_p, lg, ok):
            self._ring.flush(self._ne)
        self.n_frames += 1

    def result(self) -> Calibration:
        d = int(self.cfg.window_frames)
        if self.n_frames < d + 1:
            raise CalibrationError(
                f"the recording has {self.n_frames} frames, fewer than one window of {d} frame "
                f"intervals needs ({d + 1}); use a smaller --window-frames")
        self._ring.flush(self._ne)
        assert self._count_first is not None
        # events used: those between the first and the last frame
        on_last, off_last = self._ring.counts(self._ring.n - 1)
        n_events = on_last.astype(np.int64) + off_last - self._count_first
        cfg = self.cfg
        lam = correction_lambda(self._ne, cfg.residual_correction, cfg.limits, n_events)
        flags = np.zeros(self.sensor.n_pixels, np.uint8)
        flags[self._hi == self._lo] = Reason.CONSTANT
        flags[self._clipped > self.n_frames // 2] = Reason.SATURATED
        sol = solve_pixels(self._ne, n_events, limits=cfg.limits, overlap=float(d),
                           extra_reason=flags, residual_lambda=lam)
        on, off, last_p, lg, ok = (np.stack(a) for a in zip(*self._sample_frames, strict=True))
        noise = OverlapNoise(window_frames=d, moments=self._ring.moments, sample=self._sample,
                             on=on, off=off, last_p=last_p, lg=lg, ok=ok)
        se_c, se_b, rho, kappa, tau = overlap_standard_errors(self._ne, sol, lam, noise)
        diagnostics = OffEIDiagnostics(
            residual_lambda=lam, window_frames=d, residual_correction=cfg.residual_correction,
            log_offset_estimation=self.offset_info, n_frames=self.n_frames,
            noise_overlap=kappa, lambda_spread=tau,
            error_correlation=rho.reshape(self.sensor.shape).astype(np.float32))
        return calibration_from_solution(replace(sol, se_c=se_c, se_b=se_b), n_events,
                                         self.sensor.shape, log_offset=self.offset,
                                         method="offei", diagnostics=diagnostics)


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _frame_maps(flat: np.ndarray, lo_dn: float, hi_dn: float, offset: float, lut: np.ndarray,
                clipped: np.ndarray, lo: np.ndarray, hi: np.ndarray, lg: np.ndarray,
                ok: np.ndarray) -> Any:  # pragma: no cover - compiled
    """One pass over a frame: ``lg = log(I + offset)`` (through ``lut`` for uint8 frames,
    as :func:`~evcal.solver.log_intensity`), ``ok`` = :func:`~evcal.solver.usable`, and the
    statistics of the SATURATED / CONSTANT flags (clipped count, running min and max)."""
    use_lut = lut.size > 0
    for i in range(flat.size):
        v = np.float64(flat[i])
        u = (v > lo_dn) & (v < hi_dn)
        ok[i] = u
        clipped[i] += 0 if u else 1
        lo[i] = v if v < lo[i] else lo[i]
        hi[i] = v if v > hi[i] else hi[i]
        lg[i] = lut[np.int64(flat[i])] if use_lut else np.log((v if v > 0.0 else 0.0) + offset)


def offei_file(path: str | os.PathLike[str], config: OffEIConfig | None = None, *,
               prefix_frames: int = 250,
               progress: Callable[[int, int], None] | None = None) -> Calibration:
    """OffEI of an evcal MCAP recording read message by message (files larger than memory).

    The log offset, when ``"auto"``, is estimated on the first ``prefix_frames`` frames and
    their events (held in memory, then fed on). ``progress(done, total)`` is called with
    messages read. Gives the maps of :func:`offei` when the prefix is the whole recording or
    the offset is given.
    """
    from .io.mcap_rec import iter_mcap  # noqa: PLC0415 - io is a layer above the core

    cfg = config or OffEIConfig()
    sensor, messages, total = iter_mcap(path)
    acc: OffEIStream | None = None
    held_ev: list[np.ndarray] = []  # the prefix, while the offset is unknown
    held_fr: list[tuple[int, np.ndarray]] = []
    pending: list[np.ndarray] = []  # events not yet before a frame
    last_frame_t: int | None = None

    def start(offset: float, info: dict[str, Any]) -> OffEIStream:
        s = OffEIStream(sensor, cfg, offset, info)
        ev = concat_events(held_ev)
        t = np.array([f[0] for f in held_fr], np.int64)
        for k, chunk in frame_intervals(ev, t):
            s.events(chunk)
            s.frame(held_fr[k][0], held_fr[k][1])
        held_ev.clear()
        held_fr.clear()
        return s

    def prefix_offset() -> tuple[float, dict[str, Any]]:
        t = np.array([f[0] for f in held_fr], np.int64)
        imgs = np.stack([f[1] for f in held_fr])
        prefix = Recording(sensor, concat_events(held_ev),
                           Frames(t, imgs, np.zeros(len(t), np.int64)))
        o, info = estimate_log_offset(prefix, cfg)
        info["prefix_frames"] = len(held_fr)
        return o, info

    done = 0
    for kind, t_us, payload in messages:
        done += 1
        if progress is not None and done % 64 == 0:
            progress(done, total)
        if kind == "events":
            if last_frame_t is not None and payload.size and int(payload["t_us"][0]) < last_frame_t:
                raise RecordingError(f"{path}: events at t_us={int(payload['t_us'][0])} come "
                                     f"after the frame at t_us={last_frame_t} in the file: it "
                                     "cannot be read in one pass (open it whole instead)")
            pending.append(payload)
            continue
        ev = concat_events(pending)
        cut = frame_cut(ev["t_us"], t_us)
        before, pending = ev[:cut], [ev[cut:]]
        last_frame_t = t_us
        if acc is None:
            held_ev.append(before)
            held_fr.append((t_us, payload))
            if cfg.log_offset != "auto":
                acc = start(float(cfg.log_offset), {"method": "given"})
            elif len(held_fr) >= prefix_frames:
                acc = start(*prefix_offset())
            continue
        acc.events(before)
        acc.frame(t_us, payload)
    if acc is None:  # the whole recording is the prefix
        if len(held_fr) < int(cfg.window_frames) + 1:
            raise CalibrationError(f"{path}: {len(held_fr)} frames, fewer than one window of "
                                   f"{cfg.window_frames} frame intervals needs")
        acc = start(*prefix_offset())
    if progress is not None:
        progress(total, total)
    return acc.result()


def _events_per_pixel(rec: Recording, t0_us: int, t1_us: int) -> np.ndarray:
    ev = rec.events_between(t0_us, t1_us)
    idx = ev["y"].astype(np.int64) * rec.sensor.width + ev["x"]
    return np.bincount(idx, minlength=rec.sensor.n_pixels)


# ----------------------------------------------------------------------------------------
# log offset


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _unexplained_fraction(sp: np.ndarray, se: np.ndarray, dq: np.ndarray, fj: np.ndarray,
                          fk: np.ndarray, w: np.ndarray, offset: float, lut: np.ndarray
                          ) -> float:  # pragma: no cover - compiled
    """Mean over pixels of RSS / TSS of the per-pixel fit ``dL ~ P + E + Q`` at ``offset``.

    Arrays are ``[window, pixel]``: net polarity, count, change of last polarity, the raw
    frames at both ends and the weights; ``dL = log(I_k + offset) - log(I_j + offset)``
    (through ``lut``, the logs of 0..255, when not empty), 0 where the weight is 0. ``Q``
    takes up the sub-threshold residual so that it does not pull the offset. A pixel counts
    when its 3x3 system (ridge of 1e-9 of its trace) has a condition number below 1e8 and
    ``dL`` is not all 0. One compiled pass without the GIL (the service computes this on a
    worker thread beside the frame path); the same values as the numpy formulation it
    replaced (eigenvalues for the condition number, the adjugate for the solve) to 1e-15.
    """
    n_w, n_p = sp.shape
    use_lut = lut.size > 0
    total = 0.0
    count = 0
    for p in range(n_p):
        a00 = a01 = a02 = a11 = a12 = a22 = 0.0
        b0 = b1 = b2 = 0.0
        yy = 0.0
        for k in range(n_w):
            wk = w[k, p]
            dl = 0.0
            if wk > 0:
                if use_lut:
                    dl = lut[np.int64(fk[k, p])] - lut[np.int64(fj[k, p])]
                else:
                    dl = (np.log(max(fk[k, p], 0.0) + offset)
                          - np.log(max(fj[k, p], 0.0) + offset))
            x0 = sp[k, p]
            x1 = se[k, p]
            x2 = dq[k, p]
            x0w = x0 * wk
            x1w = x1 * wk
            x2w = x2 * wk
            a00 += x0w * x0
            a01 += x0w * x1
            a02 += x0w * x2
            a11 += x1w * x1
            a12 += x1w * x2
            a22 += x2w * x2
            b0 += x0w * dl
            b1 += x1w * dl
            b2 += x2w * dl
            yy += wk * dl * dl
        reg = 1e-9 * (a00 + a11 + a22)
        a00 += reg
        a11 += reg
        a22 += reg
        # the extreme eigenvalues of the symmetric 3x3 (trigonometric method)
        q = (a00 + a11 + a22) / 3.0
        p2 = ((a00 - q) ** 2 + (a11 - q) ** 2 + (a22 - q) ** 2
              + 2.0 * (a01 * a01 + a02 * a02 + a12 * a12))
        if p2 <= 0.0:
            lmax = lmin = q
        else:
            pp = np.sqrt(p2 / 6.0)
            c00 = (a00 - q) / pp
            c11 = (a11 - q) / pp
            c22 = (a22 - q) / pp
            c01 = a01 / pp
            c02 = a02 / pp
            c12 = a12 / pp
            r = 0.5 * (c00 * (c11 * c22 - c12 * c12) - c01 * (c01 * c22 - c12 * c02)
                       + c02 * (c01 * c12 - c11 * c02))
            r = -1.0 if r < -1.0 else (1.0 if r > 1.0 else r)
            phi = np.arccos(r) / 3.0
            lmax = q + 2.0 * pp * np.cos(phi)
            lmin = q + 2.0 * pp * np.cos(phi + 2.0 * np.pi / 3.0)
        if not ((lmin > 0.0) and (lmax < 1e8 * lmin) and (yy > 0.0)):
            continue
        m00 = a11 * a22 - a12 * a12
        m01 = a02 * a12 - a01 * a22
        m02 = a01 * a12 - a02 * a11
        m11 = a00 * a22 - a02 * a02
        m12 = a01 * a02 - a00 * a12
        m22 = a00 * a11 - a01 * a01
        det = a00 * m00 + a01 * m01 + a02 * m02
        s0 = (m00 * b0 + m01 * b1 + m02 * b2) / det
        s1 = (m01 * b0 + m11 * b1 + m12 * b2) / det
        s2 = (m02 * b0 + m12 * b1 + m22 * b2) / det
        rss = yy - (s0 * b0 + s1 * b1 + s2 * b2)
        frac = (rss if rss > 0.0 else 0.0) / yy
        if np.isfinite(frac):
            total += frac
            count += 1
    return total / count if count else np.nan


def estimate_log_offset(rec: Recording, cfg: OffEIConfig) -> tuple[float, dict[str, Any]]:
    """The offset ``o`` for which ``log(I + o)`` is best explained by the events.

    For each candidate on a log-spaced grid the per-pixel OffEI fit is solved on a sample of
    the busiest pixels; the criterion is the mean unexplained fraction ``RSS / sum(dL^2)``,
    which does not depend on the overall scale of ``dL`` (a larger offset shrinks every
    ``dL``). The grid minimum is refined by a parabola through its neighbours in ``log o``;
    ``o = 0`` (no offset: ``log(DN)``) is tried too and wins when it explains the events
    better than every grid point.
    """
    d = int(cfg.window_frames)
    _check_frames(rec, d)
    n_all = _events_per_pixel(rec, int(rec.frames.t_us[0]), int(rec.frames.t_us[-1]))
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
            ws.append(usable(ij, cfg.saturation_dn) & usable(ik, cfg.saturation_dn))
    if not sps:
        raise RecordingError("no windows to estimate the log offset from")
    best, info = offset_from_windows(
        np.asarray(sps), np.asarray(ses), np.asarray(dqs), np.asarray(f_j, np.float64),
        np.asarray(f_k, np.float64), np.asarray(ws, np.float64), cfg.offset_grid)
    info["pixels"] = int(pix.size)
    return best, info


def offset_from_windows(sp_a: np.ndarray, se_a: np.ndarray, dq_a: np.ndarray,
                        fj: np.ndarray, fk: np.ndarray, w: np.ndarray,
                        offset_grid: tuple[float, float, int] = (1.0, 400.0, 21)
                        ) -> tuple[float, dict[str, Any]]:
    """The criterion of :func:`estimate_log_offset` on prepared windows ``[window, pixel]``:
    net polarity, count, change of last polarity, the raw frames at both ends and the weights
    (1 where both frames are usable). Shared with OnEI's online estimate
    (:meth:`evcal.online.OnlineCalibrator`, ``log_offset="auto"``)."""
    lo, hi, n = offset_grid
    grid = np.geomspace(lo, hi, int(n))
    sp_a, se_a, dq_a, fj, fk, w = (np.ascontiguousarray(a, np.float64)
                                   for a in (sp_a, se_a, dq_a, fj, fk, w))
    # 8-bit frames: the logs of 0..255 once per offset instead of two per window and pixel
    eight_bit = bool(((fj >= 0) & (fj <= 255) & (fj == np.floor(fj))).all()
                     and ((fk >= 0) & (fk <= 255) & (fk == np.floor(fk))).all())
    values = np.arange(256, dtype=np.float64)

    def crit(o: float) -> float:
        with np.errstate(divide="ignore"):  # o = 0 at black pixels (unusable: weight 0)
            lut = np.log(values + o) if eight_bit else np.empty(0)
        return float(_unexplained_fraction(sp_a, se_a, dq_a, fj, fk, w, float(o), lut))

    vals = np.array([crit(o) for o in grid])
    # 0 is a candidate of its own (frames in DN whose log the sensor sees, as v2e's); it is
    # off the log-spaced grid, so it wins only by beating the grid's best outright
    crit_zero = crit(0.0)
    if not np.isfinite(vals).any() and not np.isfinite(crit_zero):
        raise CalibrationError(
            "the log offset cannot be estimated: no window has both a usable change of the "
            f"frames and events to explain it ({int((w > 0).sum())} usable windows)")
    if not np.isfinite(vals).any():
        return 0.0, {"method": "auto", "windows": int(sp_a.shape[0]),
                     "criterion_at_zero": round(float(crit_zero), 6),
                     "note": "only offset 0 gives a finite criterion"}
    i = int(np.nanargmin(vals))
    best = float(grid[i])
    if 0 < i < len(grid) - 1:
        x = np.log(grid[i - 1 : i + 2])
        y = vals[i - 1 : i + 2]
        denom = (x[0] - x[1]) * (x[0] - x[2]) * (x[1] - x[2])
        a = (x[2] * (y[1] - y[0]) + x[1] * (y[0] - y[2]) + x[0] * (y[2] - y[1])) / denom
        bq = (x[2] ** 2 * (y[0] - y[1]) + x[1] ** 2 * (y[2] - y[0])
              + x[0] ** 2 * (y[1] - y[2])) / denom
        if a > 0:
            xv = -bq / (2 * a)
            if x[0] <= xv <= x[2]:
                best = float(np.exp(xv))
    at_edge = i in (0, len(grid) - 1)
    below: dict[float, float] = {}
    if i == 0:  # the grid's lower edge: look below it, down to no offset at all
        below = {o: crit(o) for o in (0.1 * grid[0], 0.3 * grid[0], 0.6 * grid[0])}
    below[0.0] = crit_zero
    finite = {o: v for o, v in below.items() if np.isfinite(v)}
    if finite and min(finite.values()) < float(vals[i]):
        best = min(finite, key=finite.__getitem__)
        at_edge = False
    info = {
        "method": "auto",
        "criterion": "mean unexplained fraction of per-pixel OffEI fits",
        "windows": int(sp_a.shape[0]),
        "grid": grid.round(3).tolist(),
        "criterion_values": np.round(vals, 6).tolist(),
        "criterion_at_zero": round(float(crit_zero), 6),
        "at_grid_edge": bool(at_edge),
    }
    return best, info
