"""Probe (figures, not a test): does ``evcal serve --workers 2`` survive its workers' deaths
under full load, again and again?

    python scripts/probe_worker_kills.py [--kills 10] [--replays 4] [--seed 1]
                                         [--gap-s 4,12] [--recording PATH]
                                         [--serve-arg=--cfg=KEY:VALUE ...] [--log-dir DIR]

Runs ``evcal serve --workers 2`` on a free ``tcp/127.0.0.1`` port (multicast scouting off,
``--on-full block``, a state directory), then ``--replays`` processes of
``evcal replay --max-rate --loop`` (a simulated 346x260 recording of 3 s, ``--sim-sensor``,
``--sim-seconds``, unless ``--recording`` names one), cameras chosen so that each worker
serves half of them. Then ``--kills`` times, at a random moment (``--gap-s`` seconds apart,
uniform), SIGKILL to a worker drawn at random, and after each kill:

- ``restart_s``: from the kill until the supervisor reports the worker running again
  (``worker_restarts`` counted, a new pid) and its liveliness token is back;
- ``answer_s``: from the restart until a *new* client (its own process and zenoh session,
  as an operator's ``evcal query`` would be) gets every camera's status -- within
  ``--answer-timeout-s`` (10 s) or the kill fails;
- ``flow_s``: from the restart until every camera's event counter grew (the replays'
  data flows through the router to both workers again) -- within the same bound;
- with ``--calibrations``: the new client also gets every camera's calibration (a
  346x260 map set is 2.4 MB), and for ``--stay-s`` seconds after the flow every camera's
  calibration is queried again every 0.5 s, each answered within 5 s (``stay``).

At the end SIGTERM to the supervisor (with the replays still running, unless
``--stop-replays-first``), which must exit with code 0 within ``--stop-timeout-s`` (5 s).
On a failed check the probe dumps every thread of the supervisor with gdb (when there is
one) into the log directory, watches up to ``--watch-s`` whether the service answers again
(a stall that passes, or stuck for good), stops there and exits 1; 0 when every kill and
the stop passed. The load averages
seen at the start and the end are printed with the table: the machine may be shared.

``--serve-arg`` passes an option on to ``evcal serve`` (repeatable), e.g. to compare
zenoh settings of the supervisor and its workers.
"""

from __future__ import annotations

import argparse
import json
import os
import random
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from evcal.service import keys
from evcal.service.transport import Transport, ZenohOptions
from evcal.testing import ServiceProcess, endpoint, free_port, python_env

ZARGS = ["--no-multicast-scouting"]
INSTANCE = "probe"


@dataclass
class Kill:
    """What one kill cost; ``None`` for a step not reached."""

    index: int
    at_s: float  # since the replays started
    victim: str
    restart_s: float | None = None
    answer_s: float | None = None
    flow_s: float | None = None
    stay_queries: int | None = None  # calibration queries answered while staying
    failure: str | None = None


# ----------------------------------------------------------------------------- a new client


def ask(connect: str, cameras: list[str], timeout_s: float, calibrations: bool = False) -> int:
    """The child process of :func:`fresh_client_status`: open a session, ask every camera's
    status (and calibration), print ``{camera: events}`` as JSON; 0 when every camera
    answered (both)."""
    out: dict[str, int] = {}
    with Transport(ZenohOptions.loopback(connect=[connect])) as t:
        for cam in cameras:
            for r in t.get(keys.camera_key("evcal", cam, "status"), timeout_s=timeout_s):
                if r.ok:
                    out[cam] = int(json.loads(r.payload)["events"])
            if calibrations and not calibration_answered(t, cam, timeout_s):
                out.pop(cam, None)
    print(json.dumps(out), flush=True)
    return 0 if len(out) == len(cameras) else 1


def calibration_answered(t: Transport, cam: str, timeout_s: float) -> bool:
    return any(r.ok and len(r.payload) > 0
               for r in t.get(keys.camera_key("evcal", cam, "calibration"), timeout_s=timeout_s))


def fresh_client_status(ep: str, cameras: list[str], timeout_s: float,
                        calibrations: bool = False) -> dict[str, int] | None:
    """Every camera's event counter seen by a new client process within ``timeout_s``
    (killed after that: a deadlocked router also blocks a session's opening), or None.
    ``calibrations``: every camera's calibration must be answered too."""
    cmd = [sys.executable, __file__, "ask", ep, *cameras, "--timeout", str(timeout_s / 2),
           *(["--calibrations"] if calibrations else [])]
    try:
        res = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout_s,
                             env=python_env())
    except subprocess.TimeoutExpired:
        return None
    if res.returncode != 0:
        return None
    try:
        return {k: int(v) for k, v in json.loads(res.stdout.strip().splitlines()[-1]).items()}
    except (ValueError, IndexError):
        return None


