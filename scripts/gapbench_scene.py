"""Scenes, camera motion and illumination of the gap benchmark (``scripts/gap_benchmark.py``).

A case of the benchmark describes its intensity in plain JSON (scene, DN range, motion
segments, illumination); :func:`build_scene` turns that description into a :class:`Scene`,
the intensity seen by every pixel at any time, in DN (frame units). The same description
gives the same intensity in evcal's venv (the ``sim`` backend drives
``evcal.sim.nonideal.simulate`` with it) and in v2e's venv
(``scripts/gapbench_v2e_worker.py`` feeds it to v2e's ``EventEmulator``), so this module
imports only numpy, OpenCV and scikit-image (and the standard library).

Conventions: times ``t_s`` are float seconds from the start of the recording, frame times
``t_us`` integer microseconds; images are ``[y, x]`` float32 DN; the camera pose is a
translation ``(tx, ty)`` in sensor pixels (at zoom 1), an in-plane rotation in radians and a
log zoom (positive: closer).

Examples
--------
>>> case = {"sensor": [18, 24], "duration_s": 0.5, "dn_range": [20.0, 200.0],
...         "scene": {"kind": "procedural", "name": "grating", "period_px": 12.0,
...                   "angle_rad": 0.3, "square": False, "texture_seed": 1,
...                   "view_fraction": 0.5},
...         "motion": [{"kind": "still", "t0_s": 0.0, "t1_s": 0.5}],
...         "illumination": {"kind": "constant"}}
>>> scene = build_scene(case)
>>> img = scene(0.25)
>>> img.shape, img.dtype, bool(20.0 <= img.min() and img.max() <= 200.0)
((18, 24), dtype('float32'), True)
"""

from __future__ import annotations

import io
import json
import math
import os
import zipfile
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import cv2
import numpy as np

# scikit-image's bundled photos that load without a download (scikit-image 0.26; ``brain``,
# ``eagle``, ``human_mitosis``, ``kidney``, ``lily``, ``skin`` ... need pooch and a network;
# ``cat`` is ``chelsea``; ``microaneurysms`` is 102 px wide, too small; ``motorcycle`` is
# the left image of ``stereo_motorcycle``)
PHOTOS = ("astronaut", "brick", "camera", "cell", "chelsea", "clock", "coffee", "coins",
          "colorwheel", "grass", "gravel", "horse", "hubble_deep_field",
          "immunohistochemistry", "logo", "moon", "motorcycle", "page", "retina", "rocket",
          "shepp_logan_phantom", "text")
# procedural textures (their parameters are in the case; see procedural_texture)
PROCEDURAL = ("noise", "checkerboard", "grating", "blobs", "edges")
PROCEDURAL_SIZE_PX = 900       # side of a procedural texture (texture pixels)
MOTION_STEP_US = 50            # grid on which the velocities are integrated to poses
ANTIALIAS_SIGMA_PX = 0.6       # Gaussian blur of the texture, in sensor pixels
APS_BLUR_SAMPLES = 5           # renders averaged over a frame's exposure


# Textures --------------------------------------------------------------------------------

def load_photo(name: str) -> np.ndarray:
    """One of :data:`PHOTOS` as gray float64 in [0, 1] (``[y, x]``).

    RGB(A) is converted with scikit-image's luminance weights (transparency over white).
    """
    import skimage.data
    from skimage.color import rgb2gray, rgba2rgb

    if name not in PHOTOS:
        raise ValueError(f"unknown photo {name!r}; known: {', '.join(PHOTOS)}")
    img = skimage.data.stereo_motorcycle()[0] if name == "motorcycle" \
        else getattr(skimage.data, name)()
    img = np.asarray(img)
    if img.ndim == 3 and img.shape[2] == 4:
        img = rgba2rgb(img)
    if img.ndim == 3:
        return np.asarray(rgb2gray(img), np.float64)
    if img.dtype == bool:
        return img.astype(np.float64)
    if img.dtype.kind in "iu":
        return img.astype(np.float64) / float(np.iinfo(img.dtype).max)
    return np.asarray(img, np.float64)


