"""Scenes and camera motion: a real photo seen through a moving camera.

The scene is a 2-D intensity image in 8-bit frame units (DN, 0..255 is the frame range). A
:class:`Trajectory` gives the camera pose at any time: a translation (pixels), an in-plane
rotation (radians) and a zoom factor, each a sum of slow sinusoids so the motion goes back and
forth over textured regions (every pixel sees intensity rise and fall, which is what separates
``c`` from ``b``). :func:`render` samples the scene at a pose with bilinear interpolation.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from typing import Any

import numba
import numpy as np

from ..errors import ConfigError

SCENES = ("camera", "astronaut", "coffee", "chelsea", "rocket", "brick", "grass", "gravel",
          "moon", "text", "coins", "page")


def load_scene(name_or_image: str | np.ndarray, *, min_dn: float = 8.0, max_dn: float = 240.0
               ) -> np.ndarray:
    """A gray float32 scene scaled to ``[min_dn, max_dn]``.

    ``name_or_image`` is one of :data:`SCENES` (scikit-image's bundled photos), a path to an
    image file, or an array (2-D gray or 3-D RGB).
    """
    if isinstance(name_or_image, np.ndarray):
        img = np.asarray(name_or_image, np.float64)
    elif name_or_image in SCENES:
        from skimage import data  # noqa: PLC0415 - heavy import, only when a photo is asked for

        img = np.asarray(getattr(data, name_or_image)(), np.float64)
    else:
        from PIL import Image  # noqa: PLC0415

        with Image.open(name_or_image) as im:
            img = np.asarray(im.convert("L"), np.float64)
    if img.ndim == 3:
        img = img[..., :3] @ np.array([0.2125, 0.7154, 0.0721])
    if img.ndim != 2 or min(img.shape) < 8:
        raise ConfigError(f"scene has shape {img.shape}, expected a 2-D image of at least 8x8")
    lo, hi = np.percentile(img, [0.5, 99.5])
    if hi <= lo:
        raise ConfigError("scene image is constant: nothing for events to see")
    img = np.clip((img - lo) / (hi - lo), 0.0, 1.0)
    result: np.ndarray = (min_dn + (max_dn - min_dn) * img).astype(np.float32)
    return result


@dataclass(frozen=True, kw_only=True)
class Trajectory:
    """Camera pose over time: sums of sinusoids (amplitudes in pixels / radians / log-zoom).

    ``speed`` scales every frequency (1.0 is a moderate hand-held pan). The phases come from
    ``seed`` so two trajectories with different seeds differ.
    """

    pan_px: float = 40.0
    rotation_rad: float = 0.08
    zoom: float = 0.05
    shake_px: float = 0.0
    speed: float = 1.0
    seed: int = 0

    def __post_init__(self) -> None:
        for name in ("pan_px", "rotation_rad", "zoom", "shake_px", "speed"):
            if not np.isfinite(getattr(self, name)) or getattr(self, name) < 0:
                raise ConfigError(f"trajectory {name}={getattr(self, name)} must be finite "
                                  "and >= 0")

    @cached_property
    def _phases(self) -> np.ndarray:
        # drawn once per trajectory (a generator per pose would cost more than the pose)
        return np.random.default_rng(self.seed).uniform(0, 2 * np.pi, size=12)

    def pose(self, t_s: np.ndarray | float
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """``(tx_px, ty_px, rot_rad, log_zoom)`` at times ``t_s`` (seconds)."""
        t = np.asarray(t_s, np.float64) * self.speed
        ph = self._phases
        w = 2 * np.pi
        tx = self.pan_px * (0.7 * np.sin(w * 0.31 * t + ph[0]) + 0.3 * np.sin(w * 0.83 * t + ph[1]))
        ty = self.pan_px * (0.6 * np.sin(w * 0.23 * t + ph[2]) + 0.4 * np.sin(w * 0.67 * t + ph[3]))
        rot = self.rotation_rad * np.sin(w * 0.19 * t + ph[4])
        lz = self.zoom * np.sin(w * 0.13 * t + ph[5])
        if self.shake_px:
            tx = tx + self.shake_px * np.sin(w * 7.3 * t + ph[6])
            ty = ty + self.shake_px * np.sin(w * 9.1 * t + ph[7])
        return tx, ty, rot, lz


class Renderer:
    """Samples a scene through a camera of ``shape`` (H, W) at poses of a trajectory."""

    def __init__(self, scene: np.ndarray, shape: tuple[int, int], trajectory: Trajectory):
        self.scene = np.ascontiguousarray(scene, np.float32)
        self.shape = (int(shape[0]), int(shape[1]))
        self.trajectory = trajectory
        h, w = self.shape
        # The sensor sees a window of the scene scaled so that the motion stays inside it.
        sh, sw = self.scene.shape
        margin = trajectory.pan_px + trajectory.shake_px + 2
        reach = np.hypot(w / 2, h / 2) * np.exp(trajectory.zoom) + margin
        self._scale = min(1.0, (min(sh, sw) / 2 - 1) / reach) if reach > 0 else 1.0
        self._cx, self._cy = (sw - 1) / 2.0, (sh - 1) / 2.0

    def _pose_params(self, t_s: float) -> tuple[float, float, float, float, float]:
        """``(scale, cos, sin, tx, ty)`` of the scene coordinates at time ``t_s``: pixel
        ``(u, v)`` from the centre samples the scene at
        ``(cx + scale (cos u - sin v) + tx, cy + scale (sin u + cos v) + ty)``."""
        tx, ty, rot, lz = self.trajectory.pose(t_s)
        s = np.exp(float(lz)) * self._scale
        cr, sr = np.cos(float(rot)), np.sin(float(rot))
        return (float(s), float(cr), float(sr), float(tx) * self._scale,
                float(ty) * self._scale)

    def render(self, t_s: float) -> np.ndarray:
        """Scene intensity (DN, float32 ``[H, W]``) seen at time ``t_s``."""
        result: np.ndarray = self.render_many([t_s])[0]
        return result

    def render_many(self, t_s: np.ndarray | list[float], out: np.ndarray | None = None
                    ) -> np.ndarray:
        """:meth:`render` at each of the times ``t_s``: float32 ``[K, H, W]`` (into ``out``
        when given)."""
        params = np.array([self._pose_params(float(t)) for t in t_s], np.float64).reshape(-1, 5)
        shape = (params.shape[0], *self.shape)
        if out is None:
            out = np.empty(shape, np.float32)
        elif out.shape != shape or out.dtype != np.float32 or not out.flags.c_contiguous:
            raise ConfigError(f"out has shape {out.shape} and dtype {out.dtype}; expected a "
                             f"C-contiguous float32 array of shape {shape}")
        _render_poses(self.scene, params, self._cx, self._cy, out)
        return out


@numba.njit(cache=True, nogil=True)
def _render_poses(scene: np.ndarray, params: np.ndarray, cx: np.ndarray, cy: np.ndarray,
                  out: np.ndarray) -> Any:  # pragma: no cover - compiled
    """Bilinear samples of ``scene`` for each pose ``params[k] = (s, cos, sin, tx, ty)`` into
    ``out[k]``: the arithmetic (and its order) of :func:`bilinear` on the coordinates of
    :meth:`Renderer._pose_params`, so the floats are those of the numpy version. Per row, the
    coordinates first (a loop the compiler vectorises), then the samples."""
    sh, sw = scene.shape
    flat = scene.ravel()
    h, w = out.shape[1], out.shape[2]
    o = out.reshape(out.shape[0], h * w)
    x_max = sw - 1.000001
    y_max = sh - 1.000001
    hu = (w - 1) / 2.0
    hv = (h - 1) / 2.0
    us = np.empty(w, np.float64)
    for xx in range(w):
        us[xx] = xx - hu
    idx = np.empty(w, np.int64)
    fxs = np.empty(w, np.float32)
    fys = np.empty(w, np.float32)
    for k in range(params.shape[0]):
        s = params[k, 0]
        cr = params[k, 1]
        sr = params[k, 2]
        tx = params[k, 3]
        ty = params[k, 4]
        for yy in range(h):
            v = yy - hv
            sv = sr * v
            cv = cr * v
            for xx in range(w):
                u = us[xx]
                xs = cx + s * (cr * u - sv) + tx
                ys = cy + s * (sr * u + cv) + ty
                # np.clip(xs, 0, x_max)
                xs = xs if xs > 0.0 else 0.0
                xs = xs if xs < x_max else x_max
                ys = ys if ys > 0.0 else 0.0
                ys = ys if ys < y_max else y_max
                x0 = np.int64(xs)
                y0 = np.int64(ys)
                fxs[xx] = np.float32(xs - np.float64(x0))
                fys[xx] = np.float32(ys - np.float64(y0))
                idx[xx] = y0 * sw + x0
            base = yy * w
            for xx in range(w):
                i00 = idx[xx]
                fx = fxs[xx]
                a = flat[i00]
                b = flat[i00 + 1]
                c = flat[i00 + sw]
                d = flat[i00 + sw + 1]
                top = a + (b - a) * fx
                bot = c + (d - c) * fx
                o[k, base + xx] = top + (bot - top) * fys[xx]


def bilinear(img: np.ndarray, xs: np.ndarray, ys: np.ndarray) -> np.ndarray:
    """Bilinear samples of ``img`` at ``(xs, ys)``, clamped at the border (float32)."""
    h, w = img.shape
    xs = np.clip(xs, 0, w - 1.000001)
    ys = np.clip(ys, 0, h - 1.000001)
    x0 = xs.astype(np.intp)
    y0 = ys.astype(np.intp)
    fx = (xs - x0).astype(np.float32)
    fy = (ys - y0).astype(np.float32)
    flat = img.ravel()
    i00 = y0 * w + x0
    a = flat[i00]
    b = flat[i00 + 1]
    c = flat[i00 + w]
    d = flat[i00 + w + 1]
    top = a + (b - a) * fx
    bot = c + (d - c) * fx
    result: np.ndarray = (top + (bot - top) * fy).astype(np.float32)
    return result
