"""Summary statistics that the sensor effects move, computed the same way on any recording.

Every statistic is a function of a recording and its frames only (never of a model), so a
measured recording and its simulations are summarised identically. The frames are shared:
simulations in the gap workflow are driven by the measured frames, so bins defined on frames
(intensity, |dL|, static windows) are the same for both.

A window is the interval between two consecutive frames. Per pixel and window: ON and OFF
counts, ``P = ON - OFF``, ``E = ON + OFF`` and ``dL = L_k - L_j`` with ``L = log(I + o)``
at the nominal offset ``o`` (1 DN). The per-pixel fit ``dL = c P + b E`` (OffEI without
overlap; its sums and solve in :mod:`evcal.gap.pixelfit`) gives residuals ``res``.

=============================  ======================================================  ======
statistic                      value(s)                                                moved by
=============================  ======================================================  ======
iei_distribution               fraction of same-pixel inter-event intervals per        refr.,
                               log10(us) bin                                           jitter
iei_lower_edge                 log10 of the 0.1, 1, 5 % IEI quantiles (us), 0 us      refr.
                               pairs left out
static_rate_vs_intensity       events / pixel / s in static windows, per intensity     shot, hot
static_balance_vs_intensity    (ON - OFF) / pixel / s in static windows, per           leak
                               intensity bin
on_fraction_over_time          ON / (ON + OFF) in time bins                            leak
offei_residual_vs_dl           RMS residual per |dL| bin                               th.noise
offei_residual_vs_intensity    mean res * sign(dL) per bin of intensity relative to    offset
                               the pixel's median (windows with |dL| > 0.1)
offei_residual_vs_time         RMS residual per time bin                               th.noise
fit_population                 median c, median b, IQR of c of the per-pixel fit       (all)
estimate_stability             median |c1 - c2|, |b1 - b2| between the halves          th.noise
polarity_alternation           opposite-polarity fraction of consecutive same-pixel    shot
                               pairs: all, and IEI < 2 ms
rate_tail                      log10 of per-pixel count quantiles 50..99.9 % and max   hot
                               over the mean
speed_response                 events per unit |dL| in (dark, bright) x (slow, fast)   bandw.
lag_vs_intensity               weight of dL of the previous window in P, per           bandw.
                               intensity bin
timestamp_quantum              fraction of timestamps divisible by 10, 100, 1000 us    jitter
sensitivity_vs_intensity       events per unit |dL| in 5 bins of absolute intensity,   offset,
                               over all windows' (|dL| > 0.1)                          th.light
line_coincidence               still-window events per pixel-second with >= 2 other    row
                               still events of the same row (column) within 20 us      noise
=============================  ======================================================  ======
"""

from __future__ import annotations

import threading
import weakref
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..accumulate import order_by_key
from ..errors import EvcalError
from ..recording import Recording
from ..stream import event_windows as event_windows_of
from .pixelfit import fit_from_sums, window_sums
from .pixelfit import fit_pixels as fit_pixels  # tests/test_gap_speed.py imports it here
from .pixelfit import residual_from_sums as residual_from_sums  # and this one

NOMINAL_LOG_OFFSET_DN = 1.0
STATIC_DL = 0.05  # |dL| below this in a window and its neighbours: static
STATIC_HALF_WIDTH = 3
# a statistic over fitted pixels needs at least this many of them; fewer: NaN (see
# discrepancy: a component that is NaN in the measurement or a simulation is left out)
MIN_STAT_PIXELS = 20
IEI_EDGES_LOG10 = np.array([0.0, 1.0, 1.5, 2.0, 2.5, 3.0, 3.5, 4.0, 4.5, 5.0, 5.5, 7.0])


class GapError(EvcalError):
    """A recording the gap workflow cannot use (no frames, no events, too short)."""


@dataclass(frozen=True)
class StatValue:
    """One statistic: a vector of values with a label per component.

    ``floor`` is the smallest spread its components are standardised with (the size of a
    difference too small to mean anything, in the statistic's units).
    """

    name: str
    values: np.ndarray
    labels: list[str]
    floor: float | np.ndarray  # one for every component, or one each


@dataclass
class Observation:
    """Per-window arrays of one recording (see the module docstring)."""

    shape: tuple[int, int]
    frame_t_us: np.ndarray
    on: np.ndarray  # [n_w, N] int32
    off: np.ndarray
    log_i: np.ndarray  # [n_f, N] float64 at the nominal offset
    intensity: np.ndarray  # [n_f, N] float32 DN
    usable: np.ndarray  # [n_w, N] bool
    t_us: np.ndarray  # event times in range
    pix: np.ndarray  # event pixels in range
    p: np.ndarray
    # [n_w, N] bool: windows of pixels where the latent intensity between the frames is known
    # well enough for timing statistics (all True unless given; see evcal.gap.flow.trusted)
    trusted: np.ndarray | None = None
    extra: dict[str, Any] = field(default_factory=dict)
    # what depends on the frames only (static windows): shared by the observations of the
    # same frames (a measurement and its simulations), computed once
    shared: dict[str, Any] = field(default_factory=dict)

    @property
    def n_windows(self) -> int:
        return int(self.on.shape[0])

    @property
    def n_pixels(self) -> int:
        return int(self.on.shape[1])

    @property
    def window_s(self) -> np.ndarray:
        return np.diff(self.frame_t_us) * 1e-6


