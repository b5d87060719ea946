"""Shared helpers: run the command-line entry points in a subprocess."""

from __future__ import annotations

import importlib
import os
import shutil
import subprocess
import sys
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import pytest
import warm

# ~tuned: the algorithms' own defaults (tests of the tuned settings name them)
TINY = ["~tuned", "progress=false", "total_frames=200", "eval_every=100", "eval_episodes=2"]
# a finished tiny DQN run (checkpoints at 100 and 200): the tampering and ownership share
BASE = [
    "~tuned",
    "progress=false",
    "total_frames=200",
    "eval_every=100",
    "checkpoint_every=100",
    "eval_episodes=2",
    "algo.learning_starts=64",
    "algo.batch_size=32",
    "algo.frames_per_batch=20",
    "env.num_envs=2",
]
NEWEST = "ckpt_000000000200.pt"


def torchrl_stepped(env_cfg: Any) -> Callable[[], Any]:
    """A factory of ``make_env(env_cfg)`` plus a transform make_env does not add, so that
    rlpipe's lean collection passes it to TorchRL's ``Collector``."""
    from torchrl.envs import RewardScaling

    from rlpipe.envs import make_env

    def build() -> Any:
        env = make_env(env_cfg, seed=0)
        env.append_transform(RewardScaling(0.0, 2.0))
        return env

    return build


def _child_env(pythonpath: Path | None = None, env: dict[str, str] | None = None) -> dict:
    """A child's environment: ours, headless, with ``env`` added and ``pythonpath`` first."""
    env = {**os.environ, "SDL_VIDEODRIVER": "dummy", **(env or {})}
    if pythonpath is not None:
        env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(pythonpath), env.get("PYTHONPATH")]))
    env.pop("HYDRA_FULL_ERROR", None)
    return env


def run_module(
    module: str,
    *args: str,
    cwd: Path,
    timeout: float = 300,
    pythonpath: Path | None = None,
    env: dict[str, str] | None = None,
    fresh: bool = False,
) -> subprocess.CompletedProcess:
    """``python -m <module> args...`` in ``cwd`` (``pythonpath``: a folder to import from;
    ``env``: more environment variables); returns the completed process (text output).

    ``python -m rlpipe`` runs forked from a server that imported torch and the rest
    (tests/warm.py) unless ``fresh`` or one of the other two asks for a new interpreter."""
    if module == "rlpipe" and not (fresh or pythonpath or env):
        return warm.run(module, list(args), cwd=cwd, env=_child_env(), timeout=timeout)
    return subprocess.run(
        [sys.executable, "-m", module, *args],
        cwd=cwd,
        env=_child_env(pythonpath, env),
        capture_output=True,
        text=True,
        timeout=timeout,
    )


def start_module(
    module: str, *args: str, cwd: Path, stdout: int = subprocess.PIPE
) -> subprocess.Popen:
    """``python -m <module> args...`` started in the background in ``cwd``, in
    :func:`run_module`'s environment (stderr piped, text)."""
    return subprocess.Popen(
        [sys.executable, "-m", module, *args],
        cwd=cwd,
        env=_child_env(),
        stdout=stdout,
        stderr=subprocess.PIPE,
        text=True,
    )


@contextmanager
def benchmarks_importable() -> Iterator[None]:
    """The benchmarks/ folder on ``sys.path`` while in use: its scripts import as modules."""
    folder = str(Path(__file__).resolve().parents[1] / "benchmarks")
    sys.path.insert(0, folder)
    try:
        yield
    finally:
        sys.path.remove(folder)


def assert_auto_chose(stdout: str, copies: int) -> None:
    """A run's console says what ``env.backend=auto`` chose for an env EnvPool runs as gymnasium
    does, with ``copies`` env copies stepped at once: EnvPool (gymnasium where it is missing),
    but gymnasium for one copy."""
    from rlpipe.envs.backends import envpool_version

    if envpool_version() and copies == 1:
        assert "rlpipe: env backend gymnasium (auto: one env copy " in stdout, stdout
    backend = "envpool" if envpool_version() and copies > 1 else "gymnasium"
    assert f"rlpipe: env backend {backend} (auto" in stdout, stdout


