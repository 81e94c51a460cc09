"""Run every command block of README.md in order, as a newcomer would, and fail on any error.

    python scripts/run_readme.py                 # a fresh copy of this checkout, a fresh venv
    python scripts/run_readme.py --in-place      # here, with the interpreter's own venv (quick)
    python scripts/run_readme.py --committed     # the last commit alone, without the changes
    python scripts/run_readme.py --list          # the blocks and what would be done with each

The command blocks are the README's fences marked ``bash``, ``sh``, ``shell`` or ``console``
(``python`` and ``text`` fences are not commands). Each block runs as one ``bash`` script
with ``set -euo pipefail`` in the checkout's top folder; a block fails the run when a
command of it exits non-zero. A command line ending in ``&`` runs in the background, as the
service does in the walk-through: when the block's last command has finished, the background
commands still running are stopped with SIGTERM, newest first, and each must then exit 0
(within ``--stop-timeout`` seconds).

A block is marked by an HTML comment on the line before its fence (blank lines between are
allowed); the README shows nothing of it:

    <!-- readme-run: skip REASON -->    not run (REASON is printed): a ROS 2 rig, the test
                                        suite that CI has just run, ...

Unless ``--in-place``, the run is in a temporary folder: ``evcal/`` a clone of this
repository with the working tree's changes copied over it, ``shared`` a link to the shared
data (``$EVCAL_SHARED_DATA``'s parent, else the checkout's ``../shared``), so that the
README's ``../shared/data/...`` paths hold, and ``venv/`` a new virtual environment whose
``bin`` comes first on ``PATH`` (``python`` and ``pip`` are its own; pip's cache makes the
installs quick after the first). Afterwards the clone must have no file that git does not
ignore besides those copied into it: the README's examples write to ``out/``, or to names
``.gitignore`` lists. Exit status: 0 when every block succeeded, 1 otherwise, 2 bad usage.
"""

from __future__ import annotations

import argparse
import os
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
SHELLS = ("bash", "sh", "shell", "console")
FENCE = re.compile(r"^```(\w*)\s*$")
MARK = re.compile(r"^<!--\s*readme-run:\s*(\w+)\s*(.*?)\s*-->\s*$")
MODES = ("skip",)


@dataclass(frozen=True)
class Block:
    """One fenced command block: its first line's number (1-based), text and mark."""

    line: int
    text: str
    mode: str = "run"
    reason: str = ""

    @property
    def title(self) -> str:
        first = next((s for s in self.text.splitlines() if s.strip()
                      and not s.lstrip().startswith("#")), "")
        return first.strip()[:70]


def command_blocks(markdown: str) -> list[Block]:
    """The shell blocks of ``markdown`` in order, with the mark before each (ValueError for an
    unknown mark or an unclosed fence)."""
    lines = markdown.splitlines()
    out: list[Block] = []
    i = 0
    while i < len(lines):
        m = FENCE.match(lines[i])
        if not m:
            i += 1
            continue
        lang, start = m.group(1).lower(), i
        j = i + 1
        while j < len(lines) and not lines[j].startswith("```"):
            j += 1
        if j == len(lines):
            raise ValueError(f"line {start + 1}: a fence that is never closed")
        if lang in SHELLS:
            mode, reason = "run", ""
            k = start - 1
            while k >= 0 and not lines[k].strip():
                k -= 1
            mark = MARK.match(lines[k]) if k >= 0 else None
            if mark:
                mode, reason = mark.group(1), mark.group(2)
                if mode not in MODES:
                    raise ValueError(f"line {k + 1}: readme-run mark {mode!r}: expected one "
                                     f"of {', '.join(MODES)}")
            out.append(Block(start + 2, "\n".join(lines[start + 1 : j]), mode, reason))
        i = j + 1
    return out