def observe(rec: Recording, *, saturation_dn: tuple[float, float] = (0.0, 255.0),
            trusted: np.ndarray | None = None) -> Observation:
    """Window arrays of ``rec`` between its first and last frame.

    ``trusted`` (``[n_frames - 1, n_pixels]`` bool) restricts the timing statistics (intervals
    between a pixel's events, speed response, lag) to windows where the interpolation between
    frames that a simulation of the recording is driven by can be trusted; the same mask is
    given to the measurement and its simulations (it depends on the frames only).

    Raises
    ------
    GapError
        With fewer than 4 frames or no events between them.
    """
    fr = rec.frames
    if fr is None or len(fr) < 4:
        raise GapError(f"the recording has {0 if fr is None else len(fr)} frames; the gap "
                       "workflow needs at least 4 (it compares events with frame changes)")
    h, w = rec.sensor.shape
    npix = h * w
    ft = fr.t_us
    ev = rec.events_between(int(ft[0]), int(ft[-1]))
    if ev.size == 0:
        raise GapError("no events between the first and the last frame")
    n_w = len(fr) - 1
    pix = ev["y"].astype(np.int64) * w + ev["x"]
    win = np.clip(event_windows_of(ev["t_us"], ft), 0, n_w - 1)
    key = win * npix + pix
    pix = pix.astype(np.int32)  # kept for as long as the observation is
    on_m = ev["p"] > 0
    on = np.bincount(key[on_m], minlength=n_w * npix).reshape(n_w, npix).astype(np.int32)
    off = np.bincount(key[~on_m], minlength=n_w * npix).reshape(n_w, npix).astype(np.int32)
    inten, log_i, usable, shared = _frame_arrays(fr.images, saturation_dn)
    if trusted is not None:
        trusted = np.asarray(trusted, bool)
        if trusted.shape != (n_w, npix):
            raise GapError(f"trusted mask has shape {trusted.shape}, expected {(n_w, npix)}")
    obs = Observation((h, w), ft.copy(), on, off, log_i, inten, usable, ev["t_us"].copy(),
                      pix, ev["p"].copy(), trusted, shared=shared)
    obs.extra["win"] = win.astype(np.int32)
    return obs


_FRAME_LOCK = threading.Lock()
# id(images) -> (weak reference to images, saturation, arrays): the simulations of a run are
# driven by (and carry) the measured frames themselves
_FRAME_CACHE: dict[int, tuple[Any, tuple[float, ...], Any]] = {}


def _frame_arrays(images: np.ndarray, saturation_dn: tuple[float, float]
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]:
    """Intensity, log intensity at the nominal offset and usable windows of ``images``
    (read-only), and the dictionary shared by the observations of these frames: computed
    once per frames and reused while they live (a run observes the same frames some
    hundred times)."""
    with _FRAME_LOCK:
        hit = _FRAME_CACHE.get(id(images))
        if hit is not None and hit[0]() is images and hit[1] == tuple(saturation_dn):
            arrays: tuple[np.ndarray, np.ndarray, np.ndarray, dict[str, Any]] = hit[2]
            return arrays
    n_f = images.shape[0]
    inten = images.reshape(n_f, -1).astype(np.float32)
    log_i = np.log(np.maximum(inten.astype(np.float64), 0.0) + NOMINAL_LOG_OFFSET_DN)
    lo, hi = saturation_dn
    ok = (inten > lo) & (inten < hi)
    usable = ok[1:] & ok[:-1]
    for a in (inten, log_i, usable):
        a.setflags(write=False)
    arrays = (inten, log_i, usable, {})
    key = id(images)

    def forget(_ref: Any) -> None:
        with _FRAME_LOCK:
            if key in _FRAME_CACHE and _FRAME_CACHE[key][0]() is None:
                del _FRAME_CACHE[key]

    try:
        ref = weakref.ref(images, forget)
    except TypeError:  # not weakly referable (a memory map's base, say): not cached
        return arrays
    with _FRAME_LOCK:
        _FRAME_CACHE[key] = (ref, tuple(saturation_dn), arrays)
    return arrays


def every_nth_row(obs: Observation, n: int) -> Observation:
    """``obs`` on every ``n``-th row of the sensor (rows 0, n, 2n, ...): for per-pixel
    statistics and fitters that need many pixels but not all of them (the sample is the
    same for a measurement and its simulations)."""
    if n <= 1:
        return obs
    return rows_of(obs, np.arange(0, obs.shape[0], n))


def rows_of(obs: Observation, rows: np.ndarray | slice,
            frames_cache: dict[str, Any] | None = None) -> Observation:
    """``obs`` on the sensor rows ``rows`` (indices, or a slice: a band, whose per-pixel
    arrays are views), as if recorded by a sensor of those rows.

    ``frames_cache``: a dictionary kept by the caller for one set of rows, in which the
    frame-side arrays cut to them (intensity, log intensity, usable and trusted windows) and
    their shared dictionary (static windows, ...) are kept: the observations of the same
    frames (a measurement and its simulations) then share them instead of each cutting and
    deriving its own."""
    h, w = obs.shape
    if isinstance(rows, slice):
        y0, y1, step = rows.indices(h)
        if step != 1:
            return rows_of(obs, np.arange(y0, y1, step), frames_cache)
        cols: np.ndarray | slice = slice(y0 * w, y1 * w)
        n_rows = y1 - y0
        keep = (obs.pix >= y0 * w) & (obs.pix < y1 * w)
        new_pix = obs.pix[keep] - y0 * w
    else:
        rows = np.asarray(rows, np.int64)
        n_rows = rows.size
        cols = (rows[:, None] * w + np.arange(w)[None, :]).ravel()
        new_index = np.full(h * w, -1, np.int64)
        new_index[cols] = np.arange(cols.size)
        keep = new_index[obs.pix] >= 0
        new_pix = new_index[obs.pix[keep]]
    key = (id(obs.intensity), id(obs.trusted))
    if frames_cache is not None and frames_cache.get("key") == key:
        fa = frames_cache
    else:
        fa = {"key": key, "log_i": obs.log_i[:, cols], "intensity": obs.intensity[:, cols],
              "usable": obs.usable[:, cols],
              "trusted": None if obs.trusted is None else obs.trusted[:, cols],
              "shared": {}, "source": (obs.intensity, obs.trusted)}
        if frames_cache is not None:
            frames_cache.clear()
            frames_cache.update(fa)
    return Observation((n_rows, w), obs.frame_t_us, obs.on[:, cols], obs.off[:, cols],
                       fa["log_i"], fa["intensity"], fa["usable"],
                       obs.t_us[keep], new_pix.astype(np.int32), obs.p[keep], fa["trusted"],
                       shared=fa["shared"])


