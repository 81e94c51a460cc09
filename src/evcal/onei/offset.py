"""OnEI's online estimate of the log offset (``log_offset="auto"``): :class:`OnlineOffset`
decides when to judge, gathers the inputs from the large buffer and runs the criterion
(:func:`~evcal.offline.offset_from_windows` on windows of the buffered intervals) on the
executor's worker thread; the calibrator applies what it finds."""

from __future__ import annotations

import math
from concurrent.futures import Future
from typing import Any

import numpy as np

from ..errors import CalibrationError
from ..solver import usable
from .buffer import LargeBuffer
from .executor import OnEIExecutor

Found = tuple[float, dict[str, Any]]  # the estimate (DN) and how it was found


def offset_windows(pix: np.ndarray, parts: list[tuple[Any, ...]], d: int,
                    saturation_dn: tuple[float, float]) -> tuple[np.ndarray, ...]:
    """The criterion's windows of ``d`` intervals at pixels ``pix`` (sorted) from the
    frames' ``(dense, idx, on, off, last_p, image)``: net polarity, count, change of last
    polarity, the frames at both ends and the weights, ``[window, pixel]``."""
    on = np.zeros((len(parts), pix.size), np.int64)
    off = np.zeros((len(parts), pix.size), np.int64)
    for i, (dense, idx, f_on, f_off, _, _) in enumerate(parts):  # vectorised over pixels
        if dense:
            on[i] = f_on[pix]
            off[i] = f_off[pix]
            continue
        if not idx.size:
            continue
        # the chosen pixels looked up in the interval's sorted pixels (a search per chosen
        # pixel, not a pass over the ~10^5-10^6 that fired)
        at = np.minimum(np.searchsorted(idx, pix), idx.size - 1)
        hit = idx[at] == pix
        on[i, hit] = f_on[at[hit]]
        off[i, hit] = f_off[at[hit]]
    con, coff = np.cumsum(on, 0), np.cumsum(off, 0)
    ks = np.arange(d, len(parts))
    sp = ((con[ks] - coff[ks]) - (con[ks - d] - coff[ks - d])).astype(np.float64)
    se = ((con[ks] + coff[ks]) - (con[ks - d] + coff[ks - d])).astype(np.float64)
    last = np.stack([p[4][pix] for p in parts]).astype(np.float64)
    img = np.stack([p[5][pix] for p in parts]).astype(np.float64)
    ok = usable(img, saturation_dn)
    w = (ok[ks] & ok[ks - d]).astype(np.float64)
    return sp, se, last[ks] - last[ks - d], img[ks - d], img[ks], w


def offset_criterion(pix: np.ndarray, parts: list[tuple[Any, ...]], d: int,
                      saturation_dn: tuple[float, float], grid: tuple[float, float, int]
                      ) -> tuple[float, dict[str, Any]] | None:
    """``offset_from_windows`` on the windows of :func:`offset_windows` (both on the
    worker thread: 1280x720 at 20 M events/s, 69 frames, gathering them took 82 ms in the
    frame path)."""
    from ..offline import offset_from_windows  # noqa: PLC0415 - offline imports solver only

    sp, se, dq, fj, fk, w = offset_windows(pix, parts, d, saturation_dn)
    n_pix = int(pix.size)
    try:
        o, info = offset_from_windows(sp, se, dq, fj, fk, w, offset_grid=grid)
    except CalibrationError:  # nothing to judge by yet (a still scene): ask again later
        return None
    info.update(pixels=n_pix, window_frames=d, source="OnEI buffer")
    return o, info



