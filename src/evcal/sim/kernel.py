"""The per-pixel sequential part of the non-ideal DVS: one numba kernel over steps x pixels.

Between two internal samples the (optionally low-passed) log intensity of a pixel is a line
``L(f) = a + f (b - a)``, ``f`` in [0, 1]. Crossings are found exactly on that line as in
:mod:`evcal.sim.dvs` (same formulas, so with every effect off the events are those of
:class:`~evcal.sim.dvs.IdealDvs`), with on top:

- thresholds re-drawn after every event (threshold noise);
- a dead time after every event, in which crossings are lost (``drop``: the reference follows
  the log intensity until the dead time ends) or delayed (``delay``: fire at its end);
- a reference that drifts down (leak), the drift being booked so that leak events get a label
  (an ON event is labelled leak when at least half a threshold of drift is unpaid);
- at most one shot-noise event per pixel and step (Poisson rate x step << 1), which resets the
  reference to the present log intensity.

Randomness comes from a per-pixel xorshift64* stream seeded by the caller, so results do not
depend on the order pixels are visited in, and there is no global RNG state.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from .effects import LABEL_LEAK, LABEL_SHOT_NOISE, LABEL_SIGNAL

TWO_PI = 2.0 * math.pi


@numba.njit(cache=True, nogil=True, inline="always")
def _next_u01(state, i):  # pragma: no cover - compiled
    x = state[i]
    x ^= x >> np.uint64(12)
    x ^= x << np.uint64(25)
    x ^= x >> np.uint64(27)
    state[i] = x
    r = x * np.uint64(2685821657736338717)
    return (r >> np.uint64(11)) * (1.0 / 9007199254740992.0)


@numba.njit(cache=True, nogil=True, inline="always")
def _normal(state, i):  # pragma: no cover - compiled
    u1 = _next_u01(state, i)
    u2 = _next_u01(state, i)
    return math.sqrt(-2.0 * math.log(1.0 - u1)) * math.cos(TWO_PI * u2)


@numba.njit(cache=True, nogil=True)
def _grow(buf, n):  # pragma: no cover - compiled
    out = np.empty(max(2 * buf.size, n + 1024), buf.dtype)
    out[: buf.size] = buf
    return out


@numba.njit(cache=True, nogil=True)
def _step(
    k, i_start, n, t_f, t_i, pix, pol, lab,
    intensity, times, log_offset, lf, ref, th_on_nom, th_off_nom, th_on, th_off, dead_until,
    last_fire, leak_rate, leak_debt, rng_state, th_sigma, refr_us, refr_delay, leak_light_exp,
    leak_ref_dn, shot_rate_hz, shot_ref_dn, bw_cutoff_hz, bw_ref_dn, bw_min_hz,
):  # pragma: no cover - compiled
    """Pixels ``i_start..`` of step ``k``; returns ``(n, i)``: ``i < N`` when the buffers are
    too small for pixel ``i`` (nothing of it was done: grow and call again from ``i``)."""
    n_pix = intensity.shape[1]
    cap = t_f.size
    drop = refr_us > 0.0 and not refr_delay
    delay = refr_us > 0.0 and refr_delay
    t0 = times[k]
    t1 = times[k + 1]
    dt = float(t1 - t0)
    dt_s = dt * 1e-6
    for i in range(i_start, n_pix):
        inten = intensity[k, i]
        a = lf[i]
        lraw = math.log(inten + log_offset)
        if bw_cutoff_hz > 0.0:
            fc_hz = max(bw_min_hz, bw_cutoff_hz * (inten + log_offset) / bw_ref_dn)
            alpha = 1.0 - math.exp(-TWO_PI * fc_hz * dt_s)
            b = a + alpha * (lraw - a)
        else:
            b = lraw
        drift = 0.0
        if leak_rate[i] > 0.0:
            rate = leak_rate[i]
            if leak_light_exp != 0.0:
                rate *= (max(inten, 1e-3) / leak_ref_dn) ** leak_light_exp
            drift = rate * th_on_nom[i] * dt_s
        r = ref[i] - drift
        # worst case of this pixel's events (thresholds are >= 0.2 of nominal)
        th_min = 0.2 * min(th_on_nom[i], th_off_nom[i])
        need = int((abs(b - r) + abs(a - r)) / th_min) + 8
        if n + need > cap:
            return n, i
        leak_debt[i] += drift
        span = b - a
        # shot noise: at most one event in this step, at fraction fn
        fn = 2.0
        npol = 0
        if shot_rate_hz > 0.0:
            rate = shot_rate_hz * shot_ref_dn / max(inten, 0.1 * shot_ref_dn)
            pr = rate * dt_s
            u = _next_u01(rng_state, i)
            if u < pr:
                fn = u / pr
                npol = 1 if _next_u01(rng_state, i) < 0.5 else -1
        fc = 0.0
        # two passes: crossings up to the noise event (if any), then the rest of the step
        for part in range(2):
            f_end = fn if (part == 0 and fn < 1.0) else 1.0
            if part == 1 and fn >= 1.0:
                break
            # dead time (drop): the reference follows L until it ends
            if drop and dead_until[i] > t0 + fc * dt:
                fd = (dead_until[i] - t0) / dt
                if fd >= f_end:
                    fc = f_end
                    r = b if f_end >= 1.0 else a + f_end * span
                else:
                    fc = fd
                    r = a + fd * span
            while fc < f_end:
                lc = a if fc == 0.0 else a + fc * span
                le = b if f_end >= 1.0 else a + f_end * span
                hi = max(lc, le)
                lo = min(lc, le)
                level_on = r + th_on[i]
                level_off = r - th_off[i]
                if level_on <= hi:
                    level = level_on
                    p = 1
                    if lc >= level:
                        f = fc
                    else:
                        f = (level - a) / span if span > 0 else 1.0
                elif level_off >= lo:
                    level = level_off
                    p = -1
                    if lc <= level:
                        f = fc
                    else:
                        f = (a - level) / (-span) if span < 0 else 1.0
                else:
                    break
                f = min(max(f, fc), f_end)
                tf = t0 + f * dt
                ti = t0 + np.int64(np.rint(f * dt))
                if delay and tf < last_fire[i] + refr_us:
                    tf = last_fire[i] + refr_us
                    ti = np.int64(np.rint(tf))
                last_fire[i] = tf
                label = LABEL_SIGNAL
                if p > 0 and leak_debt[i] >= 0.5 * th_on_nom[i]:
                    label = LABEL_LEAK
                    leak_debt[i] -= th_on_nom[i]
                t_f[n] = tf
                t_i[n] = ti
                pix[n] = i
                pol[n] = p
                lab[n] = label
                n += 1
                r = level
                if th_sigma > 0.0:
                    th_on[i] = th_on_nom[i] * max(0.2, 1.0 + th_sigma * _normal(rng_state, i))
                    th_off[i] = th_off_nom[i] * max(0.2, 1.0 + th_sigma * _normal(rng_state, i))
                fc = f
                if drop:
                    dead_until[i] = tf + refr_us
                    fd = (dead_until[i] - t0) / dt
                    if fd >= f_end:
                        fc = f_end
                        r = b if f_end >= 1.0 else a + f_end * span
                        break
                    fc = fd
                    r = a + fd * span
            if part == 0 and fn < 1.0:
                # the shot-noise event at fn (lost in a dead time)
                tf = t0 + fn * dt
                fc = fn
                if not (drop and tf < dead_until[i]):
                    ti = t0 + np.int64(np.rint(fn * dt))
                    if delay and tf < last_fire[i] + refr_us:
                        tf = last_fire[i] + refr_us
                        ti = np.int64(np.rint(tf))
                    last_fire[i] = tf
                    t_f[n] = tf
                    t_i[n] = ti
                    pix[n] = i
                    pol[n] = npol
                    lab[n] = LABEL_SHOT_NOISE
                    n += 1
                    r = a + fn * span
                    if th_sigma > 0.0:
                        th_on[i] = th_on_nom[i] * max(0.2, 1.0 + th_sigma * _normal(rng_state, i))
                        th_off[i] = th_off_nom[i] * max(0.2, 1.0 + th_sigma * _normal(rng_state, i))
                    if drop:
                        dead_until[i] = tf + refr_us
        ref[i] = r
        lf[i] = b
    return n, n_pix


@numba.njit(cache=True, nogil=True)
def run_steps(
    intensity,  # [K, N] float64: intensity (DN) at times[1..K]
    times,  # [K + 1] int64 us: times[0] is the previous sample (the state's time)
    log_offset,
    # per-pixel state (updated in place)
    lf,  # log intensity seen by the comparator at times[0]
    ref,
    th_on_nom,
    th_off_nom,
    th_on,
    th_off,
    dead_until,  # us (float), drop mode
    last_fire,  # us (float), delay mode
    leak_rate,  # Hz per pixel (0: no leak)
    leak_debt,  # log units of drift not yet paid out as a labelled leak event
    rng_state,  # uint64 per pixel
    # effect parameters (0 disables)
    th_sigma,
    refr_us,
    refr_delay,
    leak_light_exp,
    leak_ref_dn,
    shot_rate_hz,
    shot_ref_dn,
    bw_cutoff_hz,
    bw_ref_dn,
    bw_min_hz,
    capacity,
):  # pragma: no cover - compiled
    """Events of ``K`` steps: ``(t_float_us, t_us, pixel, polarity, label)``, unsorted."""
    k_steps, n_pix = intensity.shape
    t_f = np.empty(capacity, np.float64)
    t_i = np.empty(capacity, np.int64)
    pix = np.empty(capacity, np.int32)
    pol = np.empty(capacity, np.int8)
    lab = np.empty(capacity, np.uint8)
    n = 0
    for k in range(k_steps):
        i = 0
        while i < n_pix:
            n, i = _step(k, i, n, t_f, t_i, pix, pol, lab, intensity, times, log_offset, lf,
                         ref, th_on_nom, th_off_nom, th_on, th_off, dead_until, last_fire,
                         leak_rate, leak_debt, rng_state, th_sigma, refr_us, refr_delay,
                         leak_light_exp, leak_ref_dn, shot_rate_hz, shot_ref_dn, bw_cutoff_hz,
                         bw_ref_dn, bw_min_hz)
            if i < n_pix:
                t_f = _grow(t_f, n)
                t_i = _grow(t_i, n)
                pix = _grow(pix, n)
                pol = _grow(pol, n)
                lab = _grow(lab, n)
    return t_f[:n], t_i[:n], pix[:n], pol[:n], lab[:n]
