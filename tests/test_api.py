"""Plain-Python use without Hydra, exactly as the README shows it; the public names hold."""

from __future__ import annotations

import importlib
import inspect
import pkgutil
import re
from pathlib import Path
from types import ModuleType

import rlpipe
from rlpipe import EnvConfig, EvalResult, make_env
from rlpipe.heuristic import random_policy

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
API_PAGE = ROOT / "docs" / "api.md"


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
    """What ``rlpipe/__init__.py`` binds each public name to: the object in its module."""
    return {
        name: getattr(importlib.import_module(module), name)
        for name, module in rlpipe._MODULES.items()
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


def _public_objects() -> list[tuple[str, object]]:
    """Each public name and what it is (the function, when ``rlpipe.evaluate`` is the module
    standing in for it)."""
    objects = []
    for name in rlpipe.__all__:
        value = getattr(rlpipe, name)
        if isinstance(value, ModuleType):
            value = value.__wrapped__
        objects.append((name, value))
    return objects


def _own_docstring(value: object) -> str | None:
    """``value``'s own docstring: a class's from its body (not a base's, and not the
    ``Name(field=...)`` signature that ``dataclass`` writes when there is none)."""
    if inspect.isclass(value):
        doc = vars(value).get("__doc__")
        if doc and doc.startswith(f"{value.__name__}("):  # dataclass boilerplate
            return None
        return doc
    return value.__doc__


def test_every_public_name_has_a_one_line_summary() -> None:
    """``help(rlpipe.X)`` starts with a summary: the docstring's first line is a sentence of
    its own (PEP 257), followed by a blank line or nothing. Constants such as ``ALGORITHMS``
    carry no docstring: the package docstring and docs/api.md describe them instead."""
    problems = []
    for name, value in _public_objects():
        if not (inspect.isclass(value) or inspect.isroutine(value)):
            if f"`{name}`" not in API_PAGE.read_text():
                problems.append(f"{name}: a constant, not described in docs/api.md")
            continue
        doc = _own_docstring(value)
        if not doc or not doc.strip():
            problems.append(f"{name}: no docstring of its own")
            continue
        lines = inspect.cleandoc(doc).splitlines()
        if not lines[0].endswith("."):
            problems.append(f"{name}: the first line is not a sentence: {lines[0]!r}")
        elif len(lines) > 1 and lines[1].strip():
            problems.append(f"{name}: the summary runs over two lines: {lines[0]!r}")
    assert not problems, "\n".join(problems)


def test_package_docstring_lists_every_public_name() -> None:
    """``help(rlpipe)`` reads as an API index: one line per public name, name first."""
    doc = rlpipe.__doc__ or ""
    indexed = re.findall(r"^ +(\w+)  +\S", doc, re.M)
    missing = sorted(set(rlpipe.__all__) - set(indexed))
    extra = sorted({n for n in indexed if n not in rlpipe.__all__ or indexed.count(n) > 1})
    assert not missing and not extra, f"not listed: {missing}; not public or listed twice: {extra}"
