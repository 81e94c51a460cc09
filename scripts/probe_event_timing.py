"""What the events' timing says about the log intensity at frame times (issue 39, item 2).

A research probe, not a method: figures for docs/notes/event-timing-2026-11-29.md.

Between two events of the same polarity at one pixel, its log intensity went from one
crossing to the next, ``c + b`` (ON) or ``c - b`` (OFF) apart. A frame taken between them at
the fraction ``phi`` of the way sees (if the light changed evenly) the reference plus
``phi`` times that step: the cumulative counts at the frame become fractional,
``CP + dir * phi`` and ``CE + phi``, and the sub-threshold residual that limits every
frame-pair estimator (spread ``c / sqrt(3)``) shrinks to the light's unevenness over the
bracket. Frames between events of opposite polarity (a turning point) or with none on one
side keep the integer counts.

Per recording (evcal's ideal simulator over scenes and seeds, or with ``--data`` the gap
benchmark's dev recordings; test recordings are refused) on a sample of busy pixels:

- with the true maps and offset (simulated recordings): the spread of ``log(I + o) - (c CP
  + b CE)`` about each pixel's median, by the length of the bracket, with integer counts
  and with fractional ones;
- per-pixel cumulative fits ``log(I + o) = a + c CP + b CE`` at the true offset: plain
  (with the last polarity as a regressor) and weighted by the bracket (frames' variance
  ``s0^2 + (alpha gap)^2 + (beta exposure / gap)^2``, unbracketed ``c^2/3``): c and b RMSE
  against the truth, beside OffEI's at the true offset on the same pixels (those it calls
  valid);
- the log offset: OffEI's estimate (:func:`evcal.offline.estimate_log_offset`) and the root
  of the median over pixels of the fitted curvature of ``log(I + o)`` against the events'
  reference, plain and weighted (the curvature is 0 at the true offset when the residuals
  do not depend on the light).

    python scripts/probe_event_timing.py                          # simulated, about 2 min
    python scripts/probe_event_timing.py --data /work/gapbench --only dev1005,dev1024
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from evcal.errors import EvcalError
from evcal.io import open_recording
from evcal.offline import OffEIConfig, estimate_log_offset, offei
from evcal.recording import Recording
from evcal.sim.ideal import SimConfig, simulate_ideal

SCENES = ("chelsea", "camera", "astronaut", "coffee")
SEEDS = (31, 32)
GAP_BINS_US = (0, 5_000, 20_000, 80_000, np.inf)
S0 = 0.004  # frames' own noise (8-bit quantisation of the ideal simulator), log units
ALPHA_PER_US = 1e-6  # the light's unevenness over a bracket, log units per us of its length
BETA = 0.06  # exposure blur across a bracket: about c / sqrt(12) per exposure / gap
UNBRACKETED_VAR = 0.0133  # (0.2 / sqrt(3))^2: a frame's residual without timing
READ_NOISE_DN = 0.0  # the frames' read noise in the weights (--read-noise-dn)
OFFSET_GRID = np.geomspace(1.0, 400.0, 31)


@dataclass
class Brackets:
    """``[frame, pixel]`` arrays of the sampled pixels at every frame time."""

    pix: np.ndarray
    cp: np.ndarray  # net polarity up to the frame
    ce: np.ndarray  # events up to the frame
    last_p: np.ndarray  # polarity of the last event before the frame (0: none)
    phi: np.ndarray  # fraction of the way to the next crossing (0 unless bracketed)
    direction: np.ndarray  # +1 / -1 between two ON / OFF events, else 0
    gap_us: np.ndarray  # time between the bracketing events (inf: none on one side)
    images: np.ndarray  # the frames at the pixels (float)
    exposure_us: float
    # the fractional counts averaged over each frame's exposure (``--exposure-samples``):
    # net polarity, count, bracketed at every sample, the longest bracket; None: not asked
    exposure_avg: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None = None


def brackets(rec: Recording, n_pixels: int, seed: int, min_events: int = 20,
             exposure_samples: int = 0) -> Brackets:
    """Counts and brackets of a random sample of the pixels with ``min_events`` events
    (vectorised: one search of every (pixel, frame) in the events sorted by pixel and time)."""
    ev = rec.events
    h, w = rec.sensor.shape
    flat = ev["y"].astype(np.int64) * w + ev["x"]
    n = np.bincount(flat, minlength=h * w)
    busy = np.flatnonzero(n >= min_events)
    if busy.size == 0:
        raise EvcalError(f"no pixel has {min_events} events")
    rng = np.random.default_rng(seed)
    pix = np.sort(rng.choice(busy, min(n_pixels, busy.size), replace=False))
    keep = np.isin(flat, pix)
    rank = np.searchsorted(pix, flat[keep])  # 0..P-1
    t = ev["t_us"][keep].astype(np.int64)
    pol = np.where(ev["p"][keep] > 0, 1, -1).astype(np.int64)
    order = np.lexsort((t, rank))
    rank, t, pol = rank[order], t[order], pol[order]
    span = int(max(t.max(), int(rec.frames.t_us.max())) - min(t.min(), 0)) + 2
    key = rank * span + (t - min(t.min(), 0))
    starts = np.searchsorted(rank, np.arange(pix.size))  # first event of each pixel
    cpol = np.concatenate([[0], np.cumsum(pol)])
    n_pix = np.diff(np.concatenate([starts, [rank.size]]))
    t_min = min(int(t.min()), 0)

    def at(times: np.ndarray) -> tuple[np.ndarray, ...]:
        """Counts and brackets of every sampled pixel at ``times`` ([frame])."""
        q = np.arange(pix.size)[None, :] * span + (times[:, None] - t_min)
        k = np.searchsorted(key, q, side="right")  # the pixel's events up to then, + start
        before = k - starts[None, :]
        has_prev = before > 0
        has_next = before < n_pix[None, :]
        kp = np.clip(k - 1, 0, rank.size - 1)
        kn = np.clip(k, 0, rank.size - 1)
        cp = (cpol[k] - cpol[starts][None, :]).astype(np.float64)
        gap = np.where(has_prev & has_next, (t[kn] - t[kp]).astype(np.float64), np.inf)
        same = has_prev & has_next & (pol[kp] == pol[kn])
        phi = np.where(same, (times[:, None] - t[kp]) / np.maximum(gap, 1.0), 0.0)
        return (cp, before.astype(np.float64), np.where(has_prev, pol[kp], 0), phi,
                np.where(same, pol[kn], 0), gap)

    tf = rec.frames.t_us.astype(np.int64)
    cp, ce, last_p, phi, direction, gap = at(tf)
    exposure = float(np.median(rec.frames.exposure_us))
    avg = None
    if exposure_samples > 1 and exposure > 0:
        # the frame is the exposure's average of the light: the fractional counts averaged
        # over it (to first order in the light's change across the exposure)
        acc_p = np.zeros_like(cp)
        acc_e = np.zeros_like(cp)
        all_br = np.ones(cp.shape, bool)
        longest = np.zeros_like(cp)
        for dt in np.linspace(-exposure / 2, exposure / 2, exposure_samples):
            c_k, e_k, _, phi_k, dir_k, gap_k = at(tf + int(round(dt)))
            acc_p += c_k + dir_k * phi_k
            acc_e += e_k + np.where(dir_k != 0, phi_k, 0.0)
            all_br &= dir_k != 0
            longest = np.maximum(longest, np.where(dir_k != 0, gap_k, np.inf))
        avg = (acc_p / exposure_samples, acc_e / exposure_samples, all_br, longest)
    images = rec.frames.images.reshape(len(tf), -1)[:, pix].astype(np.float64)
    return Brackets(pix, cp, ce, last_p, phi, direction, gap, images, exposure, avg)


def _wls(x: np.ndarray, y: np.ndarray, wt: np.ndarray) -> np.ndarray:
    """Per-pixel weighted least squares: ``x`` [P, F, k], ``y`` and ``wt`` [P, F]."""
    xw = x * wt[..., None]
    g = np.einsum("pfi,pfj->pij", xw, x) + 1e-9 * np.eye(x.shape[-1])
    return np.linalg.solve(g, np.einsum("pfi,pf->pi", xw, y)[..., None])[..., 0]


def fit(br: Brackets, offset: float, timing: bool | str
        ) -> tuple[np.ndarray, np.ndarray, float, np.ndarray, np.ndarray]:
    """``(c, b, median curvature, pixels of the curvature, pixels fitted)`` of the
    per-pixel cumulative fits at ``offset``; the curvature is of ``log(I + o)`` against the
    fitted reference, relative to the reference's spread (pixels with a light range of 0.3
    log units); a pixel is fitted with 8 usable frames."""
    img = br.images
    cp, ce, q, wt = _regressors(br, timing)
    y = np.log(img + offset).T
    wt, cp, ce, q = wt.T, cp.T, ce.T, q.T
    one = np.ones_like(cp)
    x = np.stack([one, cp, ce, q], -1)
    beta = _wls(x, y, wt)
    z = beta[:, 1:2] * cp + beta[:, 2:3] * ce
    tot = np.maximum(wt.sum(1, keepdims=True), 1e-12)
    zc = z - (z * wt).sum(1, keepdims=True) / tot
    zr = np.sqrt((zc ** 2 * wt).sum(1, keepdims=True) / tot)
    x2 = np.concatenate([x, ((zc / np.maximum(zr, 1e-9)) ** 2)[..., None]], -1)
    kappa = _wls(x2, y, wt)[:, -1] / np.maximum(zr[:, 0], 1e-9)
    fitted = np.isfinite(beta).all(1) & ((wt > 0).sum(1) >= 8)
    used = fitted & np.isfinite(kappa) & (beta[:, 1] > 0.02) & (zr[:, 0] > 0.3)
    med = float(np.median(kappa[used])) if used.any() else np.nan
    return beta[:, 1], beta[:, 2], med, used, fitted


def _regressors(br: Brackets, timing: bool | str
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``(cp, ce, q, weight)`` [frame, pixel]: integer counts and the last polarity
    (``timing`` False); fractional counts at the frame's middle, weighted by the bracket
    (True); or averaged over its exposure (``"exposure"``: bracketed only where every
    sample of the exposure is)."""
    img = br.images
    usable = (img > 3) & (img < 250)
    # the frames' own noise in log units (at a nominal offset of 30 DN: the weights' shape)
    s0_2 = S0 ** 2 + (READ_NOISE_DN / (np.maximum(img, 0.0) + 30.0)) ** 2
    if timing == "exposure" and br.exposure_avg is not None:
        cp, ce, bracketed, longest = br.exposure_avg
        g = np.where(bracketed, longest, 1.0)
        var = np.where(bracketed, s0_2 + (ALPHA_PER_US * g) ** 2, UNBRACKETED_VAR)
        q = np.where(bracketed, 0.0, br.last_p)
        return cp, ce, q, usable / np.minimum(var, UNBRACKETED_VAR)
    if timing:
        bracketed = br.direction != 0
        cp = br.cp + br.direction * br.phi
        ce = br.ce + np.where(bracketed, br.phi, 0.0)
        g = np.where(bracketed, br.gap_us, 1.0)
        var = np.where(bracketed, s0_2 + (ALPHA_PER_US * g) ** 2
                       + (BETA * br.exposure_us / g) ** 2, UNBRACKETED_VAR)
        q = np.where(bracketed, 0.0, br.last_p)
        return cp, ce, q, usable / np.minimum(var, UNBRACKETED_VAR)
    return br.cp, br.ce, br.last_p.astype(np.float64), usable.astype(np.float64)


