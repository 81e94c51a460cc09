"""Compile evcal's numba kernels ahead of their first use and keep them in numba's disk cache.

numba compiles a kernel on its first call and, with ``cache=True``, writes the machine code
next to the source (``__pycache__``) or under ``NUMBA_CACHE_DIR``. Without this module a fresh
install pays that compilation (tens of seconds on 2 cores) inside its first ``evcal demo``,
``calibrate`` or ``serve``. :func:`compile_kernels` runs every estimator, the simulator, the
reconstruction and the streaming calibrator once on a tiny simulated recording, so the same
types are compiled that those commands use; afterwards every process loads them from the cache.

It runs at install time (``build_backend``: an editable install compiles into the source
tree it points at) and as ``evcal warmup`` (a container image, a read-only or moved install:
set ``NUMBA_CACHE_DIR`` to a place that survives). Only numpy, numba, pillow and msgpack
are needed, so that the install's build environment can run it.
"""

from __future__ import annotations

import importlib.util
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import partial

import numpy as np

__all__ = ["WarmupReport", "compile_kernels"]


@dataclass
class WarmupReport:
    """Seconds per stage; ``failed`` names a stage and its error (the rest still ran)."""

    seconds: dict[str, float] = field(default_factory=dict)
    failed: dict[str, str] = field(default_factory=dict)

    @property
    def total_s(self) -> float:
        return sum(self.seconds.values())


def _scene(height: int, width: int) -> np.ndarray:
    """A procedural gray texture (no bundled photo: scikit-image is not needed here)."""
    y, x = np.mgrid[0:height, 0:width].astype(np.float64)
    img = (np.sin(x / 3.1) * np.cos(y / 4.7) + 0.5 * np.sin((x + y) / 7.3))
    return np.asarray(img, np.float64)


def compile_kernels(progress: Callable[[str], None] | None = None) -> WarmupReport:
    """Run every compiled path once on a 32x24, 0.8 s simulation (see the module docstring).

    A stage that fails is recorded in the report and the others still run: a warm-up must
    never stop an install or a command."""
    from .estimators import ESTIMATORS, calibrate
    from .onei import OnEIConfig
    from .online import onei
    from .reconstruct import evaluate
    from .sim.ideal import SimConfig, simulate_ideal

    report = WarmupReport()
    state: dict[str, object] = {}

    def stage(name: str, fn: Callable[[], object]) -> None:
        if progress is not None:
            progress(name)
        t = time.monotonic()
        try:
            state[name] = fn()
        except Exception as exc:  # noqa: BLE001 - reported, never raised: see the docstring
            report.failed[name] = f"{type(exc).__name__}: {exc}"
        report.seconds[name] = time.monotonic() - t

    cfg = SimConfig(height=24, width=32, duration_s=0.8, seed=0, scene=_scene(96, 128))
    stage("simulate", lambda: simulate_ideal(cfg))
    sim = state.get("simulate")
    if sim is None:
        return report
    rec = sim.recording  # type: ignore[attr-defined]
    for method in ESTIMATORS:
        stage(method, partial(calibrate, rec, method, log_offset="auto"))
    # the service's and the demo's OnEI: small buffers, eager updates
    stage("onei-stream", lambda: onei(rec, OnEIConfig(n_small=1000, n_large=100_000,
                                                      eager=True, log_offset="auto")))
    cal = state.get("offei")
    if cal is not None:  # calibrate --posterior and serve --posterior
        from .posterior import posterior_maps

        stage("posterior", lambda: posterior_maps(cal))  # type: ignore[arg-type]
    # the scores need scikit-image's SSIM, which an install's build environment lacks; the
    # reconstruction's kernels are the estimators' (accumulation), compiled above
    if cal is not None and importlib.util.find_spec("skimage") is not None:
        stage("evaluate", lambda: evaluate(rec, cal, frames_per_image=2))  # type: ignore[arg-type]
    return report
