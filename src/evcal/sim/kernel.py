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
- shot noise: a Poisson process whose rate depends on the light, drawn by thinning: each
  pixel keeps the time of its next candidate from a process at the law's highest rate, and a
  candidate becomes an event with the probability rate(I) / highest rate (at most one per
  pixel and step); an event resets the reference to the present log intensity. Nothing is
  drawn in a step without a candidate, so shot noise costs per event, not per step.

Randomness comes from a per-pixel xorshift64* stream seeded by the caller, so results do not
depend on the order pixels are visited in, and there is no global RNG state.

Speed: most pixels cannot fire in a given step, which a branch-free pass over all pixels tells
from bounds in the intensity domain (no logarithm); only the others run the crossing search.
With a photoreceptor low-pass (or thresholds that grow in the dark beside a leak) the
intensity-domain bounds do not hold: that pass then computes each pixel's comparator input
(the filter's log and exp) and compares it with the levels as the search would, so only
pixels that can fire are searched there too. The search's arithmetic is that of the plain
per-pixel version, so the shortcut changes no event (``run_steps(..., shortcut=False)`` runs
the search everywhere, for tests).
"""

from __future__ import annotations

import math
from typing import Any

import numba
import numpy as np

from .labels import LABEL_LEAK, LABEL_SHOT_NOISE, LABEL_SIGNAL

TWO_PI = 2.0 * math.pi


@numba.njit(cache=True, nogil=True, inline="always")
def _next_u01(state: np.ndarray, i: int) -> Any:  # pragma: no cover - compiled
    x = state[i]
    x ^= x >> np.uint64(12)
    x ^= x << np.uint64(25)
    x ^= x >> np.uint64(27)
    state[i] = x
    r = x * np.uint64(2685821657736338717)
    # 53 bits: through int64 the conversion is exact as from uint64, and it vectorises
    return np.float64(np.int64(r >> np.uint64(11))) * (1.0 / 9007199254740992.0)


@numba.njit(cache=True, nogil=True, inline="always")
def _normal(state: np.ndarray, i: int) -> Any:  # pragma: no cover - compiled
    u1 = _next_u01(state, i)
    u2 = _next_u01(state, i)
    return math.sqrt(-2.0 * math.log(1.0 - u1)) * math.cos(TWO_PI * u2)


@numba.njit(cache=True, nogil=True, inline="always")
def _response(x: float, tl_exp: float, tl_ref: float) -> Any:  # pragma: no cover - compiled
    """The comparator's input at ``x = I + dark``: ``ln x``, or with thresholds growing in
    the dark as ``(x / tl_ref)**(-tl_exp)`` the integral of ``d ln x`` over that factor
    (:class:`~evcal.sim.effects.ThresholdLight`), which fixed thresholds then compare."""
    if tl_exp == 0.0:
        return math.log(x)
    x = max(x, 1e-3)
    return math.log(tl_ref) + ((x / tl_ref) ** tl_exp - 1.0) / tl_exp


@numba.njit(cache=True, nogil=True, inline="always")
def _response_inv(y: float, tl_exp: float, tl_ref: float) -> Any:  # pragma: no cover
    """The ``x`` of :func:`_response` ``(x) = y`` (exponent in [0, 1]); 0 where ``y`` is
    below the response's range (every ``x`` is above it)."""
    if tl_exp == 0.0:
        return math.exp(y)
    u = 1.0 + tl_exp * (y - math.log(tl_ref))
    if u <= 0.0:
        return 0.0
    return tl_ref * u ** (1.0 / tl_exp)


@numba.njit(cache=True, nogil=True)
def _grow(buf: np.ndarray, n: int) -> Any:  # pragma: no cover - compiled
    out = np.empty(max(2 * buf.size, n + 1024), buf.dtype)
    out[: buf.size] = buf
    return out


# relative margin of the no-crossing test in the intensity domain (float32 bounds): far above
# the rounding of exp, log and float32 (1e-7), so a pixel it lets through cannot have fired
_MARGIN = 1e-6
_F32_TINY = 1.1754943508222875e-38  # smallest normal float32
# events in one bucket of the per-step sort above which insertion would cost more than merging
_MAX_BUCKET = 256
# buckets of the per-step sort (a microsecond each, up to steps of this length)
_MAX_KEYS = 1 << 20


@numba.njit(cache=True, nogil=True)
def _sort_step(t_f: np.ndarray, t_i: np.ndarray, pix: np.ndarray, pol: np.ndarray,
               lab: np.ndarray, start: np.ndarray, n: int, t0: float, dt: float,
               key: np.ndarray, order: np.ndarray, bkt: np.ndarray, tmp_i: np.ndarray,
               tmp_p: np.ndarray, tmp_o: np.ndarray, tmp_l: np.ndarray,
               tmp_f: np.ndarray) -> Any:
    """Stable sort of the events ``start..n`` of one step by ``t_f`` (all in ``[t0, t0 +
    dt]``): a counting sort on buckets of a microsecond (coarser for steps longer than
    ``key`` allows), then insertion within each bucket; a merge sort where one bucket holds
    too many. ``t_f`` is sorted too: the runs of pixel ranges are merged by it."""
    m = n - start
    if m < 2:
        return
    # any monotone bucketing keeps the sort exact
    scale = min(1.0, (key.size - 3) / dt) if dt > 0 else 1.0
    nb = int(dt * scale) + 2
    for j in range(nb + 1):
        key[j] = 0
    for q in range(m):
        b = np.int32((t_f[start + q] - t0) * scale)
        bkt[q] = b
        key[b + 1] += 1
    crowded = False
    for j in range(1, nb + 1):
        crowded |= key[j] > _MAX_BUCKET
        key[j] += key[j - 1]
    if crowded:
        o = np.argsort(t_f[start:n], kind="mergesort")
        for q in range(m):
            order[q] = o[q]
    else:
        for q in range(m):
            b = bkt[q]
            d = key[b]
            key[b] = d + 1
            order[d] = q
        # insertion inside buckets (stable: move only past strictly later times)
        for q in range(1, m):
            oq = order[q]
            tq = t_f[start + oq]
            bq = bkt[oq]
            r = q - 1
            while r >= 0:
                o_r = order[r]
                if bkt[o_r] != bq or t_f[start + o_r] <= tq:
                    break
                order[r + 1] = o_r
                r -= 1
            order[r + 1] = oq
    for q in range(m):
        tmp_i[q] = t_i[start + q]
        tmp_p[q] = pix[start + q]
        tmp_o[q] = pol[start + q]
        tmp_l[q] = lab[start + q]
        tmp_f[q] = t_f[start + q]
    for q in range(m):
        o = order[q]
        t_i[start + q] = tmp_i[o]
        pix[start + q] = tmp_p[o]
        pol[start + q] = tmp_o[o]
        lab[start + q] = tmp_l[o]
        t_f[start + q] = tmp_f[o]


@numba.njit(cache=True, nogil=True, inline="always")
def _lowpassed(a: float, inten: float, log_offset: float, dt_s: float, tl_exp: float,
               tl_ref: float, bw_cutoff_hz: float, bw_ref_dn: float, bw_min_hz: float
               ) -> Any:  # pragma: no cover - compiled
    """The photoreceptor low-pass's output at the end of a step of ``dt_s`` seconds from
    ``a``, the input's response at the step's end ``inten`` (DN), its cutoff growing with the
    light (:class:`~evcal.sim.effects.Bandwidth`)."""
    lraw = _response(inten + log_offset, tl_exp, tl_ref)
    fc_hz = max(bw_min_hz, bw_cutoff_hz * (inten + log_offset) / bw_ref_dn)
    alpha = 1.0 - math.exp(-TWO_PI * fc_hz * dt_s)
    return a + alpha * (lraw - a)


@numba.njit(cache=True, nogil=True)
def _search(j0: np.ndarray, n_slow: np.ndarray, slow_idx: np.ndarray, k: int,
            intensity: np.ndarray, times: np.ndarray, log_offset: np.ndarray, lf: np.ndarray,
            lf_ok: np.ndarray, i_prev: np.ndarray, hi_i: np.ndarray, lo_i: np.ndarray,
            ref_i: np.ndarray, ref: np.ndarray, th_on_nom: np.ndarray, th_off_nom: np.ndarray,
            th_on: np.ndarray, th_off: np.ndarray, dead_until: np.ndarray,
            last_fire: np.ndarray, leak_debt: np.ndarray, rng_state: np.ndarray,
            shot_next: np.ndarray, th_sigma: np.ndarray, refr_us: np.ndarray,
            refr_delay: np.ndarray, shot_rate_hz: np.ndarray, shot_ref_dn: np.ndarray,
            shot_exp: np.ndarray, bw_cutoff_hz: np.ndarray, bw_ref_dn: np.ndarray,
            bw_min_hz: np.ndarray, tl_exp: float, tl_ref: np.ndarray, lb: np.ndarray,
            t_f: np.ndarray, t_i: np.ndarray, pix: np.ndarray, pol: np.ndarray,
            lab: np.ndarray, n: int) -> Any:  # pragma: no cover - compiled
    """The exact crossing search of step ``k`` for the pixels ``slow_idx[j0:n_slow]``;
    returns ``(n, j)``, ``j < n_slow`` when the buffers have no room for pixel
    ``slow_idx[j]`` (nothing of it done: grow them and call again from ``j``). Where pass 1
    computed the comparator's input at the step's end (``lb`` not empty: a low-pass, or
    light-dependent thresholds with a leak), it is ``lb``."""
    cap = t_f.size
    drop = refr_us > 0.0 and not refr_delay
    delay = refr_us > 0.0 and refr_delay
    shot = shot_rate_hz > 0.0
    resp = lb.size > 0
    t0 = times[k]
    t1 = times[k + 1]
    dt = float(t1 - t0)
    for j in range(j0, n_slow):
        i = slow_idx[j]
        inten32 = intensity[k, i]
        inten = np.float64(inten32)
        r = ref[i]
        a = lf[i] if lf_ok[i] else _response(np.float64(i_prev[i]) + log_offset, tl_exp,
                                             tl_ref[i])
        b = lb[i] if resp else _response(inten + log_offset, tl_exp, tl_ref[i])
        # worst case of this pixel's events (thresholds are >= 0.2 of nominal); nothing of
        # the pixel's step is done yet when there is no room
        th_min = 0.2 * min(th_on_nom[i], th_off_nom[i])
        need = int((abs(b - r) + abs(a - r)) / th_min) + 8
        if n + need > cap:
            return n, j
        fn = 2.0
        npol = 0
        if shot and shot_next[i] < t1:
            # a candidate of the process at the highest rate (the intensity floored at a
            # tenth of the reference): an event with probability rate(I) / that rate
            f_cand = max((shot_next[i] - t0) / dt, 0.0)
            keep = (shot_ref_dn / max(inten, 0.1 * shot_ref_dn)) * 0.1
            if shot_exp != 1.0:
                keep = keep ** shot_exp
            if _next_u01(rng_state, i) < keep:
                fn = f_cand
                npol = 1 if _next_u01(rng_state, i) < 0.5 else -1
            mean_gap_us = 1e6 / (shot_rate_hz * 10.0 ** shot_exp)
            while shot_next[i] < t1:  # at most one event per step
                shot_next[i] += -math.log(1.0 - _next_u01(rng_state, i)) * mean_gap_us
        span = b - a
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
                low = min(lc, le)
                level_on = r + th_on[i]
                level_off = r - th_off[i]
                if level_on <= hi:
                    level = level_on
                    p = 1
                    if lc >= level:
                        f = fc
                    else:
                        f = (level - a) / span if span > 0 else 1.0
                elif level_off >= low:
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
                    th_off[i] = th_off_nom[i] * max(0.2,
                                                    1.0 + th_sigma * _normal(rng_state, i))
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
                        th_on[i] = th_on_nom[i] * max(
                            0.2, 1.0 + th_sigma * _normal(rng_state, i))
                        th_off[i] = th_off_nom[i] * max(
                            0.2, 1.0 + th_sigma * _normal(rng_state, i))
                    if drop:
                        dead_until[i] = tf + refr_us
        ref[i] = r
        lf[i] = b
        if not resp:
            # float32 rounds by far less than the margin, except below its normal range:
            # there hi goes to 0 (no shortcut) and lo up to the smallest normal; the
            # response is monotone, so its levels have images in the intensity domain
            hi = _response_inv(r + th_on[i], tl_exp, tl_ref[i]) * (1.0 - _MARGIN)
            lo = _response_inv(r - th_off[i], tl_exp, tl_ref[i]) * (1.0 + _MARGIN)
            hi_i[i] = np.float32(hi) if hi >= _F32_TINY else np.float32(0.0)
            lo_i[i] = np.float32(lo) if lo >= _F32_TINY else np.float32(_F32_TINY)
            ref_i[i] = r
    return n, n_slow


@numba.njit(cache=True, nogil=True)
def run_steps(
    intensity: Any,  # [K, N] float32: intensity (DN) at times[1..K]
    times: Any,  # [K + 1] int64 us: times[0] is the previous sample (the state's time)
    log_offset: Any,
    # per-pixel state (updated in place)
    lf: Any,  # log intensity seen by the comparator at times[0] (where lf_ok)
    lf_ok: Any,  # uint8: lf is up to date (else it is log(i_prev + log_offset), not yet computed)
    i_prev: Any,  # float32 intensity (DN) at times[0]
    hi_i: Any,  # float32 intensity-domain bounds: below exp(ref + th_on), above exp(ref - th_off)
    lo_i: Any,
    ref_i: Any,  # ref when hi_i, lo_i were computed (leak moves ref down between events)
    ref: Any,
    th_on_nom: Any,
    th_off_nom: Any,
    th_on: Any,
    th_off: Any,
    dead_until: Any,  # us (float), drop mode
    last_fire: Any,  # us (float), delay mode
    leak_rate: Any,  # Hz per pixel (0: no leak)
    leak_debt: Any,  # log units of drift not yet paid out as a labelled leak event
    rng_state: Any,  # uint64 per pixel
    shot_next: Any,  # float us: each pixel's next shot-noise candidate (see the module doc)
    # effect parameters (0 disables)
    th_sigma: Any,
    refr_us: Any,
    refr_delay: Any,
    leak_light_exp: Any,
    leak_ref_dn: Any,
    shot_rate_hz: Any,
    shot_ref_dn: Any,
    shot_exp: Any,
    bw_cutoff_hz: Any,
    bw_ref_dn: Any,
    bw_min_hz: Any,
    tl_exp: Any,  # ThresholdLight exponent (0: thresholds independent of light)
    tl_ref: Any,  # its reference intensity per pixel (units of I + dark)
    # output, appended from n on (grown as needed; the grown arrays are returned)
    t_f: Any,
    t_i: Any,
    pix: Any,
    pol: Any,
    lab: Any,
    n: Any,
    shortcut: bool = True,  # False: every pixel runs the exact search (for tests of the shortcut)
    p0: int = 0,  # the pixels p0..p1 (flat indices; p1 < 0: to the last) are simulated, the
    p1: int = -1,  # others' state is left alone (pixel ranges run in threads side by side)
) -> Any:  # pragma: no cover - compiled
    """Events of ``K`` steps appended to ``(t_float_us, t_us, pixel, polarity, label)`` from
    ``n`` on; returns the arrays and the new ``n``. The events of each step are sorted by time
    (stable: pixel order among equal times); in delay mode, whose events can move past the
    step's end, nothing is sorted (the caller sorts by ``t_float_us``). No pixel's events
    depend on another's, so ranges of pixels can run apart (``p0``, ``p1``; their runs
    merged by time give the events of one run over all).

    Each step runs in two passes. The first, over all pixels and free of branches, books the
    leak drift, draws the shot-noise number and tests whether the pixel can fire: not if its
    intensity at both ends of the step lies strictly between the intensity-domain images of
    its two levels (the log is monotone) and no shot noise or dead time is due. That is most
    pixels; the second pass runs the exact crossing search, with the arithmetic of the
    one-pass version, on the others only, so the events do not depend on the shortcut.
    """
    k_steps, n_all = intensity.shape
    # unsigned loop bounds: a signed index that may be negative gets a wraparound test at
    # every access, and the loops over pixels would no longer vectorise
    lo_pix = np.uint64(min(max(p0, 0), n_all))
    hi_pix = np.uint64(n_all if p1 < 0 else min(max(p1, p0), n_all))
    drop = refr_us > 0.0 and not refr_delay
    delay = refr_us > 0.0 and refr_delay
    bw = bw_cutoff_hz > 0.0
    shot = shot_rate_hz > 0.0
    leak = False
    for i in range(lo_pix, hi_pix):
        if leak_rate[i] > 0.0:
            leak = True
            break
    max_dt = 0
    for k in range(k_steps):
        max_dt = max(max_dt, int(times[k + 1] - times[k]))
    key = np.empty(min(max_dt, _MAX_KEYS) + 3, np.int64)
    order = np.empty(0, np.int64)
    bkt = np.empty(0, np.int32)
    tmp_i = np.empty(0, np.int64)
    tmp_p = np.empty(0, np.int32)
    tmp_o = np.empty(0, np.int8)
    tmp_l = np.empty(0, np.uint8)
    tmp_f = np.empty(0, np.float64)
    slow = np.empty(n_all, np.uint8)
    slow_idx = np.empty(n_all, np.int64)
    # the comparator's input at each step's end, from pass 1 (see below)
    resp = bw or (tl_exp != 0.0 and leak)
    lb = np.empty(n_all if resp else 0, np.float64)
    for k in range(k_steps):
        t0 = times[k]
        t1 = times[k + 1]
        dt = float(t1 - t0)
        dt_s = dt * 1e-6
        n_start = n
        # pass 1 (loops the compiler vectorises): leak drift and the no-crossing test (a
        # pixel with a shot-noise candidate in the step is not quiet; every draw happens in
        # pass 2, so a pixel's random stream does not depend on the shortcut)
        # without light dependence, the drift goes into the test's loop (ref is read once)
        # the intensity-domain bounds need the comparator to see a function of I + dark
        # alone (not with a low-pass, which runs the exact search everywhere), and with leak
        # a bound moved by the drift as ln's is (not a light-dependent threshold's)
        # with a low-pass the filter moves every pixel every step, and with thresholds that
        # grow in the dark a leak's drift moves the levels' intensity-domain images unlike
        # ln's: pass 1 then computes the comparator's input (a log, and the low-pass's exp,
        # per pixel) and tests it against the levels where pass 2 compares them
        exact = not resp and not shortcut
        fused = leak and leak_light_exp == 0.0 and not exact and not resp
        if leak and not fused:
            for i in range(lo_pix, hi_pix):
                rate = leak_rate[i]
                if leak_light_exp != 0.0 and rate > 0.0:
                    rate *= (max(np.float64(intensity[k, i]), 1e-3) / leak_ref_dn
                             ) ** leak_light_exp
                d = rate * th_on_nom[i] * dt_s
                ref[i] = ref[i] - d
                leak_debt[i] += d
        t1f = float(t1)
        if resp:
            for i in range(lo_pix, hi_pix):
                a = lf[i] if lf_ok[i] else _response(np.float64(i_prev[i]) + log_offset,
                                                     tl_exp, tl_ref[i])
                inten = np.float64(intensity[k, i])
                if bw:
                    b = _lowpassed(a, inten, log_offset, dt_s, tl_exp, tl_ref[i],
                                   bw_cutoff_hz, bw_ref_dn, bw_min_hz)
                else:
                    b = _response(inten + log_offset, tl_exp, tl_ref[i])
                lb[i] = b
                quiet = (max(a, b) < ref[i] + th_on[i]) & (min(a, b) > ref[i] - th_off[i])
                quiet &= shortcut
                if drop:
                    quiet &= dead_until[i] <= t0
                if shot:
                    quiet &= shot_next[i] >= t1f
                slow[i] = np.uint8(not quiet)
        elif exact:
            for i in range(lo_pix, hi_pix):
                slow[i] = 1
        elif fused:
            for i in range(lo_pix, hi_pix):
                d = leak_rate[i] * th_on_nom[i] * dt_s
                r = ref[i] - d
                ref[i] = r
                leak_debt[i] += d
                xa = np.float64(i_prev[i]) + log_offset
                xb = np.float64(intensity[k, i]) + log_offset
                # exp(r + th_on) >= exp(ref_i + th_on) (1 - (ref_i - r)): leak lowers it
                h = np.float64(hi_i[i]) * (1.0 - (ref_i[i] - r))
                lo = np.float64(lo_i[i])
                quiet = (xa < h) & (xb < h) & (xa > lo) & (xb > lo)
                if drop:
                    quiet &= dead_until[i] <= t0
                if shot:
                    quiet &= shot_next[i] >= t1f
                slow[i] = np.uint8(not quiet)
        else:
            for i in range(lo_pix, hi_pix):
                xa = np.float64(i_prev[i]) + log_offset
                xb = np.float64(intensity[k, i]) + log_offset
                h = np.float64(hi_i[i]) * (1.0 - (ref_i[i] - ref[i]))
                lo = np.float64(lo_i[i])
                quiet = (xa < h) & (xb < h) & (xa > lo) & (xb > lo)
                if drop:
                    quiet &= dead_until[i] <= t0
                if shot:
                    quiet &= shot_next[i] >= t1f
                slow[i] = np.uint8(not quiet)
        n_slow = 0
        for i in range(lo_pix, hi_pix):
            slow_idx[n_slow] = i
            n_slow += slow[i]
        # pass 2: the exact search where a pixel may fire (returns early when the buffers
        # are full: growing them here, not in its loop, keeps reference counting out of it)
        j = 0
        while j < n_slow:
            n, j = _search(j, n_slow, slow_idx, k, intensity, times, log_offset, lf, lf_ok,
                           i_prev, hi_i, lo_i, ref_i, ref, th_on_nom, th_off_nom, th_on,
                           th_off, dead_until, last_fire, leak_debt, rng_state, shot_next,
                           th_sigma, refr_us, refr_delay, shot_rate_hz, shot_ref_dn, shot_exp,
                           bw_cutoff_hz, bw_ref_dn, bw_min_hz, tl_exp, tl_ref, lb, t_f, t_i,
                           pix, pol, lab, n)
            if j < n_slow:
                t_f = _grow(t_f, n)
                t_i = _grow(t_i, n)
                pix = _grow(pix, n)
                pol = _grow(pol, n)
                lab = _grow(lab, n)
        # every pixel moves on to this step's intensity; lf is up to date where pass 2 ran
        if resp:  # the comparator's input is every pixel's
            for i in range(lo_pix, hi_pix):
                i_prev[i] = intensity[k, i]
                lf[i] = lb[i]
                lf_ok[i] = 1
        else:
            for i in range(lo_pix, hi_pix):
                i_prev[i] = intensity[k, i]
                lf_ok[i] = slow[i]
        m = n - n_start
        # delayed events may leave their step: the caller sorts those globally
        if m > 1 and not delay:
            if order.size < m:
                order = np.empty(2 * m, np.int64)
                bkt = np.empty(2 * m, np.int32)
                tmp_i = np.empty(2 * m, np.int64)
                tmp_p = np.empty(2 * m, np.int32)
                tmp_o = np.empty(2 * m, np.int8)
                tmp_l = np.empty(2 * m, np.uint8)
                tmp_f = np.empty(2 * m, np.float64)
            _sort_step(t_f, t_i, pix, pol, lab, n_start, n, float(t0), dt, key, order, bkt,
                       tmp_i, tmp_p, tmp_o, tmp_l, tmp_f)
    return t_f, t_i, pix, pol, lab, n


@numba.njit(cache=True, nogil=True)
def merge_runs(a_f: np.ndarray, a_i: np.ndarray, a_p: np.ndarray, a_o: np.ndarray,
               a_l: np.ndarray, na: int, b_f: np.ndarray, b_i: np.ndarray, b_p: np.ndarray,
               b_o: np.ndarray, b_l: np.ndarray, nb: int) -> Any:  # pragma: no cover
    """The events of two runs sorted by ``t_f`` (``a``'s first ``na``, ``b``'s first ``nb``),
    merged by ``t_f``; ``a`` first among equal times (its pixels come first)."""
    n = na + nb
    o_f = np.empty(n, np.float64)
    o_i = np.empty(n, np.int64)
    o_p = np.empty(n, np.int32)
    o_o = np.empty(n, np.int8)
    o_l = np.empty(n, np.uint8)
    i = 0
    j = 0
    for q in range(n):
        if j >= nb or (i < na and a_f[i] <= b_f[j]):
            o_f[q], o_i[q], o_p[q], o_o[q], o_l[q] = a_f[i], a_i[i], a_p[i], a_o[i], a_l[i]
            i += 1
        else:
            o_f[q], o_i[q], o_p[q], o_o[q], o_l[q] = b_f[j], b_i[j], b_p[j], b_o[j], b_l[j]
            j += 1
    return o_f, o_i, o_p, o_o, o_l


def concat_runs(a_f: np.ndarray, a_i: np.ndarray, a_p: np.ndarray, a_o: np.ndarray,
                a_l: np.ndarray, na: int, b_f: np.ndarray, b_i: np.ndarray, b_p: np.ndarray,
                b_o: np.ndarray, b_l: np.ndarray, nb: int) -> tuple[np.ndarray, ...]:
    """The events of two runs one after the other (``a``'s first ``na``, ``b``'s ``nb``)."""
    return tuple(np.concatenate([x[:na], y[:nb]]) for x, y in (
        (a_f, b_f), (a_i, b_i), (a_p, b_p), (a_o, b_o), (a_l, b_l)))


@numba.njit(cache=True, nogil=True)
def fill_events(t_out: np.ndarray, x_out: np.ndarray, y_out: np.ndarray, p_out: np.ndarray,
                t_us: np.ndarray, pix: np.ndarray, pol: np.ndarray, width: int) -> Any:
    """The fields of an events array (views) from times, flat pixel indices and polarities."""
    # y = q // width by a float reciprocal (an integer division per event costs more than the
    # rest): (q + 0.5) / width is at least 0.5 / width from an integer, far above the error
    inv_w = 1.0 / width
    for j in range(t_us.size):
        t_out[j] = t_us[j]
        q = np.int64(pix[j])
        y = np.int64((q + 0.5) * inv_w)
        y_out[j] = y
        x_out[j] = q - y * width
        p_out[j] = pol[j]


@numba.njit(cache=True, nogil=True)
def step_events(t_us: np.ndarray, pix: np.ndarray, pol: np.ndarray, lab: np.ndarray,
                n_pix: int, origin_us: float, step_us: float, t_end_us: float,
                refr_us: float, refr_drop: bool) -> Any:  # pragma: no cover - compiled
    """The events of a frame-driven simulator that decides per step of ``step_us`` (steps
    ``(origin + k step, origin + (k + 1) step]``) from the crossings ``t_us`` (sorted, with
    their pixel, polarity and label) of the same pixels run without a dead time.

    In each step a pixel's count ``n`` is its signed number of crossings not yet emitted
    (crossings of opposite sign cancel: the simulator compares the log intensity at the step's
    end with its reference). ``N``, the largest ``|n|`` of any pixel (at least 1), defines
    ``N`` slots at ``start + i step / N`` (i = 1..N); slot i emits one event of every pixel
    with ``|n| >= i``, unless the pixel is in its dead time: with ``refr_us > step / N``, an
    event passes only more than ``refr_us`` after the pixel's last emitted one (its last
    stamp, not its last crossing). What the dead time blocks stays pending into the next steps
    (``refr_drop``: it is lost). Noise events (labels other than signal and leak) are
    stamped at the step's end after the signal events and do not start a dead time; shot
    noise clears the pixel's pending count (it resets the reference). The label of an emitted
    signal event is that of the pixel's latest crossing.

    Returns ``(t_us, pix, pol, lab)`` sorted by time; with ``refr_us = 0`` and one crossing
    sign per pixel and step, the same events with new times.
    """
    n = t_us.size
    cap = n + 16
    o_t = np.empty(cap, np.int64)
    o_p = np.empty(cap, np.int32)
    o_s = np.empty(cap, np.int8)
    o_l = np.empty(cap, np.uint8)
    m = 0
    pend = np.zeros(n_pix, np.int64)
    plab = np.zeros(n_pix, np.uint8)
    mem = np.full(n_pix, -np.inf)
    active = np.empty(n_pix, np.int64)
    is_act = np.zeros(n_pix, np.bool_)
    n_act = 0
    cnt = np.empty(n_pix, np.int64)
    noise = np.empty(0, np.int64)
    k_last = np.int64(math.ceil((t_end_us - origin_us) / step_us)) - 1
    j = 0
    k = np.int64(0)
    if n > 0:
        k = max(np.int64(0), np.int64(math.ceil((t_us[0] - origin_us) / step_us)) - 1)
    while k <= k_last and (j < n or n_act > 0):
        if n_act == 0 and j < n:
            # nothing pending: jump to the step of the next crossing
            k = max(k, np.int64(math.ceil((t_us[j] - origin_us) / step_us)) - 1)
        start = origin_us + k * step_us
        end = start + step_us
        j0 = j
        n_noise = 0
        while j < n and t_us[j] <= end:
            q = pix[j]
            if lab[j] == LABEL_SIGNAL or lab[j] == LABEL_LEAK:
                pend[q] += pol[j]
                plab[q] = lab[j]
                if not is_act[q]:
                    is_act[q] = True
                    active[n_act] = q
                    n_act += 1
            else:
                n_noise += 1
            j += 1
        if n_noise > noise.size:
            noise = np.empty(2 * n_noise, np.int64)
        r = 0
        for jj in range(j0, j):
            if not (lab[jj] == LABEL_SIGNAL or lab[jj] == LABEL_LEAK):
                noise[r] = jj
                r += 1
        n_max = 0
        for a in range(n_act):
            q = active[a]
            cnt[q] = abs(pend[q])
            n_max = max(n_max, cnt[q])
        slots = max(n_max, 1)
        gate = refr_us > step_us / slots
        if m + n_max * n_act + n_noise > cap:
            cap = 2 * (m + n_max * n_act + n_noise) + 1024
            o_t, o_p, o_s, o_l = (_grow(o_t, cap), _grow(o_p, cap), _grow(o_s, cap),
                                  _grow(o_l, cap))
            cap = o_t.size
        for i in range(n_max):
            ts = start + (i + 1) * step_us / slots
            ti = np.int64(np.rint(ts))
            for a in range(n_act):
                q = active[a]
                if cnt[q] <= i or (gate and not ts - mem[q] > refr_us):
                    continue
                mem[q] = ts
                s = 1 if pend[q] > 0 else -1
                pend[q] -= s
                o_t[m] = ti
                o_p[m] = q
                o_s[m] = s
                o_l[m] = plab[q]
                m += 1
        if refr_drop:
            for a in range(n_act):
                pend[active[a]] = 0
        te = np.int64(np.rint(end))
        for r in range(n_noise):
            jj = noise[r]
            q = pix[jj]
            if lab[jj] == LABEL_SHOT_NOISE:
                pend[q] = 0
            o_t[m] = te
            o_p[m] = q
            o_s[m] = pol[jj]
            o_l[m] = lab[jj]
            m += 1
        b = 0
        for a in range(n_act):
            q = active[a]
            if pend[q] != 0:
                active[b] = q
                b += 1
            else:
                is_act[q] = False
        n_act = b
        k += 1
    return o_t[:m], o_p[:m], o_s[:m], o_l[:m]
