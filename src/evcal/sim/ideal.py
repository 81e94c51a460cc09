"""The ideal simulator: a photo moved by a camera, ideal DVS pixels with per-pixel ``c``, ``b``.

The DVS sees ``L = log(I + log_offset)`` where ``I`` is the scene intensity in frame units
(DN); APS frames are ``I`` at the frame times, optionally quantised to 8 bits. Everything is
deterministic for a seed. The non-ideal simulator (issue 3) builds on :class:`SimConfig`,
:func:`draw_maps` and :class:`~evcal.sim.dvs.IdealDvs`.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

from ..errors import ConfigError
from ..events import SensorSize, empty_events
from ..recording import Frames, Recording, concat_events
from .dvs import IdealDvs
from .scene import Renderer, Trajectory, load_scene


@dataclass(frozen=True, kw_only=True)
class SimConfig:
    """Parameters of a simulated recording (units in names; times in seconds or µs)."""

    height: int = 180
    width: int = 240
    duration_s: float = 10.0
    frame_rate_hz: float = 25.0
    internal_rate_hz: float = 1000.0
    contrast_mean: float = 0.2
    contrast_std: float = 0.03
    bias_mean: float = 0.02
    bias_std: float = 0.01
    log_offset: float = 30.0
    # a bundled photo's name, an image file, or a gray/RGB array (load_scene)
    scene: str | np.ndarray = "astronaut"
    trajectory: Trajectory = field(default_factory=Trajectory)
    quantise_frames: bool = True
    min_dn: float = 8.0
    max_dn: float = 240.0
    seed: int = 0

    def __post_init__(self) -> None:
        SensorSize(self.height, self.width)
        checks = {
            "duration_s": self.duration_s > 0,
            "frame_rate_hz": self.frame_rate_hz > 0,
            "internal_rate_hz": self.internal_rate_hz >= self.frame_rate_hz,
            "contrast_mean": self.contrast_mean > 0,
            "contrast_std": self.contrast_std >= 0,
            "bias_std": self.bias_std >= 0,
            "log_offset": self.log_offset >= 0,
        }
        for name, ok in checks.items():
            if not ok:
                raise ConfigError(f"simulation {name}={getattr(self, name)} is out of range")

    @property
    def sensor(self) -> SensorSize:
        return SensorSize(self.height, self.width)

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["trajectory"] = asdict(self.trajectory)
        if isinstance(self.scene, np.ndarray):
            d["scene"] = f"array {'x'.join(map(str, self.scene.shape))}"
        return d


def draw_maps(cfg: SimConfig, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Per-pixel ``c ~ N(contrast_mean, contrast_std)``, ``b ~ N(bias_mean, bias_std)``.

    ``c`` is kept >= 0.3 * contrast_mean and ``|b| <= 0.8 c`` so both thresholds stay positive.
    """
    shape = (cfg.height, cfg.width)
    c = rng.normal(cfg.contrast_mean, cfg.contrast_std, shape)
    c = np.maximum(c, 0.3 * cfg.contrast_mean)
    b = rng.normal(cfg.bias_mean, cfg.bias_std, shape)
    b = np.clip(b, -0.8 * c, 0.8 * c)
    return c.astype(np.float64), b.astype(np.float64)


def frame_times_us(cfg: SimConfig) -> np.ndarray:
    n = int(np.floor(cfg.duration_s * cfg.frame_rate_hz)) + 1
    result: np.ndarray = np.rint(np.arange(n) * 1e6 / cfg.frame_rate_hz).astype(np.int64)
    return result


def internal_times_us(cfg: SimConfig) -> np.ndarray:
    """Internal sample times: a regular grid plus every frame time (so frames are exact)."""
    n = int(np.ceil(cfg.duration_s * cfg.internal_rate_hz)) + 1
    grid = np.rint(np.arange(n) * 1e6 / cfg.internal_rate_hz).astype(np.int64)
    end = int(np.rint(cfg.duration_s * 1e6))
    return np.unique(np.concatenate([grid[grid <= end], frame_times_us(cfg)]))


