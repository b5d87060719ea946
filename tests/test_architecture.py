"""The house rules the code keeps: no import circles, a torch-free front door (configs, the
registry, the run dir, the command line), the runner apart from persistence, and small files
that each say their one job first."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "rlpipe"
HEAVY = ("torch", "tensordict", "torchrl")  # what the front door must not import


def _modules() -> dict[str, Path]:
    found = {}
    for path in PACKAGE.rglob("*.py"):
        parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
        name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
        found[name] = path
    return found


def _imports(name: str, path: Path, modules: dict[str, Path]) -> set[str]:
    """The rlpipe modules ``name`` imports anywhere in its code (functions and
    ``TYPE_CHECKING`` blocks included): an import circle is one wherever its lines stand."""
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    targets = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join([*anchor, *([base] if base else [])])
            for alias in node.names:
                full = f"{base}.{alias.name}"
                targets.add(full if full in modules else base)
        elif isinstance(node, ast.Import):
            targets.update(alias.name for alias in node.names)
    return {t for t in targets if t in modules and t != name}


def test_no_import_circles() -> None:
    modules = _modules()
    graph = {name: _imports(name, path, modules) for name, path in modules.items()}
    circles = []

    def visit(name: str, trail: list[str]) -> None:
        for target in graph[name]:
            if target in trail:
                circles.append(" -> ".join([*trail[trail.index(target) :], target]))
            elif target not in done:
                visit(target, [*trail, target])
        done.add(name)

    done: set[str] = set()
    for name in sorted(graph):
        if name not in done:
            visit(name, [name])
    assert not circles, circles[:5]


def test_the_runner_persists_only_through_its_run_dir() -> None:
    modules = _modules()
    runner = _imports("rlpipe.runner", modules["rlpipe.runner"], modules)
    assert not runner & {"rlpipe.rundir", "rlpipe.checkpoint", "rlpipe.files"}, runner
    rundir = _imports("rlpipe.rundir", modules["rlpipe.rundir"], modules)
    assert not {m for m in rundir if m.startswith("rlpipe.algos.") and m != "rlpipe.algos.configs"}


def test_files_are_small_and_say_their_job_first() -> None:
    for path in PACKAGE.rglob("*.py"):
        lines = path.read_text().splitlines()
        assert len(lines) <= 400, f"{path}: {len(lines)} lines"
        assert lines[0].startswith('"""') and len(lines[0]) > 3, f"{path}: no one-line job"


def _imported(code: list[str]) -> set[str]:
    """Top-level packages a fresh ``python <code>`` imports (``-X importtime``)."""
    proc = subprocess.run(
        [sys.executable, "-X", "importtime", *code],
        capture_output=True,
        text=True,
        timeout=300,
        cwd=PACKAGE.parent,
    )
    names = [line.rpartition("|")[2].strip() for line in proc.stderr.splitlines()]
    return {name.split(".")[0] for name in names if name}


@pytest.mark.parametrize(
    "code",
    [
        ["-c", "import rlpipe, rlpipe.config, rlpipe.registry, rlpipe.rundir, rlpipe.runs"],
        ["-c", "import rlpipe.cli, rlpipe.help, rlpipe.sweep, rlpipe.plot"],
        ["-m", "rlpipe", "--help"],
        ["-m", "rlpipe", "algo=nope"],
        ["-m", "rlpipe", "algo=ppo", "algo.lrr=1"],
        ["-m", "rlpipe", "algo=sac", "algo.lr=-1"],
        ["-m", "rlpipe", "algo=ars", "env=bipedal", "--cfg", "job"],
    ],
    ids=["library", "commands", "help", "unknown-option", "unknown-key", "bad-value", "cfg-job"],
)
def test_the_front_door_imports_no_torch(code: list[str]) -> None:
    imported = _imported(code)
    assert "rlpipe" in imported and not imported & set(HEAVY), sorted(imported & set(HEAVY))