def procedural_texture(spec: dict[str, Any]) -> np.ndarray:
    """A procedural texture (float64 ``[y, x]``, any range; stretched later) from ``spec``.

    ``spec["name"]`` is one of :data:`PROCEDURAL`; the random parts come from
    ``np.random.default_rng(spec["texture_seed"])``:

    - ``noise``: band-limited white noise, the difference of Gaussian low-passes at
      ``sigma_px`` and ``4 sigma_px`` (texture pixels);
    - ``checkerboard``: squares of ``square_px``, rotated by ``angle_rad``;
    - ``grating``: a sine (or square, ``square``) grating of ``period_px`` at ``angle_rad``;
    - ``blobs``: scikit-image's ``binary_blobs`` (``blob_size_fraction``,
      ``volume_fraction``), smoothed a little;
    - ``edges``: a linear gradient at ``angle_rad`` plus ``n_shapes`` random polygons and
      discs of random gray levels (sharp edges on a smooth background).
    """
    n = PROCEDURAL_SIZE_PX
    rng = np.random.default_rng(int(spec["texture_seed"]))
    name = spec["name"]
    yy, xx = np.mgrid[0:n, 0:n].astype(np.float64)
    if name == "noise":
        white = rng.standard_normal((n, n)).astype(np.float32)
        s = float(spec["sigma_px"])
        fine = cv2.GaussianBlur(white, (0, 0), s, borderType=cv2.BORDER_REFLECT_101)
        coarse = cv2.GaussianBlur(white, (0, 0), 4 * s, borderType=cv2.BORDER_REFLECT_101)
        return (fine - coarse).astype(np.float64)
    if name in ("checkerboard", "grating"):
        a = float(spec["angle_rad"])
        u = np.cos(a) * xx + np.sin(a) * yy
        v = -np.sin(a) * xx + np.cos(a) * yy
        if name == "checkerboard":
            q = float(spec["square_px"])
            return ((np.floor(u / q) + np.floor(v / q)) % 2).astype(np.float64)
        phase = np.sin(2 * np.pi * u / float(spec["period_px"]))
        return (phase > 0).astype(np.float64) if spec.get("square") else phase
    if name == "blobs":
        from skimage.data import binary_blobs

        b = binary_blobs(length=n, blob_size_fraction=float(spec["blob_size_fraction"]),
                         volume_fraction=float(spec["volume_fraction"]),
                         rng=int(spec["texture_seed"]))
        return cv2.GaussianBlur(b.astype(np.float32), (0, 0), 1.5).astype(np.float64)
    if name == "edges":
        a = float(spec["angle_rad"])
        img = (0.5 * (np.cos(a) * xx + np.sin(a) * yy) / n).astype(np.float32)
        for _ in range(int(spec["n_shapes"])):
            level = float(rng.uniform(0.0, 1.0))
            if rng.random() < 0.5:
                centre = rng.uniform(0, n, 2)
                radius = rng.uniform(0.03, 0.15) * n
                k = int(rng.integers(3, 7))
                ang = np.sort(rng.uniform(0, 2 * np.pi, k))
                pts = centre + radius * np.stack([np.cos(ang), np.sin(ang)], 1) \
                    * rng.uniform(0.6, 1.4, (k, 1))
                cv2.fillPoly(img, [np.rint(pts).astype(np.int32)], level, lineType=cv2.LINE_8)
            else:
                centre_px = tuple(int(c) for c in rng.integers(0, n, 2))
                cv2.circle(img, centre_px, int(rng.uniform(0.02, 0.1) * n), level, -1,
                           lineType=cv2.LINE_8)
        return img.astype(np.float64)
    raise ValueError(f"unknown procedural texture {name!r}; known: {', '.join(PROCEDURAL)}")


def raw_texture(spec: dict[str, Any]) -> np.ndarray:
    """The scene's texture before blur and stretch (photo or procedural)."""
    if spec["kind"] == "photo":
        return load_photo(spec["name"])
    if spec["kind"] == "procedural":
        return procedural_texture(spec)
    raise ValueError(f"unknown scene kind {spec['kind']!r} (photo or procedural)")


def view_scale(texture_shape: tuple[int, int], sensor_shape: tuple[int, int],
               view_fraction: float) -> float:
    """Texture pixels per sensor pixel so that the sensor's view spans ``view_fraction`` of
    the texture along its tighter axis (clipped to 0.5..4)."""
    th, tw = texture_shape
    h, w = sensor_shape
    return float(np.clip(view_fraction * min(th / h, tw / w), 0.5, 4.0))


