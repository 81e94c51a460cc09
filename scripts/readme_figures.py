"""The README's figures on the real DAVIS346 ``road.aedat4``, made again.

    python scripts/readme_figures.py        # ../shared/data or $EVCAL_SHARED_DATA

Prints OffEI (log offset estimated) and OnEI (default sizes: the small buffer fitted to the
recording, an eighth of its events) against DI,
reconstructing over 5 frame intervals per image, the same way as

    evcal calibrate road.aedat4 --method offei --log-offset auto --out cal.npz
    evcal evaluate road.aedat4 --calibration cal.npz --frames-per-image 5

The README quotes what this prints; re-run it when the estimators or the metrics change.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

import evcal


def main() -> int:
    base = Path(os.environ.get("EVCAL_SHARED_DATA",
                               Path(__file__).resolve().parents[2] / "shared" / "data"))
    path = base / "davis346_road" / "road.aedat4"
    if not path.exists():
        print(f"{path} not found", file=sys.stderr)
        return 1
    rec = evcal.open_recording(path)
    print(f"road.aedat4: {rec.sensor}, {rec.n_events:,} events, {len(rec.frames)} frames")
    off = evcal.calibrate(rec, "offei", log_offset="auto")
    on = evcal.calibrate(rec, "onei", log_offset="auto")
    for name, cal in (("OffEI", off), (f"OnEI n_small {on.diagnostics.n_small:,}", on)):
        s = evcal.evaluate(rec, cal, frames_per_image=5).summary()
        print(f"{name}: log offset {cal.log_offset:.1f}, valid {100 * cal.valid.mean():.1f} %, "
              f"PSNR {s['calibrated']['psnr']:.2f} dB against DI's {s['di']['psnr']:.2f} dB "
              f"({s['n_images']} images)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
