"""The image's motion between frames read from the events (evcal.gap.motion).

A camera shaken faster than the frames follow swings the image out and back between two
frames; the flow interpolation's straight path misses it. Recordings here are made by
evcal's simulator from a texture moved along a known path at 1 kHz, with 25 Hz frames: the
shift read from the events must follow the path's departure from the straight line between
the frames' positions, and stay near zero where the motion is straight.
"""

from __future__ import annotations

from functools import cache

import numpy as np
import pytest

from evcal.errors import ConfigError
from evcal.gap.model import SimSettings, population, subframe_shift
from evcal.gap.motion import SubframeShift
from evcal.gap.stats import observe
from evcal.recording import Frames, Recording
from evcal.sim.effects import ShotNoise
from evcal.sim.ideal import SimConfig
from evcal.sim.nonideal import simulate

cv2 = pytest.importorskip("cv2")

H, W = 96, 128
DURATION_S = 2.0


def _texture(seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    tex = cv2.GaussianBlur(rng.standard_normal((H + 80, W + 80)).astype(np.float32), (0, 0), 2.0)
    tex = (tex - tex.min()) / (tex.max() - tex.min())
    out: np.ndarray = (20.0 + 200.0 * tex).astype(np.float32)
    return out


class PathSource:
    """A texture seen through a camera at ``path(t) -> (x, y)`` pixels: the image at ``t`` is
    the texture sampled at ``(x, y) + path(t)``."""

    def __init__(self, seed: int, path):  # type: ignore[no-untyped-def]
        self.tex = _texture(seed)
        self.path = path
        gy, gx = np.mgrid[0:H, 0:W].astype(np.float32)
        self.gx, self.gy = gx + 40.0, gy + 40.0

    def __call__(self, t_s: float) -> np.ndarray:
        out: np.ndarray = self.render_block([t_s])[0]
        return out

    def render_block(self, t_s, out=None):  # type: ignore[no-untyped-def]
        ts = np.asarray(t_s, np.float64).reshape(-1)
        if out is None:
            out = np.empty((ts.size, H, W), np.float32)
        for i, t in enumerate(ts):
            px, py = self.path(float(t))
            out[i] = cv2.remap(self.tex, self.gx + np.float32(px), self.gy + np.float32(py),
                               cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT)
        return out


def shaken(t: float) -> tuple[float, float]:
    return (-15.0 + 15.0 * t + 3.0 * np.sin(2 * np.pi * 11.0 * t),
            2.0 * np.sin(2 * np.pi * 7.0 * t + 1.0))


def straight(t: float) -> tuple[float, float]:
    return (-25.0 + 25.0 * t, -6.0 + 6.0 * t)


def still(t: float) -> tuple[float, float]:
    return (0.0, 0.0)


@cache
def recording(kind: str, seed: int) -> Recording:
    path = {"shaken": shaken, "straight": straight, "still": still}[kind]
    effects = [ShotNoise(rate_hz=150.0)] if kind == "still" else []
    cfg = SimConfig(height=H, width=W, duration_s=DURATION_S, frame_rate_hz=25.0,
                    internal_rate_hz=1000.0, contrast_mean=0.15, contrast_std=0.02,
                    bias_mean=0.0, bias_std=0.005, log_offset=1.0, seed=seed)
    return simulate(cfg, effects, source=PathSource(seed, path)).recording


def read_shift(rec: Recording) -> tuple[SubframeShift, dict[str, float]]:
    return subframe_shift(rec, SimSettings(interpolation="flow"), population(observe(rec)))


def departure(path, t_us: np.ndarray, frame_t_us: np.ndarray) -> np.ndarray:  # type: ignore[no-untyped-def]
    """The path at ``t_us`` less the straight line between its places at the frames."""
    at = np.array([path(x * 1e-6) for x in t_us])
    at_f = np.array([path(x * 1e-6) for x in frame_t_us])
    lin = np.stack([np.interp(t_us, frame_t_us, at_f[:, i]) for i in range(2)], axis=1)
    out: np.ndarray = at - lin
    return out


@pytest.mark.parametrize("seed", [3, 4])
def test_a_shake_between_frames_is_read_from_the_events(seed: int) -> None:
    rec = recording("shaken", seed)
    assert rec.frames is not None
    shift, info = read_shift(rec)
    assert info["kept"] >= 0.8 * info["intervals"]
    true = departure(shaken, shift.t_us, rec.frames.t_us)
    for axis in range(2):
        s, d = shift.shift_px[:, axis].astype(np.float64), true[:, axis]
        assert np.corrcoef(s, d)[0, 1] > 0.85, axis
        slope = float(s @ d / (d @ d))
        assert 0.6 < slope < 1.3, (axis, slope)


def test_a_straight_motion_leaves_the_path_alone() -> None:
    rec = recording("straight", 5)
    shift, _ = read_shift(rec)
    # the shaken recording's departure is about 1.5 px RMS
    assert shift.rms_px < 0.15


def test_noise_events_in_a_still_scene_move_nothing() -> None:
    from evcal.gap.flow import FlowInterpolator
    from evcal.gap.motion import estimate_shift

    rec = recording("still", 6)
    assert rec.frames is not None
    # a still scene has no pixel to fit: the thresholds are the simulation's
    interp = FlowInterpolator(rec.frames, (H, W))
    ev = rec.events
    shift, info = estimate_shift(interp, ev["t_us"], ev["x"], ev["y"], ev["p"],
                                 contrast=0.15, bias=0.0, log_offset=1.0)
    assert info["intervals"] >= 40  # the noise makes pairs enough to try every interval
    assert shift.rms_px < 0.05


def test_the_shift_moves_the_rendered_image_between_frames_only() -> None:
    from evcal.gap.flow import FlowInterpolator

    rng = np.random.default_rng(0)
    img = cv2.GaussianBlur(rng.uniform(20, 220, (40, 50)).astype(np.float32), (0, 0), 1.5)
    frames = Frames(np.array([0, 40_000]), np.stack([img, img]), np.zeros(2, np.int64))
    shift = SubframeShift(np.array([0, 20_000, 40_000]), np.array([[0, 0], [1.0, 0], [0, 0]]))
    plain = FlowInterpolator(frames, (40, 50))
    moved = FlowInterpolator(frames, (40, 50), shift=shift)
    ts = np.array([0.0, 0.02, 0.04])
    a, b = plain.render_block(ts), moved.render_block(ts)
    assert np.array_equal(a[0], b[0])
    assert np.array_equal(a[2], b[2])
    # at 20 ms the image is sampled one pixel to the right: column x holds x + 1's value
    inner = (slice(5, -5), slice(5, -6))
    expect = np.roll(a[1], -1, axis=1)
    assert np.abs(b[1][inner] - expect[inner]).max() < 0.5
    assert np.abs(b[1][inner] - a[1][inner]).max() > 5.0


def test_a_recording_without_fitted_pixels_reads_no_shift() -> None:
    shift, info = read_shift(recording("still", 6))
    assert shift.t_us.size == 0
    assert info == {}


def test_a_shift_checks_its_knots() -> None:
    with pytest.raises(ConfigError, match="knot times"):
        SubframeShift(np.array([0, 1]), np.zeros((3, 2)))
    with pytest.raises(ConfigError, match="must not decrease"):
        SubframeShift(np.array([5, 1]), np.zeros((2, 2)))
    with pytest.raises(ConfigError, match="finite"):
        SubframeShift(np.array([0, 1]), np.array([[0, np.nan], [0, 0]]))
    s = SubframeShift(np.array([0, 10]), np.array([[0, 0], [2.0, -1.0]]))
    assert np.allclose(s.at(np.array([5, 10, 20])), [[1.0, -0.5], [2.0, -1.0], [0.0, 0.0]])