def segment_fit(br: Brackets, offset: float, timing: bool | str, frames: int
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(c, b, pixels fitted)`` of per-pixel fits with an intercept per segment of
    ``frames`` frames (the counts' drift against the frames limited to a segment): the
    weighted means of each segment taken out, then one weighted fit of ``c`` and ``b``."""
    img = br.images
    usable = (img > 3) & (img < 250)
    cp, ce, q, wt = _regressors(br, timing)
    y = np.where(usable, np.log(np.maximum(img, 0.0) + offset), 0.0)
    cols = [cp, ce, q.astype(np.float64), y]
    seg = np.arange(img.shape[0]) // max(int(frames), 2)
    n_seg = int(seg.max()) + 1
    wsum = np.zeros((n_seg, img.shape[1]))
    np.add.at(wsum, seg, wt)
    out = []
    for a in cols:
        m = np.zeros((n_seg, img.shape[1]))
        np.add.at(m, seg, wt * a)
        out.append(a - (m / np.maximum(wsum, 1e-12))[seg])
    x = np.stack(out[:3], -1).transpose(1, 0, 2)
    beta = _wls(x, out[3].T, wt.T)
    fitted = np.isfinite(beta).all(1) & ((wt > 0).sum(0) >= 8)
    return beta[:, 0], beta[:, 1], fitted


def offset_root(br: Brackets, timing: bool) -> float:
    """The offset on :data:`OFFSET_GRID` where the median curvature changes sign (NaN:
    none)."""
    g = np.array([fit(br, o, timing)[2] for o in OFFSET_GRID])
    s = np.flatnonzero(np.diff(np.sign(g)) != 0)
    if not s.size:
        return float("nan")
    k = int(s[0])
    x0, x1 = np.log(OFFSET_GRID[k]), np.log(OFFSET_GRID[k + 1])
    return float(np.exp(x0 + (x1 - x0) * g[k] / (g[k] - g[k + 1])))


def residual_table(br: Brackets, c: np.ndarray, b: np.ndarray, offset: float
                   ) -> list[tuple[str, int, float, float]]:
    """Spread of the residual at the true maps by bracket length: ``(bin, frames, plain
    sd, timing sd)`` (root mean square about each pixel's intercept)."""
    y = np.log(br.images + offset)
    out = []
    res = {}
    for name, cp, ce in (("plain", br.cp, br.ce),
                         ("timing", br.cp + br.direction * br.phi,
                          br.ce + np.where(br.direction != 0, br.phi, 0.0))):
        r = y - (c[None, :] * cp + b[None, :] * ce)
        # each pixel's intercept from its closely bracketed frames where it has some (the
        # others' residuals sit anywhere in the threshold band), else from all its frames
        close = (br.direction != 0) & (br.gap_us < 20_000)
        icpt = np.nanmedian(np.where(close, r, np.nan), 0)
        icpt = np.where(np.isfinite(icpt), icpt, np.median(r, 0))
        res[name] = r - icpt[None, :]
    bracketed = br.direction != 0
    for lo, hi in zip(GAP_BINS_US[:-1], GAP_BINS_US[1:], strict=True):
        m = bracketed & (br.gap_us >= lo) & (br.gap_us < hi)
        label = f"{lo / 1000:g}-{hi / 1000:g} ms" if np.isfinite(hi) else f">{lo / 1000:g} ms"
        out.append((label, int(m.sum()), _rms(res["plain"][m]), _rms(res["timing"][m])))
    m = ~bracketed
    out.append(("turning / one-sided", int(m.sum()), _rms(res["plain"][m]),
                _rms(res["timing"][m])))
    return out


def _rms(a: np.ndarray) -> float:
    return float(np.sqrt(np.mean(a ** 2))) if a.size else float("nan")


def cases(args: argparse.Namespace
          ) -> Iterator[tuple[str, Recording, tuple[np.ndarray, np.ndarray, float]]]:
    if args.data:
        data = Path(args.data)
        man = {c["id"]: c for c in json.loads((data / "manifest.json").read_text())["cases"]}
        for cid in args.only.split(","):
            if not cid.startswith("dev"):
                raise SystemExit(f"{cid}: only the benchmark's dev recordings may be read here")
            c = man[cid]
            npz = data / "dev" / f"{cid}.npz"
            with np.load(npz) as z:
                truth = (z["truth_contrast"].astype(np.float64).ravel(),
                         z["truth_bias"].astype(np.float64).ravel(),
                         float(np.median(z["truth_log_offset"])))
            hidden = ",".join(c["truth"]["hidden"]) or "-"
            yield f"{cid} {c['backend']} hidden {hidden}", open_recording(npz), truth
        return
    for scene in SCENES:
        for seed in SEEDS:
            sim = simulate_ideal(SimConfig(height=120, width=160, duration_s=4.0, seed=seed,
                                           scene=scene))
            truth = (sim.truth["contrast"].astype(np.float64).ravel(),
                     sim.truth["bias"].astype(np.float64).ravel(),
                     float(sim.truth["log_offset"]))
            yield f"sim {scene} s{seed}", sim.recording, truth


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--data", help="the gap benchmark's data folder (dev recordings only)")
    p.add_argument("--only", default="", help="with --data: comma-separated dev case ids")
    p.add_argument("--pixels", type=int, default=4000, help="sampled busy pixels")
    p.add_argument("--segments", default="",
                   help="comma-separated segment lengths (frames): also per-pixel fits with "
                        "an intercept per segment, c / b RMSE beside OffEI's")
    p.add_argument("--exposure-samples", type=int, default=0, metavar="K",
                   help="also fits with the fractional counts averaged over each frame's "
                        "exposure at K instants (the frame as the exposure's average)")
    p.add_argument("--read-noise-dn", type=float, default=0.0,
                   help="the frames' read noise (DN) in the bracketed frames' weights")
    args = p.parse_args(argv)
    global READ_NOISE_DN
    READ_NOISE_DN = float(args.read_noise_dn)
    seg_lengths = [int(v) for v in args.segments.split(",") if v]
    print("| recording | events (M) | offset: true / OffEI / curvature plain / timing | "
          "c RMSE OffEI / cumulative plain / timing | b RMSE OffEI / plain / timing | "
          "pixels | residual sd, plain -> timing, by bracket (frames) |")
    print("|---|---|---|---|---|---|---|")
    for name, rec, (c_true, b_true, o_true) in cases(args):
        t0 = time.monotonic()
        try:
            o_offei = estimate_log_offset(rec, OffEIConfig())[0]
        except EvcalError:
            o_offei = float("nan")
        br = brackets(rec, args.pixels, seed=0, exposure_samples=args.exposure_samples)
        ct, bt = c_true[br.pix], b_true[br.pix]
        c0, b0, _, _, u0 = fit(br, o_true, timing=False)
        c1, b1, _, _, u1 = fit(br, o_true, timing=True)
        # OffEI at the true offset on the same pixels (those it calls valid)
        ref = offei(rec, OffEIConfig(log_offset=o_true))
        c2, b2 = (a.ravel()[br.pix].astype(np.float64) for a in (ref.contrast, ref.bias))
        m = u0 & u1 & ref.valid.ravel()[br.pix]

        def rmse(a: np.ndarray, ref: np.ndarray) -> float:
            return float(np.sqrt(np.mean((a[m] - ref[m]) ** 2)))  # noqa: B023

        table = residual_table(br, ct, bt, o_true)
        resid = "; ".join(f"{lab} ({n}): {a:.3f} -> {b_:.3f}" for lab, n, a, b_ in table if n)
        print(f"| {name} | {rec.n_events / 1e6:.2f} | {o_true:.1f} / {o_offei:.1f} / "
              f"{offset_root(br, False):.1f} / {offset_root(br, True):.1f} | "
              f"{rmse(c2, ct):.4f} / {rmse(c0, ct):.4f} / {rmse(c1, ct):.4f} | "
              f"{rmse(b2, bt):.4f} / {rmse(b0, bt):.4f} / {rmse(b1, bt):.4f} | "
              f"{int(m.sum())} | {resid} |", flush=True)
        if br.exposure_avg is not None:
            c3, b3, _, _, u3 = fit(br, o_true, timing="exposure")
            me = u0 & u3 & ref.valid.ravel()[br.pix]

            def re(a: np.ndarray, tt: np.ndarray) -> float:
                return float(np.sqrt(np.mean((a[me] - tt[me]) ** 2)))  # noqa: B023

            print(f"|   exposure average ({args.exposure_samples} samples) | | | "
                  f"{re(c2, ct):.4f} / {re(c0, ct):.4f} / {re(c3, ct):.4f} | "
                  f"{re(b2, bt):.4f} / {re(b0, bt):.4f} / {re(b3, bt):.4f} | {int(me.sum())} "
                  f"| bracketed over the whole exposure: "
                  f"{float(br.exposure_avg[2].mean()):.3f} |", flush=True)
        for n_f in seg_lengths:
            cs0, bs0, f0 = segment_fit(br, o_true, False, n_f)
            cs1, bs1, f1 = segment_fit(br, o_true, True, n_f)
            mm = f0 & f1 & ref.valid.ravel()[br.pix]

            def rm(a: np.ndarray, t: np.ndarray) -> float:
                return float(np.sqrt(np.mean((a[mm] - t[mm]) ** 2)))  # noqa: B023

            print(f"|   segments of {n_f} frames | | | {rm(c2, ct):.4f} / {rm(cs0, ct):.4f} / "
                  f"{rm(cs1, ct):.4f} | {rm(b2, bt):.4f} / {rm(bs0, bt):.4f} / "
                  f"{rm(bs1, bt):.4f} | {int(mm.sum())} | |", flush=True)
        print(f"  ({time.monotonic() - t0:.0f} s)", file=sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
