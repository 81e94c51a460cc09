"""``evcal serve --workers N``: one command, N worker processes, the cameras split among them.

One service process runs every camera's decoder and worker threads under one interpreter:
the compiled kernels release the GIL, the Python between them does not, so a second camera
adds threads but hardly any throughput. ``--workers N`` runs N service processes instead,
each serving the cameras whose id hashes to it (:func:`evcal.service.keys.shard_of`: BLAKE2b
of the id modulo N, the same in every run), so that cameras use as many cores as there are
workers.

This process, the supervisor, does not touch the data:

- it opens one zenoh session in router mode where the service would have opened its session
  (the user's endpoints and configuration, :func:`~evcal.service.transport.as_router`), plus a
  private local endpoint: a Unix socket in a fresh directory only this user may enter (no
  port to race for, nothing another local user can reach);
- it starts worker ``i`` as ``python -m evcal.service <the user's options> --shard i/N
  --instance <name>-w<i> --mode client --connect <local endpoint> --no-multicast-scouting``
  (``--rrd PATH`` becomes ``PATH`` with ``.w<i>`` before its suffix, ``--rerun-serve PORT``
  port ``PORT + i``), each in its own process group with a pipe on its stdin;
- it answers ``<prefix>/cameras`` with its workers (pid, starts, last exit); each worker
  answers with its own cameras;
- a worker that exits while the supervisor runs is restarted after a back-off (0.5 s,
  doubling up to 30 s; a worker that ran 30 s starts its count afresh) and resumes its
  cameras from the shared ``--state-dir``; when it fails again after 5 such restarts in a
  row (each within 30 s of its start), or with a usage error, the supervisor stops every
  worker and exits 1;
- SIGINT or SIGTERM: SIGTERM to every worker, which drains its queues, publishes a last
  status and writes its snapshots and ``.rrd``; after 60 s a worker still running is killed.
  Then the session closes (bounded: :data:`ROUTER_CLOSE_S`); exit 0 when every worker
  stopped cleanly.

A worker never outlives the supervisor, however it ends: its stdin reaches end-of-file when
the supervisor's end of the pipe closes (it then stops as on SIGTERM), and on Linux
``PR_SET_PDEATHSIG`` sends it SIGHUP when the supervisor dies; it then also removes the
supervisor's socket directory, which a killed supervisor leaves behind.

The data path is zenoh's: every worker subscribes to every camera's keys, the router (Rust
threads, no GIL) hands each sample to every worker, and a worker leaves another shard's
sample by its key before copying the payload. The workers' links carry no shared memory
(:data:`WORKER_ZENOH_CFG`, why there): every payload, a local publisher's too, is sent to
each worker over the local socket. Queries reach every worker (a shard's queryables are not
"complete") and only the owner of a camera answers for it.
"""

from __future__ import annotations

import argparse
import contextlib
import ctypes
import logging
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ..errors import ConfigError
from ..jsonable import strict_dumps
from ..online import usable_cores
from ..signals import SignalRelay
from . import keys
from .signing import SignatureError, Signer
from .transport import Request, Transport, TransportError, ZenohOptions, as_router

log = logging.getLogger("evcal.service.workers")

RESTART_FIRST_S = 0.5  # back-off before the first restart of a worker, doubled each time
RESTART_MAX_S = 30.0  # longest back-off
STABLE_S = 30.0  # a worker that ran this long before it exited starts its count afresh
MAX_QUICK_FAILURES = 5  # more quick exits in a row than this (5 restarts failed): give up
STOP_TIMEOUT_S = 60.0  # after SIGTERM, a worker still running this long is killed
USAGE_EXIT = 2  # a worker's exit code for bad usage: restarting it cannot help

# the zenoh options of a worker are the supervisor's, never the user's: these variables
# would otherwise stand in for the flags a worker is not given (transport.options_from_args)
ZENOH_ENV = ("EVCAL_CONNECT", "EVCAL_LISTEN", "EVCAL_ZENOH_CONFIG", "EVCAL_MODE")

