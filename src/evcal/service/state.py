"""Atomic per-camera snapshots in a state directory (``--state-dir``).

One file per camera, ``<quoted camera id>.npz`` (``lab/rig1/cam0`` -> ``lab%2Frig1%2Fcam0.npz``);
a quoted id longer than ``MAX_STEM`` characters is cut and given a hash suffix
(``<first 80 characters>~<16 hex digits of its SHA-256>.npz``), so any id has a valid, bounded
and distinct file name. The id itself is stored inside (``_camera_id``), an uncompressed
``.npz`` of plain arrays (``allow_pickle=False`` on load).

Atomicity: a snapshot is written to ``<name>.tmp-<pid>-<n>`` in the same directory, flushed
and ``fsync``-ed, then renamed over the final name with :func:`os.replace` (atomic on POSIX),
and the directory is ``fsync``-ed. A reader therefore sees the previous snapshot or the new
one, never a half-written file, whatever moment the process dies at (``kill -9``, power
loss). Temporary files left by a killed writer are ignored and, once older than
``TMP_MAX_AGE_S``, removed by :meth:`StateStore.load_all`.
"""

from __future__ import annotations

import hashlib
import itertools
import logging
import os
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from urllib.parse import quote, unquote

import numpy as np

from ..errors import StateError
from ..io._util import load_npz_arrays

log = logging.getLogger("evcal.service.state")

SUFFIX = ".npz"
TMP_MAX_AGE_S = 30.0
MAX_STEM = 100  # characters of a snapshot's file name before ".npz" (file systems allow 255)
ID_KEY = "_camera_id"
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


def snapshot_name(camera: str) -> str:
    """The file name of ``camera``'s snapshot: its quoted id, or a cut one with a hash."""
    stem = quote(camera, safe="")
    if len(stem) > MAX_STEM:
        digest = hashlib.sha256(camera.encode()).hexdigest()[:16]
        stem = f"{stem[:80]}~{digest}"
    return stem + SUFFIX


@dataclass(frozen=True)
class Snapshot:
    """One readable snapshot: the camera id it holds, its file, its arrays."""

    camera: str
    path: Path
    arrays: dict[str, np.ndarray]


class StateStore:
    """The snapshots of one service instance (or of several, behind a shared volume).

    Every failure to read one snapshot moves that file aside (``.bad``) with the reason
    logged and counted in ``bad``: a damaged file never stops a start.
    """

    def __init__(self, directory: str | os.PathLike[str]):
        self.dir = Path(directory)
        self.dir.mkdir(parents=True, exist_ok=True)
        self.bad = 0

    def path(self, camera: str) -> Path:
        return self.dir / snapshot_name(camera)

    def save(self, camera: str, arrays: dict[str, np.ndarray]) -> Path:
        return atomic_savez(self.path(camera), {**arrays, ID_KEY: np.array(camera)})

    def remove(self, camera: str) -> bool:
        """Delete ``camera``'s snapshot; True if there was one."""
        try:
            self.path(camera).unlink()
            return True
        except FileNotFoundError:
            return False

    def quarantine(self, path: Path, reason: str) -> None:
        """Move an unusable snapshot aside as ``<name>.bad`` (never deleted: evidence)."""
        self.bad += 1
        log.error("snapshot %s cannot be used (%s); moved aside to %s.bad", path.name, reason,
                  path.name)
        try:
            os.replace(path, path.with_name(path.name + ".bad"))
        except OSError as exc:
            log.error("cannot move %s aside: %s", path, exc)

    def load(self, camera: str) -> Snapshot | None:
        """``camera``'s snapshot, or None (none, or unreadable: moved aside)."""
        p = self.path(camera)
        if not p.is_file():
            return None
        snap = self._read(p)
        return snap if snap is not None and snap.camera == camera else None

    def _read(self, p: Path) -> Snapshot | None:
        try:
            arrays = load_npz(p)
            ident = arrays.pop(ID_KEY, None)
            if ident is None:  # written before ids were stored inside
                camera = unquote(p.name[: -len(SUFFIX)])
            elif ident.shape != () or ident.dtype.kind != "U":
                raise StateError(f"{ID_KEY} is {ident.dtype} {ident.shape}, expected a string")
            else:
                camera = str(ident)
        except Exception as exc:  # noqa: BLE001 - any damage: aside, never fatal
            self.quarantine(p, f"{type(exc).__name__}: {exc}")
            return None
        return Snapshot(camera, p, arrays)

    def snapshots(self, want: Callable[[str], bool] | None = None) -> list[Snapshot]:
        """Every readable snapshot (with ``want``, of the cameras it accepts); removes stale
        temp files, moves unreadable ones aside. A file whose name gives its camera id and
        ``want`` refuses is not read at all (another shard's, sharing the directory)."""
        out: list[Snapshot] = []
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
            if want is not None:
                named = unquote(p.name[: -len(SUFFIX)])
                if snapshot_name(named) == p.name and not want(named):
                    continue
            snap = self._read(p)
            if snap is not None and (want is None or want(snap.camera)):
                out.append(snap)
        return out

    def load_all(self) -> dict[str, dict[str, np.ndarray]]:
        """Every readable snapshot's arrays by camera id."""
        return {s.camera: s.arrays for s in self.snapshots()}
