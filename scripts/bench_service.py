"""Benchmarks of the live service (figures, not tests): throughput, latency, memory.

    python scripts/bench_service.py throughput [--sizes 346x260,1280x720] [--events 40e6]
    python scripts/bench_service.py latency [--rates 1e6,2e6,5e6] [--seconds 20] [--rrd]
                                            [--size 346x260]
    python scripts/bench_service.py scaling [--seconds 10] [--cameras 2] [--workers 1,2]
    python scripts/bench_service.py shm [--events 40e6]
    python scripts/bench_service.py ros2 [--events 40e6]
    python scripts/bench_service.py memory [--minutes 10]
    python scripts/bench_service.py stress [--minutes 10] [--cameras 4]
    python scripts/bench_service.py all

The service runs as its own process (``python -m evcal.service``) on ``tcp/127.0.0.1`` with
``--on-full block``; this process publishes like ``evcal replay`` does (encoding included, on
the same machine: publisher and service share its cores) and reads the service's status and
calibration outputs.

throughput  sustained events/s from the first put to the service's event counter, after a
            warm-up (camera creation, compiled kernels loaded) that is not timed; the stream
            is 20 M events/s of sensor time in 100 k-event messages, like
            ``evcal replay --max-rate``. Modes: "events" (no frames: decode, validate, OnEI's
            pending buffer), "frames" (25 Hz frames: the events are folded into OnEI's
            accumulators and interval counts, no re-solve: the acceptance figure),
            "updates" (OnEI's default sizes: small-buffer equations and a re-solve with a
            published calibration at every frame).
latency     a DAVIS346-like real-time stream: 346x260, 25 Hz frames, events at ``--rates``
            events/s in 10 ms packets sent when their last event has happened, OnEI's default
            sizes. Figure of the issue: the service's own latency from a frame's arrival
            (its message received by the service) to the calibration that frame triggered
            being published (``status.latency_ms``), median and p95 over the updates, with
            the median of each step (queue wait, OnEI fold + re-solve, calibration maps,
            encode, publish). Also the round trip seen by the client: frame put -> that
            calibration received back.
scaling     1, then 2 (``--cameras``) cameras streamed at once at full rate into
            ``serve --workers W`` for each W of ``--workers`` (each camera a
            ``evcal replay --max-rate --loop`` of a 346x260 simulated recording, its own
            process; camera ids chosen so that camera c is served by worker c mod W), for
            ``--seconds``: the aggregate events/s and updates/s from the status counters over
            the timed part, the ratio to one camera into one worker, and the cores used by
            the service (supervisor and workers), by the replays (which share the machine's
            cores) and by every other process.
shm         the "events" throughput with zenoh's shared-memory transport (on by default
            between local processes for messages above 3 KiB) and with it disabled
            (``transport/shared_memory/enabled: false`` on both sides), beside the zenoh
            loopback floor: the same messages put and received by two sessions of this
            process, nothing else done with them.
ros2        the ROS 2 path (``serve --ros2``) at 346x260: libcaer_cmp EventPackets (100 k
            events, CDR) and 25 Hz mono8 Images on rmw_zenoh keys, decoded in the camera's
            decoder thread and folded into OnEI (as "frames"), beside its floors measured in
            the same run: the decoder alone (CDR + libcaer_cmp + columns) and the zenoh
            loopback of the same messages.
memory      the service's RSS every 10 s while a 346x260 camera streams 1 M events/s and
            25 Hz frames in real time (re-solves every ~10 frames).
stress      ``--cameras`` real ``evcal replay --max-rate --loop`` processes (346x260 simulated
            recordings) into one default service (``--on-full drop``) for ``--minutes``,
            then SIGINT to the replays: the service must still run, each camera's counters
            must balance (messages sent = processed + dropped + rejected, from replay's own
            account of the run), and its RSS must stay flat. The acceptance run of issue 8.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import threading
import time

import numpy as np
import psutil

from evcal.events import EVENTS_DTYPE, SensorSize
from evcal.io.wire import encode_events, encode_frame
from evcal.service import keys
from evcal.service.transport import Transport, ZenohOptions
from evcal.testing import ServiceProcess, endpoint, free_port, wait_for

ZARGS = ["--no-multicast-scouting"]
FRAME_US = 40_000  # 25 Hz


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


SHM_OFF = ["--cfg", "transport/shared_memory/enabled:false"]


def start_service(extra: list[str]) -> tuple[ServiceProcess, str]:
    ep = endpoint(free_port())
    sp = ServiceProcess(["--listen", ep, *ZARGS, "--on-full", "block", "--status-period",
                         "0.25", "--max-pixels", str(1280 * 720), *extra]).start()
    return sp, ep


def cpu_seconds(procs: list[psutil.Process]) -> float:
    """User + system CPU seconds of ``procs`` so far (processes gone count 0)."""
    total = 0.0
    for p in procs:
        try:
            c = p.cpu_times()
            total += c.user + c.system
        except psutil.Error:
            pass
    return total


def minor_faults(pid: int) -> int:
    """Minor page faults of process ``pid`` so far, all its threads (Linux; else 0)."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            return int(f.read().rsplit(")", 1)[1].split()[7])
    except (OSError, IndexError, ValueError):
        return 0


def process_tree(pid: int) -> list[psutil.Process]:
    """``pid`` and its descendants (a service with ``--workers``: supervisor and workers)."""
    root = psutil.Process(pid)
    return [root, *root.children(recursive=True)]


