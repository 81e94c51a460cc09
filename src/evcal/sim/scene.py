"""Scenes and camera motion: a real photo seen through a moving camera.

The scene is a 2-D intensity image in 8-bit frame units (DN, 0..255 is the frame range). A
:class:`Trajectory` gives the camera pose at any time: a translation (pixels), an in-plane
rotation (radians) and a zoom factor, each a sum of slow sinusoids so the motion goes back and
forth over textured regions (every pixel sees intensity rise and fall, which is what separates
``c`` from ``b``). :func:`render` samples the scene at a pose with bilinear interpolation.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

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
        raise ValueError(f"scene has shape {img.shape}, expected a 2-D image of at least 8x8")
    lo, hi = np.percentile(img, [0.5, 99.5])
    if hi <= lo:
        raise ValueError("scene image is constant: nothing for events to see")
    img = np.clip((img - lo) / (hi - lo), 0.0, 1.0)
    return (min_dn + (max_dn - min_dn) * img).astype(np.float32)


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
                raise ValueError(f"trajectory {name}={getattr(self, name)} must be finite and >= 0")

    def _phases(self) -> np.ndarray:
        return np.random.default_rng(self.seed).uniform(0, 2 * np.pi, size=12)

    def pose(self, t_s: np.ndarray | float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """``(tx_px, ty_px, rot_rad, log_zoom)`` at times ``t_s`` (seconds)."""
        t = np.asarray(t_s, np.float64) * self.speed
        ph = self._phases()
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
        yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
        self._u = xx - (w - 1) / 2.0
        self._v = yy - (h - 1) / 2.0
        # The sensor sees a window of the scene scaled so that the motion stays inside it.
        sh, sw = self.scene.shape
        margin = trajectory.pan_px + trajectory.shake_px + 2
        reach = np.hypot(w / 2, h / 2) * np.exp(trajectory.zoom) + margin
        self._scale = min(1.0, (min(sh, sw) / 2 - 1) / reach) if reach > 0 else 1.0
        self._cx, self._cy = (sw - 1) / 2.0, (sh - 1) / 2.0

    def render(self, t_s: float) -> np.ndarray:
        """Scene intensity (DN, float32 ``[H, W]``) seen at time ``t_s``."""
        tx, ty, rot, lz = self.trajectory.pose(t_s)
        s = np.exp(float(lz)) * self._scale
        cr, sr = np.cos(float(rot)), np.sin(float(rot))
        xs = self._cx + s * (cr * self._u - sr * self._v) + float(tx) * self._scale
        ys = self._cy + s * (sr * self._u + cr * self._v) + float(ty) * self._scale
        return bilinear(self.scene, xs, ys)


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
    return (top + (bot - top) * fy).astype(np.float32)
