"""Make ``mvsec_like.hdf5`` and ``dsec_like.h5`` of tests/data/formats/ (see README.md).

No maintained writer of these layouts exists (MVSEC and DSEC were written by their authors'
own scripts), so these files are laid out here with h5py after the datasets' published
descriptions, filled with the v2e events of ``v2e_truth.npz`` (made by generate_v2e.py).
Run from the repository root with evcal's venv (h5py, hdf5plugin):

    python tests/data/formats/generate_hdf5.py
"""

from __future__ import annotations

from pathlib import Path

import h5py
import hdf5plugin
import numpy as np

OUT = Path(__file__).resolve().parent
T0_S = 1504645177.0  # an MVSEC-like Unix time (s)
T_OFFSET_US = 50_000_000  # DSEC-like t_offset


def main() -> None:
    truth = np.load(OUT / "v2e_truth.npz")
    t_s, x, y, p = truth["t_s"], truth["x"], truth["y"], truth["p"]
    with h5py.File(OUT / "v2e_dvs.h5", "r") as f:
        v2e_frames = f["frame"][()]
    # MVSEC: davis/{left,right}/events float64 [x, y, t (s), p (-1/+1)], image_raw 260x346
    with h5py.File(OUT / "mvsec_like.hdf5", "w") as f:
        for cam, take in (("left", slice(None)), ("right", slice(0, 100))):
            g = f.create_group(f"davis/{cam}")
            rows = np.stack([x[take], y[take], T0_S + t_s[take], p[take]], axis=1)
            g.create_dataset("events", data=rows.astype(np.float64), compression="gzip")
        images = np.zeros((2, 260, 346), np.uint8)
        images[:, :180, :240] = v2e_frames[[0, 5]]
        g = f["davis/left"]
        g.create_dataset("image_raw", data=images, compression="gzip")
        g.create_dataset("image_raw_ts", data=T0_S + np.array([0.0005, 0.0055]))
    # DSEC: events/{x, y, t, p}, t_offset, ms_to_idx; Blosc (zstd) as DSEC ships them
    t_us = np.rint(t_s * 1e6).astype(np.uint32)
    with h5py.File(OUT / "dsec_like.h5", "w") as f:
        blosc = hdf5plugin.Blosc(cname="zstd", clevel=5, shuffle=hdf5plugin.Blosc.SHUFFLE)
        f.create_dataset("events/x", data=x.astype(np.uint16), **blosc)
        f.create_dataset("events/y", data=y.astype(np.uint16), **blosc)
        f.create_dataset("events/t", data=t_us, **blosc)
        f.create_dataset("events/p", data=(p > 0).astype(np.uint8), **blosc)
        f.create_dataset("t_offset", data=np.int64(T_OFFSET_US))
        ms = np.arange(int(t_us[-1]) // 1000 + 1) * 1000
        f.create_dataset("ms_to_idx", data=np.searchsorted(t_us, ms).astype(np.uint64))


if __name__ == "__main__":
    main()
