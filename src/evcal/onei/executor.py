"""OnEI's threads: :class:`OnEIExecutor`, an object with an explicit lifecycle.

A calibrator makes one unless its caller passes one in (the caller then owns it and closes
it); :meth:`OnEIExecutor.close` (or a ``with`` block) shuts its threads down. It is safe
across ``fork``: a forked child has none of the parent's threads, so an executor used there
first forgets the parent's pools and starts its own (a pool that believed it had threads would
never run a job, and a re-solve would wait forever). A closed executor runs everything on the
caller's thread: the results are the same with any number of threads.
"""

from __future__ import annotations

import itertools
import os
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from types import TracebackType
from typing import Any, TypeVar

import numpy as np

from .config import MAX_SOLVE_THREADS, usable_cores

# a per-frame pass over the pixels is split over threads only when each gets this many
# (handing a range to a pool thread and waiting for it costs tens of microseconds: at 346x260
# a frame's passes take about that each)
PIXELS_PER_THREAD = 1 << 17
RANGES_PER_THREAD = 4  # a threaded pass's ranges per thread (see OnEIExecutor.on_threads)

T = TypeVar("T")


class OnEIExecutor:
    """The threads of OnEI's passes over the pixels, and one worker thread for the online
    offset criterion (numpy releases the GIL in its array work, so the frame path goes on
    meanwhile).

    ``threads`` (0: the cores this process may use) is capped at ``MAX_SOLVE_THREADS``; pool
    threads start when first needed.
    """

    def __init__(self, threads: int = 0) -> None:
        self.n_threads = max(1, min(threads or usable_cores(), MAX_SOLVE_THREADS))
        self._solve: ThreadPoolExecutor | None = None
        self._offset: ThreadPoolExecutor | None = None
        self._pid = os.getpid()
        self.closed = False

    def __enter__(self) -> OnEIExecutor:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()

    def close(self) -> None:
        """Shut the threads down (waiting for a running job); later work runs on the caller's
        thread. Idempotent."""
        self.closed = True
        pools, self._solve, self._offset = (self._solve, self._offset), None, None
        if os.getpid() != self._pid:  # a forked child: the parent's threads are not here
            return
        for pool in pools:
            if pool is not None:
                pool.shutdown(wait=True)

    def _forget_after_fork(self) -> None:
        if os.getpid() != self._pid:
            self._solve = self._offset = None
            self._pid = os.getpid()

    def _solve_pool(self) -> ThreadPoolExecutor:
        self._forget_after_fork()
        if self._solve is None:
            self._solve = ThreadPoolExecutor(max_workers=max(1, self.n_threads - 1),
                                             thread_name_prefix="evcal-solve")
        return self._solve

    def submit(self, fn: Callable[..., T], *args: Any) -> Future[T]:
        """``fn(*args)`` on the offset worker thread (done at once when closed)."""
        if self.closed:
            done: Future[T] = Future()
            try:
                done.set_result(fn(*args))
            except BaseException as exc:  # the caller sees it from result(), as from a thread
                done.set_exception(exc)
            return done
        self._forget_after_fork()
        if self._offset is None:
            self._offset = ThreadPoolExecutor(max_workers=1, thread_name_prefix="evcal-offset")
        return self._offset.submit(fn, *args)

    def threads_for(self, n_items: int, per_thread: int = 1) -> int:
        """The threads :meth:`on_threads` uses for ``n_items`` (each at least ``per_thread``)."""
        if self.closed:
            return 1
        return max(1, min(self.n_threads, n_items // max(1, per_thread)))

    def on_threads(self, n_items: int, work: Callable[[int, int, int], None],
                   per_thread: int = 1) -> None:
        """``work(thread, lo, hi)`` over contiguous ranges of ``n_items`` on
        :meth:`threads_for` threads (this one among them, ``thread`` 0 .. n - 1: the index of
        the caller's scratch); which thread does which range varies from call to call (the
        ranges' results may not depend on it)."""
        n_threads = self.threads_for(n_items, per_thread)
        if n_threads == 1:
            work(0, 0, n_items)
            return
        # more ranges than threads, each thread taking the next range left: a thread the
        # machine holds back (a busy core) delays the pass by one range, not by its share
        n_ranges = min(n_items, n_threads * RANGES_PER_THREAD)
        cuts = np.linspace(0, n_items, n_ranges + 1).round().astype(np.int64).tolist()
        next_range = itertools.count()  # next() is atomic under the GIL

        def take(i: int) -> None:
            while (r := next(next_range)) < n_ranges:
                work(i, cuts[r], cuts[r + 1])

        pool = self._solve_pool()
        futures = [pool.submit(take, i) for i in range(1, n_threads)]
        try:
            take(0)
        finally:
            for f in futures:
                f.result()

    def on_pixels(self, n_items: int, work: Callable[[int, int, int], None]) -> None:
        """:meth:`on_threads` for a pass over ``n_items`` pixels (or entries of distinct
        pixels), threaded once each thread gets ``PIXELS_PER_THREAD``."""
        self.on_threads(n_items, work, PIXELS_PER_THREAD)

    def split(self, n_items: int, work: Callable[[int, int], None]) -> None:
        """A per-frame pass ``work(lo, hi)`` over ranges of ``n_items`` (:meth:`on_pixels`)."""
        self.on_pixels(n_items, lambda _i, lo, hi: work(lo, hi))
