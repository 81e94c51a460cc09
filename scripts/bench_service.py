"""Benchmarks of the live service (figures, not tests): throughput, latency, memory.

    python scripts/bench_service.py throughput [--sizes 346x260,1280x720] [--events 20e6]
    python scripts/bench_service.py latency [--seconds 20]
    python scripts/bench_service.py memory [--minutes 10]
    python scripts/bench_service.py all

The service runs as its own process (``python -m evcal.service``) on ``tcp/127.0.0.1`` with
``--on-full block``; this process publishes like ``evcal replay --max-rate`` does (encoding
included) and reads the service's status and calibration outputs.

throughput  events/s from publishing to the service's event counter at 20 M events/s of
            sensor time: "events" (no frames: decode, validate, OnEI's pending buffer),
            "frames" (25 Hz frames fold the events into the accumulators, no re-solve),
            "updates" (OnEI's default sizes: a re-solve and a published calibration at
            every frame).
latency     wall time from a frame's put to the calibration it triggered arriving back, and
            the service's own figure (frame arrival to publication), at 346x260.
memory      the service's RSS every 10 s while a 346x260 camera streams in real time.
"""

from __future__ import annotations

import argparse
import json
import sys
import threading
import time

import numpy as np
import psutil

from evcal.events import EVENTS_DTYPE, SensorSize
from evcal.io.wire import encode_events, encode_frame
from evcal.service import keys
from evcal.service.testing import ServiceProcess, endpoint, free_port, wait_for
from evcal.service.transport import Transport, ZenohOptions

ZARGS = ["--no-multicast-scouting"]


def synthetic_chunk(rng: np.random.Generator, sensor: SensorSize, n: int, t0_us: int,
                    span_us: int) -> np.ndarray:
    ev = np.empty(n, EVENTS_DTYPE)
    ev["t_us"] = np.sort(rng.integers(t0_us, t0_us + span_us, n))
    ev["x"] = rng.integers(0, sensor.width, n)
    ev["y"] = rng.integers(0, sensor.height, n)
    ev["p"] = rng.choice(np.array([-1, 1], np.int8), n)
    return ev


def status(t: Transport, camera: str) -> dict:
    r = t.get(f"evcal/{camera}/status", timeout_s=2.0)
    return json.loads(r[0].payload) if r and r[0].ok else {}


def start_service(extra: list[str]) -> tuple[ServiceProcess, str]:
    ep = endpoint(free_port())
    sp = ServiceProcess(["--listen", ep, *ZARGS, "--on-full", "block", "--status-period",
                         "0.25", "--max-pixels", str(1280 * 720), *extra]).start()
    return sp, ep


THROUGHPUT_MODES = {
    # name: (frames at 25 Hz of sensor time, service arguments)
    "events": (False, ["--n-small", "2000000000", "--n-large", "2000000000"]),
    "frames": (True, ["--n-small", "2000000000", "--n-large", "2000000000"]),
    "updates": (True, []),  # OnEI's default sizes: at 20 M ev/s an update at every frame
}