def prepare_texture(raw: np.ndarray, scale: float) -> np.ndarray:
    """``raw`` low-passed against aliasing (Gaussian, sigma = ``ANTIALIAS_SIGMA_PX`` sensor
    pixels = ``0.6 scale`` texture pixels), stretched between its 1st and 99th percentile and
    clipped: float32 in [0, 1]."""
    g = cv2.GaussianBlur(raw.astype(np.float32), (0, 0), sigmaX=ANTIALIAS_SIGMA_PX * scale,
                         borderType=cv2.BORDER_REFLECT_101)
    lo, hi = np.percentile(g, [1.0, 99.0])
    if not hi > lo:
        raise ValueError("texture is flat between its 1st and 99th percentile")
    return np.clip((g - lo) / (hi - lo), 0.0, 1.0).astype(np.float32)


# Motion ----------------------------------------------------------------------------------

def _envelope(u: np.ndarray, profile: str, duration_s: float) -> np.ndarray:
    """Speed envelope over a segment (``u`` in [0, 1]): 0 at both ends, 1 at its peak.

    ``smooth``: ``sin^2(pi u)``; ``constant``: raised-cosine ramps of ``min(0.1 s, 25 %)`` at
    both ends around a plateau. Both start and end with zero velocity and zero acceleration,
    so velocities are continuous across segment joins."""
    if profile == "smooth":
        return np.sin(np.pi * u) ** 2
    r = min(0.1 / duration_s, 0.25)
    rise = 0.5 - 0.5 * np.cos(np.pi * np.clip(u / r, 0.0, 1.0))
    fall = 0.5 - 0.5 * np.cos(np.pi * np.clip((1.0 - u) / r, 0.0, 1.0))
    return np.minimum(rise, fall)


class Motion:
    """Camera pose over time from a list of motion segments.

    Each segment is a dict with ``kind`` and ``t0_s``, ``t1_s``; the kinds and their
    parameters:

    - ``still``: the pose is exactly constant;
    - ``pan``: velocity ``speed_px_s`` (peak, sensor px/s) along ``heading_rad``, turning by
      ``turn_rad`` (a half sine over the segment), with envelope ``profile``
      (``constant`` or ``smooth``, see :func:`_envelope`);
    - ``rotation``: angular velocity ``rate_rad_s`` (signed, peak) with envelope ``profile``;
    - ``zoom``: log-zoom velocity ``rate_per_s`` (signed, peak) with envelope ``profile``;
    - ``shake``: hand shake, a displacement ``amplitude_px * sin^2(pi u) * sin(2 pi f t +
      phase)`` along x and y (``freq_x_hz``, ``freq_y_hz``, ``phase_x_rad``,
      ``phase_y_rad``), zero at both ends.

    Velocities are integrated (trapezoid) on a grid of ``MOTION_STEP_US``; the pose at a
    time is interpolated linearly on it, and held before 0 and after the end. Outside
    segments nothing moves.
    """

    def __init__(self, segments: Sequence[dict[str, Any]], duration_s: float):
        self.segments = [dict(s) for s in segments]
        self.duration_s = float(duration_s)
        n = int(math.ceil(self.duration_s * 1e6 / MOTION_STEP_US)) + 1
        t = np.arange(n) * (MOTION_STEP_US * 1e-6)
        self._t_s = t
        vel = np.zeros((4, n))          # tx, ty (px/s), rot (rad/s), log zoom (1/s)
        shake = np.zeros((2, n))        # displacement (px), added to tx, ty
        for seg in self.segments:
            t0, t1 = float(seg["t0_s"]), float(seg["t1_s"])
            m = (t >= t0) & (t <= t1)
            u = (t[m] - t0) / (t1 - t0)
            kind = seg["kind"]
            if kind == "still":
                continue
            if kind == "shake":
                env = np.sin(np.pi * u) ** 2
                shake[0, m] = seg["amplitude_px"] * env * np.sin(
                    2 * np.pi * seg["freq_x_hz"] * t[m] + seg["phase_x_rad"])
                shake[1, m] = seg["amplitude_px"] * env * np.sin(
                    2 * np.pi * seg["freq_y_hz"] * t[m] + seg["phase_y_rad"])
                continue
            env = _envelope(u, seg.get("profile", "smooth"), t1 - t0)
            if kind == "pan":
                heading = seg["heading_rad"] + seg.get("turn_rad", 0.0) * np.sin(np.pi * u)
                vel[0, m] = seg["speed_px_s"] * env * np.cos(heading)
                vel[1, m] = seg["speed_px_s"] * env * np.sin(heading)
            elif kind == "rotation":
                vel[2, m] = seg["rate_rad_s"] * env
            elif kind == "zoom":
                vel[3, m] = seg["rate_per_s"] * env
            else:
                raise ValueError(f"unknown motion segment kind {kind!r}")
        dt = MOTION_STEP_US * 1e-6
        pose = np.zeros((4, n))
        pose[:, 1:] = np.cumsum(0.5 * (vel[:, 1:] + vel[:, :-1]) * dt, axis=1)
        pose[:2] += shake
        self._pose = pose
        self._vel = vel

    def pose(self, t_s: float) -> tuple[float, float, float, float]:
        """``(tx_px, ty_px, rot_rad, log_zoom)`` at ``t_s`` (held outside [0, duration])."""
        tx, ty, rot, lz = (float(np.interp(t_s, self._t_s, p)) for p in self._pose)
        return tx, ty, rot, lz

    def end_pose(self) -> tuple[float, float, float, float]:
        """The pose at the end of the last segment."""
        return self.pose(self.duration_s)

    def peak_speed_px_s(self) -> float:
        """Largest translation speed of the pans (sensor px/s; shakes not counted)."""
        return float(np.hypot(self._vel[0], self._vel[1]).max())


