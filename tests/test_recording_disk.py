"""The recorder on a full disk and under a file-size limit (issue 23, item 2).

The `.rrd` must pass `rerun rrd verify` whenever the disk fills or RLIMIT_FSIZE is reached,
the recorder must say why it stopped, and SIGTERM must not wait on the disk. Three ways to
run out of room, from the closest to the real thing:

- a real full disk: a small tmpfs mounted in a user and mount namespace (``unshare -rm``),
  filled by another writer at a random moment, sometimes while the recorder is idle (skipped
  where unprivileged namespaces are not allowed);
- RLIMIT_FSIZE set in a child process (writes past it fail with EFBIG);
- an injected free-space function (in process).

The first two run a driver process that feeds a recorder from a thread as the service's
recorder thread does, and on SIGTERM does what ``evcal serve`` does: wait for that thread
(up to 30 s), then close the recorder. ``EVCAL_RECORDING_UNDER_TEST=<file>`` runs them against
another ``recording.py`` (relative imports made absolute), e.g. the one before the fix.
"""

from __future__ import annotations

import contextlib
import importlib.util
import json
import os
import resource
import shlex
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("rerun")

from evcal.calibration import Calibration  # noqa: E402
from evcal.events import make_events  # noqa: E402
from evcal.service.rrdlog import read_entities  # noqa: E402
from evcal.testing import python_env  # noqa: E402

RERUN = shutil.which("rerun") or str(Path(sys.executable).with_name("rerun"))
UNDER_TEST = os.environ.get("EVCAL_RECORDING_UNDER_TEST")
SIGTERM_EXIT_S = 5.0

DRIVER = r'''
import errno, faulthandler, importlib.util, json, os, shutil, signal, sys, threading, time
import numpy as np
from evcal.calibration import Calibration
from evcal.events import make_events

cfg = json.loads(sys.argv[1])
if cfg["module_path"]:
    spec = importlib.util.spec_from_file_location("recording_under_test", cfg["module_path"])
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod  # dataclasses look their module up
    spec.loader.exec_module(mod)
else:
    from evcal.service import rrdlog as mod
if cfg["no_gate"]:  # the writer's own fallback: no check before the calls
    mod._file_size_limit = lambda: 1 << 62
stop = threading.Event()
signal.signal(signal.SIGTERM, lambda *_: stop.set())
faulthandler.register(signal.SIGUSR1, all_threads=True)  # as `evcal serve`: the test's stall dump
log = mod.RrdLogger(cfg["rrd"], map_period_s=0.0, recon_period_s=0.0, recon_frames=1,
                    scalar_period_s=0.0, min_free_bytes=cfg["min_free_bytes"])
h, w = cfg["shape"]
rng = np.random.default_rng(cfg["seed"])
cal = Calibration.uniform((h, w), 0.2, 0.01, log_offset=30.0)
cal = cal.replace(contrast=(0.2 + 0.01 * rng.standard_normal((h, w))).astype(np.float32))
status = {"latency_ms": {"last": 5.0}, "event_rate_hz": 1e5, "errors_total": 0}
t0 = time.monotonic()
pause = cfg["pause"]

def feed():  # the service's recorder thread
    k = 0
    while not stop.is_set():
        now = time.monotonic() - t0
        if pause and pause[0] <= now < pause[1]:
            time.sleep(0.01)
            continue
        t = k * 40_000
        log.updated("cam0", cal, t, status)
        log.frame("cam0", t + 1, rng.integers(0, 255, (h, w)).astype(np.uint8))
        log.events("cam0", make_events([t + 2, t + 3], [1, 2], [3, 4], [1, -1]))
        k += 1
        time.sleep(cfg["period_s"])

def fill():  # another process's writer takes all the space
    time.sleep(cfg["fill_after_s"])
    fd = os.open(os.path.join(cfg["fill_dir"], "filler"), os.O_WRONLY | os.O_CREAT)
    for block in (1 << 20, 4096, 512):
        try:
            while True:
                os.write(fd, bytes(block))
        except OSError as exc:
            assert exc.errno == errno.ENOSPC, exc
    os.close(fd)
    print("filled at", round(time.monotonic() - t0, 3), flush=True)

def watch():  # tell the test when recording stops
    while not stop.is_set() and log.state()["recording"]:
        time.sleep(0.05)
    print("stopped" if not stop.is_set() else "", flush=True)

feeder = threading.Thread(target=feed, daemon=True)
feeder.start()
threading.Thread(target=watch, daemon=True).start()
if cfg["fill_after_s"] is not None:
    threading.Thread(target=fill, daemon=True).start()
print("ready", flush=True)
# as `evcal serve` waits (`while not stop.wait(tick_s)`), never without a timeout: CPython runs
# the SIGTERM handler only in the main thread, between bytecodes, and the kernel may hand the
# signal to any other thread (rerun's, the feeder; more often under load), whose C handler
# only sets a flag: a main thread asleep in an untimed stop.wait() would never run it
while not stop.wait(0.1):
    pass
t_term = time.monotonic()
feeder.join(30)  # ObserverThread.close()
log.close()
state = log.state()
close_s = time.monotonic() - t_term
if cfg["copy_to"]:
    shutil.copyfile(log.path, cfg["copy_to"])
with open(cfg["out"], "w") as f:
    json.dump({"state": state, "close_s": close_s}, f)
'''


