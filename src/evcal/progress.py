"""Progress of a long command on stderr: a tqdm bar on a terminal, else a line every
:attr:`Progress.EVERY_S` seconds (logs and CI see progress too), with the time left when the
total is known."""

from __future__ import annotations

import sys
import time
from typing import Any


class Progress:
    """``done`` of ``total`` (``None``: unknown) in ``unit``; ``decimals`` for fractional
    work. ``skip_first``: the rate is taken after the first update (when that one also pays a
    one-time cost, such as a render). The time left is the work left at the rate so far;
    with ``forecasts`` the caller says when it expects to end (:meth:`forecast`) and the time
    left is that, unknown ("?") until the first forecast (a run whose phases take
    different times per unit of work: its rate so far says little of what is left)."""

    EVERY_S = 10.0

    def __init__(self, total: float | None, desc: str, *, unit: str, quiet: bool = False,
                 tty: bool | None = None, decimals: int = 0, skip_first: bool = False,
                 opening: str | None = None, forecasts: bool = False) -> None:
        self.desc = desc
        self.unit = unit
        self.total = None if total is None else float(total)
        self.done = 0.0
        self._fmt = f"{{:.{decimals}f}}"
        self._t0 = self._last = time.monotonic()
        self._skip_first = skip_first
        self._first: tuple[float, float] | None = None  # (time, work) where the rate starts
        self._quiet = quiet
        self._forecasts = forecasts
        self._end: float | None = None  # the time.monotonic() the caller expects to end at
        self._bar: Any = None
        if not quiet and (sys.stderr.isatty() if tty is None else tty):
            from tqdm import tqdm  # noqa: PLC0415

            n = f"{{n:.{decimals}f}}"
            left = "{postfix}" if forecasts else "<{remaining}"
            self._bar = tqdm(total=self._bar_total(), desc=f"{desc} ({unit})", file=sys.stderr,
                             leave=False, bar_format="{l_bar}{bar}| " + n + "/{total} "
                             "[{elapsed}" + left + "]")
            if forecasts:
                self._bar.set_postfix_str("about ? left")
        elif not quiet and opening is not None:
            # a line at once: the first update may be a minute away (``opening`` says why)
            print(f"evcal {desc}: {self.line()}; {opening}", file=sys.stderr, flush=True)

    def _bar_total(self) -> float | None:
        return None if self.total is None else round(self.total, 1)

    def update(self, work: float = 1.0) -> None:
        """``work`` more done."""
        self.set(self.done + work)

    def set(self, done: float, total: float | None = None) -> None:
        """``done`` in all (and the ``total``, when it changes)."""
        if total is not None:
            self.plan(total)
        if self._first is None:
            self._first = (time.monotonic(), done) if self._skip_first else (self._t0, 0.0)
        step = done - self.done
        self.done = float(done)
        if self._bar is not None:
            if self._forecasts:
                self._bar.set_postfix_str(f"about {_clock(self.left())} left", refresh=False)
            self._bar.update(step)
        elif not self._quiet and time.monotonic() - self._last >= self.EVERY_S:
            self._last = time.monotonic()
            print(f"evcal {self.desc}: {self.line()}", file=sys.stderr, flush=True)

    def plan(self, total: float) -> None:
        """The total work, as now planned (never below what is done)."""
        self.total = max(float(total), self.done)
        if self._bar is not None:
            self._bar.total = self._bar_total()
            self._bar.refresh()

    def forecast(self, end: float) -> None:
        """The caller expects to end at ``end`` (a ``time.monotonic()``)."""
        self._end = float(end)
        if self._bar is not None:
            self._bar.set_postfix_str(f"about {_clock(self.left())} left")

    def left(self) -> float:
        """Seconds left (NaN while unknown), never negative: with forecasts the time to the
        forecast end (0 once it has passed: the caller's next forecast moves it), else the
        work left at the rate so far."""
        now = time.monotonic()
        if self._forecasts:
            return float("nan") if self._end is None else max(self._end - now, 0.0)
        if self.total is None or self._first is None or self.done <= self._first[1]:
            return float("nan")
        # never negative: work done beyond the plan (renewed only each round) is done
        return max(self.total - self.done, 0.0) * (now - self._first[0]) / (
            self.done - self._first[1])

    def line(self) -> str:
        now = time.monotonic()
        done = self._fmt.format(self.done)
        head = f"{done} {self.unit}" if self.total is None else \
            f"{done} of {self._fmt.format(self.total)} {self.unit}"
        line = f"{head}, {_clock(now - self._t0)} elapsed"
        if self.total is None and not self._forecasts:
            return line
        return f"{line}, about {_clock(self.left())} left"

    def close(self) -> None:
        if self._bar is not None:
            self._bar.close()

    def __enter__(self) -> Progress:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _clock(seconds: float) -> str:
    if not seconds == seconds:  # NaN: no rate yet
        return "?"
    m, sec = divmod(int(round(seconds)), 60)
    return f"{m // 60}:{m % 60:02d}:{sec:02d}" if m >= 60 else f"{m}:{sec:02d}"