def needs_extra(module: str, extra: str) -> Any:
    """``module``, imported; where it is missing the test is skipped with the command that
    installs the rlpipe extra bringing it."""
    return pytest.importorskip(
        module,
        reason=f'needs the {extra} extra ({module}): pip install torch==2.13.0 -e ".[{extra}]"',
    )


def assert_one_error_line(
    main: Callable[[list[str]], Any], argv: list[str], message: str, capsys: Any
) -> None:
    """``main(argv)`` (an entry point, in-process) exits 2 with one ``rlpipe: error:`` line."""
    with pytest.raises(SystemExit) as exit_info:
        main(argv)
    assert exit_info.value.code == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1, lines
    assert lines[0].startswith("rlpipe: error:") and message in lines[0]


@pytest.fixture
def rlpipe_cli(tmp_path: Path):
    """Run ``python -m rlpipe`` with the run dir inside ``tmp_path``."""

    def run(*args: str, run_dir: Path | None = None) -> subprocess.CompletedProcess:
        run_dir = run_dir or tmp_path / "run"
        return run_module("rlpipe", *args, f"hydra.run.dir={run_dir}", cwd=tmp_path)

    return run


@pytest.fixture
def image_env_id() -> str:
    """A registered gymnasium id whose observation is an image (not a flat vector)."""
    import gymnasium as gym

    env_id = "rlpipe/ImageCartPole-v0"
    if env_id not in gym.registry:
        gym.register(
            env_id,
            entry_point=lambda **kw: gym.wrappers.AddRenderObservation(
                gym.make("CartPole-v1", render_mode="rgb_array"), render_only=True
            ),
        )
    return env_id


@pytest.fixture(scope="session")
def finished_run(tmp_path_factory) -> Path:
    """A finished tiny DQN run (checkpoints at 100 and 200 frames), made once per test process:
    read it, never change it (``run_copy`` is a copy to change)."""
    run_dir = tmp_path_factory.mktemp("finished") / "run"
    result = run_module("rlpipe", *BASE, f"hydra.run.dir={run_dir}", cwd=run_dir.parent)
    assert result.returncode == 0, result.stderr
    assert sorted(p.name for p in (run_dir / "checkpoints").glob("ckpt_*.pt")) == [
        "ckpt_000000000100.pt",
        NEWEST,
    ]
    return run_dir


@pytest.fixture(scope="session")
def reference(tmp_path_factory):
    """The fault-injection suite's uninterrupted run per algorithm (tests/fault_harness.py)."""
    from fault_harness import reference_runs  # imports this module: not at the top

    return reference_runs(tmp_path_factory)


@pytest.fixture
def run_copy(tmp_path, finished_run) -> Path:
    """A copy of the finished run of its own, ``tmp_path/run``."""
    return Path(shutil.copytree(finished_run, tmp_path / "run"))


@pytest.fixture
def registry(monkeypatch, tmp_path):
    """The global algorithm registry, restored after the test, with the plug-in modules the test
    imported (from ``tmp_path`` or ``examples/``) forgotten: each test registers afresh."""
    from rlpipe.registry import ALGORITHMS

    monkeypatch.setattr(ALGORITHMS, "_entries", dict(ALGORITHMS._entries))
    monkeypatch.setattr(ALGORITHMS, "_entry_points_read", set())  # no entry point loaded yet
    monkeypatch.setattr(ALGORITHMS, "_variable_read", False)
    monkeypatch.delenv("RLPIPE_PLUGINS", raising=False)
    before = set(sys.modules)
    yield ALGORITHMS
    folders = (str(tmp_path), str(Path(__file__).resolve().parents[1] / "examples"))
    for name in set(sys.modules) - before:
        if str(getattr(sys.modules[name], "__file__", None)).startswith(folders):
            del sys.modules[name]


@pytest.fixture(scope="module")
def presets_bench() -> Iterator[SimpleNamespace]:
    """benchmarks/presets.py's modules, imported: common, presets_runs, presets_table, report."""
    with benchmarks_importable():
        yield SimpleNamespace(
            **{m: importlib.import_module(m) for m in ("common", "presets_runs", "presets_table")},
            report=importlib.import_module("presets_report"),
        )