def _old_module_file(tmp: Path) -> str | None:
    """``EVCAL_RECORDING_UNDER_TEST`` with its relative imports made absolute, or None."""
    if not UNDER_TEST:
        return None
    text = (Path(UNDER_TEST).read_text().replace("from ..", "from evcal.")
            .replace("from .", "from evcal.service."))
    out = tmp / "recording_under_test.py"
    out.write_text(text)
    return str(out)


def _recording_module(tmp: Path):
    path = _old_module_file(tmp)
    if path is None:
        from evcal.service import rrdlog

        return rrdlog
    spec = importlib.util.spec_from_file_location("recording_under_test", path)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod  # dataclasses look their module up
    spec.loader.exec_module(mod)
    return mod


def verify(path: Path, *extra: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([RERUN, "rrd", "verify", *extra, str(path)], capture_output=True,
                          text=True, timeout=120)


def run_driver(tmp: Path, *, rrd: Path, wrap: list[str] | None = None, run_s: float,
               until_stopped: bool = False, preexec=None, **cfg) -> tuple[dict, float, str]:
    """Run the driver, SIGTERM it after ``run_s`` seconds (or once it says the recording
    stopped, ``run_s`` at most); (result, seconds from SIGTERM to exit, output)."""
    script = tmp / "driver.py"
    script.write_text(DRIVER)
    out = tmp / "result.json"
    conf = {"rrd": str(rrd), "out": str(out), "module_path": _old_module_file(tmp),
            "no_gate": False, "shape": [48, 64], "seed": 0, "pause": None, "period_s": 0.01,
            "fill_after_s": None, "fill_dir": str(rrd.parent), "min_free_bytes": 4 << 20,
            "copy_to": None, **cfg}
    cmd = [sys.executable, str(script), json.dumps(conf)]
    if wrap:  # the last item of wrap is a shell command that ends with `exec`
        cmd = [*wrap[:-1], wrap[-1] + " " + " ".join(shlex.quote(c) for c in cmd)]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            env=python_env(), preexec_fn=preexec)
    try:
        assert proc.stdout is not None
        first = proc.stdout.readline()
        assert "ready" in first, first + proc.stdout.read()
        if until_stopped:
            _read_until(proc.stdout, "stopped", run_s)
        else:
            time.sleep(run_s)
        t0 = time.monotonic()
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(SIGTERM_EXIT_S)
        except subprocess.TimeoutExpired:  # stalled: its threads' stacks go to the output
            with contextlib.suppress(ProcessLookupError):
                proc.send_signal(signal.SIGUSR1)
            with contextlib.suppress(subprocess.TimeoutExpired):
                proc.wait(25)
        exit_s = time.monotonic() - t0
    finally:
        if proc.poll() is None:
            proc.kill()
        output = proc.communicate(timeout=10)[0]
    assert proc.returncode == 0, f"exit code {proc.returncode} after {exit_s:.1f} s:\n{output}"
    return json.loads(out.read_text()), exit_s, output