class OnlineOffset:
    """Where the online offset estimate stands: the offset in use (NaN until estimated), how
    it was found, a sentence for an operator, and the criterion being computed, if any.

    First judged once the buffer holds ``2 d + 1`` frames, then again after 4x, 16x, ... as
    many frames; the inputs are copied on the frame path (milliseconds), the criterion runs on
    the executor's worker thread and its result is taken ``LAG_FRAMES`` frames later (with
    ``OnEIConfig.offset_wait``, waiting for it there: runs are reproducible) or as soon as it
    is done.
    """

    AUTO_WINDOW = 5  # frame intervals per window of the criterion (OffEI's default d)
    # OffEI's grid (1..400 DN, 21 points) extended down to 0.1 DN at the same spacing
    GRID = (0.1, 400.0, 30)
    # frames after a check is started at which its result is applied: the criterion (a
    # fraction of a second at 4 k pixels, more on a busy machine) runs on a worker thread
    # meanwhile
    LAG_FRAMES = 8
    FIRST_FRAMES = 2 * AUTO_WINDOW + 1  # buffered frames before the first estimate
    RECHECK_FACTOR = 4  # re-checked when the frames seen have grown this much
    # frames after a criterion that found nothing to explain (a still scene) before it is
    # computed again (a camera facing a still scene would otherwise recompute it for ever)
    RETRY_FRAMES = 25
    PIXELS = 4000  # busiest pixels the criterion is computed on
    # the first estimate waits for this fraction of the pixels (at most PIXELS) to be busy, or
    # for the large buffer to be full: a first estimate from a few dozen busy pixels of a
    # scene that begins still can be far off, and stays until the next re-check
    FIRST_BUSY = 0.05
    # ... but not for ever: after this many frames it takes the busy pixels there are (a
    # still camera keeps most pixels quiet, and a buffer of the whole stream is never full)
    FIRST_PATIENCE_FRAMES = 32
    MAX_WINDOWS = 64  # the newest windows of the buffer

    def __init__(self, given: float | str) -> None:
        auto = given == "auto"
        # the offset of log(I + offset); NaN until estimated (log_offset="auto")
        self.log_offset = float(given) if not isinstance(given, str) else math.nan
        self.info: dict[str, Any] = {"method": "auto" if auto else "given"}
        self.state = "waiting for frames" if auto else "given"  # for an operator (status)
        self.next_check = 0  # frame count of the next online re-estimate
        # a criterion being computed off the frame path: (frame count to apply it at, job)
        self.job: tuple[int, Future[Found | None]] | None = None

    @property
    def known(self) -> bool:
        return not math.isnan(self.log_offset)

    def due(self, n_frames: int) -> bool:
        """A check should start at frame ``n_frames``."""
        return self.job is None and n_frames >= self.next_check and (
            not self.known or self.next_check > 0)

    def ready(self, n_frames: int, wait: bool) -> bool:
        """The running criterion's result is to be taken at frame ``n_frames`` (``wait``:
        at its frame, waiting for it; otherwise once it is done)."""
        job = self.job
        return job is not None and (n_frames >= job[0] if wait else job[1].done())

    def start(self, buffer: LargeBuffer, n_pixels: int, n_frames: int,
              executor: OnEIExecutor) -> None:
        """Start the criterion on the buffer (if it holds enough to judge by)."""
        first = not self.known
        if first and len(buffer.frames) < self.FIRST_FRAMES:
            self.state = f"waiting for {self.FIRST_FRAMES} buffered frames"
            return
        inputs = self._inputs(buffer, n_pixels)
        if inputs is None:
            if not first:
                self.next_check = n_frames * self.RECHECK_FACTOR
            return
        self.next_check = n_frames * self.RECHECK_FACTOR
        # the module's name looked up now: a test may replace the criterion
        self.job = (n_frames + self.LAG_FRAMES, executor.submit(offset_criterion, *inputs))
        self.state = f"criterion started at frame {n_frames}"

    def take(self, n_frames: int) -> Found | None:
        """The started criterion's result (waiting for it), recorded in :attr:`info` and
        :attr:`state`; None when it found nothing (then asked again later). The caller applies
        the estimate (:attr:`log_offset` is not changed here)."""
        assert self.job is not None
        found = self.job[1].result()
        self.job = None
        if found is None:  # nothing to judge by yet (a still scene): ask again later
            self.next_check = n_frames + self.RETRY_FRAMES
            self.state = (f"no estimate at frame {n_frames}: no window explains a change of "
                          f"the frames (a still scene?); next try at frame {self.next_check}")
            return None
        o, info = found
        self.state = f"estimated at frame {n_frames}"
        info.update(frames_seen=n_frames, previous=None if not self.known else self.log_offset,
                    estimate=o)
        self.info = info
        return found

    def _inputs(self, buffer: LargeBuffer, n_pixels: int) -> tuple[Any, ...] | None:
        """What the criterion is computed from: the busiest pixels and the newest
        ``MAX_WINDOWS + AUTO_WINDOW`` buffered frames' intervals, polarities and images
        (:func:`offset_windows` makes the windows from them)."""
        frames = list(buffer.frames)[-(self.MAX_WINDOWS + self.AUTO_WINDOW):]
        d = min(self.AUTO_WINDOW, len(frames) - 3)
        config = buffer.config
        busy = np.flatnonzero(buffer.sums.counts >= max(config.limits.min_events, 2 * d))
        if d < 1 or busy.size < 10:
            self.state = f"waiting for busy pixels: {busy.size} of 10"
            return None
        need = min(self.PIXELS, self.FIRST_BUSY * n_pixels)
        if not self.known and busy.size < need and buffer.holds_all and \
                len(buffer.frames) < self.FIRST_PATIENCE_FRAMES:
            self.state = (f"waiting for busy pixels: {busy.size} of {need:.0f}, or for "
                          f"{self.FIRST_PATIENCE_FRAMES} frames")
            return None
        rng = np.random.default_rng(0)
        pix = np.sort(rng.choice(busy, size=min(self.PIXELS, busy.size), replace=False))
        # references, not copies: a buffered interval's arrays are never changed, only
        # replaced (forget_interval); the windows are gathered on the worker thread
        parts = [(f.dense, f.idx, f.on, f.off, f.last_p, f.image) for f in frames]
        return pix, parts, int(d), config.saturation_dn, self.GRID
