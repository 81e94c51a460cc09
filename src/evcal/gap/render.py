"""The latent intensity of a recording, rendered once and shared by every simulation.

Every model the gap workflow evaluates is simulated on the same input: the measured frames,
interpolated (along the optical flow, :mod:`.flow`) at the same internal sample times. Only
the model (maps, effects) and the seed change between simulations. Interpolating along the
flow costs several image warps per sample time, far more than the simulator's kernel, so the
sequence is rendered once into memory (:class:`RenderCache`) and every simulation reads it
(:class:`CachedSource`). Per-seed randomness of the input (the quantisation dither) is added
on the way out.

Float32 while the sequence fits a quarter of ``max_bytes`` at 4 bytes a value, 16-bit fixed
point while it fits ``max_bytes`` at 2; beyond that nothing is cached and each simulation
renders again (the workflow keeps its working window small enough that this does not happen:
``GapConfig.max_pixel_steps``). The fixed point spans the range of the interpolator's frames
(its blends are convex, so no rendered value leaves it) in 65,535 steps: 0.004 DN for 8-bit
frames, a log-intensity step at least 25x below the smallest thresholds once the log offset
(at least 1 DN) is added. It is read back with one multiply-add, where float16 (the fallback
for a source that does not say its range) takes a conversion several times slower, once per
simulation over the whole sequence.
"""

from __future__ import annotations

import hashlib
import threading
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from ..errors import ConfigError
from ..recording import Frames
from ..sim.sources import FrameInterpolator

# bytes of rendered intensity kept at most (float32 up to a quarter of it per sequence,
# float16 above: the workflow renders a sequence per frame-side candidate besides the one
# every other simulation reads)
DEFAULT_MAX_BYTES = 1 << 30


def frames_key(frames: Frames, interpolation: str, times_us: np.ndarray) -> bytes:
    """Content key of a rendered sequence: the frames' pixels and times, the interpolation
    and the sample times."""
    h = hashlib.blake2b(digest_size=16)
    h.update(np.ascontiguousarray(frames.images).tobytes())
    h.update(np.ascontiguousarray(frames.t_us, np.int64).tobytes())
    h.update(np.ascontiguousarray(times_us, np.int64).tobytes())
    h.update(f"{interpolation},{frames.images.dtype},{frames.images.shape}".encode())
    return h.digest()


class CachedSource:
    """A source (``t_s -> [H, W]`` DN) reading a rendered sequence, plus a per-pixel offset
    (the seed's dither), floored at 0. Only the cached sample times can be asked for.

    ``lag_s``: the sequence of the same frames stamped ``lag_s`` later (the ``exposure``
    effect's lag), read as the rendered one at ``t - lag_s``: between two sample times by
    linear interpolation, before the first held at it (as an interpolator holds the first
    frame)."""

    def __init__(self, data: np.ndarray, times_s: np.ndarray, add: np.ndarray | None,
                 lag_s: float = 0.0, scale: tuple[float, float] | None = None):
        self._data = data
        self._times_s = times_s
        self._add = None if add is None else np.asarray(add, np.float32)
        self._lag_s = float(lag_s)
        # fixed-point data (see the module doc): value = stored * step + low
        self._scale = None if scale is None else (np.float32(scale[0]), np.float32(scale[1]))

    def _read(self, i: int, out: np.ndarray) -> None:
        """Sample ``i`` of the sequence into ``out`` (float32)."""
        if self._scale is None:
            np.copyto(out, self._data[i], casting="unsafe")
            return
        step, low = self._scale
        np.multiply(self._data[i], step, out=out)
        if low != 0.0:
            out += low

    def _index(self, ts: np.ndarray) -> np.ndarray:
        i = np.searchsorted(self._times_s, ts)
        i = np.clip(i, 0, self._times_s.size - 1)
        # the simulator asks with times_us * 1e-6: the same floats the cache was keyed with
        if not np.array_equal(self._times_s[i], ts):
            bad = ts[self._times_s[i] != ts][:3]
            raise ConfigError(f"times {bad.tolist()} s are not among the rendered sample times")
        return i

    def render_block(self, t_s: np.ndarray | list[float], out: np.ndarray | None = None
                     ) -> np.ndarray:
        ts = np.asarray(t_s, np.float64).reshape(-1)
        idx = self._index(ts)
        shape = (ts.size, *self._data.shape[1:])
        if out is None:
            out = np.empty(shape, np.float32)
        elif out.shape != shape or out.dtype != np.float32:
            raise ConfigError(f"out has shape {out.shape}, dtype {out.dtype}; expected "
                             f"float32 {shape}")
        if self._lag_s != 0.0:
            self._shifted(ts, out)
        else:
            for j, i in enumerate(idx):  # one frame copy per sample time, over pixels
                self._read(int(i), out[j])
        if self._add is not None:
            out += self._add[None]
        if self._add is not None:
            np.maximum(out, 0.0, out=out)
        return out

    def _shifted(self, ts: np.ndarray, out: np.ndarray) -> None:
        times = self._times_s
        u = ts - self._lag_s
        k = np.clip(np.searchsorted(times, u, side="right") - 1, 0, times.size - 1)
        k1 = np.minimum(k + 1, times.size - 1)
        span = np.where(k1 > k, times[k1] - times[k], 1.0)
        w = np.clip((u - times[k]) / span, 0.0, 1.0).astype(np.float32)
        nxt = np.empty(out.shape[1:], np.float32)
        for j in range(ts.size):  # per sample time, vectorised over pixels
            self._read(int(k[j]), out[j])
            if w[j] > 0.0:
                self._read(int(k1[j]), nxt)
                out[j] *= 1.0 - w[j]
                nxt *= w[j]
                out[j] += nxt

    def __call__(self, t_s: float) -> np.ndarray:
        one: np.ndarray = self.render_block([t_s])[0]
        return one