# Illumination ----------------------------------------------------------------------------

def illumination_gain(spec: dict[str, Any], t_s: np.ndarray | float,
                      duration_s: float) -> np.ndarray:
    """Global gain on the scene at ``t_s``: ``constant`` 1; ``ramp`` geometric from 1 to
    ``gain_end`` over the recording; ``sine`` and ``flicker`` ``1 + depth sin(2 pi freq_hz t
    + phase_rad)`` (flicker: 100 or 120 Hz, mains lighting)."""
    t = np.asarray(t_s, np.float64)
    kind = spec["kind"]
    if kind == "constant":
        return np.ones_like(t)
    if kind == "ramp":
        a = np.clip(t / duration_s, 0.0, 1.0)
        return np.asarray(float(spec["gain_end"]) ** a)
    if kind in ("sine", "flicker"):
        return 1.0 + float(spec["depth"]) * np.sin(2 * np.pi * float(spec["freq_hz"]) * t
                                                   + float(spec["phase_rad"]))
    raise ValueError(f"unknown illumination {kind!r} (constant, ramp, sine, flicker)")


def gain_bounds(spec: dict[str, Any]) -> tuple[float, float]:
    """Smallest and largest gain the illumination can reach (bounds, not the case's exact
    extremes for a slow sine)."""
    kind = spec["kind"]
    if kind == "ramp":
        g = float(spec["gain_end"])
        return min(1.0, g), max(1.0, g)
    if kind in ("sine", "flicker"):
        d = float(spec["depth"])
        return 1.0 - d, 1.0 + d
    return 1.0, 1.0


# The scene -------------------------------------------------------------------------------