PRELUDE = """\
set -euo pipefail
__bg=()
# A job forked but not yet exec'd still runs the shell's own TERM handler, which the exec
# then forgets: the signal would be lost. So wait (1 s at most) until it is its own program.
__execd() {
    local p=$1 n=0 me
    me=$(readlink /proc/$$/exe 2>/dev/null) || return 0
    while (( n < 20 )) && [ "$(readlink "/proc/$p/exe" 2>/dev/null)" = "$me" ]; do
        sleep 0.05; n=$((n + 1))
    done
}
__stop() {
    local rc=$? i p s waited
    set +e
    for (( i=${#__bg[@]}-1; i>=0; i-- )); do
        p=${__bg[i]}
        __execd "$p"
        kill -TERM "$p" 2>/dev/null
        waited=0
        while kill -0 "$p" 2>/dev/null && (( waited < STOP_TIMEOUT_DS )); do
            sleep 0.1; waited=$((waited + 1))
        done
        if kill -0 "$p" 2>/dev/null; then
            echo "readme-run: background command $p did not stop within the timeout" >&2
            kill -KILL "$p" 2>/dev/null; rc=1
        fi
        wait "$p"; s=$?
        if (( s != 0 )); then
            echo "readme-run: background command $p exited $s" >&2
            (( rc == 0 )) && rc=$s
        fi
    done
    exit $rc
}
trap __stop EXIT
"""


def script_of(block: Block, stop_timeout_s: float) -> str:
    """The bash script of ``block``: each line ending in `` &`` also records its job."""
    body = []
    for line in block.text.splitlines():
        body.append(line)
        code = line.split(" #", 1)[0].rstrip()
        if code.endswith("&") and not code.endswith("&&"):
            body.append("__bg+=($!)")
    prelude = PRELUDE.replace("STOP_TIMEOUT_DS", str(int(stop_timeout_s * 10)))
    return prelude + "\n".join(body) + "\n"


def _run(cmd: Sequence[str], cwd: Path, env: dict[str, str] | None = None) -> str:
    return subprocess.run(list(cmd), cwd=cwd, env=env, check=True, capture_output=True,
                          text=True).stdout


def untracked(checkout: Path) -> set[str]:
    """Files in ``checkout`` that git neither tracks nor ignores."""
    out = _run(["git", "status", "--porcelain", "--untracked-files=all"], checkout)
    return {line[3:] for line in out.splitlines() if line.startswith("??")}


def shared_dir() -> Path:
    data = os.environ.get("EVCAL_SHARED_DATA")
    return Path(data).resolve().parent if data else (REPO.parent / "shared").resolve()


def prepare(tmp: Path, python: str, committed: bool = False
            ) -> tuple[Path, dict[str, str], set[str]]:
    """A clone of this repository with the working tree's changes (none with ``committed``),
    the shared data beside it and a new venv first on PATH: ``(checkout, env, files copied
    over the clone)``."""
    checkout = tmp / "evcal"
    _run(["git", "clone", "--quiet", "--no-hardlinks", str(REPO), str(checkout)], REPO)
    changed = [] if committed else _run(
        ["git", "ls-files", "--modified", "--others", "--exclude-standard", "-z"],
        REPO).split("\0")
    deleted = set(_run(["git", "ls-files", "--deleted", "-z"], REPO).split("\0"))
    copied = set()
    for name in filter(None, changed):
        if name in deleted:
            (checkout / name).unlink(missing_ok=True)
            continue
        dst = checkout / name
        dst.parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(REPO / name, dst)
        copied.add(name)
    shared = shared_dir()
    if shared.exists():
        (tmp / "shared").symlink_to(shared, target_is_directory=True)
    venv = tmp / "venv"
    _run([python, "-m", "venv", str(venv)], tmp)
    env = dict(os.environ)
    env.pop("PYTHONPATH", None)
    env["VIRTUAL_ENV"] = str(venv)
    env["PATH"] = f"{venv / 'bin'}{os.pathsep}{env.get('PATH', '')}"
    return checkout, env, untracked(checkout) | copied


