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
    one-time cost, such as a render). The time left is the work left at the rate so far."""

    EVERY_S = 10.0

    def __init__(self, total: float | None, desc: str, *, unit: str, quiet: bool = False,
                 tty: bool | None = None, decimals: int = 0, skip_first: bool = False,
                 opening: str | None = None) -> None:
        self.desc = desc
        self.unit = unit
        self.total = None if total is None else float(total)
        self.done = 0.0
        self._fmt = f"{{:.{decimals}f}}"
        self._t0 = self._last = time.monotonic()
        self._skip_first = skip_first
        self._first: tuple[float, float] | None = None  # (time, work) where the rate starts
        self._quiet = quiet
        self._bar: Any = None
        if not quiet and (sys.stderr.isatty() if tty is None else tty):
            from tqdm import tqdm  # noqa: PLC0415

            n = f"{{n:.{decimals}f}}"
            self._bar = tqdm(total=self._bar_total(), desc=f"{desc} ({unit})", file=sys.stderr,
                             leave=False, bar_format="{l_bar}{bar}| " + n + "/{total} "
                             "[{elapsed}<{remaining}]")
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

    def line(self) -> str:
        now = time.monotonic()
        done = self._fmt.format(self.done)
        head = f"{done} {self.unit}" if self.total is None else \
            f"{done} of {self._fmt.format(self.total)} {self.unit}"
        line = f"{head}, {_clock(now - self._t0)} elapsed"
        if self.total is None:
            return line
        left = float("nan")
        if self._first is not None and self.done > self._first[1]:
            # never negative: work done beyond the plan (renewed only each round) is done
            left = max(self.total - self.done, 0.0) * (now - self._first[0]) / (
                self.done - self._first[1])
        return f"{line}, about {_clock(left)} left"

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
