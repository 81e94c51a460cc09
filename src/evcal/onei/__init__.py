"""OnEI: online events + intensity calibration with an event-count-driven buffer.

The package, one job per module: ``config`` (:class:`OnEIConfig`), ``executor``
(:class:`OnEIExecutor`, the threads, owned by a calibrator or its caller), ``intake`` (the
open interval and the events waiting for their frame), ``buffer`` (the large buffer: frames,
small buffers, sliding sums), ``equations`` (the blocked normal equations, their queue, the
forgotten history), ``solve`` (the re-solve), ``estimate`` (the smoothed estimate and its
maps), ``offset`` (the online log offset), ``state`` (the state format), ``kernels`` (the
compiled per-pixel loops) and ``calibrator`` (the :class:`OnlineCalibrator` facade and
:func:`onei`).

``evcal.onei`` is this package, and calling it calls the function :func:`onei`:
``evcal.onei(rec)`` (the package-level API, like ``evcal.offei(rec)``) and
``evcal.onei.offset`` (a module) both work, and so do ``from evcal import onei`` (the package,
callable), ``from evcal.onei import onei`` and ``from evcal.online import onei`` (the function).

The stream is cut at frame times into *frame intervals*. The **large buffer** is the sliding
set of the most recent whole frame intervals holding at most ``n_large`` events; when a new
interval makes it overflow, the oldest intervals are dropped (the paper's rule). The large
buffer is split into **small buffers** of about ``n_small`` events, each one equation per
pixel: ``dL = c (P + lam Q) + b (E + lam A)`` between the frame that opens it and the frame
that closes it (the OffEI equation with its residual correction, :mod:`evcal.offline`).

The split overlaps: a small buffer opens at *every* frame of the large buffer and closes at the
first later frame by which it holds ``n_small`` events. This is OffEI's overlapping windows
with an event-count instead of a frame-count window, and it is what brings OnEI's error close
to OffEI's: a disjoint split gives each pixel ~``n_large / n_small`` equations, each carrying a
full sub-threshold residual at both ends; the overlapping split uses every frame of the buffer
(the two compared: docs/MEASUREMENTS.md).

The per-pixel normal equations (:class:`~evcal.solver.NormalEquations`' sums) are updated
incrementally: a small buffer's equation is added when it closes and subtracted, recomputed
bit-identically from the same stored data, when the frame that opened it leaves the large
buffer; every ``rebuild_every`` removals they are rebuilt from the buffer to shed rounding.
That is rare by default (100 k removals, 67 minutes at 25 Hz): the cross products of counts
and polarities are integers, exact in float64, and only those with ``dL`` round; measured
after 3,000 removals they differ from a rebuild by 3e-15 of their size. A rebuild costs a
frame the work of every equation in the buffer (30 ms at 346x260 with 87 frames buffered),
a latency spike a live service should not see every 20 s.
Per frame the cost is that of the frame's events and pixels, not of the buffer's: two sliding
sums hold the counts of the small buffer closing next and of the one leaving (each interval
enters and leaves each sum once); an equation is queued as those counts, its polarity
regressors and its two frame values (``PENDING_SLOTS`` at most), and the queue is added to the
normal equations at the next solve, block by block in cache, each block then solved at once
(:mod:`evcal.onei.kernels`; the same operations in the same order as adding the equations
one by one, and :mod:`evcal.solver`'s own per-pixel kernels).

State, bounded whatever the rates. Per buffered frame (at most ``max_buffer_frames``): its raw
image and the polarity of each pixel's last event (itemsize + 1 bytes per pixel), and the ON/OFF
counts of the interval that ended at it, sparse (12 bytes per pixel that fired) or, when more
than 2/3 of the pixels fired, dense (8 bytes per pixel): at most 12 bytes per event of the
buffer (``n_large`` events' worth, but for an interval holding more on its own). Per pixel
besides: the normal equations 128 B, the queued equations 72 B (8-bit frames; 120 B for
others), the sliding sums 16 B, the open interval (packed counts, spills, last polarities)
10 B, the buffer's counts 8 B, the smoothed estimate 42 B and the residual-lambda terms 16 B:
292 B per pixel, 292 MB per megapixel (340 MB for frames other than 8-bit).

After every ``n_small`` new events (once a new equation closed) the per-pixel system is
re-solved and the estimate low-pass filtered: ``est <- (1 - smoothing) est + smoothing new`` on
pixels whose new solution is valid, with a start-up correction: a pixel's first
``1 / smoothing`` solutions are averaged with equal weights. The default smoothing 0.1 gives
the filter a memory of about ``10 n_small`` events, close to one large buffer at the paper's
sizes; the estimate follows a change of thresholds within about two large buffers.

Streaming contract: :meth:`OnlineCalibrator.feed_events` takes sorted chunks, time never going
back across chunks; frames may arrive late with respect to events (events after the latest
frame wait in a bounded pending buffer until the frame that closes their interval arrives).
:meth:`OnlineCalibrator.mark_gap` says events were lost: no small buffer spans the loss.
"""

import inspect
import sys
import types

from .calibrator import OnlineCalibrator, onei
from .config import MAX_SOLVE_THREADS, OnEIConfig, usable_cores
from .equations import PENDING_SLOTS
from .estimate import LowPassEstimate
from .executor import PIXELS_PER_THREAD, RANGES_PER_THREAD, OnEIExecutor
from .state import STATE_FORMAT

__all__ = [
    "MAX_SOLVE_THREADS",
    "PENDING_SLOTS",
    "PIXELS_PER_THREAD",
    "RANGES_PER_THREAD",
    "STATE_FORMAT",
    "LowPassEstimate",
    "OnEIConfig",
    "OnEIExecutor",
    "OnlineCalibrator",
    "onei",
    "usable_cores",
]


class _CallablePackage(types.ModuleType):
    """The class of this package's module: ``evcal.onei(...)`` is :func:`onei` (``evcal.onei``
    names both the package and the function, and the package must stay reachable as an
    attribute for ``evcal.onei.offset``, ``import evcal.onei as m`` and ``mock.patch``)."""

    __call__ = staticmethod(onei)
    __signature__ = inspect.signature(onei)  # help() and inspect see onei's parameters


sys.modules[__name__].__class__ = _CallablePackage