class Scene:
    """The intensity (DN) a sensor of ``shape`` sees: a texture through a moving camera under
    a global illumination gain.

    A sensor pixel ``(x, y)`` samples the texture at ``centre + scale (tx, ty) + scale
    e^{-log_zoom} R(rot) (x - xc, y - yc)`` (bilinear, mirrored at the texture's border),
    and its value is ``(dn_lo + (dn_hi - dn_lo) g) * gain(t)`` for a texture value ``g`` in
    [0, 1]. Callable as ``scene(t_s) -> [H, W] float32``, with ``render_block(t_s, out=None)
    -> [K, H, W]`` for several times (the protocol of ``evcal.sim.sources.MovingScene``).
    Times are clamped to ``[0, duration_s]`` (as evcal's frame renderer clamps at 0).
    """

    def __init__(self, texture: np.ndarray, scale: float, shape: tuple[int, int],
                 dn_lo: float, dn_hi: float, motion: Motion, illumination: dict[str, Any],
                 duration_s: float):
        self.texture = np.ascontiguousarray(texture, np.float32)
        self.scale = float(scale)
        self.shape = (int(shape[0]), int(shape[1]))
        self.dn_lo, self.dn_hi = float(dn_lo), float(dn_hi)
        self.motion = motion
        self.illumination = dict(illumination)
        self.duration_s = float(duration_s)
        th, tw = self.texture.shape
        self._centre = np.array([(tw - 1) / 2.0, (th - 1) / 2.0])
        h, w = self.shape
        self._sensor_centre = np.array([(w - 1) / 2.0, (h - 1) / 2.0])

    def _affine(self, t_s: float) -> np.ndarray:
        """The 2x3 map from sensor pixel (x, y) to texture coordinates at ``t_s``."""
        tx, ty, rot, lz = self.motion.pose(t_s)
        s = self.scale * math.exp(-lz)
        c, sn = math.cos(rot), math.sin(rot)
        a = s * np.array([[c, -sn], [sn, c]])
        off = self._centre + self.scale * np.array([tx, ty]) - a @ self._sensor_centre
        return np.hstack([a, off[:, None]])

    def _clamp(self, t_s: float) -> float:
        return min(max(float(t_s), 0.0), self.duration_s)

    def texture_values(self, t_s: float) -> np.ndarray:
        """The texture value ``g`` in [0, 1] each pixel sees at ``t_s`` (float32 [H, W])."""
        h, w = self.shape
        return cv2.warpAffine(self.texture, self._affine(self._clamp(t_s)), (w, h),
                              flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                              borderMode=cv2.BORDER_REFLECT_101)

    def gain(self, t_s: np.ndarray | float) -> np.ndarray:
        """The illumination gain at ``t_s`` (clamped to the recording)."""
        t = np.clip(np.asarray(t_s, np.float64), 0.0, self.duration_s)
        return illumination_gain(self.illumination, t, self.duration_s)

    def __call__(self, t_s: float) -> np.ndarray:
        """Intensity (DN, float32 [H, W]) at ``t_s``."""
        out: np.ndarray = self.render_block([t_s])[0]
        return out

    def render_block(self, t_s: Sequence[float] | np.ndarray, out: np.ndarray | None = None
                     ) -> np.ndarray:
        """Intensity (DN) at each of ``t_s``: float32 ``[K, H, W]``, into ``out`` if given."""
        ts = [float(t) for t in np.asarray(t_s, np.float64).ravel()]
        if out is None:
            out = np.empty((len(ts), *self.shape), np.float32)
        gains = self.gain(np.asarray(ts))
        span = self.dn_hi - self.dn_lo
        for k, t in enumerate(ts):
            g = self.texture_values(t)
            out[k] = (self.dn_lo + span * g) * np.float32(gains[k])
        return out

    def exposure_mean(self, t_us: int, exposure_us: float, lag_us: float = 0.0
                      ) -> np.ndarray:
        """The intensity averaged over an exposure (float64 [H, W]): the mean of
        ``APS_BLUR_SAMPLES`` renders at ``c + ((i + 0.5) / n - 0.5) exposure_us``, ``c = t_us
        + lag_us`` (one render at ``c`` without exposure), as ``evcal.sim.nonideal``'s APS
        frames."""
        centre_us = float(t_us) + float(lag_us)
        if exposure_us <= 0:
            return self(max(0.0, centre_us * 1e-6)).astype(np.float64)
        offs = (np.arange(APS_BLUR_SAMPLES) + 0.5) / APS_BLUR_SAMPLES - 0.5
        ts = [max(0.0, (centre_us + o * exposure_us) * 1e-6) for o in offs]
        return self.render_block(ts).mean(axis=0, dtype=np.float64)

    def aps_frames(self, frame_t_us: np.ndarray, exposure_us: float, read_noise_dn: float,
                   rng: np.random.Generator) -> np.ndarray:
        """APS frames stamped at ``frame_t_us`` (the middle of their exposure): the exposure
        mean, Gaussian read noise of ``read_noise_dn``, rounded and clipped to uint8
        ``[n, H, W]``."""
        out = np.empty((len(frame_t_us), *self.shape), np.uint8)
        for m, t_us in enumerate(frame_t_us):
            img = self.exposure_mean(int(t_us), exposure_us)
            if read_noise_dn > 0:
                img = img + rng.normal(0.0, read_noise_dn, img.shape)
            out[m] = np.clip(np.rint(img), 0, 255).astype(np.uint8)
        return out

    def median_frame_dn(self, frame_t_us: np.ndarray, exposure_us: float) -> float:
        """Median over pixels and frames of the noise-free frame intensity (DN): the scene's
        median intensity that the light-dependent effects' truth refers to."""
        frames = np.stack([self.exposure_mean(int(t), exposure_us) for t in frame_t_us])
        return float(np.median(frames))