# A worker's link to the router carries no shared memory: zenoh 1.10.2 deadlocks on it.
# Its shared-memory handoff (eclipse-zenoh/zenoh#2646) takes a lock per link and priority
# while it maps a payload for a partner -- under that transport's `links` read lock -- and
# holds it until the push and `handle_push_result` are done, which reads `links` again. When
# a writer queues on `links` in between (a link added or removed: a killed worker's, or one
# reconnecting after zenoh closed it for a push that waited 5 s), the writer-preferring
# RwLock closes the cycle: the router stops for good (issue 23; gdb thread dumps in
# docs/SERVICE.md, "Worker deaths under load"). Without shared memory on the link zenoh
# takes no handoff lock. The cost: the router copies every payload to each worker.
WORKER_ZENOH_CFG = ("transport/shared_memory/enabled:false",)
ROUTER_CLOSE_S = 3.0  # the router session's close is bounded (Transport.close)

# The router's receive threads. zenoh runs every link's receive loop on one pool (2 threads
# by default on 2 cores), and a loop that routes a sample to a worker whose queue is full
# waits there (the replays' congestion control is BLOCK) holding its thread. Two such waits
# -- one busy worker is enough -- left no thread to read any other link: not the answering
# worker's reply, not its keep-alives, so after the 10 s lease the router closed that link
# (docs/SERVICE.md, "The router's receive threads"). With a thread for each link the router
# may have, and spares, a busy worker slows its own links only.
def router_runtime(count: int, environ: Mapping[str, str] | None = None) -> str | None:
    """The ``ZENOH_RUNTIME`` the supervisor's router runs with (``count`` workers): more
    receive threads than links (see above), or None when the user set ``ZENOH_RUNTIME``."""
    if (os.environ if environ is None else environ).get("ZENOH_RUNTIME"):
        return None
    return f"(rx: (worker_threads: {router_rx_threads(count)}))"


def router_rx_threads(count: int) -> int:
    """Receive threads of the router: one per worker link, one per client link among the
    first few dozen (replays, queries, recorders, the user's routers), and spares."""
    return 2 * count + 32

# options the supervisor sets for each worker instead of passing the user's through
OWN_OPTIONS = frozenset({"help", "mode", "connect", "listen", "config",
                         "no_multicast_scouting", "cfg", "workers", "shard", "instance", "rrd",
                         "rerun_serve", "supervised"})


def worker_rrd(path: str | Path, index: int) -> str:
    """The ``.rrd`` of worker ``index``: ``run.rrd`` -> ``run.w0.rrd`` (``run`` -> ``run.w0``)."""
    p = Path(path)
    return str(p.with_name(f"{p.stem}.w{index}{p.suffix}"))


LOCAL_DIR_PREFIX = "evcal-serve-"  # the supervisor's private directory for its socket


def local_endpoint(directory: str | Path) -> str:
    """The supervisor's endpoint for its workers: a Unix socket in ``directory`` (a private
    temporary directory), or a free TCP port on the loopback where there are no Unix
    sockets."""
    if os.name == "posix":
        return f"unixsock-stream/{Path(directory) / 'router.sock'}"
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return f"tcp/127.0.0.1:{s.getsockname()[1]}"


def passthrough_args(parser: argparse.ArgumentParser, args: argparse.Namespace) -> list[str]:
    """The command-line options of ``args`` that a worker takes as they are: every option of
    ``parser`` given a value other than its default, except :data:`OWN_OPTIONS`."""
    out: list[str] = []
    for action in parser._actions:  # argparse has no public list of a parser's options
        if not action.option_strings or action.dest in OWN_OPTIONS:
            continue
        value = getattr(args, action.dest, None)
        if value is None or value == action.default:
            continue
        opt = max(action.option_strings, key=len)  # the long form
        if action.nargs == 0:  # a flag: store_true once, a count (-v) as often as given
            out += [opt] * (1 if isinstance(value, bool) else int(value))
        elif isinstance(value, list):  # a repeatable option
            out += [f"{opt}={v}" for v in value]
        else:
            out.append(f"{opt}={value}")
    return out