# ----------------------------------------------------------------------------- the probe


def spread_cameras(n: int, workers: int) -> list[str]:
    """``n`` camera ids, camera ``c`` served by worker ``c % workers``."""
    out = []
    for c in range(n):
        out.append(next(f"probe/cam{c}-{k}" for k in range(1000)
                        if keys.shard_of(f"probe/cam{c}-{k}", workers) == c % workers))
    return out


def supervisor_doc(t: Transport) -> dict[str, Any] | None:
    for r in t.get("evcal/cameras", timeout_s=2.0):
        if r.ok:
            doc = json.loads(r.payload)
            if doc.get("supervisor"):
                return dict(doc)
    return None


def events(t: Transport, cameras: list[str], timeout_s: float = 2.0) -> dict[str, int]:
    out = {}
    for cam in cameras:
        for r in t.get(keys.camera_key("evcal", cam, "status"), timeout_s=timeout_s):
            if r.ok:
                out[cam] = int(json.loads(r.payload)["events"])
    return out


def poll(fn: Any, timeout_s: float, interval_s: float = 0.2) -> float | None:
    """Seconds until ``fn()`` was true, or None after ``timeout_s``."""
    t0 = time.monotonic()
    while time.monotonic() - t0 <= timeout_s:
        try:
            if fn():
                return time.monotonic() - t0
        except Exception:  # a reply that did not parse: keep polling
            pass
        time.sleep(interval_s)
    return None


def flowing(t: Transport, cameras: list[str], since: dict[str, int], timeout_s: float
            ) -> float | None:
    """Seconds until every camera's event counter exceeds ``since``, or None."""
    return poll(lambda: (now := events(t, cameras)).keys() == set(cameras)
                and all(now[c] > since.get(c, -1) for c in cameras), timeout_s)


def dump_threads(pid: int, path: Path) -> str:
    """Every thread's stack of process ``pid`` (gdb), written to ``path``; a short note."""
    gdb = shutil.which("gdb")
    if gdb is None:
        return "no gdb here for a thread dump"
    try:
        res = subprocess.run([gdb, "-p", str(pid), "-batch", "-ex", "thread apply all bt"],
                             capture_output=True, text=True, timeout=120)
    except subprocess.TimeoutExpired:
        return "gdb timed out"
    path.write_text(res.stdout + res.stderr)
    return f"threads of pid {pid} in {path}"


def probe(args: argparse.Namespace, log_dir: Path) -> tuple[list[Kill], dict[str, Any]]:
    rng = random.Random(args.seed)
    cams = spread_cameras(args.replays, 2)
    rec = args.recording or str(_simulated(args, log_dir))
    ep = endpoint(free_port())
    serve = ["--workers", "2", "--instance", INSTANCE, "--listen", ep, *ZARGS,
             "--on-full", "block", "--state-dir", str(log_dir / "state"),
             "--snapshot-period", "2", "--status-period", "0.5", *args.serve_arg]
    kills: list[Kill] = []
    end: dict[str, Any] = {"load_start": os.getloadavg(), "watch_s": args.watch_s}
    replays: list[subprocess.Popen[bytes]] = []
    sp = ServiceProcess(serve, log_path=log_dir / "serve.log").start()
    t = Transport(ZenohOptions.loopback(connect=[ep]))
    try:
        t.open()
        if poll(lambda: len(t.alive(f"evcal/@service/{INSTANCE}-w$*", timeout_s=1.0)) == 2,
                90) is None:
            raise RuntimeError(f"the workers did not start; see {log_dir / 'serve.log'}")
        with open(log_dir / "replays.log", "ab") as rlog:
            replays = [subprocess.Popen(
                [sys.executable, "-m", "evcal.clients.replay", rec, "--camera", cam,
                 "--connect", ep, *ZARGS, "--max-rate", "--loop"],
                stdout=rlog, stderr=rlog, env=python_env()) for cam in cams]
        t0 = time.monotonic()
        if flowing(t, cams, {}, 60) is None:
            raise RuntimeError("the replays' events did not reach every camera in 60 s")
        for i in range(args.kills):
            time.sleep(rng.uniform(*args.gap_s))
            k = _kill_once(t, ep, cams, i, t0, rng, args.answer_timeout_s,
                           calibrations=args.calibrations, stay_s=args.stay_s)
            kills.append(k)
            print(_row(k), flush=True)
            if k.failure is not None:
                end["dump"] = dump_threads(sp.pid, log_dir / f"threads-kill{i}.txt")
                end["recovered_s"] = _watch(ep, cams, args.watch_s)
                if end["recovered_s"] is None:  # the same threads still stuck?
                    dump_threads(sp.pid, log_dir / f"threads-kill{i}-later.txt")
                break
        end["load_end"] = os.getloadavg()
        if args.stop_replays_first:
            for r in replays:
                r.kill()
                r.wait()
            time.sleep(1.0)  # what the router still held has reached the workers
        t_stop = time.monotonic()
        sp.proc.send_signal(signal.SIGTERM)
        try:
            end["exit_code"] = sp.proc.wait(args.stop_timeout_s)
            end["stop_s"] = time.monotonic() - t_stop
        except subprocess.TimeoutExpired:
            end["exit_code"] = None
            end["dump"] = dump_threads(sp.pid, log_dir / "threads-stop.txt")
            try:  # what it does in the end (gdb held it for a while)
                end["late_exit"] = (sp.proc.wait(60), time.monotonic() - t_stop)
            except subprocess.TimeoutExpired:
                end["late_exit"] = None
    finally:
        for r in replays:
            r.kill()
            r.wait()
        sp.__exit__(None, None, None)
        # the observer's own session may sit behind a deadlocked router: its close is
        # bounded (the process's exit ends it otherwise)
        t.close(timeout_s=3.0)
    return kills, end