def build_scene(case: dict[str, Any]) -> Scene:
    """The :class:`Scene` of a benchmark case description (``sensor`` [H, W],
    ``duration_s``, ``scene``, ``dn_range`` [lo, hi] over the recording with the
    illumination included, ``motion``, ``illumination``)."""
    shape = (int(case["sensor"][0]), int(case["sensor"][1]))
    spec = case["scene"]
    raw = raw_texture(spec)
    scale = view_scale(raw.shape, shape, float(spec["view_fraction"]))
    texture = prepare_texture(raw, scale)
    g_min, g_max = gain_bounds(case["illumination"])
    lo, hi = (float(v) for v in case["dn_range"])
    motion = Motion(case["motion"], float(case["duration_s"]))
    return Scene(texture, scale, shape, lo / g_min, hi / g_max, motion, case["illumination"],
                 float(case["duration_s"]))


# Frames and files ------------------------------------------------------------------------

def frame_times_us(duration_s: float, period_us: int, phase_us: int = 0) -> np.ndarray:
    """APS frame stamps ``phase_us + m period_us`` within ``[0, duration]`` (int64 us)."""
    end_us = int(round(duration_s * 1e6))
    return np.arange(int(phase_us), end_us + 1, int(period_us), dtype=np.int64)


def write_npz(path: str | os.PathLike[str], arrays: dict[str, np.ndarray]) -> int:
    """Write ``arrays`` as a compressed ``.npz`` (numpy's layout, fixed member dates, so
    equal arrays give equal bytes) atomically: to a temporary file renamed into place.
    Returns the file's size in bytes."""
    path = Path(path)
    tmp = path.with_name(path.name + f".tmp{os.getpid()}")
    with open(tmp, "wb") as f, zipfile.ZipFile(f, "w", compression=zipfile.ZIP_DEFLATED,
                                               compresslevel=6) as zf:
        for key, arr in arrays.items():
            info = zipfile.ZipInfo(key + ".npy", date_time=(1980, 1, 1, 0, 0, 0))
            info.compress_type = zipfile.ZIP_DEFLATED
            info.external_attr = 0o644 << 16
            buf = io.BytesIO()
            np.lib.format.write_array(buf, np.asanyarray(arr), allow_pickle=False)
            zf.writestr(info, buf.getvalue(), compresslevel=6)
    os.replace(tmp, path)
    return path.stat().st_size


def recording_arrays(t_us: np.ndarray, x: np.ndarray, y: np.ndarray, p: np.ndarray,
                     frame_t_us: np.ndarray, frame_images: np.ndarray,
                     exposure_us: int, metadata_json: str) -> dict[str, np.ndarray]:
    """The arrays of an evcal ``.npz`` recording with event columns (``evcal.io.npz``):
    ``t_us`` int64, ``x``, ``y`` uint16, ``p`` int8 (+1 ON, -1 OFF), the frames, ``sensor``
    = [H, W] and the metadata."""
    n, h, w = frame_images.shape
    return {
        "t_us": np.asarray(t_us, np.int64),
        "x": np.asarray(x, np.uint16),
        "y": np.asarray(y, np.uint16),
        "p": np.where(np.asarray(p) > 0, 1, -1).astype(np.int8),
        "frame_t_us": np.asarray(frame_t_us, np.int64),
        "frame_images": np.asarray(frame_images, np.uint8),
        "frame_exposure_us": np.full(n, int(exposure_us), np.int64),
        "sensor": np.array([h, w], np.int64),
        "metadata_json": np.array(metadata_json),
    }


def write_json(path: str | os.PathLike[str], obj: Any) -> None:
    """Write ``obj`` as indented JSON atomically (temporary file renamed into place)."""
    path = Path(path)
    tmp = path.with_name(path.name + f".tmp{os.getpid()}")
    tmp.write_text(json.dumps(obj, indent=1, allow_nan=False) + "\n")
    os.replace(tmp, path)
