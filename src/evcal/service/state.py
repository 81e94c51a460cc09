"""Atomic per-camera snapshots in a state directory (``--state-dir``).

One file per camera, ``<quoted camera id>.npz`` (``lab/rig1/cam0`` -> ``lab%2Frig1%2Fcam0.npz``),
an uncompressed ``.npz`` of plain arrays (``allow_pickle=False`` on load).

Atomicity: a snapshot is written to ``<name>.tmp-<pid>-<n>`` in the same directory, flushed
and ``fsync``-ed, then renamed over the final name with :func:`os.replace` (atomic on POSIX),
and the directory is ``fsync``-ed. A reader therefore sees the previous snapshot or the new
one, never a half-written file, whatever moment the process dies at (``kill -9``, power
loss). Temporary files left by a killed writer are ignored and, once older than
``TMP_MAX_AGE_S``, removed by :meth:`StateStore.load_all`.
"""

from __future__ import annotations

import itertools
import logging
import os
import time
from pathlib import Path
from urllib.parse import quote, unquote

import numpy as np

from ..errors import StateError
from ..io._util import load_npz_arrays

log = logging.getLogger("evcal.service.state")

SUFFIX = ".npz"
TMP_MAX_AGE_S = 30.0
_counter = itertools.count()


def _fsync_dir(path: Path) -> None:
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def atomic_savez(path: Path, arrays: dict[str, np.ndarray]) -> Path:
    """Write ``arrays`` as an ``.npz`` at ``path`` atomically (temp file, fsync, rename)."""
    path = Path(path)
    tmp = path.with_name(f"{path.name}.tmp-{os.getpid()}-{next(_counter)}")
    try:
        with open(tmp, "wb") as f:
            np.savez(f, **arrays)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    _fsync_dir(path.parent)
    return path


def load_npz(path: Path) -> dict[str, np.ndarray]:
    return load_npz_arrays(path, StateError, "the snapshot")


class StateStore:
    """The snapshots of one service instance (or of several, behind a shared volume)."""

    def __init__(self, directory: str | os.PathLike[str]):
        self.dir = Path(directory)
        self.dir.mkdir(parents=True, exist_ok=True)

    def path(self, camera: str) -> Path:
        return self.dir / (quote(camera, safe="") + SUFFIX)

    def save(self, camera: str, arrays: dict[str, np.ndarray]) -> Path:
        return atomic_savez(self.path(camera), arrays)

    def load_all(self) -> dict[str, dict[str, np.ndarray]]:
        """Every readable snapshot by camera id; removes temp files, renames unreadable ones."""
        out: dict[str, dict[str, np.ndarray]] = {}
        for p in sorted(self.dir.iterdir()):
            if ".tmp-" in p.name:
                # a writer died before the rename; a young one may belong to a live
                # instance sharing the directory
                try:
                    if time.time() - p.stat().st_mtime > TMP_MAX_AGE_S:
                        p.unlink(missing_ok=True)
                except OSError:
                    pass
                continue
            if not p.name.endswith(SUFFIX):
                continue
            camera = unquote(p.name[: -len(SUFFIX)])
            try:
                out[camera] = load_npz(p)
            except StateError as exc:
                log.error("%s; moved aside to %s.bad", exc, p.name)
                os.replace(p, p.with_name(p.name + ".bad"))
        return out