def worker_command(parser: argparse.ArgumentParser, args: argparse.Namespace, *, index: int,
                   count: int, endpoint: str, instance: str) -> list[str]:
    """The command line of worker ``index`` of ``count`` (see the module's docstring)."""
    cmd = [sys.executable, "-m", "evcal.service", *passthrough_args(parser, args),
           "--mode", "client", "--connect", endpoint, "--no-multicast-scouting",
           *(f"--cfg={c}" for c in WORKER_ZENOH_CFG),
           "--shard", f"{index}/{count}", "--instance", instance,
           "--supervised", str(os.getpid())]
    if not args.threads:
        # the re-solve's threads: the cores shared out among the workers (16 cores, 4
        # workers: 4 each), not every worker on every core
        cmd += ["--threads", str(max(1, usable_cores() // count))]
    if args.rrd:
        cmd += ["--rrd", worker_rrd(args.rrd, index)]
    if args.rerun_serve is not None:
        cmd += ["--rerun-serve", str(args.rerun_serve + index)]
    return cmd


def worker_env(environ: Mapping[str, str] | None = None) -> dict[str, str]:
    """A worker's environment: this one without the zenoh variables (:data:`ZENOH_ENV`).
    Call it before the router's runtime is set (:func:`router_runtime`): a worker has one
    link and keeps the user's ``ZENOH_RUNTIME``, if any."""
    env = {k: v for k, v in (os.environ if environ is None else environ).items()
           if k not in ZENOH_ENV}
    env["PYTHONUNBUFFERED"] = "1"
    return env


def describe_exit(returncode: int) -> str:
    """``"exit code 1"`` or ``"signal 9 (SIGKILL)"``."""
    if returncode < 0:
        try:
            return f"signal {-returncode} ({signal.Signals(-returncode).name})"
        except ValueError:
            return f"signal {-returncode}"
    return f"exit code {returncode}"


# ----------------------------------------------------------------------------- supervision


@dataclass
class WorkerSlot:
    """One worker's place: its command, its current process and its history."""

    index: int
    instance: str
    command: list[str]
    proc: subprocess.Popen[bytes] | None = None
    started_s: float = 0.0  # time.monotonic() of the current process's start
    starts: int = 0
    quick_failures: int = 0  # exits in a row, each within STABLE_S of its start
    next_start_s: float = 0.0  # time.monotonic() when a stopped worker is started again
    last_exit: str | None = None
    exit_codes: list[int] = field(default_factory=list)

    def info(self, now_s: float) -> dict[str, Any]:
        alive = self.proc is not None and self.proc.poll() is None
        return {"instance": self.instance, "index": self.index,
                "pid": self.proc.pid if self.proc is not None else None, "alive": alive,
                "up_s": round(now_s - self.started_s, 1) if alive else None,
                "starts": self.starts, "last_exit": self.last_exit}


class Supervisor:
    """Keeps one process running per command; thread-safe :meth:`info`.

    Call :meth:`poll` from the thread that created the supervisor (on Linux a worker's
    parent-death signal fires when the thread that started it ends), every ~0.2 s, until it
    returns False (a worker keeps failing) or the supervisor is to stop; then :meth:`stop`.
    """

    def __init__(self, commands: Sequence[Sequence[str]], instances: Sequence[str], *,
                 env: Mapping[str, str] | None = None, first_backoff_s: float = RESTART_FIRST_S,
                 max_backoff_s: float = RESTART_MAX_S, stable_s: float = STABLE_S,
                 max_quick_failures: int = MAX_QUICK_FAILURES) -> None:
        if len(commands) != len(instances) or not commands:
            raise ConfigError(f"{len(commands)} commands for {len(instances)} instances")
        self.slots = [WorkerSlot(i, name, list(cmd))
                      for i, (cmd, name) in enumerate(zip(commands, instances, strict=True))]
        self.env = dict(env) if env is not None else None
        self.first_backoff_s = first_backoff_s
        self.max_backoff_s = max_backoff_s
        self.stable_s = stable_s
        self.max_quick_failures = max_quick_failures
        self.restarts = 0
        self.failed: str | None = None  # why the supervisor gave up
        self._lock = threading.Lock()

    def _start(self, slot: WorkerSlot, now_s: float) -> None:
        with self._lock:
            slot.started_s = now_s
        try:
            proc = subprocess.Popen(slot.command, stdin=subprocess.PIPE, env=self.env,
                                    start_new_session=True)
        except OSError as exc:
            log.error("worker %s could not be started: %s", slot.instance, exc)
            with self._lock:
                slot.last_exit = f"not started: {exc}"
            self._failed(slot, now_s, usage=False)
            return
        with self._lock:
            slot.proc = proc
            slot.starts += 1
            if slot.starts > 1:
                self.restarts += 1
        log.info("worker %s started (pid %d%s)", slot.instance, proc.pid,
                 f", start {slot.starts}" if slot.starts > 1 else "")

    def _failed(self, slot: WorkerSlot, now_s: float, *, usage: bool) -> None:
        """Count a worker's exit; schedule its restart or give up."""
        with self._lock:
            ran_s = now_s - slot.started_s
            slot.quick_failures = slot.quick_failures + 1 if ran_s < self.stable_s else 1
            slot.next_start_s = now_s + min(
                self.max_backoff_s, self.first_backoff_s * 2 ** (slot.quick_failures - 1))
        if usage or slot.quick_failures > self.max_quick_failures:
            self.failed = (f"worker {slot.instance} failed {slot.quick_failures} time(s) in a "
                           f"row, last {slot.last_exit}" + (" (bad usage)" if usage else ""))
            log.error("%s: giving up", self.failed)

    def poll(self, now_s: float | None = None) -> bool:
        """Start the workers that are due, notice the ones that exited; False once the
        supervisor has given up (see :attr:`failed`)."""
        now = time.monotonic() if now_s is None else now_s
        for slot in self.slots:
            if self.failed is not None:
                break
            if slot.proc is None:
                if now >= slot.next_start_s:
                    self._start(slot, now)
                continue
            code = slot.proc.poll()
            if code is None:
                continue
            if slot.proc.stdin is not None:
                slot.proc.stdin.close()
            with self._lock:
                slot.proc = None
                slot.last_exit = describe_exit(code)
                slot.exit_codes.append(code)
            self._failed(slot, now, usage=code == USAGE_EXIT)
            if self.failed is None:
                log.warning("worker %s exited (%s) after %.1f s: restart in %.1f s",
                            slot.instance, slot.last_exit, now - slot.started_s,
                            slot.next_start_s - now)
        return self.failed is None

    def stop(self, timeout_s: float = STOP_TIMEOUT_S) -> bool:
        """SIGTERM to every worker, wait for them (``timeout_s`` in all, then SIGKILL);
        True when every running worker exited with code 0."""
        running = [s for s in self.slots if s.proc is not None and s.proc.poll() is None]
        for slot in running:
            assert slot.proc is not None
            with contextlib.suppress(ProcessLookupError):
                slot.proc.send_signal(signal.SIGTERM)
        deadline = time.monotonic() + timeout_s
        clean = True
        for slot in running:
            proc = slot.proc
            assert proc is not None
            try:
                code = proc.wait(max(0.0, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                log.error("worker %s (pid %d) still running %.0f s after SIGTERM: killed",
                          slot.instance, proc.pid, timeout_s)
                proc.kill()
                code = proc.wait()
            if proc.stdin is not None:
                proc.stdin.close()
            with self._lock:
                slot.last_exit = describe_exit(code)
                slot.exit_codes.append(code)
            clean = clean and code == 0
            took_s = timeout_s - max(0.0, deadline - time.monotonic())
            if code != 0:
                log.warning("worker %s stopped with %s after %.1f s", slot.instance,
                            slot.last_exit, took_s)
            else:
                log.info("worker %s stopped after %.1f s", slot.instance, took_s)
        for slot in self.slots:  # the pipes of workers that had exited before
            if slot.proc is not None and slot.proc.stdin is not None:
                slot.proc.stdin.close()
        return clean

    def info(self) -> dict[str, Any]:
        now = time.monotonic()
        with self._lock:
            return {"workers": [s.info(now) for s in self.slots],
                    "worker_restarts": self.restarts}


# ----------------------------------------------------------------------------- the worker side


def set_parent_death_signal(sig: int) -> bool:
    """Ask Linux to send ``sig`` to this process when its parent dies
    (``prctl(PR_SET_PDEATHSIG)``); False elsewhere or when it failed."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        return int(libc.prctl(1, int(sig), 0, 0, 0)) == 0  # 1 = PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        return False


def watch_parent(parent_pid: int, stop: threading.Event) -> threading.Event:
    """A worker's side of the supervision (call from the main thread): set ``stop`` when the
    supervisor ``parent_pid`` goes away, however it ends -- its end of the pipe on our stdin
    closes (end-of-file), and on Linux the kernel sends SIGHUP (``PR_SET_PDEATHSIG``; not
    SIGTERM, which the supervisor sends to stop a worker it outlives). Returns the event set
    when the supervisor is known gone (already gone: at once)."""
    gone = threading.Event()

    def parent_gone(why: str) -> None:
        if not gone.is_set():
            log.warning("the supervising process %d is gone (%s): stopping", parent_pid, why)
        gone.set()
        stop.set()

    if hasattr(signal, "SIGHUP"):  # for the process's life (relayed: see evcal.signals)
        SignalRelay([signal.SIGHUP], lambda _s: parent_gone("SIGHUP"))
        set_parent_death_signal(signal.SIGHUP)
    if os.getppid() != parent_pid:  # it died before the death signal was asked for
        parent_gone("not our parent")
        return gone
    try:
        fd = sys.stdin.fileno() if sys.stdin is not None else -1
    except (OSError, ValueError):
        fd = -1
    if fd < 0:
        return gone

    def watch() -> None:
        try:  # os.read, not sys.stdin: a daemon thread blocked in a buffered reader's lock
            while os.read(fd, 4096):  # aborts the interpreter's shutdown
                pass
        except Exception as exc:  # a closed or broken descriptor means the same
            log.debug("reading the supervisor's pipe: %s", exc)
        parent_gone("its pipe closed")

    threading.Thread(target=watch, name="evcal-supervisor-watch", daemon=True).start()
    return gone


def remove_orphaned_socket(connect: Sequence[str]) -> bool:
    """After a worker whose supervisor died without cleaning up (``kill -9``) stopped: remove
    the supervisor's private socket directory (named in ``connect``); True if it is gone.
    Every worker may try; the first one wins."""
    for ep in connect:
        proto, _, path = ep.partition("/")
        d = Path(path).parent
        if proto == "unixsock-stream" and d.name.startswith(LOCAL_DIR_PREFIX):
            shutil.rmtree(d, ignore_errors=True)
            log.info("the supervisor's socket directory %s %s", d,
                     "removed" if not d.exists() else "could not be removed")
            return not d.exists()
    return False


# ----------------------------------------------------------------------------- the supervisor


def serve_workers(parser: argparse.ArgumentParser, args: argparse.Namespace, *,
                  zenoh: ZenohOptions, prefix: str, instance: str, claims: str,
                  stop: threading.Event, poll_s: float = 0.2) -> int:
    """Run ``args.workers`` workers under a router session opened where ``zenoh`` says,
    until ``stop`` is set; the exit code of ``evcal serve`` (0 clean, 1 a failure)."""
    count = int(args.workers)
    try:
        Signer.from_file(instance or "evcal", args.sign_key)  # a bad key fails here, once
    except SignatureError as exc:
        print(f"evcal serve: {exc}", file=sys.stderr)
        return 1
    env = worker_env()
    runtime = router_runtime(count)
    if runtime is not None:  # read by zenoh when its runtime starts: at the session's open
        os.environ["ZENOH_RUNTIME"] = runtime
    with tempfile.TemporaryDirectory(prefix=LOCAL_DIR_PREFIX) as tmp:
        endpoint = local_endpoint(tmp)
        t = Transport(as_router(zenoh, endpoint))
        try:
            t.open()
        except TransportError as exc:
            print(f"evcal serve: {exc}", file=sys.stderr)
            return 1
        try:
            name = instance or t.zid
            names = [f"{name}-w{i}" for i in range(count)]
            sup = Supervisor(
                [worker_command(parser, args, index=i, count=count, endpoint=endpoint,
                                instance=n) for i, n in enumerate(names)],
                names, env=env)
            _declare(t, sup, prefix=prefix, name=name, claims=claims, names=names)
            log.info("supervisor %s: %d workers, local endpoint %s", name, count, endpoint)
            try:
                ok = sup.poll()
                while ok and not stop.wait(poll_s):
                    ok = sup.poll()
            finally:  # whatever happened, the workers stop before the router
                log.info("stopping %d workers", count)
                clean = sup.stop()
        finally:
            # bounded: a router that zenoh cannot close (its own close gives up after 10 s
            # with "close operation timed out") must not hold up the stop; its links end
            # with this process
            t0 = time.monotonic()
            if not t.close(timeout_s=ROUTER_CLOSE_S):
                log.warning("%s; its links end with this process", t.close_error)
            else:
                log.info("router closed in %.1f s", time.monotonic() - t0)
    if sup.failed is not None:
        print(f"evcal serve: {sup.failed}", file=sys.stderr)
        return 1
    # the exit code says whether every worker stopped cleanly (drained, state and .rrd
    # written); the router holds no state, so its close is reported, not counted
    print(f"evcal serve: stopped; {count} workers, {sup.restarts} restart(s)"
          + (f"; {t.close_error}" if t.close_error else ""), file=sys.stderr)
    return 0 if clean else 1


def _declare(t: Transport, sup: Supervisor, *, prefix: str, name: str, claims: str,
             names: list[str]) -> None:
    """The supervisor's reply on ``<prefix>/cameras`` and its watch of the workers' tokens
    (a log line when one comes or goes; the ``ready`` line once all are up)."""

    def on_cameras(req: Request) -> None:
        doc = {"instance": name, "prefix": prefix, "claims": claims, "supervisor": True,
               "pid": os.getpid(), **sup.info(), "cameras": []}
        req.reply(keys.cameras_key(prefix), strict_dumps(doc).encode(), keys.ENC_CAMERAS)

    t.queryable(keys.cameras_key(prefix), on_cameras, complete=False)
    tokens = {keys.service_token_key(prefix, n.replace("/", "_")): n for n in names}
    up: set[str] = set()
    ready = threading.Event()

    def on_token(key: str, alive: bool) -> None:
        worker = tokens.get(key)
        if worker is None:
            return
        if alive:
            up.add(worker)
            log.info("worker %s up", worker)
        else:
            up.discard(worker)
            log.info("worker %s down", worker)
        if len(up) == len(names) and not ready.is_set():
            ready.set()
            print(f"evcal serve: ready ({name}: {len(names)} workers)", file=sys.stderr,
                  flush=True)

    t.watch_alive(keys.service_token_key(prefix, "*"), on_token)
