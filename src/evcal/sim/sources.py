"""Intensity sources for the simulator: callables ``t_s -> [H, W] float32`` intensity in DN.

- :class:`MovingScene`: a photo (scikit-image's bundled ones, any image file, an array) moved
  by a :class:`~evcal.sim.scene.Trajectory`, with a :class:`SpeedProfile` (still to fast) and
  an :class:`Illumination` (gain ramp and flicker) on top;
- :class:`FrameInterpolator`: a sequence of real frames (a recording's APS frames, or a folder
  such as the Event Camera Dataset's ``images.txt`` + PNGs) interpolated linearly in time,
  resized to the sensor. The gap workflow drives its simulations with the measured frames
  through this class.

Time ``t_s`` is seconds from the start of the simulation. A source may also have
``render_block(t_s, out=None) -> [K, H, W]`` float32, the intensity at several times in one
call, written into ``out`` when given (the simulator renders its steps in blocks through it
when there is one).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numba
import numpy as np

from ..errors import ConfigError
from ..recording import Frames
from .scene import Renderer, Trajectory, load_scene


@dataclass(frozen=True, kw_only=True)
class SpeedProfile:
    """Piecewise-constant motion speed: ``segments`` of ``(duration_s, speed)``.

    The trajectory is evaluated at the warped time ``tau(t) = integral of speed``; speed 0 is a
    still camera, 1 the trajectory's own speed. After the last segment the last speed holds.
    """

    segments: tuple[tuple[float, float], ...] = ((1.0, 0.0), (1.0, 1.0), (1.0, 3.0))

    def __post_init__(self) -> None:
        if not self.segments:
            raise ConfigError("speed profile needs at least one (duration_s, speed) segment")
        for d, s in self.segments:
            if not (d > 0 and s >= 0 and np.isfinite(d) and np.isfinite(s)):
                raise ConfigError(f"speed segment ({d}, {s}) needs duration > 0 and speed >= 0")

    def warp(self, t_s: float) -> float:
        tau, t0 = 0.0, 0.0
        speed = 0.0
        for d, speed in self.segments:
            if t_s <= t0 + d:
                return tau + (t_s - t0) * speed
            tau += d * speed
            t0 += d
        return tau + (t_s - t0) * speed


@dataclass(frozen=True, kw_only=True)
class Illumination:
    """Gain on the scene: linear ramp from ``gain_start`` to ``gain_end`` over ``ramp_s``, times
    ``1 + flicker_depth * sin(2 pi flicker_hz t)``."""

    gain_start: float = 1.0
    gain_end: float = 1.0
    ramp_s: float = 1.0
    flicker_depth: float = 0.0
    flicker_hz: float = 0.0

    def __post_init__(self) -> None:
        if self.gain_start <= 0 or self.gain_end <= 0 or self.ramp_s <= 0:
            raise ConfigError("illumination gains and ramp_s must be > 0")
        if not 0 <= self.flicker_depth < 1:
            raise ConfigError(f"flicker_depth={self.flicker_depth} must be in [0, 1)")

    def gain(self, t_s: float) -> float:
        a = min(max(t_s / self.ramp_s, 0.0), 1.0)
        g = self.gain_start + a * (self.gain_end - self.gain_start)
        if self.flicker_depth and self.flicker_hz:
            g *= 1.0 + self.flicker_depth * np.sin(2 * np.pi * self.flicker_hz * t_s)
        return float(g)


class MovingScene:
    """A photo through a moving camera, with optional speed profile and illumination."""

    def __init__(self, scene: str | np.ndarray, shape: tuple[int, int], trajectory: Trajectory,
                 *, speed: SpeedProfile | None = None, illumination: Illumination | None = None,
                 min_dn: float = 8.0, max_dn: float = 240.0):
        self.renderer = Renderer(load_scene(scene, min_dn=min_dn, max_dn=max_dn), shape,
                                 trajectory)
        self.speed = speed
        self.illumination = illumination

    def __call__(self, t_s: float) -> np.ndarray:
        result: np.ndarray = self.render_block([t_s])[0]
        return result

    def render_block(self, t_s: np.ndarray | list[float], out: np.ndarray | None = None
                     ) -> np.ndarray:
        """The intensity at each of the times ``t_s``, float32 ``[K, H, W]`` (one call for a
        block of simulator steps; the same floats as calling the source at each time), into
        ``out`` when given."""
        ts = [float(t) for t in t_s]
        taus = [self.speed.warp(t) for t in ts] if self.speed is not None else ts
        img = self.renderer.render_many(taus, out)
        if self.illumination is not None:
            img *= np.array([np.float32(self.illumination.gain(t)) for t in ts],
                            np.float32)[:, None, None]
        return img


def _resize(img: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    if img.shape == tuple(shape):
        return img.astype(np.float32)
    from skimage.transform import resize  # noqa: PLC0415 - only when sizes differ

    result: np.ndarray = resize(img.astype(np.float32), shape, order=1, preserve_range=True,
                  anti_aliasing=True).astype(np.float32)
    return result


class FrameInterpolator:
    """Frames ``images[k]`` at ``t_us[k]`` as a continuous source (linear in intensity).

    ``t_s`` counts from ``t_origin_us`` (default: the first frame). Before the first and after
    the last frame the end frames hold.
    """

    def __init__(self, frames: Frames, shape: tuple[int, int] | None = None, *,
                 t_origin_us: int | None = None, gain: float = 1.0):
        if len(frames) == 0:
            raise ConfigError("frame source needs at least one frame")
        shape = (int(shape[0]), int(shape[1])) if shape is not None else frames.shape
        self.images = np.stack([_resize(np.asarray(f, np.float32), shape) * np.float32(gain)
                                for f in frames.images])
        self.t_us = frames.t_us.astype(np.int64)
        self.t_origin_us = int(self.t_us[0] if t_origin_us is None else t_origin_us)
        self._t_rel_s = (self.t_us - self.t_origin_us) * 1e-6

    @classmethod
    def from_folder(cls, path: str | os.PathLike[str], shape: tuple[int, int], **kw: Any
                    ) -> FrameInterpolator:
        """Frames of an Event Camera Dataset-style folder (``images.txt`` + images)."""
        from ..io import read_ecd  # noqa: PLC0415

        rec = read_ecd(Path(path))
        return cls(rec.frames, shape, **kw)

    @property
    def duration_s(self) -> float:
        return float(self._t_rel_s[-1] - self._t_rel_s[0])

    def __call__(self, t_s: float) -> np.ndarray:
        tr = self._t_rel_s
        if t_s <= tr[0]:
            result: np.ndarray = self.images[0]
            return result
        if t_s >= tr[-1]:
            result_160: np.ndarray = self.images[-1]
            return result_160
        k = int(np.searchsorted(tr, t_s, side="right")) - 1
        w = float((t_s - tr[k]) / (tr[k + 1] - tr[k]))
        a, b = self.images[k], self.images[k + 1]
        result_165: np.ndarray = a + np.float32(w) * (b - a)
        return result_165

    def render_block(self, t_s: np.ndarray | list[float], out: np.ndarray | None = None
                     ) -> np.ndarray:
        """The source at each of the times ``t_s``: float32 ``[K, H, W]``, the same floats as
        calling it at each time (into ``out`` when given)."""
        ts = np.asarray(t_s, np.float64).reshape(-1)
        out = self._block_buffer(ts.size, out)
        k, w = self._locate(ts)
        _lerp_frames(self.images, k, w, out)
        return out

    def _block_buffer(self, n: int, out: np.ndarray | None) -> np.ndarray:
        """``out`` checked to hold ``n`` frames (C-contiguous float32), or a new one."""
        shape = (n, *self.images.shape[1:])
        if out is None:
            return np.empty(shape, np.float32)
        if out.shape != shape or out.dtype != np.float32 or not out.flags.c_contiguous:
            raise ConfigError(f"out has shape {out.shape} and dtype {out.dtype}; expected a "
                             f"C-contiguous float32 array of shape {shape}")
        return out

    def _locate(self, ts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """For each time: ``k`` (-1 before the first frame, -2 after the last, else between
        frames ``k`` and ``k + 1``) and the float32 fraction ``w`` of the way to ``k + 1``."""
        tr = self._t_rel_s
        k = np.searchsorted(tr, ts, side="right") - 1
        k = np.where(ts <= tr[0], -1, np.where(ts >= tr[-1], -2, k))
        kk = np.clip(k, 0, max(tr.size - 2, 0))
        nxt = np.minimum(kk + 1, tr.size - 1)
        with np.errstate(invalid="ignore", divide="ignore"):
            w = ((ts - tr[kk]) / (tr[nxt] - tr[kk])).astype(np.float32)
        return k, w


@numba.njit(cache=True, nogil=True)
def _lerp_frames(images: np.ndarray, k: np.ndarray, w: np.ndarray, out: np.ndarray) -> Any:
    """``out[j] = a + w[j] (b - a)`` in float32 with ``a, b`` frames ``k[j], k[j] + 1`` (the
    first or last frame where ``k[j]`` is -1 or -2), as :meth:`FrameInterpolator.__call__`."""
    n_f = images.shape[0]
    for j in range(k.size):
        if k[j] == -1 or k[j] == -2:
            src = images[0] if k[j] == -1 else images[n_f - 1]
            out[j] = src
            continue
        a = images[k[j]]
        b = images[k[j] + 1]
        wj = w[j]
        o = out[j]
        for y in range(a.shape[0]):
            for x in range(a.shape[1]):
                o[y, x] = a[y, x] + wj * (b[y, x] - a[y, x])
