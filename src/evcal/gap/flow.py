"""Motion-compensated frame interpolation: the latent intensity between two frames.

Between frames 40 ms apart (25 Hz, what DAVIS cameras deliver) an edge crosses many pixels.
A linear blend of the two frames makes every pixel it crosses ramp slowly over the whole
interval, so a simulation driven by it fires those events spread over 40 ms where the sensor
fired them in a burst when the edge passed: interval statistics, refractory losses and the
speed response all come out wrong. Here the motion is followed instead:

- dense optical flow both ways between consecutive frames, by OpenCV's DIS (Kroeger et al.
  2016, maintained in ``opencv-python-headless``; imported only when used), on frames
  upsampled to at least ``min_size`` pixels on their short side so that its patches resolve
  small sensors;
- the flow from an intermediate time ``tau`` (0..1) back to each frame under linear motion
  (the approximation of Jiang et al. 2018, "Super SloMo")::

      F_tau->0 = -(1 - tau) tau F_0->1 + tau^2 F_1->0
      F_tau->1 = (1 - tau)^2 F_0->1 - tau (1 - tau) F_1->0

- both frames warped to ``tau`` (bilinear) and blended with weights ``(1 - tau) v0`` and
  ``tau v1``, ``v`` the forward-backward consistency of each frame's flow (1 where following
  the flow there and back returns within ``consistency_px``, falling to 0 by twice that);
  where neither frame's flow is consistent (occlusions, flow failures), the plain linear blend
  of the two frames at that pixel is used, so a failure degrades to the old behaviour rather
  than inventing structure.

At ``tau = 0`` and ``tau = 1`` the frames are returned exactly.
"""

from __future__ import annotations

import hashlib
from collections import OrderedDict
from typing import Any

import numpy as np

from ..errors import ConfigError
from ..recording import Frames
from ..sim.sources import FrameInterpolator
from .motion import SubframeShift

