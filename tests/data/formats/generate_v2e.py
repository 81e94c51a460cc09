"""Make ``v2e_dvs.h5`` and ``v2e_davis240.aedat`` of tests/data/formats/ with v2e's writers.

Run with the v2e venv of scripts/v2e_data/README.md (v2e at the commit pinned there):

    /path/to/v2e-venv/bin/python tests/data/formats/generate_v2e.py --v2e /path/to/v2e-src

One EventEmulator run (240x180, 6 input frames at 1 kHz of skimage's ``camera``, blurred
(sigma 3 px), moving right by 0.4 px a frame, seed 7, v2e's default thresholds, no noise) writes
both files
through v2e's own output code: ``dvs_h5`` (``events`` N x 4 uint32 [t_us, x, y, p in
{0, 1}], ``frame`` uint8 of every input frame, ``frame_ts`` uint32 µs, ``frame_idx``) and
``dvs_aedat2`` (jAER AEDAT-2.0, DAVIS address layout, v2e's ``AEDat2Output``). The events
v2e returned are also saved (``v2e_truth.npz``: t_s float64, x, y, p +-1) as the truth.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

OUT = Path(__file__).resolve().parent
W, H = 240, 180


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--v2e", required=True)
    args = parser.parse_args()
    sys.path.insert(0, args.v2e)
    import cv2
    import skimage.data
    from v2ecore.emulator import EventEmulator

    texture = cv2.GaussianBlur(skimage.data.camera().astype(np.float64), (0, 0), 3.0)
    texture = 25 + 210 * (texture - texture.min()) / np.ptp(texture)
    times = np.arange(6) / 1000.0
    emu = EventEmulator(seed=7, device="cpu", output_width=W, output_height=H,
                        output_folder=str(OUT), dvs_h5="v2e_dvs.h5",
                        dvs_aedat2="v2e_davis240.aedat", leak_rate_hz=0.0,
                        shot_noise_rate_hz=0.0)
    emu.prepare_storage(len(times), times)
    chunks = []
    for k, t in enumerate(times):
        m = np.float32([[1, 0, -100 - 0.4 * k], [0, 0, -150]])
        m[1, 1] = 1
        frame = cv2.warpAffine(texture, m, (W, H), flags=cv2.INTER_LINEAR)
        ev = emu.generate_events(frame, float(t))
        if ev is not None and len(ev):
            chunks.append(np.asarray(ev, np.float64))
    emu.cleanup()
    ev = np.concatenate(chunks)
    np.savez_compressed(OUT / "v2e_truth.npz", t_s=ev[:, 0], x=ev[:, 1].astype(np.uint16),
                        y=ev[:, 2].astype(np.uint16), p=ev[:, 3].astype(np.int8))
    print(len(ev), "events")


if __name__ == "__main__":
    main()