def _read_until(stream, word: str, timeout_s: float) -> None:
    """Read lines of ``stream`` until one holds ``word`` or ``timeout_s`` passed."""
    import selectors

    deadline = time.monotonic() + timeout_s
    with selectors.DefaultSelector() as sel:
        sel.register(stream, selectors.EVENT_READ)
        while (left := deadline - time.monotonic()) > 0:
            if sel.select(left) and word in stream.readline():
                return


def _namespaces_allowed() -> bool:
    if shutil.which("unshare") is None:
        return False
    res = subprocess.run(["unshare", "-rm", "sh", "-c", "mount -t tmpfs -o size=1m tmpfs /mnt"],
                         capture_output=True, timeout=30)
    return res.returncode == 0


needs_tmpfs = pytest.mark.skipif(not _namespaces_allowed(),
                                 reason="needs unprivileged user and mount namespaces "
                                        "(unshare -rm) to mount a small tmpfs")


@needs_tmpfs
@pytest.mark.parametrize("seed", [*range(3), *(pytest.param(s, marks=pytest.mark.slow)
                                               for s in range(3, 10))])
def test_a_disk_filled_at_a_random_moment_leaves_a_verified_file(tmp_path, seed):
    """A 24 MiB tmpfs filled by another writer at a random moment: while the recorder works
    (seed % 3 == 0), while it is idle and then works again (1), or while it is idle until
    SIGTERM (2, the issue's case). The file passes `rerun rrd verify`, SIGTERM exits within
    5 s, and a recorder that worked after the fill says disk_full."""
    rng = np.random.default_rng(seed)
    fill_after = float(rng.uniform(0.3, 2.0))
    pause = [None, [fill_after - 0.2, fill_after + 0.6], [fill_after - 0.2, 60.0]][seed % 3]
    mnt = tmp_path / "mnt"
    mnt.mkdir()
    kept = tmp_path / "kept.rrd"
    result, exit_s, output = run_driver(
        tmp_path, rrd=mnt / "run.rrd", run_s=fill_after + 1.2, seed=seed, pause=pause,
        fill_after_s=fill_after, copy_to=str(kept),
        wrap=["unshare", "-rm", "sh", "-c", f"mount -t tmpfs -o size=24m tmpfs {mnt} && exec"])
    state = result["state"]
    print(f"seed {seed}: fill at {fill_after:.2f} s, pause {pause}, SIGTERM exit "
          f"{exit_s:.2f} s (close {result['close_s']:.2f} s), {state.get('bytes')} bytes, "
          f"reason {state.get('reason')}")
    assert exit_s < SIGTERM_EXIT_S, output
    res = verify(kept)
    assert res.returncode == 0, res.stdout + res.stderr + output
    assert read_entities(kept)["/cameras/cam0/series/latency_ms"] > 0
    assert (state["complete"], state["bytes"]) == (True, kept.stat().st_size), state
    if seed % 3 != 2:
        assert (state["recording"], state["reason"]) == (False, "disk_full"), state


def _fsize_limit(nbytes: int):
    def set_limit() -> None:
        resource.setrlimit(resource.RLIMIT_FSIZE, (nbytes, nbytes))
    return set_limit


@pytest.mark.parametrize("shape", [(48, 64), (180, 240)])
def test_a_file_size_limit_stops_recording_with_a_verified_file(tmp_path, shape):
    """RLIMIT_FSIZE of 3 MiB (the issue's case): recording stops before the limit with the
    reason and the bytes written, the file passes `rerun rrd verify`, SIGTERM exits fast."""
    rrd = tmp_path / "run.rrd"
    result, exit_s, output = run_driver(tmp_path, rrd=rrd, run_s=20.0, until_stopped=True,
                                        shape=list(shape), preexec=_fsize_limit(3 << 20))
    state = result["state"]
    print(f"shape {shape}: SIGTERM exit {exit_s:.2f} s, state {state}")
    assert exit_s < SIGTERM_EXIT_S, output
    res = verify(rrd)
    assert res.returncode == 0, res.stdout + res.stderr + output
    assert (state["recording"], state["reason"], state["complete"]) == (
        False, "file_size_limit", True), state
    assert state["bytes"] == rrd.stat().st_size <= 3 << 20
    assert read_entities(rrd)["/cameras/cam0/maps/contrast"] > 0


