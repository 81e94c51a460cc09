"""Signals handled outside their handler (standard library only).

Python runs a signal handler in the main thread between two bytecodes, wherever that thread
is, possibly inside ``threading.Event.set`` with the event's lock held: a handler that sets
the same event (or any lock the main thread holds) then waits for itself for ever. A worker
of ``evcal serve --workers`` hung so in CI: its supervisor was killed, SIGHUP arrived while
its main thread was in ``Event.set``, and the handler's own ``Event.set`` blocked on the
event's lock (the stacks: ``tests/test_service_workers_e2e.py``). So the handlers installed
here only write the signal's number to a pipe (``os.write``: no Python lock); a daemon thread
reads it and calls the callback there, where taking locks is safe.
"""

from __future__ import annotations

import logging
import os
import signal
import threading
from collections.abc import Callable, Iterable
from typing import Any

log = logging.getLogger("evcal")


class SignalRelay:
    """``callback(signum)`` on a thread of its own for each of ``signums`` received, until
    :meth:`close` (which puts the previous handlers back). Install from the main thread."""

    def __init__(self, signums: Iterable[int], callback: Callable[[int], None]) -> None:
        self._callback = callback
        self.received = threading.Event()  # a signal has arrived (any of ``signums``)
        self._r, self._w = os.pipe()
        os.set_blocking(self._w, False)  # a full pipe drops a signal, never blocks
        self._thread = threading.Thread(target=self._run, name="evcal-signals", daemon=True)
        self._thread.start()
        self._old: dict[int, Any] = {}
        for s in signums:
            self._old[s] = signal.signal(s, self._handler)

    def _handler(self, signum: int, _frame: object) -> None:
        try:
            os.write(self._w, bytes([signum & 0xFF]))
        except OSError:  # closed or full: the signals before it are being handled
            pass

    def _run(self) -> None:
        try:
            while data := os.read(self._r, 64):
                for signum in data:
                    self.received.set()
                    try:
                        self._callback(signum)
                    except Exception:  # a callback's bug must not end the relay
                        log.exception("handling signal %d", signum)
        finally:
            os.close(self._r)

    def close(self, *, ignore_after_stop: bool = False) -> None:
        """Put the previous handlers back; the relay thread ends.

        ``ignore_after_stop``: when a signal has arrived (the command is stopping), ignore
        these signals from now on instead: the command is finishing what the first one
        asked for (its state saved, its files closed, its threads joined at exit), and a
        second one, with the default handler back, would kill it halfway with status 143
        (a supervisor or a shell's exit trap signals every job it started, including one
        already told to stop). SIGKILL still ends it."""
        ignore = ignore_after_stop and self.received.is_set()
        for s, h in self._old.items():
            signal.signal(s, signal.SIG_IGN if ignore else h)
        self._old.clear()
        if self._w >= 0:
            os.close(self._w)  # end of file for the relay thread
            self._w = -1


STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)  # what stops a command
