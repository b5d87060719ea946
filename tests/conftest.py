"""Shared helpers: run the command-line entry points in a subprocess."""

from __future__ import annotations

import os
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

# ~tuned: the algorithms' own defaults (tests of the tuned settings name them)
TINY = ["~tuned", "progress=false", "total_frames=200", "eval_every=100", "eval_episodes=2"]


def run_module(
    module: str, *args: str, cwd: Path, timeout: float = 300, pythonpath: Path | None = None
) -> subprocess.CompletedProcess:
    """``python -m <module> args...`` in ``cwd`` (``pythonpath``: a folder to import from);
    returns the completed process (text output)."""
    env = {**os.environ, "SDL_VIDEODRIVER": "dummy"}
    if pythonpath is not None:
        env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(pythonpath), env.get("PYTHONPATH")]))
    env.pop("HYDRA_FULL_ERROR", None)
    return subprocess.run(
        [sys.executable, "-m", module, *args],
        cwd=cwd,
        env=env,
        capture_output=True,
        text=True,
        timeout=timeout,
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