def throughput(sensor: SensorSize, n_events: int, *, mode: str, chunk: int = 100_000
               ) -> dict:
    rng = np.random.default_rng(0)
    rate_hz = 20e6  # sensor-time event rate of the synthetic stream
    span = int(chunk / rate_hz * 1e6)
    # a few distinct chunks, re-stamped in time (keeps this process's CPU for publishing)
    base = [synthetic_chunk(rng, sensor, chunk, 0, span) for _ in range(4)]
    img = rng.integers(0, 255, sensor.shape).astype(np.uint8)
    frames, extra = THROUGHPUT_MODES[mode]
    sp, ep = start_service(extra)
    cam = f"bench/{sensor}"
    try:
        with Transport(ZenohOptions.loopback(connect=[ep])) as t:
            wait_for(lambda: t.alive("evcal/@service/*", timeout_s=1.0), timeout_s=60)
            pub_ev = t.publisher(keys.camera_key("evcal", cam, "events"), keys.ENC_EVENTS,
                                 block=True)
            pub_fr = t.publisher(keys.camera_key("evcal", cam, "frames"), keys.ENC_FRAME,
                                 block=True)
            wait_for(lambda: pub_ev.has_subscribers, timeout_s=10)
            n_msgs = n_events // chunk
            frame_every = max(1, int(40_000 * rate_hz / 1e6 / chunk))  # 25 Hz sensor time
            seq_f = 0
            t0 = time.monotonic()
            for i in range(n_msgs):
                ev = base[i % 4].copy()
                ev["t_us"] += i * span
                if frames and i % frame_every == 0:
                    pub_fr.put(encode_frame(int(ev["t_us"][0]), img, exposure_us=0,
                                            seq=seq_f))
                    seq_f += 1
                pub_ev.put(encode_events(ev, height=sensor.height, width=sensor.width,
                                         seq=i))
            t_pub = time.monotonic() - t0
            total = n_msgs * chunk
            wait_for(lambda: status(t, cam).get("events", 0) >= total, timeout_s=600,
                     interval_s=0.05)
            t_all = time.monotonic() - t0
            st = status(t, cam)
        rss = psutil.Process(sp.pid).memory_info().rss
    finally:
        sp.stop()
    return {"sensor": str(sensor), "mode": mode, "events": total,
            "publish_s": t_pub, "total_s": t_all, "events_per_s": total / t_all,
            "updates": st.get("updates"), "errors": st.get("errors_total"),
            "service_rss_mb": rss / 2**20}