def test_a_write_past_the_limit_is_cut_back_to_a_whole_message(tmp_path):
    """Without the checks before each call, a write fails with EFBIG: the writer cuts the
    file back to its last whole message (no footer: readable, `verify --check-footers
    false` accepts it), says so, and rerun never blocks on it."""
    rrd = tmp_path / "run.rrd"
    result, exit_s, output = run_driver(tmp_path, rrd=rrd, run_s=20.0, until_stopped=True,
                                        no_gate=True, preexec=_fsize_limit(3 << 20))
    state = result["state"]
    assert exit_s < SIGTERM_EXIT_S, output
    assert (state["reason"], state["complete"]) == ("file_size_limit", False), state
    assert state["bytes"] == rrd.stat().st_size <= 3 << 20
    res = verify(rrd, "--check-footers", "false")
    assert res.returncode == 0, res.stdout + res.stderr


@pytest.mark.parametrize("seed", range(10))
def test_injected_free_space_stops_before_the_margin(tmp_path, seed):
    """A disk of a random capacity seen through an injected free-space function: recording
    stops with min_free_bytes still free, the file (footer included) verifies."""
    mod = _recording_module(tmp_path)
    rng = np.random.default_rng(seed)
    capacity = int(rng.uniform(2, 6) * (1 << 20))
    min_free = 1 << 20
    path = tmp_path / "run.rrd"
    holder: dict = {}

    def free(_p: Path) -> int:
        used = path.stat().st_size if path.exists() else 0
        rec = holder.get("log")
        reserved = rec._file.reserved if rec is not None and hasattr(rec, "_file") else 0
        return capacity - used - reserved

    log = mod.RrdLogger(path, map_period_s=0.0, recon_period_s=0.0, recon_frames=1,
                        scalar_period_s=0.0, min_free_bytes=min_free, disk_free=free)
    holder["log"] = log
    shape = (48, 64) if seed % 2 else (120, 160)
    cal = Calibration.uniform(shape, 0.2, 0.01, log_offset=30.0)
    cal = cal.replace(contrast=(0.2 + 0.01 * rng.standard_normal(shape)).astype(np.float32))
    status = {"latency_ms": {"last": 5.0}, "event_rate_hz": 1e5, "errors_total": 0}
    for k in range(2000):
        if not log.state()["recording"]:
            break
        log._next_disk_check = 0.0  # the code before the fix checked once a second
        t = k * 40_000
        log.updated("cam0", cal, t, status)
        log.frame("cam0", t + 1, rng.integers(0, 255, shape).astype(np.uint8))
        log.events("cam0", make_events([t + 2, t + 3], [1, 2], [3, 4], [1, -1]))
    t0 = time.monotonic()
    log.close()
    assert time.monotonic() - t0 < SIGTERM_EXIT_S
    res = verify(path)
    assert res.returncode == 0, res.stdout + res.stderr
    assert path.stat().st_size <= capacity - min_free
    state = log.state()
    assert (state["recording"], state.get("reason")) == (False, "disk_full"), state
    assert (state["complete"], state["bytes"]) == (True, path.stat().st_size)


