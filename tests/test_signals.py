"""Signals handled outside their handler (evcal.signals), as the service and clients use them."""

from __future__ import annotations

import os
import signal
import threading
import time

import pytest

from evcal.signals import SignalRelay

pytestmark = [pytest.mark.timeout(60),
              pytest.mark.skipif(not hasattr(signal, "SIGUSR2"), reason="POSIX signals")]


def test_a_signal_arriving_while_the_main_thread_holds_the_events_lock_still_sets_it():
    """The hang a worker met in CI: SIGHUP while its main thread was inside ``Event.set``.
    A handler that set the event itself would wait for the lock its own thread holds; the
    relay sets it from its thread once the main thread lets go."""
    stop = threading.Event()
    got: list[int] = []

    def on_signal(signum: int) -> None:
        got.append(signum)
        stop.set()

    before = signal.getsignal(signal.SIGUSR2)
    relay = SignalRelay([signal.SIGUSR2], on_signal)
    try:
        with stop._cond:  # the main thread inside the event's lock, as in Event.set
            os.kill(os.getpid(), signal.SIGUSR2)
            deadline = time.monotonic() + 0.5
            while time.monotonic() < deadline:  # bytecodes: the handler runs among them
                pass
            assert not stop.is_set()
        assert stop.wait(10)
        assert got == [signal.SIGUSR2]
    finally:
        relay.close()
    assert signal.getsignal(signal.SIGUSR2) is before  # the previous handler is back


def test_a_callback_that_raises_leaves_the_relay_working(caplog):
    calls: list[int] = []
    done = threading.Event()

    def flaky(signum: int) -> None:
        calls.append(signum)
        if len(calls) == 1:
            raise RuntimeError("a bug")
        done.set()

    relay = SignalRelay([signal.SIGUSR2], flaky)
    try:
        os.kill(os.getpid(), signal.SIGUSR2)
        for _ in range(100):
            if calls:
                break
            time.sleep(0.01)
        os.kill(os.getpid(), signal.SIGUSR2)
        assert done.wait(10)
    finally:
        relay.close()
    assert "handling signal" in caplog.text


def test_after_a_stop_a_second_signal_is_ignored_while_the_command_finishes():
    """A command told to stop saves and closes what it holds, then exits: a second stop
    signal in that time (a shell's exit trap signals every job it started, the one already
    stopping too) must not kill it halfway. Without a signal received, close() puts the
    previous handler back as before."""
    before = signal.getsignal(signal.SIGUSR2)
    quiet = SignalRelay([signal.SIGUSR2], lambda _s: None)
    quiet.close(ignore_after_stop=True)
    assert signal.getsignal(signal.SIGUSR2) is before
    relay = SignalRelay([signal.SIGUSR2], lambda _s: None)
    try:
        os.kill(os.getpid(), signal.SIGUSR2)
        assert relay.received.wait(10)
    finally:
        relay.close(ignore_after_stop=True)
    try:
        assert signal.getsignal(signal.SIGUSR2) == signal.SIG_IGN
        os.kill(os.getpid(), signal.SIGUSR2)  # ignored: the default would end the process
    finally:
        signal.signal(signal.SIGUSR2, before)