def _kill_once(t: Transport, ep: str, cams: list[str], i: int, t0: float,
               rng: random.Random, answer_timeout_s: float, *, calibrations: bool = False,
               stay_s: float = 0.0) -> Kill:
    doc = supervisor_doc(t)
    if doc is None:
        return Kill(i, time.monotonic() - t0, "?", failure="the supervisor did not answer")
    victim = rng.choice(doc["workers"])
    k = Kill(i, time.monotonic() - t0, victim["instance"])
    restarts = doc["worker_restarts"]
    before = events(t, cams)
    os.kill(victim["pid"], signal.SIGKILL)
    t_kill = time.monotonic()

    def back() -> bool:
        d = supervisor_doc(t)
        w = d["workers"][victim["index"]] if d else None
        return bool(d and d["worker_restarts"] > restarts and w["alive"]
                    and w["pid"] != victim["pid"]
                    and t.alive(keys.service_token_key("evcal", victim["instance"]),
                                timeout_s=1.0))

    if poll(back, 60) is None:
        k.failure = "not restarted within 60 s"
        return k
    k.restart_s = time.monotonic() - t_kill
    t_back = time.monotonic()
    answered = None
    while answered is None and time.monotonic() - t_back < answer_timeout_s:
        answered = fresh_client_status(ep, cams, answer_timeout_s
                                       - (time.monotonic() - t_back), calibrations)
    if answered is None:
        k.failure = f"a new client got no status of every camera within {answer_timeout_s:g} s"
        return k
    k.answer_s = time.monotonic() - t_back
    # the killed worker's cameras restart from their snapshots (fewer events than before
    # the kill): compare with the smaller of the two counts
    since = {c: min(before.get(c, 0), answered[c]) for c in cams}
    flow = flowing(t, cams, since, max(0.0, answer_timeout_s - k.answer_s))
    if flow is None:
        k.failure = f"the events did not flow to every camera within {answer_timeout_s:g} s"
        return k
    k.flow_s = time.monotonic() - t_back
    if calibrations and stay_s > 0:
        k.stay_queries = 0
        t_stay = time.monotonic()
        while time.monotonic() - t_stay < stay_s:
            for cam in cams:
                if not calibration_answered(t, cam, 5.0):
                    k.failure = (f"{cam}'s calibration not answered within 5 s, "
                                 f"{time.monotonic() - t_stay:.1f} s into the stay")
                    return k
                k.stay_queries += 1
            time.sleep(0.5)
    return k


def _watch(ep: str, cams: list[str], watch_s: float) -> float | None:
    """After a failed check: seconds until a new client gets every camera's status again
    (a stall that passes), or None when none did within ``watch_s`` (stuck for good)."""
    t0 = time.monotonic()
    while time.monotonic() - t0 < watch_s:
        if fresh_client_status(ep, cams, 10.0) is not None:
            return time.monotonic() - t0
        time.sleep(1.0)
    return None


def _simulated(args: argparse.Namespace, log_dir: Path) -> Path:
    from evcal.io import write_recording
    from evcal.sim.ideal import SimConfig, simulate_ideal

    width, _, height = args.sim_sensor.partition("x")
    sim = simulate_ideal(SimConfig(height=int(height), width=int(width),
                                   duration_s=args.sim_seconds, seed=11))
    return Path(write_recording(sim.recording, log_dir / "sim.npz"))


def _f(x: float | None) -> str:
    return "-" if x is None else f"{x:.1f}"