def run_block(block: Block, cwd: Path, env: dict[str, str], timeout_s: float,
              stop_timeout_s: float) -> int:
    """Run ``block`` in ``cwd``; its exit status (124 on timeout)."""
    proc = subprocess.Popen(["bash", "-c", script_of(block, stop_timeout_s)], cwd=cwd,
                            env=env, start_new_session=True)
    try:
        return proc.wait(timeout_s)
    except subprocess.TimeoutExpired:
        print(f"readme-run: the block took more than {timeout_s:g} s: stopped",
              file=sys.stderr, flush=True)
        os.killpg(proc.pid, signal.SIGTERM)
        try:
            proc.wait(stop_timeout_s)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
        return 124
    finally:
        if proc.poll() is None:  # interrupted: leave nothing running
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="run_readme.py",
                                description=__doc__.split("\n")[0] if __doc__ else None)
    p.add_argument("--readme", default="README.md", help="relative to the checkout")
    p.add_argument("--in-place", action="store_true",
                   help="run in this checkout with this interpreter's environment first on "
                        "PATH (quick; pip re-installs this checkout into it)")
    p.add_argument("--committed", action="store_true",
                   help="the last commit alone: without the working tree's changes")
    p.add_argument("--keep", action="store_true", help="keep the temporary folder")
    p.add_argument("--python", default=sys.executable,
                   help="interpreter that makes the fresh venv (default: this one)")
    p.add_argument("--timeout", type=float, default=600.0, metavar="S",
                   help="seconds a block may take (default 600)")
    p.add_argument("--stop-timeout", type=float, default=60.0, metavar="S",
                   help="seconds a background command may take to stop (default 60)")
    p.add_argument("--list", action="store_true", help="list the blocks and stop")
    return p


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        blocks = command_blocks((REPO / args.readme).read_text())
    except (OSError, ValueError) as exc:
        print(f"run_readme: {args.readme}: {exc}", file=sys.stderr)
        return 2
    if args.list:
        for b in blocks:
            what = f"skip ({b.reason})" if b.mode == "skip" else "run"
            print(f"line {b.line:4d}  {what}: {b.title}")
        return 0
    tmp = Path(tempfile.mkdtemp(prefix="evcal-readme-"))
    t0 = time.monotonic()
    results: list[tuple[Block, str, float]] = []
    try:
        if args.in_place:
            checkout, before = REPO, untracked(REPO)
            env = dict(os.environ)
            env["PATH"] = f"{Path(sys.executable).parent}{os.pathsep}{env.get('PATH', '')}"
        else:
            print(f"run_readme: a fresh checkout and venv in {tmp}", flush=True)
            checkout, env, before = prepare(tmp, args.python, args.committed)
        failed = False
        for b in blocks:
            if b.mode == "skip" or failed:
                why = b.reason if b.mode == "skip" else "an earlier block failed"
                results.append((b, f"skipped: {why}", 0.0))
                continue
            print(f"\n=== README line {b.line}: {b.title}", flush=True)
            t = time.monotonic()
            rc = run_block(b, checkout, env, args.timeout, args.stop_timeout)
            dt = time.monotonic() - t
            results.append((b, "ok" if rc == 0 else f"FAILED (exit {rc})", dt))
            failed = rc != 0
        left = sorted(untracked(checkout) - before)
        if left and not failed:
            print(f"\nrun_readme: the README's examples left files git does not ignore: "
                  f"{', '.join(left[:10])}" + (" ..." if len(left) > 10 else ""),
                  file=sys.stderr)
            failed = True
    finally:
        if args.keep:
            print(f"run_readme: kept {tmp}")
        else:
            shutil.rmtree(tmp, ignore_errors=True)
    print("\nrun_readme: README.md command blocks")
    for b, what, dt in results:
        print(f"  line {b.line:4d}  {dt:6.1f} s  {what:<10.70}  {b.title}")
    print(f"run_readme: {'FAILED' if failed else 'all passed'} in "
          f"{time.monotonic() - t0:.0f} s")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
