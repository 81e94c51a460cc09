"""scripts/run_readme.py: which README blocks it runs, and how a block with background
commands is run and stopped (the README itself is run by CI, not here)."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def runner():
    spec = importlib.util.spec_from_file_location("run_readme", ROOT / "scripts" / "run_readme.py")
    assert spec is not None
    assert spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    sys.modules["run_readme"] = mod
    spec.loader.exec_module(mod)
    yield mod
    sys.modules.pop("run_readme", None)


def test_blocks_and_marks(runner):
    text = ("# t\n\n```bash\necho one\n```\n\n```python\nprint(2)\n```\n\n"
            "<!-- readme-run: skip needs a rig -->\n\n```sh\necho three\n```\n```text\nx\n```\n")
    blocks = runner.command_blocks(text)
    assert [(b.line, b.text, b.mode, b.reason) for b in blocks] == [
        (4, "echo one", "run", ""), (14, "echo three", "skip", "needs a rig")]
    with pytest.raises(ValueError, match="never closed"):
        runner.command_blocks("```bash\necho\n")
    with pytest.raises(ValueError, match="expected one of skip"):
        runner.command_blocks("<!-- readme-run: later -->\n```bash\necho\n```\n")


def test_the_readme_runs_the_walk_through_and_skips_the_test_command(runner):
    blocks = runner.command_blocks((ROOT / "README.md").read_text())
    run = [b for b in blocks if b.mode == "run"]
    assert any("evcal demo" in b.text for b in run)
    assert any("evcal serve --listen" in b.text and "evcal query" in b.text for b in run)
    skipped = [b for b in blocks if b.mode == "skip"]
    assert any("pytest" in b.text for b in skipped)


def test_background_commands_are_stopped_and_must_exit_0(runner, tmp_path):
    """A background command still running when the block ends gets SIGTERM and must exit 0
    (evcal's serve and record do); one that dies of the signal fails the block, as does a
    failing foreground command (its background commands are stopped all the same)."""
    env = {"PATH": "/usr/bin:/bin"}
    # it says when its handler is in place (else the SIGTERM could come first)
    clean = ("bash -c 'trap \"exit 0\" TERM; touch ready; sleep 30 & wait' &\n"
             "while [ ! -e ready ]; do sleep 0.05; done")
    ok = runner.Block(1, f"{clean}\necho fg > out.txt")
    assert "__bg+=($!)" in runner.script_of(ok, 5.0)
    assert runner.run_block(ok, tmp_path, env, 20.0, 5.0) == 0
    assert (tmp_path / "out.txt").read_text() == "fg\n"
    assert runner.run_block(runner.Block(1, "sleep 30 &\ntrue"), tmp_path, env, 20.0,
                            5.0) == 143
    assert runner.run_block(runner.Block(1, f"{clean}\nfalse\necho no > out.txt"), tmp_path,
                            env, 20.0, 5.0) == 1
    assert (tmp_path / "out.txt").read_text() == "fg\n"
    # a block that outlasts its timeout is stopped
    assert runner.run_block(runner.Block(1, "sleep 30"), tmp_path, env, 1.0, 5.0) == 124