def event_windows(obs: Observation) -> np.ndarray:
    """The window of each event of ``obs`` (int32)."""
    if "win" not in obs.extra:
        obs.extra["win"] = np.clip(event_windows_of(obs.t_us, obs.frame_t_us), 0,
                                   obs.n_windows - 1).astype(np.int32)
    result: np.ndarray = obs.extra["win"]
    return result


# ------------------------------------------------------------------------------ per-pixel fit


def _fit(obs: Observation) -> dict[str, Any]:
    if "fit" in obs.extra:
        cached: dict[str, Any] = obs.extra["fit"]
        return cached
    # counts stay int32 and the residual float32: a few such arrays per observation are
    # kept for as long as the observation is
    P = obs.on - obs.off
    E = obs.on + obs.off
    dL = _dl(obs)
    wgt = _shared(obs, "wgt", lambda: obs.usable.astype(np.float64))
    halves = window_sums(P, E, dL, wgt, split=obs.n_windows // 2)
    c, b, ok = fit_from_sums(*(halves[0] + halves[1])[:6])
    c1, b1, ok1 = fit_from_sums(*halves[0][:6])
    c2, b2, ok2 = fit_from_sums(*halves[1][:6])
    res = np.where(ok[None, :] & obs.usable, dL - np.nan_to_num(c) * P - np.nan_to_num(b) * E,
                   np.nan).astype(np.float32)
    out = {"P": P, "E": E, "dL": dL, "c": c, "b": b, "ok": ok, "res": res,
           "c1": c1, "c2": c2, "b1": b1, "b2": b2, "ok12": ok1 & ok2}
    obs.extra["fit"] = out
    return out


# frames per window of the fit the base model's maps are anchored by (:func:`block_fit`)
BLOCK_FIT_FRAMES = 5


def block_fit(obs: Observation) -> dict[str, Any]:
    """Per pixel ``c``, ``b`` (NaN where not fitted) and ``ok`` of the fit of :func:`_fit`
    over windows of :data:`BLOCK_FIT_FRAMES` frame intervals (at most a quarter of them),
    not one: a block counts where every interval of it is usable.

    One interval's change is a part of a threshold where the light changes slowly: a pixel
    fires in one interval of several, and the fit over intervals then says how fast the
    light changes, not what the threshold is (on a slow sine the same whether the
    thresholds are 0.1 or 0.3). Over a few intervals the change holds whole thresholds and
    the fit follows them, as OffEI's windows of several frames do."""
    if "block_fit" in obs.extra:
        cached: dict[str, Any] = obs.extra["block_fit"]
        return cached
    k = max(1, min(BLOCK_FIT_FRAMES, obs.n_windows // 4))
    n = (obs.n_windows // k) * k

    def blocks(a: np.ndarray) -> np.ndarray:
        out: np.ndarray = a[:n].reshape(n // k, k, -1).sum(1)
        return out

    def make_frames() -> np.ndarray:
        dl = blocks(_dl(obs))
        w = obs.usable[:n].reshape(n // k, k, -1).all(1).astype(np.float64)
        return np.stack([np.where(w > 0, dl, 0.0), w])

    dl, wgt = _shared(obs, f"block_fit_{k}", make_frames)
    s = window_sums(blocks(obs.on - obs.off).astype(np.int32),
                    blocks(obs.on + obs.off).astype(np.int32), dl, wgt)
    c, b, ok = fit_from_sums(*s[:6])
    out = {"c": c, "b": b, "ok": ok, "frames": k}
    obs.extra["block_fit"] = out
    return out


def _shared(obs: Observation, key: str, make: Any) -> np.ndarray:
    """``obs.shared[key]``, made (read-only) by ``make()`` on first use."""
    if key not in obs.shared:
        a = np.asarray(make())
        a.setflags(write=False)
        obs.shared[key] = a
    result: np.ndarray = obs.shared[key]
    return result


def _dl(obs: Observation) -> np.ndarray:
    """Each window's change of the frames' log intensity (nominal offset)."""
    return _shared(obs, "dL", lambda: obs.log_i[1:] - obs.log_i[:-1])


def _i_mid(obs: Observation) -> np.ndarray:
    """Each window's mean of its two frames' intensity, DN."""
    return _shared(obs, "i_mid", lambda: 0.5 * (obs.intensity[1:] + obs.intensity[:-1]))


def _plan(obs: Observation, name: str, make: Callable[[], Any]) -> Any:
    """What a statistic takes from the frames and the trusted mask alone (its windows, their
    bins, the frame-side sums), made by ``make()`` once per frames and mask and shared by
    the measurement and every simulation of them: a simulation then only gathers its own
    counts. Made again for an observation with another mask."""
    key = f"plan_{name}"
    hit = obs.shared.get(key)
    if hit is not None and hit[0] is obs.trusted:
        return hit[1]
    plan = make()
    obs.shared[key] = (obs.trusted, plan)
    return plan


def _quantile_edges(v: np.ndarray, n: int) -> np.ndarray:
    v = v[np.isfinite(v)]
    if v.size == 0:
        return np.linspace(0, 1, n + 1)
    e = np.unique(np.quantile(v, np.linspace(0, 1, n + 1)))
    if e.size < 2:
        e = np.array([e[0] - 1, e[0] + 1])
    e[0], e[-1] = -np.inf, np.inf
    return e


def _bin_of(key: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """The bin of each of ``key`` among ``edges`` (int8: at most a few dozen bins)."""
    return np.clip(np.searchsorted(edges, key, side="right") - 1, 0,
                   edges.size - 2).astype(np.int8)


# a bin of a mean over pixel-windows holds at least this many of them, else it is NaN (left
# out of the comparison): which pixels' fits are valid depends on their events, so a bin a
# few measured pixels reach may be empty in every simulation, and the mean of a handful
# against none, standardised by the statistic's small floor, would outweigh every other
# statistic
MIN_BIN_SAMPLES = 50


def _binned(values: np.ndarray, idx: np.ndarray, nb: int, *, how: str) -> np.ndarray:
    """The mean (``how="mean"``) or RMS (``"rms"``) of ``values`` in each of ``nb`` bins,
    ``idx`` each value's bin; NaN in a bin of fewer than :data:`MIN_BIN_SAMPLES` values."""
    n = np.bincount(idx, minlength=nb)
    enough = n >= MIN_BIN_SAMPLES
    if how == "mean":
        s = np.bincount(idx, weights=values, minlength=nb)
        return np.where(enough, s / np.maximum(n, 1), np.nan)
    if how == "rms":
        s = np.bincount(idx, weights=values * values, minlength=nb)
        return np.sqrt(np.where(enough, s / np.maximum(n, 1), np.nan))
    raise EvcalError(how)


def _edge_labels(edges: np.ndarray, unit: str, fmt: str = "{:.3g}") -> list[str]:
    out = []
    for a, b in zip(edges[:-1], edges[1:], strict=True):
        sa = "-inf" if not np.isfinite(a) else fmt.format(a)
        sb = "inf" if not np.isfinite(b) else fmt.format(b)
        out.append(f"{unit} {sa}..{sb}")
    return out


# ------------------------------------------------------------------------------ statistics


def _iei(obs: Observation) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Intervals between consecutive events of a pixel (us), whether the pair's polarities
    differ, and the pair's pixel; only pairs in trusted windows when the observation has a
    trusted mask."""
    if "iei" in obs.extra:
        cached: tuple[np.ndarray, np.ndarray, np.ndarray] = obs.extra["iei"]
        return cached
    order = order_by_key(obs.pix, obs.n_pixels)
    ps, ts, pp = obs.pix[order], obs.t_us[order], obs.p[order]
    same = ps[1:] == ps[:-1]
    if obs.trusted is not None:  # both events of a pair in trusted windows of their pixel
        tr = obs.trusted[event_windows(obs)[order], ps]
        same &= tr[1:] & tr[:-1]
    iei = (ts[1:] - ts[:-1])[same].astype(np.float64)
    opp = (pp[1:] != pp[:-1])[same]
    obs.extra["iei"] = (iei, opp, ps[1:][same])
    result: tuple[np.ndarray, np.ndarray, np.ndarray] = obs.extra["iei"]
    return result


def stat_iei_distribution(obs: Observation) -> StatValue:
    iei, _, _ = _iei(obs)
    lg = np.log10(np.maximum(iei, 1.0))
    h = histogram_sorted_edges(lg, IEI_EDGES_LOG10)
    frac = h / max(h.sum(), 1.0)
    labels = [f"IEI 10^{a:g}..10^{b:g} us" for a, b in zip(IEI_EDGES_LOG10[:-1],
                                                           IEI_EDGES_LOG10[1:], strict=True)]
    return StatValue("iei_distribution", frac, labels, 0.004)


def histogram_sorted_edges(x: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """``np.histogram(x, edges)[0]`` as float64 (bins ``[a, b)``, the last ``[a, b]``) by a
    binary search per value: ``np.histogram`` sorts the values when the bins are not even."""
    i = np.searchsorted(edges, x, side="right") - 1
    i[x == edges[-1]] = edges.size - 2
    ok = (i >= 0) & (i < edges.size - 1)
    return np.bincount(i[ok], minlength=edges.size - 1).astype(np.float64)


def mid_quantile(x: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Quantiles ``q`` of ``x`` from its distinct values at their mid-distribution
    positions (``F(v) - P(v) / 2``), interpolated between them: continuous in the shares of
    tied values, where the usual quantile jumps a whole gap between two ties when a share
    crosses ``q``; the usual quantile where there are no ties."""
    q = np.asarray(q, np.float64)
    x = np.asarray(x).ravel()
    # lower quantiles need only the values up to a little beyond the largest: a partition
    # instead of a sort of them all (the ties at the cut come whole, so the shares below
    # it are exact; the full sort stands where they do not reach the largest quantile)
    k = int(np.ceil(1.25 * float(q.max(initial=0.0)) * x.size)) + 1 if x.size else 0
    if 0 < k < x.size // 2:
        cut = np.partition(x, k)[k]
        v, n = np.unique(x[x <= cut], return_counts=True)
        f = (np.cumsum(n) - 0.5 * n) / x.size
        if f[-1] >= q.max():
            low: np.ndarray = np.interp(q, f, v)
            return low
    v, n = np.unique(x, return_counts=True)
    f = (np.cumsum(n) - 0.5 * n) / x.size
    out: np.ndarray = np.interp(q, f, v)
    return out


def stat_iei_lower_edge(obs: Observation) -> StatValue:
    """The lower edge of a pixel's intervals (dead time, jitter), without simultaneous
    pairs: a pixel cannot fire twice at once, so 0 us pairs are a stamping scheme's (a
    frame-driven simulator's noise event at a step's end beside a signal event there;
    :func:`stat_timestamp_quantum` sees the scheme). The intervals of such schemes come in
    ties at the step's slots, hence the mid-distribution quantiles."""
    iei, _, _ = _iei(obs)
    iei = iei[iei > 0]
    q = np.array([0.001, 0.01, 0.05])
    v = mid_quantile(np.log10(iei), q) if iei.size else np.zeros(3)
    return StatValue("iei_lower_edge", v, [f"IEI quantile {x:g} (log10 us)" for x in q], 0.05)


def _common_dl(obs: Observation) -> np.ndarray:
    """Per window, the change of the light common to the scene (log units): the median
    change over the pixels lit inside the range in both frames (10..245 DN). A moving scene
    brightens as many pixels as it darkens; a ramp or a breathing light moves them all."""
    def make() -> np.ndarray:
        i = obs.intensity
        lit = (i[1:] > 10) & (i[1:] < 245) & (i[:-1] > 10) & (i[:-1] < 245)
        dl = _dl(obs)
        out = np.zeros(obs.n_windows)
        for k in range(obs.n_windows):
            m = lit[k]
            if m.sum() >= 100:
                out[k] = float(np.median(dl[k][m]))
        return out

    return _shared(obs, "common_dl", make)


def _static(obs: Observation) -> np.ndarray:
    """Windows of a still pixel: |dL| < STATIC_DL (less the change of the light common to the
    scene, :func:`_common_dl`: a still scene under a ramping light is still) in the window
    and STATIC_HALF_WIDTH windows either side (a short pause of a moving texture is not
    still: sub-quantum changes there still make events that frames cannot show)."""
    if "static" in obs.shared:
        result: np.ndarray = obs.shared["static"]
        return result
    dl = np.abs(_dl(obs) - _common_dl(obs)[:, None]) < STATIC_DL
    st = dl.copy()
    for k in range(1, STATIC_HALF_WIDTH + 1):
        st[k:] &= dl[:-k]
        st[:-k] &= dl[k:]
        st[:k] = False
        st[-k:] = False
    st &= obs.usable
    st.setflags(write=False)
    obs.shared["static"] = st
    result_272: np.ndarray = st
    return result_272


def _static_bins(obs: Observation, n_bins: int = 4
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Still windows, their intensity bins (``n_bins`` quantiles of the windows' mean
    intensity), the bin edges and each bin's window seconds: frame-side, made once for the
    frames (:func:`_plan`; the rate and the balance both bin the same windows)."""
    def make() -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        st = _static(obs)
        key = _i_mid(obs)[st]
        edges = _quantile_edges(key, n_bins)
        idx = _bin_of(key, edges)
        ws = np.broadcast_to(obs.window_s[:, None], st.shape)[st]
        den = np.bincount(idx, weights=ws, minlength=edges.size - 1)
        return st, idx, edges, den

    result: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] = _plan(
        obs, f"static_bins_{n_bins}", make)
    return result


# a still-window bin of fewer pixel-seconds than this says nothing (NaN: left out); above it,
# a rate is never told apart by less than one event in the bin (its floor)
MIN_STILL_PIXEL_S = 2.0


def _still_rate(num: np.ndarray, den: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per bin, events per pixel-second (NaN below :data:`MIN_STILL_PIXEL_S`) and the floor
    of its spread: 0.05 Hz, or the rate of one event in the bin when that is more (a count
    of a few events is as uncertain as a Poisson count, whatever the seeds show)."""
    ok = den >= MIN_STILL_PIXEL_S
    v = np.where(ok, num / np.maximum(den, 1e-12), np.nan)
    floor = np.maximum(0.05, 1.0 / np.maximum(den, MIN_STILL_PIXEL_S))
    return v, floor


def stat_static_rate(obs: Observation) -> StatValue:
    st, idx, edges, den = _static_bins(obs)
    e = (obs.on + obs.off)[st].astype(np.float64)
    # events per pixel-second: sum(E) / sum(window seconds) per bin
    v, floor = _still_rate(np.bincount(idx, weights=e, minlength=edges.size - 1), den)
    return StatValue("static_rate_vs_intensity", v, _edge_labels(edges, "static, I (DN)"),
                     floor)


def stat_static_balance(obs: Observation) -> StatValue:
    st, idx, edges, den = _static_bins(obs)
    pnet = (obs.on - obs.off)[st].astype(np.float64)
    v, floor = _still_rate(np.bincount(idx, weights=pnet, minlength=edges.size - 1), den)
    return StatValue("static_balance_vs_intensity", v, _edge_labels(edges, "static, I (DN)"),
                     floor)


def stat_on_fraction_over_time(obs: Observation, n_bins: int = 6) -> StatValue:
    edges = np.linspace(obs.frame_t_us[0], obs.frame_t_us[-1], n_bins + 1)
    idx = np.clip(np.searchsorted(edges, obs.t_us, side="right") - 1, 0, n_bins - 1)
    n = np.bincount(idx, minlength=n_bins).astype(np.float64)
    non = np.bincount(idx, weights=(obs.p > 0).astype(np.float64), minlength=n_bins)
    # a share of a few events says nothing (NaN: left out), where a default in its place
    # would be compared with a simulation's few events
    v = np.where(n >= MIN_BIN_SAMPLES, non / np.maximum(n, 1), np.nan)
    t0 = obs.frame_t_us[0]
    labels = [f"t {(a - t0) * 1e-6:.2f}..{(b - t0) * 1e-6:.2f} s"
              for a, b in zip(edges[:-1], edges[1:], strict=True)]
    return StatValue("on_fraction_over_time", v, labels, 0.005)


RESIDUAL_DL_EDGES = np.array([-np.inf, 0.05, 0.15, 0.3, 0.6, np.inf])
RESIDUAL_REL_EDGES = np.array([-np.inf, -0.4, -0.15, 0.0, 0.15, 0.4, np.inf])


def stat_residual_vs_dl(obs: Observation) -> StatValue:
    f = _fit(obs)
    m = np.isfinite(f["res"])
    edges = RESIDUAL_DL_EDGES
    idx = _plan(obs, "residual_dl", lambda: _bin_of(np.abs(_dl(obs)), edges))
    v = _binned(f["res"][m], idx[m], edges.size - 1, how="rms")
    return StatValue("offei_residual_vs_dl", v, _edge_labels(edges, "|dL|"), 0.003)


def stat_residual_vs_intensity(obs: Observation) -> StatValue:
    f = _fit(obs)
    edges = RESIDUAL_REL_EDGES

    def make() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        dl = _dl(obs)
        lmid = 0.5 * (obs.log_i[1:] + obs.log_i[:-1])
        lmed = np.median(obs.log_i, axis=0)
        return np.abs(dl) > 0.1, np.sign(dl), _bin_of(lmid - lmed[None, :], edges)

    changing, sign, idx = _plan(obs, "residual_rel", make)
    m = np.isfinite(f["res"]) & changing
    v = _binned(f["res"][m] * sign[m], idx[m], edges.size - 1, how="mean")
    return StatValue("offei_residual_vs_intensity", v,
                     _edge_labels(edges, "log I - pixel median"), 0.003)


def stat_residual_vs_time(obs: Observation, n_bins: int = 5) -> StatValue:
    f = _fit(obs)
    m = np.isfinite(f["res"])
    # per window first (a sum over its pixels), then the windows binned
    sq = np.square(np.where(m, f["res"], 0.0), dtype=np.float64).sum(1)
    edges = np.linspace(0, obs.n_windows, n_bins + 1)
    edges[0], edges[-1] = -np.inf, np.inf
    idx = np.clip(np.searchsorted(edges, np.arange(obs.n_windows), side="right") - 1, 0,
                  n_bins - 1)
    num = np.bincount(idx, weights=sq, minlength=n_bins)
    den = np.bincount(idx, weights=m.sum(1), minlength=n_bins)
    v = np.sqrt(np.where(den >= MIN_BIN_SAMPLES, num / np.maximum(den, 1e-30), np.nan))
    dur = (obs.frame_t_us[-1] - obs.frame_t_us[0]) * 1e-6
    labels = [f"t {dur * k / n_bins:.2f}..{dur * (k + 1) / n_bins:.2f} s" for k in range(n_bins)]
    return StatValue("offei_residual_vs_time", v, labels, 0.003)


def stat_fit_population(obs: Observation) -> StatValue:
    f = _fit(obs)
    ok = f["ok"]
    if ok.sum() < MIN_STAT_PIXELS:
        v = np.full(3, np.nan)  # too few fitted pixels to say anything
    else:
        c, b = f["c"][ok], f["b"][ok]
        q1, q3 = np.percentile(c, [25, 75])
        v = np.array([np.median(c), np.median(b), q3 - q1])
    return StatValue("fit_population", v, ["median c", "median b", "IQR c"], 0.003)


def stat_stability(obs: Observation) -> StatValue:
    f = _fit(obs)
    m = f["ok12"]
    if m.sum() < MIN_STAT_PIXELS:
        # a sparse recording (a still camera) has few pixels busy enough to be fitted in
        # each half: a median of a handful of pixels says nothing
        v = np.full(2, np.nan)
    else:
        v = np.array([np.median(np.abs(f["c1"] - f["c2"])[m]),
                      np.median(np.abs(f["b1"] - f["b2"])[m])])
    return StatValue("estimate_stability", v, ["median |c1 - c2|", "median |b1 - b2|"], 0.003)


def stat_polarity_alternation(obs: Observation) -> StatValue:
    """The share of consecutive same-pixel events of opposite polarity, of all pairs and of
    those less than 2 ms apart; NaN (left out of the comparison) where fewer than
    :data:`MIN_BIN_SAMPLES` pairs make the share. A share of a handful of pairs says
    nothing, and a model with no pairs that close (a refractory period a little above 2 ms)
    would otherwise stand at a share of 0 with no spread against the measured one: a
    discrepancy of thousands from a bin the interval statistics already judge."""
    iei, opp, _ = _iei(obs)
    short = iei < 2000
    n_short = int(short.sum())
    v = np.array([opp.mean() if opp.size >= MIN_BIN_SAMPLES else np.nan,
                  opp[short].mean() if n_short >= MIN_BIN_SAMPLES else np.nan])
    return StatValue("polarity_alternation", v, ["all pairs", "pairs with IEI < 2 ms"], 0.004)


def stat_rate_tail(obs: Observation) -> StatValue:
    """Per-pixel event rate in still windows (pixels still for at least 5 % of the longest
    still time): quantiles and max, log10 of (rate + 1 Hz)."""
    st = _static(obs)
    t_still = (st * obs.window_s[:, None]).sum(0)
    q = [0.5, 0.9, 0.99, 0.999]
    labels = [f"still-pixel rate quantile {x:g}" for x in q] + ["still-pixel rate max"]
    ok = t_still > 0.05 * max(t_still.max(), 1e-9)
    if ok.sum() < 10:
        return StatValue("rate_tail", np.zeros(5), labels, 0.05)
    rate = ((obs.on + obs.off) * st).sum(0)[ok] / t_still[ok]
    v = np.log10(np.append(np.quantile(rate, q), rate.max()) + 1.0)
    return StatValue("rate_tail", v, labels, 0.05)


def _changing_windows(obs: Observation) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """abs(dL), the windows whose frames change by more than 0.1 in log (usable, and
    trusted where the observation has a mask) and the windows' mean intensity."""
    adl = np.abs(_dl(obs))
    m = obs.usable & (adl > 0.1)
    if obs.trusted is not None:
        m &= obs.trusted
    return adl, m, _i_mid(obs)


def stat_speed_response(obs: Observation) -> StatValue:
    def make() -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        adl, m, i_mid = _changing_windows(obs)
        i_sel = i_mid[m]
        a_sel = adl[m]
        speed = (adl / obs.window_s[:, None])[m]
        ie = _quantile_edges(i_sel, 2)
        se = _quantile_edges(speed, 2)
        # every selected window in one (intensity, speed) cell: [ie[a], ie[a + 1]) x [se[s],..)
        ok = np.isfinite(i_sel) & np.isfinite(speed)
        ia = np.searchsorted(ie, i_sel[ok], side="right") - 1
        js = np.searchsorted(se, speed[ok], side="right") - 1
        cell = ia * (se.size - 1) + js
        den = np.bincount(cell, weights=a_sel[ok], minlength=(ie.size - 1) * (se.size - 1))
        return np.flatnonzero(m)[ok], cell, den, ie, se

    at, cell, den, ie, se = _plan(obs, "speed_response", make)
    n_s = se.size - 1
    num = np.bincount(cell, weights=_fit(obs)["E"].ravel()[at], minlength=den.size)
    vals = np.where(den > 0, num / np.where(den > 0, den, 1.0), 0.0)
    labels = [f"{'dark' if a == 0 else 'bright'} (I split {ie[1]:.3g} DN), "
              f"{'slow' if s == 0 else 'fast'} (|dL|/s split {se[1]:.3g})"
              for a in range(ie.size - 1) for s in range(n_s)]
    return StatValue("speed_response", vals, labels, 0.1)


def stat_lag(obs: Observation) -> StatValue:
    def make() -> tuple[np.ndarray, ...]:
        dL = _dl(obs)
        m = obs.usable[1:] & obs.usable[:-1] & (np.abs(dL[1:]) + np.abs(dL[:-1]) > 0.05)
        if obs.trusted is not None:
            m &= obs.trusted[1:] & obs.trusted[:-1]
        imean = obs.intensity.mean(0)
        edges = _quantile_edges(imean, 3)
        pb = _bin_of(imean, edges)
        nb = edges.size - 1
        key = np.broadcast_to(pb[None, :], m.shape)[m]
        x1 = dL[1:][m].astype(np.float64)
        x2 = dL[:-1][m].astype(np.float64)
        n = np.bincount(key, minlength=nb)
        s11, s12, s22 = (np.bincount(key, weights=w, minlength=nb)
                         for w in (x1 * x1, x1 * x2, x2 * x2))
        return np.flatnonzero(m), key, x1, x2, edges, n, s11, s12, s22

    # the normal equations of P[k] ~ b1 dL[k] + b2 dL[k-1] in each intensity bin, their sums
    # taken in one pass over the selected windows (the frame side's once for the frames)
    at, key, x1, x2, edges, n, s11, s12, s22 = _plan(obs, "lag", make)
    nb = edges.size - 1
    y = _fit(obs)["P"][1:].ravel()[at].astype(np.float64)
    s1y, s2y = (np.bincount(key, weights=w, minlength=nb) for w in (x1 * y, x2 * y))
    vals = []
    for j in range(nb):
        a = np.array([[s11[j], s12[j]], [s12[j], s22[j]]])
        r = np.array([s1y[j], s2y[j]])
        if n[j] < MIN_BIN_SAMPLES or \
                np.linalg.det(a) <= 1e-12 * max(a[0, 0] * a[1, 1], 1e-30):
            vals.append(np.nan)  # too few windows for the regression: left out
            continue
        b1, b2 = np.linalg.solve(a, r)
        vals.append(float(b2 / (b1 + b2)) if abs(b1 + b2) > 1e-9 else np.nan)
    return StatValue("lag_vs_intensity", np.asarray(vals),
                     _edge_labels(edges, "pixel mean I (DN)"), 0.01)


def stat_timestamp_quantum(obs: Observation) -> StatValue:
    return timestamp_quantum(obs.t_us)


def timestamp_quantum(t: np.ndarray) -> StatValue:
    """:func:`stat_timestamp_quantum` of event times ``t`` (us)."""
    v = np.array([np.mean(t % q == 0) if t.size else 0.0 for q in (10, 100, 1000)])
    return StatValue("timestamp_quantum", v, ["t % 10 us == 0", "t % 100 us == 0",
                                              "t % 1000 us == 0"], 0.01)


def stat_sensitivity_vs_intensity(obs: Observation, n_bins: int = 5) -> StatValue:
    """Events per unit ``|dL|`` (nominal log) in windows with ``|dL| > 0.1``, in ``n_bins``
    quantile bins of the window's absolute mean intensity, over the same for all of them.

    The shape over absolute intensity is what tells a dark level under the log (sensitivity
    ``I / (I + d)``: flat in the bright, falling below ``d``) from thresholds that scale with
    light as a power (``I^e``: the same slope in log I everywhere); the per-pixel residual
    against the pixel's own median (:func:`stat_residual_vs_intensity`) sees both alike."""
    def make() -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        adl, m, i_mid = _changing_windows(obs)
        key = np.log(np.maximum(i_mid[m].astype(np.float64), 0.0) + NOMINAL_LOG_OFFSET_DN)
        edges = _quantile_edges(key, n_bins)
        idx = _bin_of(key, edges)
        dl = np.bincount(idx, weights=adl[m], minlength=edges.size - 1)
        return np.flatnonzero(m), idx, edges, dl

    at, idx, edges, dl = _plan(obs, f"sensitivity_{n_bins}", make)
    nb = edges.size - 1
    ev = np.bincount(idx, weights=_fit(obs)["E"].ravel()[at], minlength=nb)
    total = ev.sum() / max(dl.sum(), 1e-12)
    v = np.where(dl > 0, ev / np.maximum(dl, 1e-12), 0.0) / max(total, 1e-12)
    lab_edges = np.exp(edges) - NOMINAL_LOG_OFFSET_DN
    return StatValue("sensitivity_vs_intensity", v, _edge_labels(lab_edges, "I (DN)"), 0.02)


LINE_COINCIDENCE_US = 20  # a readout-line burst's events lie within this of each other
LINE_COINCIDENCE_MIN = 2  # other events of the line within it: three make a burst


def line_events(obs: Observation, axis: str) -> dict[str, np.ndarray]:
    """Events in still windows of their pixel, sorted by (line, time) along ``axis`` ("row":
    line = y, "column": line = x), with the number of other such events of their line within
    +-:data:`LINE_COINCIDENCE_US` (``n_near``), their line and window.

    Still windows only: there an event is noise (a pixel's own signal needs a change the
    frames show), so events that coincide along a line are a correlated disturbance of the
    line, not an edge sweeping it (edges fire lines of pixels at once by geometry)."""
    key_name = f"line_{axis}"
    if key_name in obs.extra:
        cached: dict[str, np.ndarray] = obs.extra[key_name]
        return cached
    h, w = obs.shape
    st = _static(obs)
    win = event_windows(obs)
    keep = st[win, obs.pix]
    pix, t, win = obs.pix[keep], obs.t_us[keep].astype(np.int64), win[keep]
    line = pix // w if axis == "row" else pix % w
    dt = LINE_COINCIDENCE_US
    t_rel = t - (int(t.min()) if t.size else 0)
    span = (int(t_rel.max()) if t.size else 0) + 4 * dt + 1
    key = line.astype(np.int64) * span + t_rel  # lines far apart in key space
    # by line, stable: the events are in time order, so this is the order of the key
    order = order_by_key(line, h if axis == "row" else w)
    key = key[order]
    if key.size > 1 and np.any(key[1:] < key[:-1]):  # events not in time order
        order = order[np.argsort(key, kind="stable")]
        key = line.astype(np.int64)[order] * span + t_rel[order]
    n_near = (np.searchsorted(key, key + dt, side="right")
              - np.searchsorted(key, key - dt, side="left") - 1)
    out = {"key": key, "line": line[order], "win": win[order], "pix": pix[order],
           "t": t[order], "n_near": n_near}
    obs.extra[key_name] = out
    return out


def still_pixel_seconds(obs: Observation) -> float:
    """Pixel-seconds of still windows (the exposure of :func:`line_events`)."""
    st = _static(obs)
    return float((st * obs.window_s[:, None]).sum())


def stat_line_coincidence(obs: Observation) -> StatValue:
    """Events per still pixel-second that have at least :data:`LINE_COINCIDENCE_MIN` other
    still events of their row (resp. column) within +-:data:`LINE_COINCIDENCE_US`: bursts of
    a readout or bias line (``row_noise``). Independent noise almost never does that (shot
    noise at 2 Hz in a 346-pixel row: 1e-4 chance of one other event within 20 us); the floor
    of 0.02 Hz keeps chance coincidences of busy noisy scenes from counting."""
    exposure = still_pixel_seconds(obs)
    vals = []
    for axis in ("row", "column"):
        le = line_events(obs, axis)
        n = float((le["n_near"] >= LINE_COINCIDENCE_MIN).sum())
        vals.append(n / exposure if exposure > 0 else 0.0)
    return StatValue("line_coincidence", np.asarray(vals),
                     ["same-row bursts (Hz per still pixel)",
                      "same-column bursts (Hz per still pixel)"], 0.02)


# log change (nominal) of a pixel's frames from the first frame to its first event's window
FIRST_CHANGE_EDGES = np.array([0.0, 0.04, 0.08, 0.12, 0.16, 0.24, 0.36, np.inf])


def first_event_change(obs: Observation) -> tuple[np.ndarray, np.ndarray]:
    """Per pixel that fires in a window its frames show unclipped: the change of its
    frames' log intensity from the first frame to the middle of the window of its first
    event (absolute, nominal log), and the pixels' indices."""
    def make() -> tuple[np.ndarray, np.ndarray]:
        fired = (obs.on + obs.off) > 0
        idx = np.flatnonzero(fired.any(axis=0))
        k = np.argmax(fired[:, idx], axis=0)
        ok = obs.usable[k, idx]
        idx, k = idx[ok], k[ok]
        mid = 0.5 * (obs.log_i[k, idx] + obs.log_i[k + 1, idx])
        return np.abs(mid - obs.log_i[0, idx]), idx

    if "first_event_change" not in obs.extra:
        obs.extra["first_event_change"] = make()
    out: tuple[np.ndarray, np.ndarray] = obs.extra["first_event_change"]
    return out


def stat_first_event_change(obs: Observation) -> StatValue:
    """The shares of the firing pixels by the change their frames show before their first
    event: a sensor that ran before the recording fires its first events after any part of
    a threshold, one reset at the start (a frame-driven simulator) after a whole one."""
    d, _ = first_event_change(obs)
    h = histogram_sorted_edges(d, FIRST_CHANGE_EDGES)
    frac = h / max(h.sum(), 1.0)
    if d.size < MIN_BIN_SAMPLES:
        frac = np.full(h.size, np.nan)
    labels = [f"change before the first event {a:g}..{b:g}" for a, b in
              zip(FIRST_CHANGE_EDGES[:-1], FIRST_CHANGE_EDGES[1:], strict=True)]
    # the floor: a simulation driven by the frames reproduces these shares to a few per
    # cent only, whatever the seeds say (where the frames show little of a change, the
    # first events of the sensor and of the model fall in other windows); a reset at the
    # start moves them by tens of per cent
    return StatValue("first_event_change", frac, labels, 0.03)


STATISTICS = (
    stat_iei_distribution,
    stat_iei_lower_edge,
    stat_static_rate,
    stat_static_balance,
    stat_on_fraction_over_time,
    stat_residual_vs_dl,
    stat_residual_vs_intensity,
    stat_residual_vs_time,
    stat_fit_population,
    stat_stability,
    stat_polarity_alternation,
    stat_rate_tail,
    stat_speed_response,
    stat_lag,
    stat_timestamp_quantum,
    stat_sensitivity_vs_intensity,
    stat_line_coincidence,
    stat_first_event_change,
)


def summarise(obs: Observation) -> dict[str, StatValue]:
    """Every statistic of :data:`STATISTICS` for one observation, by name. A component
    without the data for a value is NaN (an infinite one too): the comparison leaves it
    out (:func:`.compare.discrepancy`), where a zero in its place would be compared."""
    out = {}
    for fn in STATISTICS:
        s = fn(obs)
        v = np.asarray(s.values, np.float64)
        out[s.name] = StatValue(s.name, np.where(np.isfinite(v), v, np.nan), s.labels,
                                s.floor)
    return out
