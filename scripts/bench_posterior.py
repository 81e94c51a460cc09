"""How close each estimator's maps come to the truth, raw and as posterior maps (issue 39).

On recordings whose true per-pixel maps are known: evcal's ideal simulator over several
scenes and seeds (some with planted hot, cold, warm and cool pixels), and, with ``--data``,
the benchmark's dev recordings (``scripts/gap_benchmark.py``; v2e's own thresholds and
evcal's simulator; test-split recordings are refused: they are for reporting the gap
workflow, not for tuning anything). Per recording and method (OffEI and OnEI raw and
posterior, OffE and the paper's OffE, ``offe_paper``): the share of valid pixels, the RMSE
of ``c`` and ``b`` over the valid pixels the truth calls normal, the spread of the z-scores
``(estimate - truth) / stderr`` (1 when the stated errors are calibrated), the special
pixels' precision and recall against the truth's own classes, and the reconstruction PSNR
(``evcal.evaluate``, standard dB) with the maps and with the true maps. OffE, which has no
absolute scale without frames, is anchored at the truth's median contrast
(``OffEConfig.c0``) and log offset: its figures are those of its maps relative to the
population. ``--real`` recordings (no truth): the
valid share, the special pixels found and the PSNR, raw and posterior.

    python scripts/bench_posterior.py                       # simulated, about 3 min
    python scripts/bench_posterior.py --data /work/gapbench --only dev1009,dev1019
    python scripts/bench_posterior.py --json out.jsonl      # one line per recording
    python scripts/bench_posterior.py --no-sim --real ../shared/data/road.aedat4

Prints a table per recording and the medians over them of the posterior's RMSE over the
raw's. Nothing here is tuned to these figures: they say where each method stands.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

import evcal
from evcal.calibration import Calibration, Special
from evcal.errors import CalibrationError
from evcal.estimators import ERROR_SCALES
from evcal.fusion import with_event_timing
from evcal.offe import OffEConfig, offe
from evcal.posterior import POSTERIOR_METHODS, posterior_maps
from evcal.recording import Recording
from evcal.sim.ideal import SimConfig, draw_maps, simulate_ideal
from evcal.special import classify

SCENES = ("astronaut", "coffee", "chelsea", "camera")
SEEDS = (31, 32)
PLANT_SHARE = 0.01  # of the pixels, per special class, in the planted recordings
METHODS = ("offei", "onei", "offe", "offe_paper")


def planted_maps(cfg: SimConfig, rng: np.random.Generator
                 ) -> tuple[np.ndarray, np.ndarray]:
    """The simulator's maps with ``PLANT_SHARE`` of the pixels each made hot (c x 0.45),
    cold (c x 1.9), warm (b - 6 sigma_b) and cool (b + 6 sigma_b)."""
    c, b = draw_maps(cfg, rng)
    n = c.size
    k = int(PLANT_SHARE * n)
    idx = rng.choice(n, 4 * k, replace=False)
    hot, cold, warm, cool = (idx[i * k:(i + 1) * k] for i in range(4))
    c.flat[hot] *= 0.45
    c.flat[cold] *= 1.9
    b.flat[warm] -= 6 * cfg.bias_std
    b.flat[cool] += 6 * cfg.bias_std
    b = np.clip(b, -0.8 * c, 0.8 * c)
    return c, b


Case = tuple[str, Recording, np.ndarray, np.ndarray, float]  # name, recording, c, b, offset


def simulated(scene: str, seed: int, planted: bool, duration_s: float) -> Case:
    cfg = SimConfig(height=120, width=160, duration_s=duration_s, seed=seed, scene=scene)
    maps = planted_maps(cfg, np.random.default_rng(seed)) if planted else None
    sim = simulate_ideal(cfg, maps=maps)
    c, b = (sim.truth[k].astype(np.float64) for k in ("contrast", "bias"))
    name = f"sim {scene} s{seed}" + (" planted" if planted else "")
    return name, sim.recording, c, b, float(sim.truth["log_offset"])


def from_benchmark(data: Path, case_id: str) -> Case:
    if not case_id.startswith("dev"):
        raise SystemExit(f"{case_id}: only the benchmark's dev recordings may be read here")
    npz = data / "dev" / f"{case_id}.npz"
    rec = evcal.open_recording(npz)
    with np.load(npz) as z:
        c = z["truth_contrast"].astype(np.float64)
        b = z["truth_bias"].astype(np.float64)
        offset = float(np.median(z["truth_log_offset"]))
    meta = json.loads((data / "dev" / f"{case_id}.json").read_text())
    backend = meta.get("generated", {}).get("backend", "?")
    hidden = ",".join(meta.get("truth", {}).get("hidden", [])) or "-"
    return f"{case_id} {backend} hidden {hidden}", rec, c, b, offset


def special_scores(cal: Calibration, truth_cls: np.ndarray) -> dict[str, float]:
    """Precision and recall of the special pixels (any class, the class must match)."""
    spec = (cal.special != Special.NORMAL) & (cal.special != Special.UNOBSERVED)
    true = truth_cls != Special.NORMAL
    hit = spec & (cal.special == truth_cls)
    n_spec, n_true = int(spec.sum()), int(true.sum())
    return {"special_found": n_spec, "special_true": n_true,
            "precision": float(hit.sum() / n_spec) if n_spec else float("nan"),
            "recall": float(hit.sum() / n_true) if n_true else float("nan")}


def map_scores(cal: Calibration, c: np.ndarray, b: np.ndarray, normal: np.ndarray
               ) -> dict[str, float]:
    m = cal.valid & normal
    out: dict[str, float] = {"valid": float(cal.valid.mean())}
    for key, est, se, t in (("c", cal.contrast, cal.stderr_contrast, c),
                            ("b", cal.bias, cal.stderr_bias, b)):
        err = (est[m] - t[m]).astype(np.float64)
        out[f"{key}_rmse"] = float(np.sqrt(np.mean(err ** 2))) if err.size else float("nan")
        s = se[m].astype(np.float64)
        ok = np.isfinite(s) & (s > 0)
        out[f"{key}_std_z"] = float(np.std(err[ok] / s[ok])) if ok.sum() > 10 else float("nan")
    return out


def psnr(rec: Recording, cal: Calibration) -> float:
    res = evcal.evaluate(rec, cal)
    return float(res.summary()["calibrated"]["psnr"])


def score(name: str, rec: Recording, c: np.ndarray, b: np.ndarray, offset: float,
          error_scale: str = "auto") -> dict[str, Any]:
    truth_cls = classify(c, b, np.zeros_like(c), np.zeros_like(b), np.ones(c.shape, bool))
    normal = truth_cls == Special.NORMAL
    row: dict[str, Any] = {"recording": name, "n_events": int(rec.n_events),
                           "truth_special": int((~normal).sum())}
    truth_cal = Calibration.uniform(c.shape, 0.1, 0.0, log_offset=offset).replace(
        contrast=c.astype(np.float32), bias=b.astype(np.float32))
    row["psnr_truth"] = psnr(rec, truth_cal)
    for method in METHODS:
        t0 = time.perf_counter()
        try:
            if method in ("offe", "offe_paper"):  # anchored at the truth's median and log offset
                # (offe_paper: the population's median r, not the neighbours')
                k = 0 if method == "offe_paper" else OffEConfig.neighbourhood_px
                cal = offe(rec, OffEConfig(c0=float(np.median(c[normal])),
                                           neighbourhood_px=k)).replace(log_offset=offset)
            else:
                cal = evcal.calibrate(rec, method, error_scale=error_scale)
        except CalibrationError as e:  # too few events for this method: said, not fatal
            row[method] = {"error": str(e)}
            if method in POSTERIOR_METHODS:
                row[f"{method}_posterior"] = {"error": str(e)}
            continue
        row[method] = {**map_scores(cal, c, b, normal), **special_scores(cal, truth_cls),
                       "seconds": time.perf_counter() - t0}
        if "error_scale" in cal.diagnostics.extra:
            row[method]["error_scale"] = cal.diagnostics.extra["error_scale"]
        row[method]["psnr"] = psnr(rec, cal)
        if method in POSTERIOR_METHODS:
            # the frames' maps fused with OffE's (evcal.fusion), raw and posterior
            fused = with_event_timing(rec, cal)
            for key, m in ((f"{method}_timing", fused),
                           (f"{method}_timing_posterior", posterior_maps(fused))):
                row[key] = {**map_scores(m, c, b, normal), **special_scores(m, truth_cls),
                            "psnr": psnr(rec, m), **m.diagnostics.extra.get("fusion", {})}
            post = posterior_maps(cal)
            row[f"{method}_posterior"] = {**map_scores(post, c, b, normal),
                                          **special_scores(post, truth_cls),
                                          "psnr": psnr(rec, post)}
    return row


def score_real(name: str, rec: Recording, error_scale: str = "auto") -> dict[str, Any]:
    """A recording without known maps: what a user of it sees, raw and posterior."""
    row: dict[str, Any] = {"recording": name, "n_events": int(rec.n_events), "real": True}
    for method in POSTERIOR_METHODS:
        try:
            cal = evcal.calibrate(rec, method, error_scale=error_scale)
        except CalibrationError as e:
            row[method] = {"error": str(e)}
            continue
        fused = with_event_timing(rec, cal)
        for key, m in ((method, cal), (f"{method}_posterior", posterior_maps(cal)),
                       (f"{method}_timing", fused),
                       (f"{method}_timing_posterior", posterior_maps(fused))):
            special = (m.special != Special.NORMAL) & (m.special != Special.UNOBSERVED)
            row[key] = {"valid": float(m.valid.mean()), "special": int(special.sum()),
                        "psnr": psnr(rec, m)}
        if "error_scale" in cal.diagnostics.extra:
            row[method]["error_scale"] = cal.diagnostics.extra["error_scale"]
    return row


def print_real(row: dict[str, Any]) -> None:
    print(f"\n{row['recording']}  ({row['n_events'] / 1e6:.2f} M events, no truth)")
    print(f"  {'method':16s} {'valid':>6s} {'special':>8s} {'PSNR dB':>8s}")
    for key in ("offei", "offei_posterior", "offei_timing", "offei_timing_posterior", "onei",
                "onei_posterior", "onei_timing", "onei_timing_posterior"):
        r = row.get(key)
        if r is None:
            continue
        if "error" in r:
            print(f"  {key:16s} {r['error']}")
            continue
        print(f"  {key:16s} {r['valid']:6.3f} {r['special']:8d} {r['psnr']:8.2f}")


def print_row(row: dict[str, Any]) -> None:
    print(f"\n{row['recording']}  ({row['n_events'] / 1e6:.2f} M events, "
          f"{row['truth_special']} special pixels in the truth; true maps: PSNR "
          f"{row['psnr_truth']:.2f} dB)")
    print(f"  {'method':16s} {'valid':>6s} {'c RMSE':>8s} {'std z':>6s} {'b RMSE':>8s} "
          f"{'std z':>6s} {'PSNR dB':>8s} {'special P':>9s} {'R':>5s}")
    for key in ("offei", "offei_posterior", "offei_timing", "offei_timing_posterior", "onei",
                "onei_posterior", "onei_timing", "onei_timing_posterior", "offe",
                "offe_paper"):
        if key not in row:
            continue
        r = row[key]
        if "error" in r:
            print(f"  {key:16s} {r['error']}")
            continue
        print(f"  {key:16s} {r['valid']:6.3f} {r['c_rmse']:8.4f} {r['c_std_z']:6.2f} "
              f"{r['b_rmse']:8.4f} {r['b_std_z']:6.2f} {r.get('psnr', float('nan')):8.2f} "
              f"{r['precision']:9.2f} {r['recall']:5.2f}")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, help="the gap benchmark's directory (dev cases)")
    ap.add_argument("--only", help="comma-separated dev case ids (with --data)")
    ap.add_argument("--no-sim", action="store_true", help="only the benchmark's recordings")
    ap.add_argument("--duration", type=float, default=4.0, help="simulated seconds (4)")
    ap.add_argument("--json", type=Path, help="append one JSON line per recording")
    ap.add_argument("--real", type=Path, action="append", default=[],
                    help="a recording without known maps (repeatable): PSNR, valid share and "
                         "special pixels, raw and posterior")
    ap.add_argument("--error-scale", choices=list(ERROR_SCALES), default="auto",
                    help="the stated errors' split-half check (evcal.splithalf; default: "
                         "evcal.calibrate's, OnEI only)")
    args = ap.parse_args(argv)
    jobs: list[Any] = []
    if not args.no_sim:
        for i, scene in enumerate(SCENES):
            for seed in SEEDS:
                planted = (i + seed) % 2 == 1  # half of the recordings
                jobs.append(lambda s=scene, d=seed, p=planted: simulated(s, d, p,
                                                                         args.duration))
    if args.data is not None:
        ids = [x for x in (args.only or "").split(",") if x]
        if not ids:
            raise SystemExit("--data needs --only (dev case ids)")
        jobs += [lambda i=i: from_benchmark(args.data, i) for i in ids]
    for path in args.real:
        real = score_real(path.name, evcal.open_recording(path), args.error_scale)
        print_real(real)
        if args.json is not None:
            with args.json.open("a") as f:
                f.write(json.dumps(real) + "\n")
        sys.stdout.flush()
    rows = []
    for job in jobs:
        name, rec, c, b, offset = job()
        row = score(name, rec, c, b, offset, args.error_scale)
        rows.append(row)
        print_row(row)
        if args.json is not None:
            with args.json.open("a") as f:
                f.write(json.dumps(row) + "\n")
        sys.stdout.flush()
    for method, post in [(m, f"{m}{v}") for m in POSTERIOR_METHODS
                         for v in ("_posterior", "_timing", "_timing_posterior")]:
        done = [r for r in rows if "error" not in r[method]]
        if not done:
            continue
        ratio_c = [r[post]["c_rmse"] / r[method]["c_rmse"] for r in done]
        ratio_b = [r[post]["b_rmse"] / r[method]["b_rmse"] for r in done]
        d_psnr = [r[post]["psnr"] - r[method]["psnr"] for r in done]
        print(f"\n{len(done)} recordings: {post} / raw {method} RMSE, median (range): c "
              f"{np.median(ratio_c):.2f} ({min(ratio_c):.2f}-{max(ratio_c):.2f}), b "
              f"{np.median(ratio_b):.2f} ({min(ratio_b):.2f}-{max(ratio_b):.2f}); PSNR "
              f"{post} - raw {np.median(d_psnr):+.3f} dB ({min(d_psnr):+.3f} to "
              f"{max(d_psnr):+.3f})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
