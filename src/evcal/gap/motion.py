"""The image's motion between frames that the frames do not show, read from the events.

Flow interpolation (:mod:`evcal.gap.flow`) moves each pixel along a straight line from one
frame to the next. A camera shaken at 5-15 Hz, filmed at 20-30 Hz, does not go there in a
straight line: between two frames the image swings out and back by pixels, and an edge
crosses a pixel two or three times where the interpolation has it cross once (or not at
all: a shake the frame rate aliases). A simulation driven by the straight path fires the
wrong events however right its thresholds are.

The events say where the image went. Two consecutive events of one pixel, at ``t1`` and
``t2``, mark two crossings: the log intensity there changed between them by exactly one
step, ``c p2 + b`` (``p2`` the second one's polarity), whatever the pixel's reference was
before (a sum of events over a window would lose up to a threshold at each end, and bias a
swing out and back towards none). With the image at ``t`` the flow interpolation sampled
``shift(t)`` away (one vector for the whole image, linear between knots at eighths of the
frame interval, zero at the frames, which say where the image is then), each pair gives

    L(x + shift(t2), t2) - L(x + shift(t1), t1)  =  c p2 + b

solved for the knots' shifts by Gauss-Newton (the interpolation rendered along the shift so
far, its gradient for the linear step), Huber-weighted (a pair of noise events is not the
light's change), with a weak prior towards no shift and towards a smooth one. Beside the
shift, two terms the shift must not take on: a change common to every pixel at each knot
(a flickering light, a leak) and a lag of the events behind the straight path (a slow
photoreceptor, frames stamped off their exposure's middle; the straight path moved by the
flow over a share of the interval), so that the effects the gap workflow looks for later are
still in the data for it. The shift follows a camera's shake, not objects moving on their
own (those keep the straight path).

The estimate needs only the frames' interpolation, the events and the sensor's typical
``c`` and ``b`` (from the measurement's own fit): a per-pixel spread of the thresholds adds
noise, not a bias. An interval keeps the straight path unless the shift explains the pairs
beyond what the lag and the common change do, both by an F statistic of at least
:data:`MIN_F` and by a share of at least :data:`MIN_EXPLAINED` of what those leave: a
systematic misfit on hundreds of thousands of pairs passes any test of noise, not the share.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from ..errors import ConfigError

# steps per frame interval (at least 2 ms each)
STEPS_PER_INTERVAL = 8
MIN_STEP_US = 2000
# Gauss-Newton steps (each renders the interval's knots along the shift so far)
ITERATIONS = 2
# residuals beyond this many robust standard deviations are down-weighted (Huber)
HUBER_K = 2.0
# the shift's prior precision, a share of its columns' mean information
SHIFT_PRIOR = 0.02
# and on its second differences
SHIFT_SMOOTH = 0.02
# an interval needs this many pairs of events of one pixel
MIN_PAIRS = 200
# knots of the common change per knot of the shift
COMMON_PER_KNOT = 4
# and uses at most this many (evenly through them)
MAX_PAIRS = 50_000
# a shift larger than this (pixels) is not a shake the straight path missed
MAX_SHIFT_PX = 6.0
# the least share of the pairs' weighted squared misfit left by the lag and the common
# change that an interval's shift must explain to be kept
MIN_EXPLAINED = 0.3
# and the F statistic of the shift's columns at the straight path at least this
MIN_F = 30.0
# and the shift must reach this far (pixels) somewhere in the interval: below, what the
# straight path misses in a scene of sharp edges (a blur the frames' deblurring left, a
# flicker) passes both tests as a shift of a few tenths that jitters edges back and forth,
# firing short intervals the sensor did not (a shake's swing is larger)
MIN_SHIFT_PX = 0.5


@dataclass(frozen=True, eq=False)
class SubframeShift:
    """The image's shift (pixels, x then y) at knot times ``t_us`` (absolute, int64): the
    latent image at ``t`` is the flow interpolation sampled at ``(x, y) + shift(t)``,
    linear between knots, zero outside them."""

    t_us: np.ndarray
    shift_px: np.ndarray

    def __post_init__(self) -> None:
        t = np.asarray(self.t_us, np.int64)
        s = np.asarray(self.shift_px, np.float32)
        if t.ndim != 1 or s.shape != (t.size, 2):
            raise ConfigError(f"shift: {t.shape} knot times for shifts of shape {s.shape}")
        if t.size and np.any(np.diff(t) < 0):
            raise ConfigError("shift: knot times must not decrease")
        if not np.isfinite(s).all():
            raise ConfigError("shift: shifts must be finite")
        object.__setattr__(self, "t_us", t)
        object.__setattr__(self, "shift_px", s)

    def at(self, t_us: np.ndarray) -> np.ndarray:
        """``[n, 2]`` float32 shifts at the times ``t_us``."""
        t = np.asarray(t_us, np.float64).reshape(-1)
        out = np.zeros((t.size, 2), np.float32)
        if self.t_us.size:
            for i in range(2):
                out[:, i] = np.interp(t, self.t_us, self.shift_px[:, i], left=0.0, right=0.0)
        return out

    def digest(self) -> bytes:
        h = hashlib.blake2b(self.t_us.tobytes(), digest_size=16)
        h.update(self.shift_px.tobytes())
        return h.digest()

    @property
    def rms_px(self) -> float:
        return float(np.sqrt(np.mean(self.shift_px.astype(np.float64) ** 2) * 2)) \
            if self.t_us.size else 0.0


class ShiftableInterpolator(Protocol):
    """What the estimate needs of :class:`evcal.gap.flow.FlowInterpolator`: the frames, their
    times, the flow forward from each and a render of an interval along a shift."""

    images: np.ndarray
    t_us: np.ndarray
    fwd: np.ndarray

    def between(self, k: int, tau: float, shift: np.ndarray | None = None) -> np.ndarray: ...


def _log(img: np.ndarray, offset: float) -> np.ndarray:
    out: np.ndarray = np.log(np.maximum(img, 0.0) + np.float32(offset))
    return out


def _pairs(t: np.ndarray, pix: np.ndarray, pol: np.ndarray
           ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Consecutive events of the same pixel (time-ordered ``t``): the pixel, the two times
    and the second event's polarity."""
    order = np.argsort(pix, kind="stable")
    ps, ts, qs = pix[order], t[order], pol[order]
    same = ps[1:] == ps[:-1]
    return ps[1:][same], ts[:-1][same], ts[1:][same], qs[1:][same]


