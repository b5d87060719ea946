"""Plain-Python use without Hydra, exactly as the README shows it; the public names hold."""

from __future__ import annotations

import ast
import importlib
import pkgutil
import re
from pathlib import Path
from types import ModuleType

import rlpipe
from rlpipe import EnvConfig, EvalResult, make_env
from rlpipe.heuristic import random_policy

README = Path(__file__).resolve().parents[1] / "README.md"


def test_readme_python_example_runs(tmp_path, monkeypatch):
    block = re.search(r"<!-- api-example -->\s*```python\n(.*?)```", README.read_text(), re.S)
    assert block, "README must contain the marked Python API example"
    monkeypatch.chdir(tmp_path)
    namespace: dict = {}
    exec(compile(block.group(1), "README-example", "exec"), namespace)
    result = namespace["result"]
    assert result.frames >= 300 and result.eval_episodes == 5
    assert (tmp_path / "runs" / "api-demo" / "summary.json").exists()


def _exports() -> dict[str, object]:
    """What ``rlpipe/__init__.py`` binds each public name to, read from its import lines."""
    tree = ast.parse(Path(rlpipe.__file__).read_text())
    return {
        alias.asname or alias.name: getattr(importlib.import_module(node.module), alias.name)
        for node in tree.body
        if isinstance(node, ast.ImportFrom) and node.module
        for alias in node.names
    }


def test_importing_submodules_keeps_the_public_names() -> None:
    """A submodule named like an export (``rlpipe.evaluate``, the command) must not hide it."""
    for module in pkgutil.walk_packages(rlpipe.__path__, "rlpipe."):
        try:
            importlib.import_module(module.name)
        except ModuleNotFoundError as err:  # an optional extra that is not installed
            if (err.name or "").startswith("rlpipe"):
                raise
    exports = _exports()
    for name in rlpipe.__all__:
        value, exported = getattr(rlpipe, name), exports[name]
        if isinstance(value, ModuleType) and not isinstance(exported, ModuleType):
            # the one allowed stand-in: a module that forwards calls to the export
            assert callable(value) and value.__wrapped__ is exported, name
        else:
            assert value is exported, name

    env = make_env(EnvConfig(id="CartPole-v1"), num_envs=2, seed=0)
    try:
        result = rlpipe.evaluate(random_policy(env), env, 2)
    finally:
        env.close()
    assert isinstance(result, EvalResult) and len(result.returns) == 2
