"""evcal's build backend: setuptools, plus the numba kernels compiled at editable install.

``pip install -e .`` builds an editable wheel whose modules are the files under ``src/``, so
numba's disk cache written there now (``__pycache__`` beside each kernel) is the cache every
later ``evcal`` command loads from: the first ``evcal demo`` or ``calibrate`` is then no
slower than the second. The kernels are compiled by :func:`evcal.warmup.compile_kernels` in a
subprocess of the build environment, which gets numba and the few packages it imports from
:func:`get_requires_for_build_editable`. numba's cache checks its own version and the
source files' stamps on load, so a build environment whose numba differs from the
installed one costs a compilation on first use, never a wrong kernel.

Regular wheels (``pip install .``, the container image) are installed elsewhere than the
sources they are built from, so they compile on first use or by ``evcal warmup``. Set
``EVCAL_NO_PRECOMPILE=1`` to skip the step. A failure here is reported and never stops the
install.
"""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

from setuptools import build_meta as _setuptools
from setuptools.build_meta import *  # noqa: F403 - every other hook is setuptools' own

# the imports of evcal.warmup's stages (the same bounds as the project's dependencies)
KERNEL_REQUIRES = ["numpy>=1.26", "numba>=0.59", "pillow>=10", "msgpack>=1.0"]
TIMEOUT_S = 900


def get_requires_for_build_editable(config_settings=None):  # type: ignore[no-untyped-def]
    requires = list(_setuptools.get_requires_for_build_editable(config_settings))
    if os.environ.get("EVCAL_NO_PRECOMPILE") != "1":
        requires += KERNEL_REQUIRES
    return requires


def build_editable(wheel_directory, config_settings=None,  # type: ignore[no-untyped-def]
                   metadata_directory=None):
    name = _setuptools.build_editable(wheel_directory, config_settings, metadata_directory)
    if os.environ.get("EVCAL_NO_PRECOMPILE") != "1":
        _compile_kernels(Path.cwd())
    return name


def _compile_kernels(root: Path) -> None:
    src = root / "src"
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(p for p in (str(src), env.get("PYTHONPATH")) if p)
    code = ("from evcal.warmup import compile_kernels\n"
            "r = compile_kernels()\n"
            "print(f'{r.total_s:.1f}')\n"
            "for k, v in r.failed.items(): print(f'{k}: {v}')\n")
    t = time.monotonic()
    try:
        out = subprocess.run([sys.executable, "-c", code], cwd=root, env=env, text=True,
                             capture_output=True, timeout=TIMEOUT_S, check=False)
    except (OSError, subprocess.TimeoutExpired) as exc:
        print(f"evcal: kernels not compiled at install ({exc}); they compile on first use",
              file=sys.stderr)
        return
    if out.returncode != 0:
        tail = (out.stderr or out.stdout).strip().splitlines()[-1:] or ["no output"]
        print(f"evcal: kernels not compiled at install ({tail[0]}); they compile on first "
              "use", file=sys.stderr)
        return
    print(f"evcal: compiled the numba kernels in {time.monotonic() - t:.0f} s "
          f"({out.stdout.strip()})", file=sys.stderr)