class RenderCache:
    """Rendered sequences by content (:func:`frames_key`), least recently used dropped first
    while the total exceeds ``max_bytes``. ``make_source(frames)`` builds the interpolator of
    a key's frames when it must be rendered."""

    def __init__(self, max_bytes: int = DEFAULT_MAX_BYTES,
                 on_use: Callable[[float], None] | None = None, workers: int = 1):
        self.max_bytes = int(max_bytes)
        # threads rendering a sequence's blocks at once (the warps of the flow interpolation
        # run in OpenCV and numpy without the GIL; the other simulations wait for the render)
        self.workers = max(1, int(workers))
        # called once per source served (one per simulation), with the share of the
        # sensor's rows it serves
        self._on_use = on_use
        # key -> (data, sample times in s, fixed-point (step, low) or None)
        self._entries: dict[bytes, tuple[np.ndarray, np.ndarray, tuple[float, float] | None]] = {}
        self.renders = 0  # sequences rendered (for the benchmark and the tests)
        self.hits = 0
        self._lock = threading.Lock()

    def nbytes(self) -> int:
        return sum(e[0].nbytes for e in self._entries.values())

    def source(self, key: bytes, times_us: np.ndarray, shape: tuple[int, int],
               make_source: Callable[[], FrameInterpolator], add: np.ndarray | None = None,
               rows: slice | None = None, lag_s: float = 0.0) -> CachedSource | _Offset:
        """The cached sequence of ``key`` as a source, rendered now if it is new; when it
        cannot be kept within ``max_bytes`` the interpolator itself (no cache). ``rows``:
        the source of those sensor rows only (``add`` is theirs), read from the whole
        sequence's render. ``lag_s``: of the same frames stamped that much later (see
        :class:`CachedSource`; ``make_source`` then makes the unlagged interpolator)."""
        with self._lock:  # simulations on several threads: one renders, the others wait
            src = self._source(key, times_us, shape, make_source, add, rows, lag_s)
        if self._on_use is not None:
            self._on_use(1.0 if rows is None else
                         len(range(*rows.indices(shape[0]))) / shape[0])
        return src

    def _source(self, key: bytes, times_us: np.ndarray, shape: tuple[int, int],
                make_source: Callable[[], FrameInterpolator], add: np.ndarray | None,
                rows: slice | None, lag_s: float) -> CachedSource | _Offset:
        times_s = np.asarray(times_us, np.int64) * 1e-6
        band = slice(None) if rows is None else rows
        hit = self._entries.get(key)
        if hit is not None:
            self.hits += 1
            self._entries[key] = self._entries.pop(key)  # most recently used last
            return CachedSource(hit[0][:, band], hit[1], add, lag_s, hit[2])
        if rows is not None:
            # a band of a sequence not rendered whole (a frame-side candidate screened on
            # the band): the band's rows only, when the interpolator can render them alone
            band_key = key + f"rows {rows.start}:{rows.stop}".encode()
            hit = self._entries.get(band_key)
            if hit is not None:
                self.hits += 1
                self._entries[band_key] = self._entries.pop(band_key)
                return CachedSource(hit[0], hit[1], add, lag_s, hit[2])
            src = make_source()
            only_rows = getattr(src, "only_rows", None)
            if only_rows is not None:
                n_rows = len(range(*rows.indices(shape[0])))
                got = self._render(only_rows(rows), times_s, (n_rows, shape[1]))
                if got is None:
                    return _Offset(src, add, None, lag_s)  # not kept: rendered per use
                self._entries[band_key] = (got[0], times_s, got[1])
                return CachedSource(got[0], times_s, add, lag_s, got[1])
        n_values = times_s.size * shape[0] * shape[1]
        if 2 * n_values > self.max_bytes:
            return _Offset(make_source(), add, rows, lag_s)
        got = self._render(make_source(), times_s, shape)
        assert got is not None
        self._entries[key] = (got[0], times_s, got[1])
        return CachedSource(got[0][:, band], times_s, add, lag_s, got[1])

    def _render(self, src: FrameInterpolator, times_s: np.ndarray, shape: tuple[int, int]
                ) -> tuple[np.ndarray, tuple[float, float] | None] | None:
        """``src`` rendered at ``times_s`` (room made for it) and its fixed-point scale
        (``None``: stored as floats), or None when it cannot be kept."""
        n_values = times_s.size * shape[0] * shape[1]
        if 2 * n_values > self.max_bytes:
            return None
        scale: tuple[float, float] | None = None
        dtype: type[np.generic] = np.float32
        if 4 * n_values > self.max_bytes // 4:
            images = getattr(src, "images", None)
            dtype = np.float16
            if images is not None and np.asarray(images).size:
                low, high = float(np.min(images)), float(np.max(images))
                if np.isfinite(low) and np.isfinite(high):
                    dtype = np.uint16
                    scale = (max(high - low, 1e-6) / 65535.0, low)
        while self._entries and self.nbytes() + n_values * np.dtype(dtype).itemsize \
                > self.max_bytes:
            self._entries.pop(next(iter(self._entries)))
        data = np.empty((times_s.size, *shape), dtype)
        block = 64
        starts = list(range(0, times_s.size, block))
        n_threads = min(self.workers, len(starts))

        def render_blocks(part: int) -> None:
            buf = np.empty((block, *shape), np.float32)
            for k in starts[part::n_threads]:
                n = min(block, times_s.size - k)
                rendered = src.render_block(times_s[k:k + n], out=buf[:n])
                if scale is not None:
                    step, low = scale
                    rendered -= np.float32(low)
                    rendered *= np.float32(1.0 / step)
                    np.rint(rendered, out=rendered)
                    np.clip(rendered, 0.0, 65535.0, out=rendered)
                data[k:k + n] = rendered

        if n_threads == 1:
            render_blocks(0)
        else:
            with ThreadPoolExecutor(max_workers=n_threads) as pool:
                list(pool.map(render_blocks, range(n_threads)))
        self.renders += 1
        return data, scale


class _Offset:
    """An uncached source plus a per-pixel offset, floored at 0 (as :class:`CachedSource`)."""

    def __init__(self, src: FrameInterpolator, add: np.ndarray | None,
                 rows: slice | None = None, lag_s: float = 0.0):
        self._src = src
        self._add = None if add is None else np.asarray(add, np.float32)
        self._rows = rows
        self._lag_s = float(lag_s)

    def render_block(self, t_s: np.ndarray | list[float], out: np.ndarray | None = None
                     ) -> np.ndarray:
        if self._lag_s != 0.0:  # the unlagged interpolator at the earlier times
            t_s = np.asarray(t_s, np.float64) - self._lag_s
        if self._rows is None:
            res: np.ndarray = self._src.render_block(t_s, out=out)
        else:  # the whole frame rendered, its rows kept
            full = self._src.render_block(t_s)[:, self._rows]
            res = full.copy() if out is None else out
            if res is out:
                np.copyto(out, full)
        if self._add is not None:
            res += self._add[None]
            np.maximum(res, 0.0, out=res)
        return res

    def __call__(self, t_s: float) -> np.ndarray:
        one: np.ndarray = self.render_block([t_s])[0]
        return one
