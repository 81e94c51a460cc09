"""The layering contract (ARCHITECTURE.md), checked on the source and in a fresh interpreter.

- the core (everything but ``service``, ``clients`` and the two display modules) never imports
  zenoh, rerun or matplotlib, at module level or inside a function;
- ``evcal.service.transport`` is the only module importing zenoh;
- rerun is imported by exactly one module for the service (``service/rrdlog.py``) and
  one for the gap workflow (``gap/rrd.py``); matplotlib only by ``gap/report.py``;
- importing ``evcal`` and running its core loads none of them;
- the version is declared once (pyproject) and the package reports it.
"""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

import evcal

SRC = Path(evcal.__file__).resolve().parent
HEAVY = ("zenoh", "rerun", "matplotlib")
ALLOWED = {
    "zenoh": {"service/transport.py"},
    "rerun": {"service/rrdlog.py", "gap/rrd.py"},
    "matplotlib": {"gap/report.py"},
}


def _imports(path: Path) -> set[str]:
    """Top-level package names a module imports anywhere in its body."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    out: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out.update(a.name.split(".")[0] for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            out.add(node.module.split(".")[0])
    return out


def _modules() -> list[tuple[str, Path]]:
    return sorted((p.relative_to(SRC).as_posix(), p) for p in SRC.rglob("*.py"))


def test_the_source_tree_is_where_the_contract_expects_it():
    names = {rel for rel, _ in _modules()}
    assert {"service/transport.py", "service/rrdlog.py", "gap/rrd.py",
            "gap/report.py", "service/camera.py", "service/ingest.py",
            "service/outputs.py", "stream.py", "solver.py", "offline.py"} <= names


@pytest.mark.parametrize("package", HEAVY)
def test_heavy_imports_live_in_their_one_module(package):
    users = {rel for rel, path in _modules() if package in _imports(path)}
    assert users == ALLOWED[package], f"{package} is imported by {sorted(users)}"


def test_the_core_never_imports_the_service_layers():
    core = [(rel, p) for rel, p in _modules()
            if not rel.startswith(("service/", "clients/")) and rel != "cli.py"]
    assert len(core) > 20
    for rel, path in core:
        tree = ast.parse(path.read_text(encoding="utf-8"))
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom):
                mod = node.module or ""
                target = mod if node.level == 0 else "." * node.level + mod
                parts = target.split(".")
                assert "service" not in parts, f"{rel} imports {target}"
                assert "clients" not in parts, f"{rel} imports {target}"


def test_core_runs_without_the_service_extras():
    # a fresh interpreter where zenoh, rerun and matplotlib cannot be imported at all: the
    # core imports, simulates, calibrates, evaluates and writes files
    code = """
import sys
class Block:
    def find_spec(self, name, path=None, target=None):
        if name.split('.')[0] in ('zenoh', 'rerun', 'matplotlib'):
            raise ImportError(f'{name} is blocked in this test')
