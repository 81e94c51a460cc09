#!/usr/bin/env python3
"""Sanity check of the v2e test recordings: run in evcal's venv.

    python scripts/v2e_data/check.py [DIR]          (default tests/data/v2e)

For every recording in DIR's manifest.json (or every *.npz): opens it with
``evcal.open_recording``, prints events, frames, duration, events / pixel / s, checks the
file's sha256 against the manifest, runs OffEI (``evcal.offei``, log offset 0: every input
intensity is above v2e's lin-log threshold) and compares ``c`` and ``b`` with the truth
maps stored in the archive (``truth_contrast``, ``truth_bias``). RMSE over pixels whose
OffEI estimate is valid (and over all pixels), then a per-case summary.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
from collections import defaultdict
from pathlib import Path

import numpy as np

import evcal
from evcal.offline import OffEIConfig


def rmse(a: np.ndarray, b: np.ndarray, mask: np.ndarray) -> float:
    d = (a - b)[mask]
    return float(np.sqrt(np.mean(d * d))) if d.size else float("nan")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("dir", nargs="?", default=str(Path(__file__).resolve().parents[2]
                                                  / "tests" / "data" / "v2e"))
    ap.add_argument("--window-frames", type=int, default=OffEIConfig().window_frames)
    ap.add_argument("--json", help="write the per-recording numbers to this file")
    args = ap.parse_args(argv)
    d = Path(args.dir)
    man_path = d / "manifest.json"
    if man_path.is_file():
        manifest = json.loads(man_path.read_text())
        entries = manifest["recordings"]
    else:
        entries = [{"file": p.name} for p in sorted(d.glob("*.npz"))]
    cfg = OffEIConfig(log_offset=0.0, window_frames=args.window_frames)

    hdr = (f"{'recording':24s} {'events':>7s} {'ON%':>5s} {'frames':>6s} {'dur_s':>5s} "
           f"{'ev/px/s':>7s} {'valid%':>6s} {'c_true':>6s} {'c_med':>6s} {'c_rmse':>6s} "
           f"{'c_rmse_all':>10s} {'b_rmse':>6s} {'c_corr':>6s}")
    print(hdr)
    rows = []
    bad = 0
    for e in entries:
        path = d / e["file"]
        if "sha256" in e:
            digest = hashlib.sha256(path.read_bytes()).hexdigest()
            if digest != e["sha256"]:
                print(f"{path.name}: sha256 {digest} differs from the manifest's", file=sys.stderr)
                bad += 1
        rec = evcal.open_recording(path)
        with np.load(path, allow_pickle=False) as z:
            tc = z["truth_contrast"].astype(np.float64)
            tb = z["truth_bias"].astype(np.float64)
        meta = rec.metadata
        ev = rec.events
        n = int(ev.size)
        dur = (int(ev["t_us"][-1]) - int(ev["t_us"][0])) / 1e6 if n else 0.0
        dur = max(dur, float(meta.get("duration_s", dur)))
        cal = evcal.offei(rec, cfg)
        c = cal.contrast.astype(np.float64)
        b = cal.bias.astype(np.float64)
        valid = cal.valid.astype(bool)
        allpx = np.ones_like(valid)
        row = dict(
            file=path.name, case=meta.get("case"), scene=meta.get("scene"), events=n,
            on_fraction=float(np.mean(ev["p"] > 0)) if n else float("nan"),
            frames=len(rec.frames), duration_s=dur,
            ev_px_s=n / rec.sensor.n_pixels / dur if dur else float("nan"),
            valid_fraction=float(valid.mean()), c_true_mean=float(tc.mean()),
            c_median=float(np.median(c[valid])) if valid.any() else float("nan"),
            c_rmse=rmse(c, tc, valid), c_rmse_all=rmse(c, tc, allpx),
            b_rmse=rmse(b, tb, valid),
            c_corr=float(np.corrcoef(c[valid], tc[valid])[0, 1]) if valid.sum() > 2
            else float("nan"),
        )
        rows.append(row)
        print(f"{row['file']:24s} {n:7d} {100 * row['on_fraction']:5.1f} {row['frames']:6d} "
              f"{dur:5.2f} {row['ev_px_s']:7.2f} {100 * row['valid_fraction']:6.1f} "
              f"{row['c_true_mean']:6.3f} {row['c_median']:6.3f} {row['c_rmse']:6.4f} "
              f"{row['c_rmse_all']:10.4f} {row['b_rmse']:6.4f} {row['c_corr']:6.3f}")

    print("\nper case (mean over scenes)")
    print(f"{'case':12s} {'events':>8s} {'ev/px/s':>7s} {'c_rmse':>7s} {'c_rmse_all':>10s} "
          f"{'b_rmse':>7s} {'c_med-c_true':>12s}")
    by = defaultdict(list)
    for r in rows:
        by[r["case"]].append(r)
    for case, rs in by.items():
        print(f"{str(case):12s} {np.mean([r['events'] for r in rs]):8.0f} "
              f"{np.mean([r['ev_px_s'] for r in rs]):7.2f} "
              f"{np.mean([r['c_rmse'] for r in rs]):7.4f} "
              f"{np.mean([r['c_rmse_all'] for r in rs]):10.4f} "
              f"{np.mean([r['b_rmse'] for r in rs]):7.4f} "
              f"{np.mean([r['c_median'] - r['c_true_mean'] for r in rs]):+12.4f}")
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1) + "\n")
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
