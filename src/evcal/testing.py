"""Helpers for tests, benchmarks and the demo: free ports, service subprocesses, polling.

Every session they open is on ``tcp/127.0.0.1`` with multicast scouting off.
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any, Protocol, TypeVar

T = TypeVar("T")


class _Cameras(Protocol):
    """What :func:`settle` reads of a service (the core never imports the service layer)."""

    @property
    def cameras(self) -> Mapping[str, Any]: ...


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def endpoint(port: int) -> str:
    return f"tcp/127.0.0.1:{port}"


def wait_for(fn: Callable[[], T], *, timeout_s: float = 30.0, interval_s: float = 0.1,
             what: str = "condition") -> T:
    """Call ``fn`` until it returns a truthy value; TimeoutError after ``timeout_s``."""
    deadline = time.monotonic() + timeout_s
    last_exc: Exception | None = None
    while True:
        try:
            value = fn()
            if value:
                return value
        except Exception as exc:  # keep polling; report the last failure
            last_exc = exc
        if time.monotonic() > deadline:
            raise TimeoutError(f"{what} not reached within {timeout_s:g} s"
                               + (f" (last error: {last_exc})" if last_exc else ""))
        time.sleep(interval_s)


def settle(service: _Cameras, timeout_s: float = 20.0) -> None:
    """Wait until every camera of an in-process ``service`` has processed every message it
    was given and published what they produced; TimeoutError after ``timeout_s``."""
    wait_for(lambda: not any(c.in_flight for c in service.cameras.values()),
             timeout_s=timeout_s, interval_s=0.01, what="every camera's messages processed")


def python_env() -> dict[str, str]:
    """The environment of child Python processes (evcal must be installed, e.g. ``-e .``)."""
    env = dict(os.environ)
    env["PYTHONUNBUFFERED"] = "1"
    return env


class ServiceProcess:
    """``python -m evcal.service ARGS`` as a child process (a context manager).

    ``stop()`` sends SIGTERM and waits; ``kill()`` sends SIGKILL (no clean-up at all).
    """

    def __init__(self, args: Sequence[str], *, log_path: str | Path | None = None):
        self.args = list(args)
        self.log_path = Path(log_path) if log_path else None
        self.proc: subprocess.Popen[bytes] | None = None
        self._log: Any = None

    def start(self) -> ServiceProcess:
        out: Any = subprocess.DEVNULL
        if self.log_path is not None:
            self._log = open(self.log_path, "ab")
            out = self._log
        self.proc = subprocess.Popen([sys.executable, "-m", "evcal.service", *self.args],
                                     stdout=out, stderr=out, env=python_env())
        return self

    def __enter__(self) -> ServiceProcess:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.kill()
        if self._log is not None:
            self._log.close()

    @property
    def pid(self) -> int:
        assert self.proc is not None
        return self.proc.pid

    def alive(self) -> bool:
        return self.proc is not None and self.proc.poll() is None

    def stop(self, timeout_s: float = 30.0) -> int:
        assert self.proc is not None
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
        return self.proc.wait(timeout_s)

    def kill(self) -> int:
        assert self.proc is not None
        if self.proc.poll() is None:
            self.proc.kill()
        return self.proc.wait(10)

    def log_text(self) -> str:
        if self.log_path is None or not self.log_path.exists():
            return ""
        return self.log_path.read_text(errors="replace")


def run_client(module: str, args: Sequence[str], *, timeout_s: float = 120.0
               ) -> subprocess.CompletedProcess[str]:
    """``python -m evcal.clients.<module> ARGS``, captured."""
    return subprocess.run([sys.executable, "-m", f"evcal.clients.{module}", *args],
                          capture_output=True, text=True, timeout=timeout_s, env=python_env())