def to_frame(intensity: np.ndarray, quantise: bool) -> np.ndarray:
    if quantise:
        result: np.ndarray = np.clip(np.rint(intensity), 0, 255).astype(np.uint8)
        return result
    return intensity.astype(np.float32)


@dataclass
class SimResult:
    recording: Recording
    truth: dict[str, Any]


def iter_ideal(
    cfg: SimConfig,
    contrast: np.ndarray,
    bias: np.ndarray,
    rng: np.random.Generator,
    *,
    intensity_fn: Callable[[float], np.ndarray] | None = None,
    progress: Callable[[int], None] | None = None,
) -> Iterator[tuple[int, np.ndarray, np.ndarray | None]]:
    """Yield ``(t_us, events_since_previous_sample, frame_or_None)`` for every internal sample.

    ``intensity_fn(t_s)`` overrides the moving photo (e.g. to drive the sensor with measured
    frames).
    """
    if intensity_fn is None:
        scene = load_scene(cfg.scene, min_dn=cfg.min_dn, max_dn=cfg.max_dn)
        renderer = Renderer(scene, (cfg.height, cfg.width), cfg.trajectory)
        intensity_fn = renderer.render
    dvs = IdealDvs(contrast, bias)
    frame_set = set(frame_times_us(cfg).tolist())
    times = internal_times_us(cfg)
    i0 = intensity_fn(0.0)
    dvs.reset(np.log(i0.astype(np.float64) + cfg.log_offset), int(times[0]), rng)
    yield int(times[0]), empty_events(), (
        to_frame(i0, cfg.quantise_frames) if int(times[0]) in frame_set else None
    )
    for k, t in enumerate(times[1:], 1):
        img = intensity_fn(t * 1e-6)
        ev = dvs.step(np.log(img.astype(np.float64) + cfg.log_offset), int(t))
        frame = to_frame(img, cfg.quantise_frames) if int(t) in frame_set else None
        if progress is not None:
            progress(k)
        yield int(t), ev, frame


def simulate_ideal(
    cfg: SimConfig,
    *,
    maps: tuple[np.ndarray, np.ndarray] | None = None,
    progress: Callable[[int], None] | None = None,
) -> SimResult:
    """Simulate a whole recording in memory; ``truth`` holds the maps, offset and seed.

    ``maps``: the true ``(contrast, bias)`` ([H, W] each) in place of those ``cfg`` draws
    (drawn all the same, so that the rest of the run sees the same random stream)."""
    rng = np.random.default_rng(cfg.seed)
    c, b = draw_maps(cfg, rng)
    if maps is not None:
        c, b = (np.asarray(m, np.float64) for m in maps)
        if c.shape != cfg.sensor.shape or b.shape != cfg.sensor.shape:
            raise ConfigError(f"maps of shapes {c.shape} and {b.shape}; the sensor is "
                              f"{cfg.sensor.shape}")
    chunks: list[np.ndarray] = []
    f_t: list[int] = []
    f_img: list[np.ndarray] = []
    for t, ev, frame in iter_ideal(cfg, c, b, rng, progress=progress):
        if ev.size:
            chunks.append(ev)
        if frame is not None:
            f_t.append(t)
            f_img.append(frame)
    frames = Frames(
        t_us=np.asarray(f_t, np.int64),
        images=np.stack(f_img),
        exposure_us=np.zeros(len(f_t), np.int64),
    )
    rec = Recording(
        cfg.sensor,
        concat_events(chunks),
        frames,
        {"source": "evcal.sim.ideal", "sim_config": cfg.to_dict()},
    )
    truth = {
        "contrast": c.astype(np.float32),
        "bias": b.astype(np.float32),
        "log_offset": float(cfg.log_offset),
        "seed": int(cfg.seed),
    }
    return SimResult(rec, truth)