def latency(seconds: float) -> dict:
    """Real-time 346x260 stream at 2 M events/s, 25 Hz frames, OnEI's default buffer sizes
    (an update about every 5 frames); latency of the frames that triggered an update."""
    sensor = SensorSize(260, 346)
    rng = np.random.default_rng(1)
    rate = 2_000_000  # events/s of sensor time
    per_frame = rate // 25
    sp, ep = start_service([])
    cam = "bench/latency"
    sent: dict[int, float] = {}
    got: list[float] = []
    try:
        with Transport(ZenohOptions.loopback(connect=[ep])) as t:
            wait_for(lambda: t.alive("evcal/@service/*", timeout_s=1.0), timeout_s=60)

            def on_cal(key: str, payload: bytes, enc: str) -> None:
                import msgpack

                t_us = msgpack.unpackb(payload)["t_us"]
                if t_us in sent:
                    got.append(time.monotonic() - sent[t_us])

            t.subscribe(keys.camera_key("evcal", cam, "calibration"), on_cal)
            pub_ev = t.publisher(keys.camera_key("evcal", cam, "events"), keys.ENC_EVENTS,
                                 block=True)
            pub_fr = t.publisher(keys.camera_key("evcal", cam, "frames"), keys.ENC_FRAME,
                                 block=True)
            wait_for(lambda: pub_ev.has_subscribers, timeout_s=10)
            n_frames = int(seconds * 25)
            wall0 = time.monotonic()
            for k in range(n_frames):
                t_us = k * 40_000
                due = wall0 + t_us * 1e-6
                time.sleep(max(0.0, due - time.monotonic()))
                img = rng.integers(0, 255, sensor.shape).astype(np.uint8)
                sent[t_us] = time.monotonic()
                pub_fr.put(encode_frame(t_us, img, exposure_us=0, seq=k))
                ev = synthetic_chunk(rng, sensor, per_frame, t_us, 40_000)
                for j in range(0, per_frame, 20_000):  # 10 ms-ish chunks
                    pub_ev.put(encode_events(ev[j:j + 20_000], height=260, width=346,
                                             seq=k * 100 + j // 20_000))
            time.sleep(1.0)
            st = status(t, cam)
    finally:
        sp.stop()
    lat = np.array(got[3:]) * 1e3
    return {"frames": n_frames, "calibrations_back": len(got),
            "roundtrip_ms_median": float(np.median(lat)) if lat.size else None,
            "roundtrip_ms_p95": float(np.percentile(lat, 95)) if lat.size else None,
            "roundtrip_ms_max": float(lat.max()) if lat.size else None,
            "service_latency_ms": st.get("latency_ms")}


def memory(minutes: float) -> dict:
    sensor = SensorSize(260, 346)
    rng = np.random.default_rng(2)
    rate = 1_000_000
    per_frame = rate // 25
    sp, ep = start_service([])
    cam = "bench/memory"
    samples: list[tuple[float, float]] = []
    stop = threading.Event()
    proc = psutil.Process(sp.pid)
    try:
        with Transport(ZenohOptions.loopback(connect=[ep])) as t:
            wait_for(lambda: t.alive("evcal/@service/*", timeout_s=1.0), timeout_s=60)
            pub_ev = t.publisher(keys.camera_key("evcal", cam, "events"), keys.ENC_EVENTS,
                                 block=True)
            pub_fr = t.publisher(keys.camera_key("evcal", cam, "frames"), keys.ENC_FRAME,
                                 block=True)
            wait_for(lambda: pub_ev.has_subscribers, timeout_s=10)

            def sampler() -> None:
                t0 = time.monotonic()
                while not stop.wait(10.0):
                    samples.append((time.monotonic() - t0, proc.memory_info().rss / 2**20))
                    print(f"  t={samples[-1][0]:6.0f} s  service RSS {samples[-1][1]:7.1f} MiB",
                          file=sys.stderr, flush=True)

            th = threading.Thread(target=sampler, daemon=True)
            th.start()
            wall0 = time.monotonic()
            img = rng.integers(0, 255, sensor.shape).astype(np.uint8)
            ev = synthetic_chunk(rng, sensor, per_frame, 0, 40_000)
            k = 0
            while time.monotonic() - wall0 < minutes * 60:
                t_us = k * 40_000
                time.sleep(max(0.0, wall0 + t_us * 1e-6 - time.monotonic()))
                pub_fr.put(encode_frame(t_us, img, exposure_us=0, seq=k))
                chunk = ev.copy()
                chunk["t_us"] += t_us
                pub_ev.put(encode_events(chunk, height=260, width=346, seq=k))
                k += 1
            stop.set()
            st = status(t, cam)
    finally:
        stop.set()
        sp.stop()
    rss = np.array([s[1] for s in samples])
    half = len(rss) // 2
    return {"minutes": minutes, "frames": k, "updates": st.get("updates"),
            "rss_mb_first": float(rss[0]) if rss.size else None,
            "rss_mb_mid": float(rss[half]) if rss.size else None,
            "rss_mb_last": float(rss[-1]) if rss.size else None,
            "rss_mb_max": float(rss.max()) if rss.size else None}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("what", choices=["throughput", "latency", "memory", "all"])
    p.add_argument("--sizes", default="346x260,1280x720")
    p.add_argument("--events", type=float, default=20e6)
    p.add_argument("--seconds", type=float, default=20.0)
    p.add_argument("--minutes", type=float, default=10.0)
    args = p.parse_args(argv)
    if args.what in ("throughput", "all"):
        for size in args.sizes.split(","):
            for mode in THROUGHPUT_MODES:
                r = throughput(SensorSize.parse(size), int(args.events), mode=mode)
                print(f"throughput {r['sensor']:>9} {mode:<8} "
                      f"{r['events_per_s'] / 1e6:6.1f} M events/s end to end "
                      f"({r['events'] / 1e6:.0f} M events in {r['total_s']:.2f} s; published "
                      f"in {r['publish_s']:.2f} s; {r['updates']} updates; service RSS "
                      f"{r['service_rss_mb']:.0f} MiB)", flush=True)
    if args.what in ("latency", "all"):
        r = latency(args.seconds)
        sl = r["service_latency_ms"] or {}
        print(f"latency 346x260, 2 M ev/s, 25 Hz frames, default OnEI sizes: frame put -> "
              f"calibration "
              f"received median {r['roundtrip_ms_median']:.1f} ms, p95 "
              f"{r['roundtrip_ms_p95']:.1f} ms, max {r['roundtrip_ms_max']:.1f} ms "
              f"({r['calibrations_back']} of {r['frames']} frames); inside the service "
              f"(arrival -> published) mean {sl.get('mean', float('nan')):.1f} ms, p95 "
              f"{sl.get('p95', float('nan')):.1f} ms", flush=True)
    if args.what in ("memory", "all"):
        r = memory(args.minutes)
        print(f"memory 346x260, 1 M ev/s real time for {r['minutes']:g} min: service RSS "
              f"{r['rss_mb_first']:.1f} -> {r['rss_mb_mid']:.1f} -> {r['rss_mb_last']:.1f} MiB "
              f"(max {r['rss_mb_max']:.1f}); {r['updates']} updates", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