class OtherLoad:
    """CPU used by other processes while a figure is measured (in cores), to flag runs that
    shared the machine: ``with OtherLoad(pid) as load: ...; load.cores``."""

    def __init__(self, *pids: int):
        self.procs = [psutil.Process(p) for p in (*pids, psutil.Process().pid)]
        self.cores = float("nan")

    @staticmethod
    def _busy() -> float:
        t = psutil.cpu_times()  # guest time is already counted in user
        return float(sum(t) - t.idle - sum(getattr(t, k, 0.0)
                                           for k in ("iowait", "guest", "guest_nice")))

    def _ours(self) -> float:
        return cpu_seconds(self.procs)

    def __enter__(self) -> OtherLoad:
        self._t0, self._busy0, self._ours0 = time.monotonic(), self._busy(), self._ours()
        return self

    def __exit__(self, *exc: object) -> None:
        wall = time.monotonic() - self._t0
        other = (self._busy() - self._busy0) - (self._ours() - self._ours0)
        self.cores = max(0.0, other) / wall if wall > 0 else float("nan")


class Stream:
    """One camera's publishers and sequence numbers (what ``evcal replay`` keeps)."""

    def __init__(self, t: Transport, camera: str, sensor: SensorSize):
        self.sensor = sensor
        self.pub_ev = t.publisher(keys.camera_key("evcal", camera, "events"), keys.ENC_EVENTS,
                                  block=True)
        self.pub_fr = t.publisher(keys.camera_key("evcal", camera, "frames"), keys.ENC_FRAME,
                                  block=True)
        self.seq_ev = self.seq_fr = 0
        wait_for(lambda: self.pub_ev.has_subscribers and self.pub_fr.has_subscribers,
                 timeout_s=10)

    def events(self, ev: np.ndarray) -> None:
        self.pub_ev.put(encode_events(ev, height=self.sensor.height, width=self.sensor.width,
                                      seq=self.seq_ev))
        self.seq_ev += 1

    def frame(self, t_us: int, image: np.ndarray) -> None:
        self.pub_fr.put(encode_frame(t_us, image, exposure_us=0, seq=self.seq_fr))
        self.seq_fr += 1


# ----------------------------------------------------------------------------- throughput

THROUGHPUT_MODES = {
    # name: (frames at 25 Hz of sensor time, service arguments)
    "events": (False, ["--n-small", "2000000000", "--n-large", "2000000000"]),
    "frames": (True, ["--n-small", "2000000000", "--n-large", "2000000000"]),
    # OnEI's default sizes (at 20 M ev/s an update every ~5 frames at 1280x720, every frame
    # at 346x260), the offset given: its online estimate on these random frames may take
    # the whole timed stream to settle
    "updates": (True, ["--log-offset", "30"]),
}


