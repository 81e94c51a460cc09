"""Make ``davis240_v31.aedat`` of tests/data/formats/ (see README.md there).

No maintained Python writer of AEDAT 3.1 exists (jAER writes 2.0, DV and the ``aedat`` and
``dv-processing`` packages write 4.0; cAER, which wrote 3.1, is C and retired), and no small
real 3.1 file with a compatible licence was found. This packer follows libcaer's
``events/common.h``, ``polarity.h`` and ``frame.h`` and fills the file with the v2e events
and input frames of ``v2e_truth.npz`` / ``v2e_dvs.h5`` (made by generate_v2e.py), shifted
to start at 2^31 - 3500 µs (+ v2e time) so that the 31-bit timestamp overflows within the
file. Run from the repository root with evcal's venv:

    python tests/data/formats/generate_aedat31.py

Packets, in file order: a special packet (type 0, one zero event), polarity packets of at
most 1000 events split where the overflow counter changes (the first one holds one extra
event with its valid bit clear), two frame packets (type 2) of one 240x180 gray frame each
(v2e frames 1 and 4; exposure 1000 µs; pixels = v2e frame * 257), an IMU6 packet (type 3,
one zero event).
"""

from __future__ import annotations

import struct
from pathlib import Path

import h5py
import numpy as np

OUT = Path(__file__).resolve().parent
T_START = (1 << 31) - 3500  # v2e times 2000..5000 µs: the overflow falls at 3500
W, H = 240, 180


def packet(ev_type: int, size: int, ts_offset: int, overflow: int, body: bytes, n: int,
           source: int = 1) -> bytes:
    return struct.pack("<hhiiiiii", ev_type, source, size, ts_offset, overflow, n, n, n) + body


def main() -> None:
    truth = np.load(OUT / "v2e_truth.npz")
    with h5py.File(OUT / "v2e_dvs.h5", "r") as f:
        frames = f["frame"][()]
        frame_ts = f["frame_ts"][()].astype(np.int64)
    t = T_START + np.rint(truth["t_s"] * 1e6).astype(np.int64)
    x = truth["x"].astype(np.uint32)
    y = truth["y"].astype(np.uint32)
    on = (truth["p"] > 0).astype(np.uint32)
    data = (x << 17) | (y << 2) | (on << 1) | 1
    header = (b"#!AER-DAT3.1\r\n#Format: RAW\r\n#Source 1: DAVIS240C\r\n"
              b"#Start-Time: 2026-01-01 00:00:00 (TZ+0000)\r\n#!END-HEADER\r\n")
    out = [header, packet(0, 8, 4, 0, struct.pack("<Ii", 0, int(T_START)), 1)]
    overflow = t >> 31
    bounds = sorted({0, t.size, *(np.flatnonzero(np.diff(overflow)) + 1).tolist(),
                     *range(0, t.size, 1000)})
    for i, (a, b) in enumerate(zip(bounds[:-1], bounds[1:], strict=True)):
        rec = np.zeros(b - a, [("d", "<u4"), ("t", "<i4")])
        rec["d"] = data[a:b]
        rec["t"] = t[a:b] & 0x7FFFFFFF
        body = rec.tobytes()
        n = b - a
        if i == 0:  # an invalid event (valid bit clear) that a reader must skip
            body += struct.pack("<Ii", (5 << 17) | (5 << 2), int(t[a] & 0x7FFFFFFF))
            n += 1
        out.append(packet(1, 8, 4, int(overflow[a]), body, n))
    fsize = 36 + W * H * 2
    for k in (1, 4):
        tf = T_START + int(frame_ts[k])
        ov = tf >> 31
        pix = (frames[k].astype(np.uint16) * 257).astype("<u2").tobytes()
        lo = tf - (ov << 31)
        body = struct.pack("<Iiiiiiiii", 1 | (1 << 1), lo - 600, lo - 400, lo - 500,
                           lo + 500, W, H, 0, 0) + pix
        # frame 1 (v2e t=1000 us) is before the overflow, frame 4 (4000 us) after it: a
        # packet has one overflow value, so one packet each
        out.append(packet(2, fsize, 12, int(ov), body, 1))
    out.append(packet(3, 36, 4, 1, bytes(36), 1))
    (OUT / "davis240_v31.aedat").write_bytes(b"".join(out))


if __name__ == "__main__":
    main()