HEADER = f"{'kill':>4} {'at_s':>7} {'victim':>9} {'restart_s':>9} {'answer_s':>8} " \
         f"{'flow_s':>6} {'stay':>5}  result"


def _row(k: Kill) -> str:
    return (f"{k.index:>4} {k.at_s:>7.1f} {k.victim:>9} {_f(k.restart_s):>9} "
            f"{_f(k.answer_s):>8} {_f(k.flow_s):>6} "
            f"{'-' if k.stay_queries is None else k.stay_queries:>5}  {k.failure or 'ok'}")


def report(kills: list[Kill], end: dict[str, Any], n_wanted: int) -> int:
    print(HEADER)
    for k in kills:
        print(_row(k))
    ok = [k for k in kills if k.failure is None]
    if ok:
        for name in ("restart_s", "answer_s", "flow_s"):
            xs = sorted(getattr(k, name) for k in ok)
            print(f"{name}: median {xs[len(xs) // 2]:.1f}, max {xs[-1]:.1f} s")
    print(f"kills passed: {len(ok)} of {n_wanted}")
    if end.get("exit_code") is not None:
        print(f"SIGTERM: exit code {end['exit_code']} after {_f(end.get('stop_s'))} s")
    else:
        late = end.get("late_exit")
        print("SIGTERM: still running after the timeout; "
              + (f"exit code {late[0]} after {late[1]:.1f} s (gdb included)" if late
                 else "still running 60 s later"))
    la0, la1 = end.get("load_start"), end.get("load_end")
    print("load average (1, 5, 15 min): start " + " ".join(f"{x:.2f}" for x in la0)
          + (", end " + " ".join(f"{x:.2f}" for x in la1) if la1 else ""))
    if "dump" in end:
        print(end["dump"])
    if "recovered_s" in end:
        rec = end["recovered_s"]
        print("after the failure: " + (f"every camera answered again {rec:.1f} s later"
                                       if rec is not None else "no answer for "
                                       f"{end.get('watch_s', 0):g} s (stuck)"))
    passed = len(ok) == n_wanted and end.get("exit_code") == 0
    return 0 if passed else 1


def _gap(text: str) -> tuple[float, float]:
    lo, _, hi = text.partition(",")
    return float(lo), float(hi or lo)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--kills", type=int, default=10)
    p.add_argument("--replays", type=int, default=4)
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--gap-s", type=_gap, default=(4.0, 12.0), metavar="LO,HI",
                   help="seconds between kills, uniform in [LO, HI] (default 4,12)")
    p.add_argument("--answer-timeout-s", type=float, default=10.0)
    p.add_argument("--stop-timeout-s", type=float, default=5.0)
    p.add_argument("--stop-replays-first", action="store_true",
                   help="end the replays before the SIGTERM (a worker drains its queues "
                        "before it exits, and under full load new input keeps coming)")
    p.add_argument("--watch-s", type=float, default=60.0,
                   help="after a failed check, how long to wait for the service to answer "
                        "again (a stall, or stuck for good?) before stopping (default 60)")
    p.add_argument("--recording", help="replay this recording instead of a simulated one")
    p.add_argument("--sim-sensor", default="346x260", metavar="WxH",
                   help="the simulated recording's sensor (default 346x260)")
    p.add_argument("--sim-seconds", type=float, default=3.0)
    p.add_argument("--serve-arg", action="append", default=[], metavar="OPTION",
                   help="an option for evcal serve, e.g. --serve-arg=--cfg=KEY:VALUE")
    p.add_argument("--calibrations", action="store_true",
                   help="the new client also fetches every camera's calibration")
    p.add_argument("--stay-s", type=float, default=0.0,
                   help="with --calibrations: query them this long after each recovery")
    p.add_argument("--log-dir", help="keep the logs here (default: a new temporary folder)")
    return p


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["ask"]:  # the new client of fresh_client_status
        a = argparse.ArgumentParser()
        a.add_argument("connect")
        a.add_argument("cameras", nargs="+")
        a.add_argument("--timeout", type=float, default=5.0)
        a.add_argument("--calibrations", action="store_true")
        ns = a.parse_args(argv[1:])
        return ask(ns.connect, ns.cameras, ns.timeout, ns.calibrations)
    args = build_parser().parse_args(argv)
    log_dir = Path(args.log_dir or tempfile.mkdtemp(prefix="evcal-probe-kills-"))
    log_dir.mkdir(parents=True, exist_ok=True)
    print(f"logs in {log_dir}; {args.kills} kills, {args.replays} replays at full rate",
          flush=True)
    print(HEADER, flush=True)
    kills, end = probe(args, log_dir)
    print()
    return report(kills, end, args.kills)


if __name__ == "__main__":
    sys.exit(main())