@needs_tmpfs
@pytest.mark.timeout(240)
@pytest.mark.parametrize("after_fill", ["sigterm", "replay"])
def test_the_service_on_a_disk_filled_while_idle(tmp_path, after_fill):
    """`evcal serve --rrd` on a 72 MiB tmpfs (64 MiB kept free, the default), filled by another
    writer while the service is idle; then SIGTERM at once (the issue's case: it hung for
    more than 90 s), or a second replay first (the `cameras` document then reports the stop
    while queries go on). The file passes `rerun rrd verify`; SIGTERM exits within 5 s."""
    pytest.importorskip("zenoh")
    from evcal.io import write_recording
    from evcal.service.transport import Transport, ZenohOptions
    from evcal.sim.ideal import SimConfig, simulate_ideal
    from evcal.testing import endpoint, free_port, run_client, wait_for

    sim = simulate_ideal(SimConfig(height=48, width=64, duration_s=2.0, seed=3))
    rec_path = write_recording(sim.recording, tmp_path / "sim.npz")
    mnt, kept = tmp_path / "mnt", tmp_path / "kept.rrd"
    mnt.mkdir()
    trigger, filled = tmp_path / "fill-now", tmp_path / "filled"
    ep = endpoint(free_port())
    # zenoh's shared memory does not cross into the service's user namespace
    conf = tmp_path / "zenoh.json5"
    conf.write_text('{transport: {shared_memory: {enabled: false}}}')
    zargs = ["--no-multicast-scouting", "--config", str(conf)]
    serve = " ".join(shlex.quote(a) for a in [
        sys.executable, "-m", "evcal.service", "--listen", ep, *zargs, "--on-full", "block",
        "--rrd", str(mnt / "run.rrd"), "--rrd-map-period", "0.05", "--rrd-recon-period",
        "0.05", "--status-period", "0.2"])
    # the shell holds the namespace: it fills the tmpfs on the trigger, and copies the file
    # out once the service exited
    script = (f"mount -t tmpfs -o size=72m tmpfs {mnt} || exit 9; "
              f"(while [ ! -e {trigger} ]; do sleep 0.05; done; "
              f"dd if=/dev/zero of={mnt}/filler bs=1M 2>/dev/null; touch {filled}) & "
              f"{serve} & echo $! > {tmp_path}/pid; wait $!; echo $? > {tmp_path}/rc; "
              f"cp {mnt}/run.rrd {kept}")
    log_file = open(tmp_path / "service.log", "wb")  # noqa: SIM115 - closed below
    shell = subprocess.Popen(["unshare", "-rm", "sh", "-c", script], stdout=log_file,
                             stderr=subprocess.STDOUT, env=python_env())
    try:
        with Transport(ZenohOptions.loopback(connect=[ep])) as t:
            wait_for(lambda: t.alive("evcal/@service/*", timeout_s=1.0), timeout_s=60,
                     what="the service's liveliness token")

            def recorder() -> dict:
                return json.loads(t.get("evcal/cameras", timeout_s=3.0)[0].payload)["recorder"]

            def replay() -> None:
                res = run_client("replay", [str(rec_path), "--camera", "cam0", "--connect", ep,
                                            *zargs, "--max-rate"])
                assert res.returncode == 0, res.stderr

            replay()
            wait_for(lambda: recorder()["image_bytes"] > 0, timeout_s=30, what="maps recorded")
            time.sleep(1.0)  # idle: the recorder has written all it had
            trigger.touch()
            wait_for(filled.exists, timeout_s=30, what="the tmpfs filled")
            assert recorder()["recording"] is True  # nothing logged since the fill
            if after_fill == "replay":
                replay()
                state = wait_for(lambda: (r := recorder())["recording"] is False and r,
                                 timeout_s=30, what="the recorder reporting its stop")
                assert (state["reason"], state["complete"]) == ("disk_full", True), state
                res = run_client("query", ["--camera", "cam0", "--connect", ep, *zargs,
                                           "--out", str(tmp_path / "cal.npz")])
                assert res.returncode == 0, res.stderr  # queries go on
        pid = int((tmp_path / "pid").read_text())
        t0 = time.monotonic()
        os.kill(pid, signal.SIGTERM)
        wait_for(lambda: (tmp_path / "rc").exists(), timeout_s=60, interval_s=0.02,
                 what="the service's exit")
        exit_s = time.monotonic() - t0
        shell.wait(30)
    finally:
        if shell.poll() is None:  # a failed test: the service too, not only its shell
            pid_file = tmp_path / "pid"
            if pid_file.exists():
                with contextlib.suppress(ProcessLookupError, ValueError):
                    os.kill(int(pid_file.read_text()), signal.SIGKILL)
            shell.kill()
            shell.wait(10)
        log_file.close()
    output = (tmp_path / "service.log").read_text(errors="replace")
    print(f"{after_fill}: SIGTERM exit {exit_s:.2f} s, {kept.stat().st_size} bytes")
    assert (tmp_path / "rc").read_text().strip() == "0", output
    assert exit_s < SIGTERM_EXIT_S, output
    res = verify(kept)
    assert res.returncode == 0, res.stdout + res.stderr + output
    assert read_entities(kept)["/cameras/cam0/maps/contrast"] > 0