sys.meta_path.insert(0, Block())
import tempfile, pathlib
import evcal
from evcal.sim.ideal import SimConfig, simulate_ideal
rec = simulate_ideal(SimConfig(height=16, width=20, duration_s=0.4, seed=3)).recording
cal = evcal.calibrate(rec, 'offei', window_frames=2)
res = evcal.evaluate(rec, cal, frames_per_image=2)
d = pathlib.Path(tempfile.mkdtemp())
evcal.save_calibration(cal, d / 'c.npz'); evcal.write_recording(rec, d / 'r.mcap')
assert evcal.load_calibration(d / 'c.npz').shape == (16, 20)
assert evcal.open_recording(d / 'r.mcap').n_events == rec.n_events
loaded = sorted(m for m in sys.modules if m.split('.')[0] in ('zenoh', 'rerun', 'matplotlib'))
assert not loaded, loaded
print('ok', res.n_images)
"""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.startswith("ok ")


def test_version_is_declared_once():
    root = SRC.parents[1]
    pyproject = root / "pyproject.toml"
    if not pyproject.is_file():
        pytest.skip("not running from a source checkout")
    text = pyproject.read_text(encoding="utf-8")
    declared = next(line.split("=")[1].strip().strip('"') for line in text.splitlines()
                    if line.startswith("version ="))
    assert evcal.__version__ == declared
    for rel, path in _modules():
        src = path.read_text(encoding="utf-8")
        assert f'"{declared}"' not in src, rel
        assert f"'{declared}'" not in src, rel


def test_public_api_is_at_package_level():
    for name in ("offei", "onei", "OnlineCalibrator", "offe", "brandli", "calibrate",
                 "open_recording", "load_calibration", "save_calibration", "evaluate",
                 "simulate", "run_gap", "EvcalError", "StreamGuard", "frame_intervals"):
        assert name in evcal.__all__, name
        assert hasattr(evcal, name), name
    # one error base: every error class the package defines derives from it
    for rel, path in _modules():
        tree = ast.parse(path.read_text(encoding="utf-8"))
        for node in ast.walk(tree):
            if isinstance(node, ast.ClassDef) and node.name.endswith("Error"):
                mod = "evcal." + rel[:-3].replace("/", ".")
                cls = getattr(__import__(mod, fromlist=["x"]), node.name, None)
                if cls is None or not issubclass(cls, Exception):
                    continue
                if rel.startswith(("service/transport", "clients/", "cli")):
                    continue  # network and command-line failures, not input errors
                assert issubclass(cls, evcal.EvcalError), f"{mod}.{node.name}"


def test_architecture_md_names_every_module():
    """ARCHITECTURE.md's module list names each module by its path (``io/evencode``,
    ``denoise``), in backticks."""
    doc = SRC.parents[1] / "ARCHITECTURE.md"
    if not doc.is_file():
        pytest.skip("not running from a source checkout")
    text = doc.read_text(encoding="utf-8")
    missing = [rel[:-3] for rel, _ in _modules()
               if not rel.endswith("__init__.py") and f"`{rel[:-3]}`" not in text]
    assert not missing, f"ARCHITECTURE.md does not name {missing}"


def test_evcal_onei_is_the_package_and_calls_the_function():
    """``evcal.onei`` names the OnEI package and its function: both uses work."""
    import importlib
    import inspect

    from evcal.online import onei

    pkg = importlib.import_module("evcal.onei")
    assert evcal.onei is pkg
    assert evcal.onei.offset is importlib.import_module("evcal.onei.offset")
    assert pkg.onei is onei
    assert callable(evcal.onei)
    assert inspect.signature(evcal.onei) == inspect.signature(onei)
    assert evcal.ESTIMATORS["onei"].name == "onei"


# builtin exceptions that evcal raises only where arguments are parsed: argparse and the
# flag helpers turn a ValueError into a usage message (exit 2) with the flag's name
BUILTIN_RAISES = {"ValueError", "RuntimeError", "TypeError", "Exception"}
ARGUMENT_PARSING = {
    "service/cli.py": {"ros2_from_args", "main_serve"},
    "service/transport.py": {"options_from_args", "_scouting", "check_key"},
    "service/ros2.py": {"default_domain", "TopicMap.parse"},
}
# raises in modules being rewritten when this check came (issue 22), converted since: empty,
# and it stays so
NOT_YET: dict[str, set[str]] = {}


def _builtin_raises(tree: ast.AST) -> list[tuple[int, str, str]]:
    """``(line, enclosing function's dotted name, exception)`` of every ``raise ValueError``
    (or another of :data:`BUILTIN_RAISES`), called or not."""
    found: list[tuple[int, str, str]] = []
    scope: list[str] = []

    class Visitor(ast.NodeVisitor):
        def visit_FunctionDef(self, node: ast.FunctionDef | ast.AsyncFunctionDef
                              | ast.ClassDef) -> None:
            scope.append(node.name)
            self.generic_visit(node)
            scope.pop()

        visit_AsyncFunctionDef = visit_ClassDef = visit_FunctionDef

        def visit_Raise(self, node: ast.Raise) -> None:
            exc = node.exc.func if isinstance(node.exc, ast.Call) else node.exc
            if isinstance(exc, ast.Name) and exc.id in BUILTIN_RAISES:
                found.append((node.lineno, ".".join(scope), exc.id))

    Visitor().visit(tree)
    return found


def test_errors_raised_are_evcal_errors_outside_argument_parsing():
    """Every ``raise`` of the package names an :class:`~evcal.EvcalError` class (with its
    ``ErrorReason``), not ``ValueError`` or ``RuntimeError``, except in the functions that
    parse command-line arguments."""
    bad = []
    for rel, path in _modules():
        allowed = ARGUMENT_PARSING.get(rel, set()) | NOT_YET.get(rel, set())
        for line, where, name in _builtin_raises(ast.parse(path.read_text(encoding="utf-8"))):
            if where not in allowed:
                bad.append(f"{rel}:{line} {where or '<module>'} raises {name}")
    assert not bad, "\n".join(bad)


def test_the_raise_check_sees_raises_of_builtin_errors():
    tree = ast.parse("class A:\n    def f(self):\n        raise ValueError('x')\n"
                     "def g():\n    raise RuntimeError\n"
                     "def h():\n    raise evcal.ConfigError('y')\n")
    assert _builtin_raises(tree) == [(3, "A.f", "ValueError"), (5, "g", "RuntimeError")]


def test_the_package_is_strictly_typed_and_lint_clean():
    """``mypy`` (strict on all of ``src/evcal``, configured in pyproject.toml, no module
    excluded) and ``ruff check src tests scripts`` pass: part of the test command, so CI
    checks them with everything else."""
    root = SRC.parents[1]
    if not (root / "pyproject.toml").is_file():
        pytest.skip("not running from a source checkout")
    pytest.importorskip("mypy")
    assert "ignore_errors" not in (root / "pyproject.toml").read_text(encoding="utf-8")
    res = subprocess.run([sys.executable, "-m", "mypy"], cwd=root, capture_output=True,
                         text=True, timeout=600)
    assert res.returncode == 0, res.stdout[-4000:] + res.stderr[-2000:]
    assert "Success" in res.stdout
    if __import__("shutil").which("ruff") or _has_module("ruff"):
        res = subprocess.run([sys.executable, "-m", "ruff", "check", "src", "tests", "scripts"],
                             cwd=root, capture_output=True, text=True, timeout=300)
        assert res.returncode == 0, res.stdout[-4000:]


def _has_module(name: str) -> bool:
    import importlib.util

    return importlib.util.find_spec(name) is not None
