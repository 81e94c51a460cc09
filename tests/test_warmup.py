"""Kernels compiled once per install (issue 40): the warm-up compiles every kernel the
commands use, so that a first ``evcal demo`` or ``calibrate`` after an editable install is no
slower than a second; the build backend asks for what the warm-up imports."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

# another workload than the warm-up's: other sizes, a bundled photo, fixed and estimated
# offsets, every estimator, the streaming calibrator, the reconstruction, the file formats
WORKLOAD = r"""
import json, sys, tempfile
from pathlib import Path
import numba.core.registry
import evcal
from evcal.estimators import ESTIMATORS, calibrate
from evcal.onei import OnEIConfig
from evcal.online import onei
from evcal.reconstruct import evaluate
from evcal.sim.ideal import SimConfig, simulate_ideal

rec = simulate_ideal(SimConfig(height=40, width=56, duration_s=1.0, seed=3)).recording
for m in ESTIMATORS:
    for offset in ("auto", 5.0):
        calibrate(rec, m, log_offset=offset)
onei(rec, OnEIConfig(n_small=4000, n_large=200_000, eager=True, log_offset="auto"))
cal = evcal.offei(rec)
evaluate(rec, cal, frames_per_image=3)
with tempfile.TemporaryDirectory() as d:
    evcal.save_calibration(cal, Path(d) / "c.npz")
    evcal.load_calibration(Path(d) / "c.npz")

missed = {}
for name, mod in list(sys.modules.items()):
    if not name.startswith("evcal"):
        continue
    for attr, obj in vars(mod).items():
        if isinstance(obj, numba.core.registry.CPUDispatcher):
            stats = obj.stats
            if stats.cache_misses:
                missed[f"{name}.{attr}"] = [str(k) for k in stats.cache_misses]
print(json.dumps(missed))
"""


def _run(args: list[str], **kw: object) -> subprocess.CompletedProcess[str]:
    env = {k: v for k, v in os.environ.items() if k != "NUMBA_DISABLE_JIT"}
    return subprocess.run(args, cwd=ROOT, env=env, text=True, capture_output=True,
                          timeout=600, check=False, **kw)  # type: ignore[call-overload]


def test_warmup_compiles_every_kernel_the_commands_use() -> None:
    # the warm-up (a no-op when the install compiled already), then another process
    warm = _run([sys.executable, "-m", "evcal", "warmup", "-q"])
    assert warm.returncode == 0, warm.stderr
    assert "kernels in" in warm.stdout
    work = _run([sys.executable, "-c", WORKLOAD])
    assert work.returncode == 0, work.stderr
    missed = json.loads(work.stdout.strip().splitlines()[-1])
    # a kernel compiled here and not loaded from the cache is one the warm-up left out
    assert missed == {}, f"kernels the warm-up does not compile: {missed}"


def test_build_backend_asks_for_what_the_warmup_imports(monkeypatch: pytest.MonkeyPatch
                                                         ) -> None:
    sys.path.insert(0, str(ROOT / "build_backend"))
    try:
        import evcal_build
    finally:
        sys.path.pop(0)
    tomllib = pytest.importorskip("tomllib")  # Python 3.11+
    pyproject = tomllib.loads((ROOT / "pyproject.toml").read_text())
    assert pyproject["build-system"]["build-backend"] == "evcal_build"
    deps = set(pyproject["project"]["dependencies"])
    # the same bounds as the runtime's, so both environments resolve alike
    assert set(evcal_build.KERNEL_REQUIRES) <= deps
    # setuptools' own list needs its build environment (setuptools >= 77): ours is added
    monkeypatch.setattr(evcal_build._setuptools, "get_requires_for_build_editable",
                        lambda config_settings=None: ["wheel"])
    asked = evcal_build.get_requires_for_build_editable()
    assert asked[0] == "wheel"
    assert set(evcal_build.KERNEL_REQUIRES) <= set(asked)
    monkeypatch.setenv("EVCAL_NO_PRECOMPILE", "1")
    assert evcal_build.get_requires_for_build_editable() == ["wheel"]


def test_warmup_reports_a_failed_stage_and_goes_on(monkeypatch: pytest.MonkeyPatch) -> None:
    from evcal import estimators, warmup

    calls: list[str] = []
    real = estimators.calibrate

    def flaky(rec: object, method: str, **kw: object) -> object:
        calls.append(method)
        if method == "offe":
            raise RuntimeError("boom")
        return real(rec, method, **kw)  # type: ignore[arg-type]

    monkeypatch.setattr(estimators, "calibrate", flaky)
    report = warmup.compile_kernels()
    assert report.failed == {"offe": "RuntimeError: boom"}
    assert {"offei", "brandli"} <= set(calls)  # the stages after it still ran