def _hat(u: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """For knot positions ``u`` (0..n): the knot below and the weight of the one above."""
    j = np.clip(np.floor(u).astype(np.int64), 0, n - 1)
    return j, (u - j).astype(np.float64)


def estimate_shift(interp: ShiftableInterpolator, event_t_us: np.ndarray, event_x: np.ndarray,
                   event_y: np.ndarray, event_p: np.ndarray, *, contrast: float, bias: float,
                   log_offset: float, full_scale_dn: float = 255.0,
                   steps: int = STEPS_PER_INTERVAL, iterations: int = ITERATIONS
                   ) -> tuple[SubframeShift, dict[str, float]]:
    """The shift of the image between frames (module docstring) from the events, given the
    interpolator ``interp`` (a :class:`evcal.gap.flow.FlowInterpolator` of the frames the
    events saw; its ``between(k, tau, shift)`` renders frame interval ``k`` at ``tau``).
    Returns the shifts and a summary (intervals kept, RMS shift, share explained)."""
    between = interp.between
    images = np.asarray(interp.images)
    frame_t = np.asarray(interp.t_us, np.int64)
    n_f, h, w = images.shape
    t = np.asarray(event_t_us, np.int64)
    pix = np.asarray(event_y, np.int64) * w + np.asarray(event_x, np.int64)
    pol = np.asarray(event_p, np.float64)
    bounds = np.searchsorted(t, frame_t, side="left")
    knots_t: list[np.ndarray] = []
    knots_s: list[np.ndarray] = []
    explained: list[float] = []
    f_stats: list[float] = []
    for k in range(n_f - 1):
        t0, t1 = int(frame_t[k]), int(frame_t[k + 1])
        n = int(max(1, min(steps, (t1 - t0) // MIN_STEP_US)))
        lo, hi = int(bounds[k]), int(bounds[k + 1])
        if n < 2 or hi - lo < MIN_PAIRS:
            continue
        p_pix, p_t1, p_t2, p_pol = _pairs(t[lo:hi], pix[lo:hi], pol[lo:hi])
        # pixels whose frames are clipped at full scale say nothing of the light there
        unclipped = ((images[k] < full_scale_dn) & (images[k + 1] < full_scale_dn)).ravel()
        keep = unclipped[p_pix]
        if keep.sum() > MAX_PAIRS:
            # plenty for a handful of unknowns: every m-th pair, the same on every run
            thin = np.zeros(keep.size, bool)
            idx = np.flatnonzero(keep)
            thin[idx[np.linspace(0, idx.size - 1, MAX_PAIRS).astype(np.int64)]] = True
            keep = thin
        p_pix, p_t1, p_t2, p_pol = p_pix[keep], p_t1[keep], p_t2[keep], p_pol[keep]
        if p_pix.size < MIN_PAIRS:
            continue
        span = float(t1 - t0)
        fwd = np.asarray(interp.fwd[k], np.float64)
        # per interval (the lag's unit: a share of the interval, columns of like size)
        vel = np.stack([fwd[..., 0].ravel(), fwd[..., 1].ravel()])
        j1, w1 = _hat((p_t1 - t0) * (n / span), n)
        j2, w2 = _hat((p_t2 - t0) * (n / span), n)
        target = contrast * p_pol + bias
        n_free = n - 1  # the interior knots; the frames hold the ends
        # the common change on a finer grid (a mains flicker of 100-120 Hz has periods of a
        # quarter of a 25 Hz interval; on the shift's knots it would alias into the shift),
        # held at zero at the interval's start (only its changes are seen)
        n_m = COMMON_PER_KNOT * n
        m1, mw1 = _hat((p_t1 - t0) * (n_m / span), n_m)
        m2, mw2 = _hat((p_t2 - t0) * (n_m / span), n_m)
        # columns: x and y shift at each interior knot, the common log change at each of
        # its knots but the first, and the events' lag
        n_col = 2 * n_free + n_m + 1
        # second differences of the shift over the knots (the ends held at zero)
        d2 = (np.eye(n + 1, k=0)[:-2] - 2 * np.eye(n + 1, k=1)[:-2] + np.eye(n + 1, k=2)[:-2]
              )[:, 1:n]
        rough = d2.T @ d2
        rows = np.arange(p_pix.size, dtype=np.int64)
        s = np.zeros((n + 1, 2), np.float64)
        wgt = np.ones(p_pix.size)
        rss_r0 = rss = 0.0
        for it in range(iterations):
            logs = np.empty((n + 1, h * w), np.float64)
            grads = np.empty((n + 1, 2, h * w), np.float64)
            for j in range(n + 1):
                img = images[k] if j == 0 else images[k + 1] if j == n else \
                    between(k, j / n, s[j].astype(np.float32))
                lg = _log(img, log_offset)
                gy, gx = np.gradient(lg)
                logs[j] = lg.ravel()
                grads[j, 0], grads[j, 1] = gx.ravel(), gy.ravel()
            resid = target - ((1 - w2) * logs[j2, p_pix] + w2 * logs[j2 + 1, p_pix]
                              - (1 - w1) * logs[j1, p_pix] - w1 * logs[j1 + 1, p_pix])
            # Huber weights: a pair of noise events (shot noise, a hot pixel) is not the
            # light's change and must not pull the shift
            sigma = 1.4826 * float(np.median(np.abs(resid))) + 1e-9
            wgt = np.minimum(1.0, HUBER_K * sigma / np.maximum(np.abs(resid), 1e-12))
            flat, vals = [], []
            for jj, wt, sign in ((j1, w1, -1.0), (j2, w2, 1.0)):
                # the events' lag behind the straight path (a slow photoreceptor, frames
                # stamped off their exposure): a column of its own, so that the shift
                # does not take it on; d/dt of the log intensity at the event
                gx_e = (1 - wt) * grads[jj, 0, p_pix] + wt * grads[jj + 1, 0, p_pix]
                gy_e = (1 - wt) * grads[jj, 1, p_pix] + wt * grads[jj + 1, 1, p_pix]
                # the straight path carries the image by the flow: d/dt L = -grad L . v
                dldt = -(gx_e * vel[0, p_pix] + gy_e * vel[1, p_pix])
                flat.append(rows * n_col + (n_col - 1))
                vals.append(-sign * dldt)
                for knot, wk in ((jj, 1 - wt), (jj + 1, wt)):
                    inner = (knot >= 1) & (knot <= n_free)
                    r_in, c0 = rows[inner], knot[inner] - 1
                    for comp in range(2):
                        flat.append(r_in * n_col + c0 + comp * n_free)
                        vals.append(sign * wk[inner] * grads[knot[inner], comp, p_pix[inner]])
            for mj, mw, sign in ((m1, mw1, -1.0), (m2, mw2, 1.0)):
                for knot, wk in ((mj, 1 - mw), (mj + 1, mw)):
                    on = knot >= 1
                    flat.append(rows[on] * n_col + 2 * n_free + knot[on] - 1)
                    vals.append(sign * wk[on])
            cols = np.bincount(np.concatenate(flat), weights=np.concatenate(vals),
                               minlength=p_pix.size * n_col).reshape(p_pix.size, n_col)
            cw = cols * wgt[:, None]
            ata = cw.T @ cols
            ata += np.eye(n_col) * (1e-6 * max(float(np.trace(ata)), 1e-12) / n_col)
            atr = cw.T @ resid
            # a prior on the shift (not on the lag): what a lag explains as well, a shift
            # that is the same all through the interval, goes to the lag
            n_s = 2 * n_free
            lam = SHIFT_PRIOR * float(np.mean(np.diag(ata)[:n_s]))
            ata[:n_s, :n_s] += np.eye(n_s) * lam
            atr[:n_s] -= lam * np.r_[s[1:n, 0], s[1:n, 1]]
            # and on its roughness: a camera's shake is smooth, and at the frames it is
            # where they are
            lam2 = SHIFT_SMOOTH * float(np.mean(np.diag(ata)[:n_s]))
            for comp in range(2):
                blk = slice(comp * n_free, (comp + 1) * n_free)
                ata[blk, blk] += lam2 * rough
                atr[blk] -= lam2 * (rough @ s[1:n, comp])
            try:
                delta = np.linalg.solve(ata, atr)
            except np.linalg.LinAlgError:
                break
            if it == 0:
                # the shift must explain the events beyond what a lag and a common change
                # alone do, by more than fitting noise would (an F test on the straight
                # path's linearisation): still scenes with noise events keep their path
                keep_c = np.r_[2 * n_free:n_col]
                try:
                    d_r = np.linalg.solve(ata[np.ix_(keep_c, keep_c)], atr[keep_c])
                except np.linalg.LinAlgError:
                    break
                rss_r = float(np.sum(wgt * (resid - cols[:, keep_c] @ d_r) ** 2))
                rss_r0 = rss_r
                rss_f = float(np.sum(wgt * (resid - cols @ delta) ** 2))
                dof = max(p_pix.size - n_col, 1)
                f_stat = ((rss_r - rss_f) / (2 * n_free)) / max(rss_f / dof, 1e-30)
                f_stats.append(f_stat)
                if f_stat < MIN_F:
                    break
            after = resid - cols @ delta
            rss = float(np.sum(wgt * after ** 2))
            s[1:n, 0] += delta[:n_free]
            s[1:n, 1] += delta[n_free:2 * n_free]
            np.clip(s, -MAX_SHIFT_PX, MAX_SHIFT_PX, out=s)
        if not f_stats or f_stats[-1] < MIN_F:
            continue
        # the share of what the lag and a common change leave that the shift explains
        share = 1.0 - rss / rss_r0 if rss_r0 > 0 else 0.0
        explained.append(share)
        if share < MIN_EXPLAINED or np.abs(s).max() < MIN_SHIFT_PX:
            continue
        knots_t.append(t0 + np.rint(span * np.arange(n + 1) / n).astype(np.int64))
        knots_s.append(s.astype(np.float32))
    if knots_t:
        shift = SubframeShift(np.concatenate(knots_t), np.concatenate(knots_s))
    else:
        shift = SubframeShift(np.zeros(0, np.int64), np.zeros((0, 2), np.float32))
    info = {"intervals": float(len(f_stats)), "moving": float(len(explained)),
            "kept": float(len(knots_t)),
            "rms_px": shift.rms_px,
            "explained_median": float(np.median(explained)) if explained else 0.0}
    return shift, info