_FLOW_CACHE: OrderedDict[bytes, tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = \
    OrderedDict()
_FLOW_CACHE_SIZE = 4


def _cv2() -> Any:
    try:
        import cv2  # noqa: PLC0415
    except ImportError as exc:  # pragma: no cover - depends on the install
        raise ImportError("motion-compensated interpolation needs OpenCV: "
                          "pip install 'evcal[gap]' (opencv-python-headless)") from exc
    return cv2


def _to_u8(img: np.ndarray) -> np.ndarray:
    out: np.ndarray = np.clip(np.rint(img), 0, 255).astype(np.uint8)
    return out


def _consistency(fwd: np.ndarray, bwd: np.ndarray, tol_px: float) -> np.ndarray:
    """Weight in [0, 1] per pixel of ``fwd``: 1 where ``fwd`` followed by ``bwd`` (sampled at
    the arrival point) comes back within ``tol_px``, 0 beyond twice that."""
    cv2 = _cv2()
    h, w = fwd.shape[:2]
    gy, gx = np.mgrid[0:h, 0:w].astype(np.float32)
    mx = gx + fwd[..., 0]
    my = gy + fwd[..., 1]
    back = cv2.remap(bwd, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    err = np.hypot(fwd[..., 0] + back[..., 0], fwd[..., 1] + back[..., 1])
    inside = (mx >= 0) & (mx <= w - 1) & (my >= 0) & (my <= h - 1)
    wgt: np.ndarray = np.clip(2.0 - err / tol_px, 0.0, 1.0).astype(np.float32) * inside
    return wgt


def frame_flows(images: np.ndarray, *, min_size: int = 192, preset: str = "medium"
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Forward and backward flow (pixels, ``[K-1, H, W, 2]`` float32, x then y) between
    consecutive images and their forward-backward consistency weights (``[K-1, H, W]``)."""
    cv2 = _cv2()
    k, h, w = images.shape
    key_h = hashlib.blake2b(np.ascontiguousarray(images).tobytes(), digest_size=16)
    key_h.update(f"{min_size},{preset},{images.dtype},{images.shape}".encode())
    key = key_h.digest()
    if key in _FLOW_CACHE:
        _FLOW_CACHE.move_to_end(key)
        return _FLOW_CACHE[key]
    scale = max(1.0, min_size / min(h, w))
    size = (int(round(w * scale)), int(round(h * scale)))
    presets = {"ultrafast": cv2.DISOPTICAL_FLOW_PRESET_ULTRAFAST,
               "fast": cv2.DISOPTICAL_FLOW_PRESET_FAST,
               "medium": cv2.DISOPTICAL_FLOW_PRESET_MEDIUM}
    dis = cv2.DISOpticalFlow_create(presets[preset])
    up = [cv2.resize(_to_u8(im), size, interpolation=cv2.INTER_CUBIC) if scale > 1
          else _to_u8(im) for im in images]
    fwd = np.zeros((max(k - 1, 0), h, w, 2), np.float32)
    bwd = np.zeros_like(fwd)
    for i in range(k - 1):  # one flow per frame pair (not per pixel)
        for out, a, b in ((fwd, up[i], up[i + 1]), (bwd, up[i + 1], up[i])):
            f = dis.calc(a, b, None)
            if scale > 1:
                f = cv2.resize(f, (w, h), interpolation=cv2.INTER_AREA) / np.float32(scale)
            out[i] = f
    v_fwd = np.stack([_consistency(fwd[i], bwd[i], 1.0) for i in range(k - 1)]) \
        if k > 1 else np.zeros((0, h, w), np.float32)
    v_bwd = np.stack([_consistency(bwd[i], fwd[i], 1.0) for i in range(k - 1)]) \
        if k > 1 else np.zeros((0, h, w), np.float32)
    _FLOW_CACHE[key] = (fwd, bwd, v_fwd, v_bwd)
    while len(_FLOW_CACHE) > _FLOW_CACHE_SIZE:
        _FLOW_CACHE.popitem(last=False)
    return fwd, bwd, v_fwd, v_bwd


class FlowInterpolator(FrameInterpolator):
    """:class:`~evcal.sim.sources.FrameInterpolator` that follows the motion between frames
    (see the module docstring). ``flow_images`` are the frames the flow is computed on (the
    undithered measured frames, so that the flow is computed once per recording); by default
    the frames themselves."""

    def __init__(self, frames: Frames, shape: tuple[int, int] | None = None, *,
                 t_origin_us: int | None = None, gain: float = 1.0,
                 flow_images: np.ndarray | None = None, min_size: int = 192,
                 shift: SubframeShift | None = None):
        super().__init__(frames, shape, t_origin_us=t_origin_us, gain=gain)
        # the image's motion between frames off the straight path (evcal.gap.motion)
        self.shift = shift
        src = self.images if flow_images is None else np.asarray(flow_images)
        if src.shape != self.images.shape:
            raise ConfigError(f"flow_images have shape {src.shape}, the frames "
                             f"{self.images.shape}")
        self.fwd, self.bwd, self.v_fwd, self.v_bwd = frame_flows(src, min_size=min_size)
        h, w = self.images.shape[1:]
        gy, gx = np.mgrid[0:h, 0:w].astype(np.float32)
        self._gx, self._gy = gx, gy
        self._ext: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        self._rows = slice(0, h)

    def only_rows(self, rows: slice) -> FlowInterpolator:
        """Render the sensor rows ``rows`` only (``render_block`` gives ``[K, rows, W]``):
        the same values as the whole frame's rows, the warps sampling the whole frames (a
        band of rows for screening costs its share of the warps)."""
        h = self.images.shape[1]
        y0, y1, step = rows.indices(h)
        if step != 1 or y1 <= y0:
            raise ConfigError(f"rows {rows} must be a non-empty contiguous band of 0..{h}")
        self._rows = slice(y0, y1)
        return self

    def between(self, k: int, tau: float, shift: np.ndarray | None = None) -> np.ndarray:
        """Frame interval ``k`` at ``tau`` (0..1) of the way, the image sampled ``shift``
        (pixels, x then y) away from the straight path."""
        cv2 = _cv2()
        r = self._rows  # the output's rows; the warps sample the whole frames
        a, b = self.images[k][r], self.images[k + 1][r]
        f01, f10 = self.fwd[k][r], self.bwd[k][r]
        gx, gy = self._gx[r], self._gy[r]
        t = np.float32(tau)
        ft0 = -(1 - t) * t * f01 + t * t * f10
        ft1 = (1 - t) * (1 - t) * f01 - t * (1 - t) * f10
        if shift is not None and np.any(shift):
            sh = np.asarray(shift, np.float32)
            ft0 = ft0 + sh
            ft1 = ft1 + sh
            # the blend that stands in where the flow fails moves with the image too
            a, b = (cv2.remap(self.images[i], gx + sh[0], gy + sh[1], cv2.INTER_LINEAR,
                              borderMode=cv2.BORDER_REPLICATE) for i in (k, k + 1))
        w0 = self._warp(k, 0, ft0)
        w1 = self._warp(k, 1, ft1)
        # visibility: the consistency of each frame's flow, sampled where the pixel comes from
        v0 = cv2.remap(self.v_fwd[k], gx + ft0[..., 0], gy + ft0[..., 1],
                       cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        v1 = cv2.remap(self.v_bwd[k], gx + ft1[..., 0], gy + ft1[..., 1],
                       cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        c0 = (1 - t) * v0
        c1 = t * v1
        den = c0 + c1
        lin = a + t * (b - a)
        trust = np.clip(v0 + v1, 0.0, 1.0)  # neither consistent: the linear blend
        with np.errstate(invalid="ignore", divide="ignore"):
            warped = np.where(den > 1e-6, (c0 * w0 + c1 * w1) / den, lin)
        out: np.ndarray = (trust * warped + (1 - trust) * lin).astype(np.float32)
        return out

    def _warp(self, k: int, side: int, flow: np.ndarray) -> np.ndarray:
        """Frame ``k + side`` sampled at the pixels displaced by ``flow``: bicubic, kept
        within the four pixels around each point. A bilinear resampling at a sub-pixel shift
        averages neighbours and takes up to half the contrast of fine texture (at 25 Hz on the
        v2e gravel scene the interpolated images had 0.89x the true gradients, bicubic 0.99x),
        and with it the events of texture passing a pixel; the clamp keeps bicubic's
        overshoot at strong edges from making events of its own."""
        cv2 = _cv2()
        img = self.images[k + side]
        mx, my = self._gx[self._rows] + flow[..., 0], self._gy[self._rows] + flow[..., 1]
        cub = cv2.remap(img, mx, my, cv2.INTER_CUBIC, borderMode=cv2.BORDER_REPLICATE)
        lo, hi = self._extremes(k + side)
        fx, fy = np.floor(mx), np.floor(my)  # the top-left of the four pixels around
        lo_s = cv2.remap(lo, fx, fy, cv2.INTER_NEAREST, borderMode=cv2.BORDER_REPLICATE)
        hi_s = cv2.remap(hi, fx, fy, cv2.INTER_NEAREST, borderMode=cv2.BORDER_REPLICATE)
        out: np.ndarray = np.clip(cub, lo_s, hi_s)
        return out

    def _extremes(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        """Per pixel (y, x): min and max of frame ``i`` over rows y..y+1 and columns
        x..x+1 (the border replicated)."""
        if i not in self._ext:
            a = self.images[i]
            down = np.concatenate([a[1:], a[-1:]], axis=0)
            ext = []
            for f in (np.minimum, np.maximum):
                v = f(a, down)
                ext.append(f(v, np.concatenate([v[:, 1:], v[:, -1:]], axis=1)))
            self._ext[i] = (ext[0], ext[1])
        return self._ext[i]

    def __call__(self, t_s: float) -> np.ndarray:
        one: np.ndarray = self.render_block([t_s])[0]
        return one

    def render_block(self, t_s: np.ndarray | list[float], out: np.ndarray | None = None
                     ) -> np.ndarray:
        ts = np.asarray(t_s, np.float64).reshape(-1)
        r = self._rows
        shape = (ts.size, r.stop - r.start, self.images.shape[2])
        if out is None:
            out = np.empty(shape, np.float32)
        elif out.shape != shape or out.dtype != np.float32:
            raise ConfigError(f"out has shape {out.shape} and dtype {out.dtype}; expected "
                             f"float32 {shape}")
        ks, ws = self._locate(ts)
        shifts = None if self.shift is None else \
            self.shift.at(self.t_origin_us + np.rint(ts * 1e6))
        for j in range(ts.size):  # one warp per requested time, vectorised over pixels
            k, tau = int(ks[j]), float(ws[j])
            if k < 0:
                out[j] = self.images[0 if k == -1 else -1][r]
            else:
                out[j] = self.images[k][r] if tau <= 0 else \
                    self.between(k, tau, None if shifts is None else shifts[j])
        return out


# the longest blur (pixels) the second-order correction is trusted with: beyond it, the
# Taylor series of the box blur is no longer a small correction
MAX_BLUR_PX = 6.0
DEBLUR_SAMPLES = 7  # points along the blur segment
DEBLUR_ITERATIONS = 8


def _box_along(cv2: Any, x: np.ndarray, gx: np.ndarray, gy: np.ndarray, blur: np.ndarray,
               steps: np.ndarray) -> np.ndarray:
    """``x`` averaged along each pixel's blur segment (``steps`` points of it)."""
    acc = np.zeros(x.shape, np.float32)
    for f in steps:
        acc += cv2.remap(x, gx + f * blur[..., 0], gy + f * blur[..., 1], cv2.INTER_LINEAR,
                         borderMode=cv2.BORDER_REPLICATE)
    acc /= np.float32(steps.size)
    return acc


def deblurred(images: np.ndarray, t_us: np.ndarray, exposure_us: np.ndarray,
              flow_images: np.ndarray | None = None, *, min_size: int = 192) -> np.ndarray:
    """``images`` (``[K, H, W]``, frames averaged over their exposure) with the motion blur
    of their exposure taken out: a frame exposed for ``e`` while the image
    moves at ``v`` (px/s, from the flow to the neighbouring frames, where it is consistent)
    is the sharp image averaged along a segment ``L = v e``: the sharp image is found by
    Landweber's iteration ``I <- I + blur_L(B - blur_L(I))`` from ``I = B``
    (:data:`DEBLUR_ITERATIONS` steps, the blur sampled at :data:`DEBLUR_SAMPLES` points
    along the segment; the centred box is its own adjoint), kept within the range of the
    blurred frame around the pixel (a sharp edge does not overshoot). Blurs are limited to
    :data:`MAX_BLUR_PX` (the direction kept): beyond, two frames do not say enough of the
    path.

    Not Van Cittert's ``I <- I + (B - blur_L(I))``: a box blur's response is negative
    between its first two zeros (periods between ``L / 2`` and ``L``), where that iteration
    grows without bound and turns fine texture (a grating, grass) upside down and larger
    than it was; a simulation driven by such frames fires far too many short intervals.
    Landweber's converges at every frequency (its step is the response squared) and
    restores little of what the blur nearly erased.

    A simulation driven by blurred frames fires an edge's events spread over the time the
    blur spans: at 10 ms exposure and a fast pan over text, 3x too few same-pixel intervals
    of 0.3-1 ms against the sensor, which saw the sharp edge."""
    cv2 = _cv2()
    imgs = np.asarray(images, np.float32)
    k = imgs.shape[0]
    exp_s = np.asarray(exposure_us, np.float64).reshape(-1) * 1e-6
    if k < 2 or not (exp_s > 0).any():
        return imgs
    src = imgs if flow_images is None else np.asarray(flow_images, np.float32)
    fwd, bwd, v_fwd, v_bwd = frame_flows(src, min_size=min_size)
    dt = np.diff(np.asarray(t_us, np.float64)) * 1e-6
    out = imgs.copy()
    for i in range(k):
        if exp_s[i] <= 0:
            continue
        parts, wts = [], []
        if i < k - 1:  # towards the next frame, on frame i's grid
            parts.append(fwd[i] / dt[i])
            wts.append(v_fwd[i])
        if i > 0:  # from the previous frame: minus the flow back to it, on frame i's grid
            parts.append(-bwd[i - 1] / dt[i - 1])
            wts.append(v_bwd[i - 1])
        wsum = np.sum(wts, axis=0)
        vel = np.sum([p * w[..., None] for p, w in zip(parts, wts, strict=True)], axis=0) / \
            np.maximum(wsum, 1e-6)[..., None]
        blur = vel * np.float32(exp_s[i]) * np.clip(wsum, 0.0, 1.0)[..., None]
        length = np.hypot(blur[..., 0], blur[..., 1])
        blur = (blur * (np.minimum(length, MAX_BLUR_PX) / np.maximum(length, 1e-6))[..., None]
                ).astype(np.float32)
        b = imgs[i]
        r = int(np.ceil(MAX_BLUR_PX / 2))
        kernel = np.ones((2 * r + 1, 2 * r + 1), np.uint8)
        lo, hi = cv2.erode(b, kernel), cv2.dilate(b, kernel)
        gy, gx = np.mgrid[0:b.shape[0], 0:b.shape[1]].astype(np.float32)
        steps = (np.arange(DEBLUR_SAMPLES, dtype=np.float32) + 0.5) / DEBLUR_SAMPLES - 0.5
        sharp = b.copy()
        for _ in range(DEBLUR_ITERATIONS):  # Landweber: I <- I + A(B - A I)
            step = _box_along(cv2, b - _box_along(cv2, sharp, gx, gy, blur, steps),
                              gx, gy, blur, steps)
            sharp = np.clip(sharp + step, lo, hi).astype(np.float32)
        out[i] = sharp
    result: np.ndarray = out
    return result


def trusted_windows(frames: Frames, *, max_px: float = 2.0, min_consistency: float = 0.5,
                    min_size: int = 192) -> np.ndarray:
    """``[n_frames - 1, n_pixels]`` bool: windows of pixels where the motion between the two
    frames is small (at most ``max_px`` pixels either way) and its flow consistent, so that
    an interpolation of the frames knows when the pixel's intensity changed within the window.

    Where the motion is fast, two frames do not say when within the interval an edge crossed a
    pixel (nor how often texture finer than the displacement went up and down there): timing
    statistics of such windows compare the sensor with the interpolation, not with the model.
    """
    imgs = frames.images.astype(np.float32)
    fwd, bwd, v_fwd, v_bwd = frame_flows(imgs, min_size=min_size)
    mag = np.maximum(np.hypot(fwd[..., 0], fwd[..., 1]), np.hypot(bwd[..., 0], bwd[..., 1]))
    ok: np.ndarray = (mag <= max_px) & (np.minimum(v_fwd, v_bwd) >= min_consistency)
    return ok.reshape(ok.shape[0], -1)


def unclipped_windows(frames: Frames, *, full_scale_dn: float = 255.0) -> np.ndarray:
    """``[n_frames - 1, n_pixels]`` bool: windows of pixels where neither frame is at full
    scale (``full_scale_dn``, an 8-bit APS frame's 255).

    A frame clipped there says only that the light was past the APS's full well; the DVS
    pixel still follows it, and a simulation driven by the clipped frames does not. The fits
    leave such windows out already (:attr:`Observation.usable`); the timing statistics must
    too, for the same reason as fast motion: there they would compare the sensor with the
    clipping, not with the model."""
    im = frames.images.reshape(len(frames), -1)
    top = im >= full_scale_dn
    ok: np.ndarray = ~(top[1:] | top[:-1])
    return ok