def throughput(sensor: SensorSize, n_events: int, *, mode: str, chunk: int = 100_000,
               warmup_events: int = 4_000_000, shm: bool = True) -> dict:
    rng = np.random.default_rng(0)
    rate_hz = 20e6  # sensor-time event rate of the synthetic stream
    span = int(chunk / rate_hz * 1e6)
    # a few distinct chunks, re-stamped in time (keeps this process's CPU for publishing)
    base = [synthetic_chunk(rng, sensor, chunk, 0, span) for _ in range(4)]
    imgs = [rng.integers(0, 255, sensor.shape).astype(np.uint8) for _ in range(8)]
    pick = np.random.default_rng(2)  # chunks drawn, not cycled (see latency's stream)
    frames, extra = THROUGHPUT_MODES[mode]
    frame_every = max(1, int(FRAME_US * rate_hz / 1e6 / chunk))  # 25 Hz of sensor time
    cam = f"bench/{sensor}"

    def sender(t: Transport):
        s = Stream(t, cam, sensor)

        def send(i0: int, i1: int) -> None:
            for i in range(i0, i1):
                ev = base[int(pick.integers(len(base)))].copy()
                ev["t_us"] += i * span
                if frames and i % frame_every == 0:
                    s.frame(int(ev["t_us"][0]), imgs[(i // frame_every) % len(imgs)])
                s.events(ev)
        return send

    r = timed_stream(extra, cam, sender, n_events=n_events, chunk=chunk,
                     warmup_events=warmup_events, shm=shm)
    return {"sensor": str(sensor), "mode": mode, **r}


def timed_stream(service_args: list[str], camera: str, sender, *, n_events: int, chunk: int,
                 warmup_events: int, shm: bool = True) -> dict:
    """Sustained events/s into a service started with ``service_args``: ``sender(t)`` returns
    ``send(i0, i1)``, which publishes messages ``i0..i1`` of ``chunk`` events each for
    ``camera``; a warm-up that is not timed (the camera's state allocated, compiled kernels
    loaded), then the time from the first timed put to the service's event counter."""
    sp, ep = start_service(service_args + ([] if shm else SHM_OFF))
    zopts = ZenohOptions.loopback(connect=[ep])
    if not shm:
        zopts = ZenohOptions(mode="peer", connect=(ep,), multicast_scouting=False,
                             extra=(("transport/shared_memory/enabled", "false"),))
    try:
        with Transport(zopts) as t:
            wait_for(lambda: t.alive("evcal/@service/*", timeout_s=1.0), timeout_s=60)
            send = sender(t)
            n_warm = warmup_events // chunk
            send(0, n_warm)
            wait_for(lambda: status(t, camera).get("events", 0) >= n_warm * chunk,
                     timeout_s=120, interval_s=0.05)
            n_msgs = n_events // chunk
            with OtherLoad(sp.pid) as load:
                t0 = time.monotonic()
                send(n_warm, n_warm + n_msgs)
                t_pub = time.monotonic() - t0
                total = (n_warm + n_msgs) * chunk
                wait_for(lambda: status(t, camera).get("events", 0) >= total, timeout_s=600,
                         interval_s=0.02)
                t_all = time.monotonic() - t0
            st = status(t, camera)
        rss = psutil.Process(sp.pid).memory_info().rss
    finally:
        sp.stop()
    timed = n_msgs * chunk
    return {"events": timed, "shm": shm, "publish_s": t_pub, "total_s": t_all,
            "events_per_s": timed / t_all, "updates": st.get("updates"),
            "errors": st.get("errors_total"), "service_rss_mb": rss / 2**20,
            "other_load_cores": load.cores}


# ----------------------------------------------------------------------------- latency


def latency(rate: float, seconds: float, *, chunk_ms: float = 10.0, rrd: str | None = None,
            warmup_s: float = 3.0, size: str = "346x260", settle_s: float = 0.0,
            service_args: list[str] | None = None, verbose: bool = False,
            publisher_nice: int = 0) -> dict:
    """A real-time stream at ``rate`` events/s, 25 Hz frames, OnEI's default sizes.

    ``publisher_nice``: every thread of this publisher (zenoh's included) at that niceness
    once the service runs, as a camera's publisher on another core or host would leave the
    service the machine (the service keeps the default).

    The client's round trips are split at ``settle_s`` of the measured camera's stream: the
    start-up (first log-offset estimate, equations formed from the whole buffer, the
    re-checks at 44 and 176 frames) and the steady state after it."""
    sensor = SensorSize.parse(size)
    rng = np.random.default_rng(1)
    chunk_us = int(chunk_ms * 1000)
    per_chunk = int(rate * chunk_us / 1e6)
    chunks_per_frame = FRAME_US // chunk_us
    # one second of distinct packets and eight frames, re-stamped (the publisher's CPU is
    # the machine's too)
    n_pool = max(8, min(1_000_000 // chunk_us, 4_000_000 // max(per_chunk, 1)))
    pool = [synthetic_chunk(rng, sensor, per_chunk, 0, chunk_us) for _ in range(n_pool)]
    images = [rng.integers(0, 255, sensor.shape).astype(np.uint8) for _ in range(8)]
    extra = (["--rrd", rrd] if rrd else []) + list(service_args or [])
    sp, ep = start_service(extra)
    cam = "bench/latency"
    sent: dict[int, float] = {}
    got: list[tuple[int, float]] = []  # (frame t_us, round trip s)
    faults_at: list[int] = []  # the service's page faults after settle_s and at the end
    try:
        with Transport(ZenohOptions.loopback(connect=[ep])) as t:
            wait_for(lambda: t.alive("evcal/@service/*", timeout_s=1.0), timeout_s=60)

            def on_cal(key: str, payload: bytes, enc: str) -> None:
                import msgpack

                t_rx = time.monotonic()  # received (decoding it is the client's own work)
                t_us = msgpack.unpackb(payload)["t_us"]
                if t_us in sent:
                    got.append((t_us, t_rx - sent.pop(t_us)))

            t.subscribe(keys.camera_key("evcal", cam, "calibration"), on_cal)

            def stream(s: Stream, duration_s: float, record: bool) -> int:
                pick = np.random.default_rng(2)
                n_frames = int(duration_s * 1e6 / FRAME_US)
                wall0 = time.monotonic()
                for k in range(n_frames):
                    t_f = k * FRAME_US
                    time.sleep(max(0.0, wall0 + t_f * 1e-6 - time.monotonic()))
                    if record:
                        sent[t_f] = time.monotonic()
                    s.frame(t_f, images[k % len(images)])
                    for j in range(chunks_per_frame):
                        t0 = t_f + j * chunk_us
                        # a packet leaves when its last event has happened
                        time.sleep(max(0.0, wall0 + (t0 + chunk_us) * 1e-6 - time.monotonic()))
                        # drawn, not cycled: a cycle of whole frames' worth of packets
                        # gives every window of OnEI's offset criterion the same events (a
                        # rank-deficient fit: at 20 M events/s, 5 frames per cycle, no
                        # offset estimate and no update ever)
                        ev = pool[int(pick.integers(len(pool)))].copy()
                        ev["t_us"] += t0
                        s.events(ev)
                return n_frames

            if publisher_nice:
                for tid in os.listdir("/proc/self/task"):
                    os.setpriority(os.PRIO_PROCESS, int(tid), publisher_nice)
            # warm-up on another camera: the service process loads its compiled kernels
            stream(Stream(t, "bench/warmup", sensor), warmup_s, record=False)
            svc = psutil.Process(sp.pid)
            me = psutil.Process()
            cpu0, mine0, wall0 = cpu_seconds([svc]), cpu_seconds([me]), time.monotonic()
            faults0 = minor_faults(sp.pid)
            with OtherLoad(sp.pid) as load:
                s = Stream(t, cam, sensor)
                # the page faults of the steady state (after settle_s of the stream)
                timer = threading.Timer(settle_s,
                                        lambda: faults_at.append(minor_faults(sp.pid)))
                timer.start()
                n_frames = stream(s, seconds, record=True)
            timer.cancel()  # a stream shorter than settle_s: no steady state to count
            timer.join()
            faults_at.append(minor_faults(sp.pid))
            wall = time.monotonic() - wall0
            service_cpu, client_cpu = cpu_seconds([svc]) - cpu0, cpu_seconds([me]) - mine0
            time.sleep(1.0)
            st = status(t, cam)
            info = t.get("evcal/cameras", timeout_s=2.0)
            recorder = json.loads(info[0].payload) if info and info[0].ok else {}
        rss = psutil.Process(sp.pid).memory_info().rss
    finally:
        sp.stop()
    t_sent = np.array([g[0] for g in got], np.int64)
    rt_all = np.array([g[1] for g in got]) * 1e3
    if verbose:
        print("  round trips (frame s: ms): " + ", ".join(
            f"{t / 1e6:.2f}: {r:.0f}" for t, r in zip(t_sent, rt_all, strict=True)), flush=True)
    rt = rt_all[t_sent >= settle_s * 1e6]  # the steady state
    start = rt_all[t_sent < settle_s * 1e6]
    return {"sensor": str(sensor), "rate": rate, "frames": n_frames,
            "updates": st.get("updates"), "settle_s": settle_s,
            "calibrations_back": len(got), "calibrations_steady": int(rt.size),
            "roundtrip_ms_median": float(np.median(rt)) if rt.size else float("nan"),
            "roundtrip_ms_p95": float(np.percentile(rt, 95)) if rt.size else float("nan"),
            "roundtrip_ms_p99": float(np.percentile(rt, 99)) if rt.size else float("nan"),
            "roundtrip_ms_max": float(rt.max()) if rt.size else float("nan"),
            "startup_ms_max": float(start.max()) if start.size else float("nan"),
            "service_latency_ms": st.get("latency_ms") or {},
            "errors": st.get("errors_total"), "dropped": st.get("dropped"),
            "recorder_dropped": recorder.get("recorder_dropped") if rrd else None,
            "service_rss_mb": rss / 2**20, "other_load_cores": load.cores,
            "steady_faults_per_update": ((faults_at[-1] - faults_at[0]) / max(rt.size, 1)
                                         if len(faults_at) == 2 and faults0 else None),
            "gc": recorder.get("gc"), "shm": recorder.get("shm"),
            "service_cores": service_cpu / max(wall, 1e-9),
            # the service's work per frame (its CPU time over the timed stream's frames,
            # every thread: what an option that adds work at each update costs per frame)
            "service_cpu_ms_per_frame": service_cpu * 1e3 / max(n_frames, 1),
            "client_cores": client_cpu / max(wall, 1e-9)}


# ----------------------------------------------------------------------------- scaling


def spread_camera_ids(n: int, workers: int, stem: str = "scale/cam") -> list[str]:
    """``n`` camera ids, camera ``c`` on worker ``c % workers`` of ``serve --workers``
    (ids are spread by a hash: without choosing them, 2 cameras share one of 2 workers half
    of the time)."""
    out = []
    for c in range(n):
        out.append(next(f"{stem}{c}" + (f"-{k}" if k else "") for k in range(1000)
                        if keys.shard_of(f"{stem}{c}" + (f"-{k}" if k else ""), workers)
                        == c % workers))
    return out


def scaling(seconds: float, max_cameras: int, workers: list[int], *, shm: bool = True
            ) -> list[dict]:
    """Aggregate service throughput with 1..max_cameras cameras at full rate into
    ``serve --workers W`` for each W of ``workers``; CPU in cores of the service (supervisor
    and workers), of the replays and of every other process. ``shm=False``: the replays'
    shared memory off, their payloads reach the service as a remote publisher's would."""
    import subprocess
    import tempfile
    from pathlib import Path

    from evcal.io import write_recording
    from evcal.sim.ideal import SimConfig, simulate_ideal
    from evcal.testing import python_env

    d = Path(tempfile.mkdtemp(prefix="evcal-scaling-"))
    sim = simulate_ideal(SimConfig(height=260, width=346, duration_s=4.0, seed=11))
    path = write_recording(sim.recording, d / "cam.npz")
    out = []
    for w in workers:
        for n in range(1, max_cameras + 1):
            sp, ep = start_service(["--workers", str(w)])
            reps: list[subprocess.Popen[str]] = []
            cams = spread_camera_ids(n, w)
            try:
                with Transport(ZenohOptions.loopback(connect=[ep])) as t:
                    wait_for(lambda w=w: len(t.alive("evcal/@service/*", timeout_s=1.0)) >= w,
                             timeout_s=60)
                    for cam in cams:
                        reps.append(subprocess.Popen(
                            [sys.executable, "-m", "evcal.clients.replay", str(path),
                             "--camera", cam, "--connect", ep, *ZARGS, "--max-rate", "--loop",
                             *([] if shm else SHM_OFF)],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                            env=python_env()))
                    time.sleep(5.0)  # warm-up: cameras created, kernels loaded

                    def counters(cams: list[str] = cams) -> list[tuple[int, int, int]]:
                        sts = [status(t, c) for c in cams]
                        return [(x.get("events", 0), x.get("updates", 0),
                                 x.get("event_messages", 0) + x.get("frames", 0)) for x in sts]

                    service = process_tree(sp.pid)
                    replays = [psutil.Process(r.pid) for r in reps]
                    with OtherLoad(*(p.pid for p in service + replays)) as load:
                        c0 = counters()
                        cpu0 = (cpu_seconds(service), cpu_seconds(replays),
                                *(cpu_seconds([p]) for p in service))
                        t0 = time.monotonic()
                        time.sleep(seconds)
                        c1 = counters()
                        cpu1 = (cpu_seconds(service), cpu_seconds(replays),
                                *(cpu_seconds([p]) for p in service))
                        dt = time.monotonic() - t0
            finally:
                for r in reps:
                    r.kill()
                    r.wait()
                sp.stop()
            per_camera = [(b[0] - a[0]) / dt for a, b in zip(c0, c1, strict=True)]
            out.append({"workers": w, "cameras": n, "events_per_s": sum(per_camera),
                        "per_camera_events_per_s": per_camera,
                        "updates_per_s": sum(b[1] - a[1] for a, b in zip(c0, c1, strict=True))
                        / dt,
                        "messages_per_s": sum(b[2] - a[2] for a, b in zip(c0, c1, strict=True))
                        / dt,
                        "service_cores": (cpu1[0] - cpu0[0]) / dt,
                        "replay_cores": (cpu1[1] - cpu0[1]) / dt,
                        # with workers: the supervisor alone (zenoh routing to the workers),
                        # then each worker (one without cameras only leaves others' samples)
                        "supervisor_cores": (cpu1[2] - cpu0[2]) / dt if w > 1 else None,
                        "worker_cores": [(b - a) / dt for a, b in zip(cpu0[3:], cpu1[3:],
                                                                      strict=True)]
                        if w > 1 else None,
                        "other_load_cores": load.cores})
    return out


# ----------------------------------------------------------------------------- ros2


def ros2(n_events: int, *, chunk: int = 100_000, warmup_events: int = 4_000_000) -> dict:
    """The ROS 2 path at 346x260 (``serve --ros2``): libcaer_cmp EventPackets of ``chunk``
    events and 25 Hz mono8 Images as CDR on rmw_zenoh keys with attachments, every event
    decoded in the camera's decoder thread and folded into OnEI (the "frames" mode: no
    re-solve); beside it, measured in this run on the same messages, the decoder alone
    (CDR + payload decoding + columns, one thread of this process) and the zenoh loopback."""
    from evcal.io.evencode import encode_libcaer_cmp
    from evcal.io.ros2msg import event_packet_cdr, image_cdr
    from evcal.io.rosbag import EVENT_PACKET, IMAGE
    from evcal.service import ros2 as r2

    sensor = SensorSize(260, 346)
    rng = np.random.default_rng(0)
    rate_hz = 20e6
    span = int(chunk / rate_hz * 1e6)
    t_base = 1_744_227_144_000_000  # µs: ROS time, as drivers stamp
    base = [synthetic_chunk(rng, sensor, chunk, 0, span) for _ in range(4)]
    payloads = [encode_libcaer_cmp(b) for b in base]  # times relative to time_base
    img = rng.integers(0, 255, sensor.shape).astype(np.uint8)
    frame_every = max(1, int(FRAME_US * rate_hz / 1e6 / chunk))

    def packet(i: int) -> bytes:
        t0 = t_base + i * span + int(base[i % 4]["t_us"][0])
        return event_packet_cdr(payloads[i % 4], encoding="libcaer_cmp", seq=i,
                                time_base_ns=t0 * 1000, t_ns=t0 * 1000, height=260,
                                width=346, frame_id="bench")

    def frame(i: int) -> bytes:
        return image_cdr(img, t_ns=(t_base + i * span) * 1000, frame_id="bench",
                         encoding="mono8")

    # the decoder alone, on the messages the service gets
    dec = r2.RosDecoder()
    msgs = [packet(i) for i in range(40)]
    for m in msgs[:4]:  # warm-up: the typestore is built, numpy's paths are hot
        dec.decode("events", r2.RosSample(m, EVENT_PACKET, "/bench/ros2/events"))
    t0 = time.perf_counter()
    for m in msgs:
        dec.decode("events", r2.RosSample(m, EVENT_PACKET, "/bench/ros2/events"))
    decoder_eps = len(msgs) * chunk / (time.perf_counter() - t0)
    floor_eps = zenoh_loopback_floor(n_events, chunk, payload=msgs[0])
    node = r2.RosNode(zid="bench", name="bench_driver")

    def sender(t: Transport):
        ev_pub = r2.RosPublication(node, "/bench/ros2/events", EVENT_PACKET)
        fr_pub = r2.RosPublication(node, "/bench/ros2/image_raw", IMAGE)
        zev = t.publisher(ev_pub.key, r2.ENCODING, block=True)
        zfr = t.publisher(fr_pub.key, r2.ENCODING, block=True)
        wait_for(lambda: zev.has_subscribers and zfr.has_subscribers, timeout_s=10)

        def send(i0: int, i1: int) -> None:
            for i in range(i0, i1):
                if i % frame_every == 0:
                    zfr.put(frame(i), attachment=fr_pub.attachment())
                zev.put(packet(i), attachment=ev_pub.attachment())
        return send

    r = timed_stream(["--ros2", *THROUGHPUT_MODES["frames"][1]], "bench/ros2", sender,
                     n_events=n_events, chunk=chunk, warmup_events=warmup_events)
    return {**r, "decoder_events_per_s": decoder_eps, "zenoh_floor_events_per_s": floor_eps,
            "bytes_per_event": len(msgs[0]) / chunk}


# ----------------------------------------------------------------------------- shm


def zenoh_loopback_floor(n_events: int, chunk: int = 100_000, shm: bool = True,
                         payload: bytes | None = None) -> float:
    """Events/s of the same messages (``payload``, else an evcal events message of ``chunk``
    events) put by one session and received by another of this process (the transport
    alone: nothing decoded)."""
    rng = np.random.default_rng(0)
    if payload is None:
        payload = encode_events(synthetic_chunk(rng, SensorSize(260, 346), chunk, 0, 5000),
                                height=260, width=346, seq=0)
    n_msgs = max(1, n_events // chunk)
    ep = endpoint(free_port())
    extra = () if shm else (("transport/shared_memory/enabled", "false"),)
    got = threading.Semaphore(0)
    with Transport(ZenohOptions(mode="peer", listen=(ep,), multicast_scouting=False,
                                extra=extra)) as rx, \
            Transport(ZenohOptions(mode="peer", connect=(ep,), multicast_scouting=False,
                                   extra=extra)) as tx:
        rx.subscribe("bench/floor", lambda key, data, enc: got.release())
        pub = tx.publisher("bench/floor", keys.ENC_EVENTS, block=True)
        wait_for(lambda: pub.has_subscribers, timeout_s=10)
        for _ in range(20):  # warm-up
            pub.put(payload)
        for _ in range(20):
            got.acquire(timeout=10)
        t0 = time.monotonic()
        for _ in range(n_msgs):
            pub.put(payload)
        for _ in range(n_msgs):
            if not got.acquire(timeout=60):
                break
        dt = time.monotonic() - t0
    return n_msgs * chunk / dt


def publication(nbytes: int, n_msgs: int = 30, *, shm_pool_mb: float) -> dict:
    """One large calibration-sized payload at a time (a 1280x720 camera's message is 16 MB)
    put with :meth:`Transport.put` (the service's path) and received by another session of
    this process over TCP loopback: the put's duration and put-to-callback latency (the
    callback gets the payload as bytes, as the service's subscribers do). ``shm_pool_mb`` 0
    sends ordinary bytes (zenoh still copies them into its shared memory in its pipeline)."""
    payload = np.random.default_rng(0).integers(0, 255, nbytes, np.uint8).tobytes()
    ep = endpoint(free_port())
    got: dict[int, float] = {}
    arrived = threading.Semaphore(0)

    def on_msg(key: str, data: bytes, enc: str) -> None:
        got[int.from_bytes(data[:4], "little")] = time.perf_counter()
        arrived.release()

    put_ms, latency_ms = [], []
    with Transport(ZenohOptions(mode="peer", listen=(ep,), multicast_scouting=False)) as rx, \
            Transport(ZenohOptions(mode="peer", connect=(ep,), multicast_scouting=False),
                      shm_pool_mb=shm_pool_mb) as tx:
        rx.subscribe("bench/publication", on_msg)
        time.sleep(1.0)
        for i in range(n_msgs + 5):  # 5 warm-up messages
            msg = i.to_bytes(4, "little") + payload[4:]
            t0 = time.perf_counter()
            tx.put("bench/publication", msg, keys.ENC_CALIBRATION, block=True)
            t1 = time.perf_counter()
            arrived.acquire(timeout=10)
            if i >= 5:
                put_ms.append((t1 - t0) * 1e3)
                latency_ms.append((got.get(i, math.nan) - t0) * 1e3)
            time.sleep(0.04)  # one frame interval at 25 Hz
        stats = tx.shm.stats()
    return {"put_ms_median": float(np.median(put_ms)),
            "latency_ms_median": float(np.nanmedian(latency_ms)),
            "latency_ms_p90": float(np.nanpercentile(latency_ms, 90)),
            "lost": int(np.isnan(latency_ms).sum()), "shm": stats}


# ----------------------------------------------------------------------------- memory


def memory(minutes: float) -> dict:
    sensor = SensorSize(260, 346)
    rng = np.random.default_rng(2)
    rate = 1_000_000
    per_frame = rate * FRAME_US // 1_000_000
    sp, ep = start_service([])
    cam = "bench/memory"
    samples: list[tuple[float, float]] = []
    stop = threading.Event()
    proc = psutil.Process(sp.pid)
    try:
        with Transport(ZenohOptions.loopback(connect=[ep])) as t:
            wait_for(lambda: t.alive("evcal/@service/*", timeout_s=1.0), timeout_s=60)
            s = Stream(t, cam, sensor)

            def sampler() -> None:
                t0 = time.monotonic()
                while not stop.wait(10.0):
                    samples.append((time.monotonic() - t0, proc.memory_info().rss / 2**20))
                    print(f"  t={samples[-1][0]:6.0f} s  service RSS {samples[-1][1]:7.1f} MiB",
                          file=sys.stderr, flush=True)

            th = threading.Thread(target=sampler, daemon=True)
            th.start()
            wall0 = time.monotonic()
            imgs = [rng.integers(0, 255, sensor.shape).astype(np.uint8) for _ in range(4)]
            evs = [synthetic_chunk(rng, sensor, per_frame, 0, FRAME_US) for _ in range(4)]
            k = 0
            while time.monotonic() - wall0 < minutes * 60:
                t_us = k * FRAME_US
                time.sleep(max(0.0, wall0 + t_us * 1e-6 - time.monotonic()))
                s.frame(t_us, imgs[k % 4])
                chunk = evs[k % 4].copy()
                chunk["t_us"] += t_us
                s.events(chunk)
                k += 1
            stop.set()
            st = status(t, cam)
    finally:
        stop.set()
        sp.stop()
    rss = np.array([x[1] for x in samples])
    half = len(rss) // 2
    return {"minutes": minutes, "frames": k, "updates": st.get("updates"),
            "errors": st.get("errors_total"),
            "rss_mb_first": float(rss[0]) if rss.size else float("nan"),
            "rss_mb_mid": float(rss[half]) if rss.size else float("nan"),
            "rss_mb_last": float(rss[-1]) if rss.size else float("nan"),
            "rss_mb_max": float(rss.max()) if rss.size else float("nan"),
            "rss_mb_growth_2nd_half": (float(rss[-1] - rss[half]) if rss.size
                                       else float("nan"))}


def stress(minutes: float, n_cameras: int) -> dict:
    import re
    import signal
    import subprocess
    import tempfile
    from pathlib import Path

    from evcal.io import write_recording
    from evcal.sim.ideal import SimConfig, simulate_ideal
    from evcal.testing import python_env

    d = Path(tempfile.mkdtemp(prefix="evcal-stress-"))
    sim = simulate_ideal(SimConfig(height=260, width=346, duration_s=4.0, seed=11))
    path = write_recording(sim.recording, d / "cam.npz")
    ep = endpoint(free_port())
    sp = ServiceProcess(["--listen", ep, *ZARGS, "--status-period", "1", "--state-dir",
                         str(d / "state"), "--max-pixels", str(1280 * 720)],
                        log_path=d / "service.log").start()
    proc = psutil.Process(sp.pid)
    rss: list[float] = []
    reps: list[subprocess.Popen[str]] = []
    try:
        with Transport(ZenohOptions.loopback(connect=[ep])) as t:
            wait_for(lambda: t.alive("evcal/@service/*", timeout_s=1.0), timeout_s=60)
            for c in range(n_cameras):
                reps.append(subprocess.Popen(
                    [sys.executable, "-m", "evcal.clients.replay", str(path), "--camera",
                     f"stress/cam{c}", "--connect", ep, *ZARGS, "--max-rate", "--loop"],
                    stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                    env=python_env()))
            t0 = time.monotonic()
            while time.monotonic() - t0 < minutes * 60:
                time.sleep(10.0)
                rss.append(proc.memory_info().rss / 2**20)
                alive = sp.alive()
                print(f"  t={time.monotonic() - t0:6.0f} s  service "
                      f"{'running' if alive else 'EXITED'}, RSS {rss[-1]:7.1f} MiB",
                      file=sys.stderr, flush=True)
                if not alive:
                    break
            for r in reps:
                r.send_signal(signal.SIGINT)
            outs = [r.communicate(timeout=120)[1] for r in reps]
            # the service may still be working through its queues: wait until every camera's
            # queue is empty and its counters stop moving
            last: list[dict] = []
            for _ in range(120):
                now = [status(t, f"stress/cam{c}") for c in range(n_cameras)]
                if now == last and all(st.get("queue_messages", 0) == 0 for st in now):
                    break
                last = now
                time.sleep(1.0)
            per_cam = []
            for c, err in enumerate(outs):
                m = re.search(r"sent (\d+) events in (\d+) messages and (\d+) frames", err)
                st = status(t, f"stress/cam{c}")
                sent = int(m.group(2)) + int(m.group(3)) if m else -1
                got = (st.get("event_messages", 0) + st.get("frames", 0)
                       + sum(st.get("dropped_messages", {}).values())
                       + st.get("errors_total", 0))
                per_cam.append({"camera": f"stress/cam{c}", "sent_messages": sent,
                                "processed": st.get("event_messages", 0) + st.get("frames", 0),
                                "dropped": sum(st.get("dropped_messages", {}).values()),
                                "rejected": st.get("errors_total", 0),
                                "accounted": got, "restarts": st.get("restarts"),
                                "updates": st.get("updates")})
            alive = sp.alive()
    finally:
        for r in reps:
            if r.poll() is None:
                r.kill()
        code = sp.stop() if sp.alive() else sp.proc.returncode  # type: ignore[union-attr]
    half = len(rss) // 2
    return {"minutes": minutes, "cameras": n_cameras, "service_alive": alive,
            "service_exit": code, "per_camera": per_cam,
            "rss_mb_first": rss[0] if rss else float("nan"),
            "rss_mb_last": rss[-1] if rss else float("nan"),
            "rss_mb_growth_2nd_half": rss[-1] - rss[half] if rss else float("nan"),
            "log": str(d / "service.log")}


# ----------------------------------------------------------------------------- main


def print_latency(r: dict) -> None:
    sl = r["service_latency_ms"]
    parts = sl.get("parts_median") or {}
    slow = sl.get("slowest")
    nan = float("nan")
    print(f"latency {r['sensor']}, {r['rate'] / 1e6:g} M ev/s, 25 Hz frames, default OnEI "
          "sizes, "
          f"{r['updates']} updates in {r['frames']} frames:\n"
          f"  frame arrival -> calibration published (service): median "
          f"{sl.get('median') or nan:.1f} ms, p95 {sl.get('p95') or nan:.1f} ms, p99 "
          f"{sl.get('p99') or nan:.1f} ms, max "
          f"{sl.get('max') or nan:.1f} ms\n"
          f"    median steps: " + ", ".join(f"{k} {v:.1f}" for k, v in parts.items()) + " ms\n"
          + (f"    slowest of the last 200: frame at {slow['t_us'] / 1e6:.2f} s, "
             f"{slow['total']:.1f} ms: " + ", ".join(f"{k} {v:.1f}"
                                                    for k, v in slow["parts"].items())
             + " ms\n" if slow else "")
          + "  frame put -> calibration received (client round trip"
          + (f", after the first {r['settle_s']:g} s" if r["settle_s"] else "") + "): median "
          f"{r['roundtrip_ms_median']:.1f} ms, p95 {r['roundtrip_ms_p95']:.1f} ms, p99 "
          f"{r['roundtrip_ms_p99']:.1f} ms, max {r['roundtrip_ms_max']:.1f} ms "
          f"({r['calibrations_steady']} of {r['calibrations_back']} calibrations back)"
          + (f"; start-up max {r['startup_ms_max']:.1f} ms" if r["settle_s"] else "")
          + f"; errors {r['errors']}, dropped "
          f"{r['dropped']}, service RSS {r['service_rss_mb']:.0f} MiB"
          + (f"; recording, recorder dropped {r['recorder_dropped']} calls"
             if r["recorder_dropped"] is not None else "")
          + (f"; service page faults per update after start-up "
             f"{r['steady_faults_per_update']:.0f}"
             if r.get("steady_faults_per_update") is not None else "")
          + f"; cores used by the service {r['service_cores']:.2f} (CPU "
          f"{r['service_cpu_ms_per_frame']:.2f} ms a frame), by this publisher "
          f"{r['client_cores']:.2f}, by other processes {r['other_load_cores']:.2f}"
          + (f"; garbage collector: max pause {r['gc'].get('max_pause_ms', nan):.1f} ms"
             if isinstance(r.get("gc"), dict) else "")
          + (f"; shared memory: {r['shm'].get('puts')} puts, {r['shm'].get('fallbacks')} "
             "as bytes" if isinstance(r.get("shm"), dict) else ""), flush=True)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=(__doc__ or "").split("\n")[0])
    p.add_argument("what", choices=["throughput", "latency", "memory", "stress", "scaling",
                                    "shm", "ros2", "all"])
    p.add_argument("--size", default="346x260", help="latency: sensor size WxH")
    p.add_argument("--cameras", type=int, default=4,
                   help="stress: replays at once; scaling: 1 .. this many cameras (give 2)")
    p.add_argument("--workers", default="1,2",
                   help="scaling: the service's --workers values, comma-separated")
    p.add_argument("--no-shm", action="store_true",
                   help="scaling: replays without zenoh's shared memory (as remote cameras)")
    p.add_argument("--sizes", default="346x260,1280x720", help="throughput: sensor sizes")
    p.add_argument("--modes", default=",".join(THROUGHPUT_MODES),
                   help="throughput: modes (events, frames, updates)")
    p.add_argument("--events", type=float, default=40e6, help="throughput: timed events")
    p.add_argument("--rates", default="1e6,2e6,5e6", help="latency: events/s, comma-separated")
    p.add_argument("--seconds", type=float, default=20.0, help="latency: stream length")
    p.add_argument("--settle-s", type=float, default=0.0,
                   help="latency: the client's figures after this start-up of the stream")
    p.add_argument("--rrd", metavar="PATH", help="latency: the service also records to PATH")
    p.add_argument("--service-args", default="",
                   help="latency: extra `evcal serve` options, e.g. '--history 0'")
    p.add_argument("--publisher-nice", type=int, default=0,
                   help="latency: run the publisher at this niceness once the service is up "
                        "(as a camera's publisher elsewhere would leave the service the "
                        "cores)")
    p.add_argument("--verbose", action="store_true",
                   help="latency: print every round trip with its frame's time")
    p.add_argument("--minutes", type=float, default=10.0, help="memory: stream length")
    args = p.parse_args(argv)
    if args.what in ("throughput", "all"):
        for size in args.sizes.split(","):
            for mode in args.modes.split(","):
                r = throughput(SensorSize.parse(size), int(args.events), mode=mode)
                print(f"throughput {r['sensor']:>9} {mode:<8} "
                      f"{r['events_per_s'] / 1e6:6.1f} M events/s sustained "
                      f"({r['events'] / 1e6:.0f} M events in {r['total_s']:.2f} s after the "
                      f"warm-up; published in {r['publish_s']:.2f} s; {r['updates']} updates; "
                      f"{r['errors']} errors; service RSS {r['service_rss_mb']:.0f} MiB; "
                      f"other processes used {r['other_load_cores']:.2f} cores)", flush=True)
    if args.what in ("latency", "all"):
        for rate in args.rates.split(","):
            print_latency(latency(float(rate), args.seconds, rrd=args.rrd, size=args.size,
                                  settle_s=args.settle_s,
                                  service_args=args.service_args.split(),
                                  verbose=args.verbose, publisher_nice=args.publisher_nice))
    if args.what in ("scaling", "all"):
        rows = scaling(args.seconds, args.cameras if args.what == "scaling" else 2,
                       [int(w) for w in args.workers.split(",")], shm=not args.no_shm)
        one = rows[0]["events_per_s"] or float("nan")
        how = ", replays without shared memory" if args.no_shm else ""
        for r in rows:
            print(f"scaling --workers {r['workers']}, {r['cameras']} camera(s) at full rate "
                  f"(346x260, default OnEI{how}): "
                  f"{r['events_per_s'] / 1e6:.1f} M events/s in all "
                  f"({r['events_per_s'] / one:.2f}x one camera into one worker; per camera "
                  + ", ".join(f"{e / 1e6:.1f}" for e in r["per_camera_events_per_s"])
                  + f"), {r['messages_per_s']:.0f} messages/s, {r['updates_per_s']:.1f} "
                  f"updates/s; cores used: service "
                  f"{r['service_cores']:.2f}"
                  + (f" (supervisor {r['supervisor_cores']:.2f}, workers "
                     + ", ".join(f"{c:.2f}" for c in r["worker_cores"]) + ")"
                     if r["supervisor_cores"] is not None else "")
                  + f", replays {r['replay_cores']:.2f}, other "
                  f"processes {r['other_load_cores']:.2f}", flush=True)
    if args.what in ("shm", "all"):
        for pool_mb in (64.0, 0.0):
            r = publication(16 << 20, shm_pool_mb=pool_mb)
            how = ("written into a zenoh shared-memory pool first" if pool_mb
                   else "as bytes (zenoh's own shared-memory copy in its pipeline)")
            print(f"shm publication of a 16 MiB calibration message (1280x720), {how}: put "
                  f"{r['put_ms_median']:.1f} ms, put to subscriber callback median "
                  f"{r['latency_ms_median']:.1f} ms, p90 {r['latency_ms_p90']:.1f} ms "
                  f"({r['lost']} lost; pool {r['shm']})", flush=True)
        for shm in (True, False):
            floor = zenoh_loopback_floor(int(args.events), shm=shm)
            r = throughput(SensorSize(260, 346), int(args.events), mode="events", shm=shm)
            print(f"shm {'on ' if shm else 'off'}: service {r['events_per_s'] / 1e6:.1f} M "
                  f"events/s (events mode, 346x260); zenoh loopback floor "
                  f"{floor / 1e6:.1f} M events/s; ratio {r['events_per_s'] / floor:.2f}; "
                  f"other processes used {r['other_load_cores']:.2f} cores", flush=True)
    if args.what in ("ros2", "all"):
        r = ros2(int(args.events))
        print(f"ros2 346x260 frames: {r['events_per_s'] / 1e6:.1f} M events/s decoded and "
              f"folded (libcaer_cmp EventPackets of 100 k events, {r['bytes_per_event']:.2f} "
              f"bytes/event, + 25 Hz mono8 Images, over rmw_zenoh keys; {r['events'] / 1e6:.0f}"
              f" M events in {r['total_s']:.2f} s; {r['errors']} errors); floors in this run: "
              f"decoder alone {r['decoder_events_per_s'] / 1e6:.1f} M events/s (one thread), "
              f"zenoh loopback of the same messages {r['zenoh_floor_events_per_s'] / 1e6:.1f} "
              f"M events/s; other processes used {r['other_load_cores']:.2f} cores",
              flush=True)
    if args.what in ("memory", "all"):
        r = memory(args.minutes)
        print(f"memory 346x260, 1 M ev/s and 25 Hz in real time for {r['minutes']:g} min: "
              f"service RSS {r['rss_mb_first']:.1f} -> {r['rss_mb_mid']:.1f} -> "
              f"{r['rss_mb_last']:.1f} MiB (max {r['rss_mb_max']:.1f}; second half "
              f"{r['rss_mb_growth_2nd_half']:+.1f} MiB); {r['updates']} updates, "
              f"{r['errors']} errors", flush=True)
    if args.what == "stress":
        r = stress(args.minutes, args.cameras)
        print(f"stress: {r['cameras']} cameras at --max-rate --loop for {r['minutes']:g} min "
              f"into a --on-full drop service: service "
              f"{'alive' if r['service_alive'] else 'DEAD'}, exit {r['service_exit']}; RSS "
              f"{r['rss_mb_first']:.0f} -> {r['rss_mb_last']:.0f} MiB (second half "
              f"{r['rss_mb_growth_2nd_half']:+.1f} MiB)", flush=True)
        for c in r["per_camera"]:
            ok = "balanced" if c["sent_messages"] == c["accounted"] else "NOT BALANCED"
            print(f"  {c['camera']}: sent {c['sent_messages']} = processed {c['processed']} + "
                  f"dropped {c['dropped']} + rejected {c['rejected']} ({ok}); "
                  f"{c['updates']} updates, restarts {c['restarts']}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
