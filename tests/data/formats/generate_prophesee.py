"""Make the Prophesee test files of tests/data/formats/ (see README.md there).

Run with a Python that has faery 0.7.1 and numpy (not evcal's venv; faery is not an evcal
dependency), from the repository root:

    python tests/data/formats/generate_prophesee.py /path/to/faery/tests/data/evt2.raw

- ``evt2_real.raw``: the header and the first 24,000 words of faery's real ``evt2.raw``
  (a Gen3 640x480 camera), cut at a word boundary;
- ``evt3_faery.raw``, ``cd_faery.dat``: the first 20,000 events of that file as faery
  decodes them, written by faery's own EVT 3.0 and DAT encoders (640x480 declared);
- ``evt21.raw``, ``evt21_legacy.raw``: the same events packed as EVT 2.1 by the code below,
  following Prophesee's EVT 2.1 page (no maintained EVT 2.1 writer exists: faery panics
  "not yet implemented", expelliarmus has none), one TIME_HIGH per 64 µs step and one
  word per (time, y, polarity, 32-pixel group).
"""

from __future__ import annotations

import sys
from pathlib import Path

import faery
import numpy as np

OUT = Path(__file__).resolve().parent
N_WORDS = 24_000
N_EVENTS = 20_000


def header_length(data: bytes) -> int:
    pos = 0
    while data[pos : pos + 1] == b"%":
        pos = data.index(b"\n", pos) + 1
    return pos


def pack_evt21(ev: np.ndarray, legacy: bool) -> bytes:
    t = ev["t"].astype(np.uint64)
    x = ev["x"].astype(np.uint64)
    y = ev["y"].astype(np.uint64)
    p = ev["on"].astype(np.uint64)
    group = x >> np.uint64(5)
    # one word per run of equal (t, y, p, group); events inside a word keep ascending x
    key = np.stack([t, y, p, group])
    new = np.concatenate([[True], (key[:, 1:] != key[:, :-1]).any(axis=0)])
    word_id = np.cumsum(new) - 1
    firsts = np.flatnonzero(new)
    mask = np.zeros(firsts.size, np.uint64)
    np.bitwise_or.at(mask, word_id, np.uint64(1) << (x & np.uint64(31)))
    tw, yw, pw, gw = t[firsts], y[firsts], p[firsts], group[firsts]
    upper = (pw << np.uint64(28)) | ((tw & np.uint64(63)) << np.uint64(22)) | \
        ((gw << np.uint64(5)) << np.uint64(11)) | yw
    cd = (upper << np.uint64(32)) | mask
    high = tw >> np.uint64(6)
    th_needed = np.concatenate([[True], high[1:] != high[:-1]])
    th = (np.uint64(8) << np.uint64(60)) | (high << np.uint64(32))
    words = []
    for i in range(cd.size):  # a writer, not evcal: clarity over speed
        if th_needed[i]:
            words.append(th[i])
        words.append(cd[i])
    out = np.array(words, np.uint64)
    if legacy:
        out = (out << np.uint64(32)) | (out >> np.uint64(32))
    return out.astype("<u8").tobytes()


def main(source: str) -> None:
    data = Path(source).read_bytes()
    n = header_length(data)
    real = data[: n + 4 * N_WORDS]
    (OUT / "evt2_real.raw").write_bytes(real)
    decoder = faery.evt.Decoder(OUT / "evt2_real.raw", dimensions_fallback=(640, 480),
                                version_fallback=None)
    ev = np.concatenate([p["events"] for p in decoder if "events" in p])[:N_EVENTS]
    with faery.evt.Encoder(OUT / "evt3_faery.raw", version="evt3", zero_t0=False,
                           dimensions=(640, 480), enforce_monotonic=True) as enc:
        enc.write({"events": ev})
    cd = np.zeros(ev.size, [("t", "<u8"), ("x", "<u2"), ("y", "<u2"), ("payload", "u1")])
    cd["t"], cd["x"], cd["y"], cd["payload"] = ev["t"], ev["x"], ev["y"], ev["on"]
    with faery.dat.Encoder(OUT / "cd_faery.dat", version="dat2", event_type="cd",
                           zero_t0=False, dimensions=(640, 480)) as enc:
        enc.write(cd)
    for name, legacy, fmt in (("evt21.raw", False, "EVT21;height=480;width=640"),
                              ("evt21_legacy.raw", True,
                               "EVT21;height=480;width=640;endianness=legacy")):
        head = f"% camera_integrator_name evcal test\n% format {fmt}\n% end\n".encode()
        (OUT / name).write_bytes(head + pack_evt21(ev, legacy))


if __name__ == "__main__":
    main(sys.argv[1])
