"""``python -m rlpipe.play``: injected key presses drive the env; unplayable envs fail clearly."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from types import SimpleNamespace

import pytest
from conftest import run_module

from rlpipe import EnvConfig
from rlpipe.errors import RlpipeError
from rlpipe.play import PlayConfig, play


@pytest.fixture
def pygame(monkeypatch: pytest.MonkeyPatch):
    """pygame with the dummy video driver (no window), set before it is imported."""
    monkeypatch.setenv("SDL_VIDEODRIVER", "dummy")
    monkeypatch.setenv("PYGAME_HIDE_SUPPORT_PROMPT", "1")
    return pytest.importorskip(
        "pygame", reason="needs pygame (gymnasium's renderer): pip install pygame"
    )


def scripted(batches: list[list[SimpleNamespace]]) -> Iterator[list[SimpleNamespace]]:
    yield from batches
    while True:
        yield []


def test_play_injected_keys(pygame) -> None:
    key = SimpleNamespace
    batches = [
        [key(type=pygame.KEYDOWN, key=pygame.K_d)],  # push right...
        [],
        [key(type=pygame.KEYUP, key=pygame.K_d), key(type=pygame.KEYDOWN, key=pygame.K_a)],
        [key(type=pygame.KEYUP, key=pygame.K_a)],  # ...left, then no force
        [],
        [key(type=pygame.KEYDOWN, key=pygame.K_ESCAPE)],
    ]
    events = scripted(batches)
    cfg = PlayConfig(env=EnvConfig(id="rlpipe/CartPoleNoop-v0"), fps=0, seed=0)
    result = play(cfg, events=lambda: next(events))
    assert result.actions == [2, 2, 0, 1, 1]  # right, right, left, noop, noop; Esc stops
    assert result.returns == []  # no episode finished


def test_play_finishes_episodes(pygame) -> None:
    cfg = PlayConfig(
        env=EnvConfig(id="CartPole-v1", max_episode_steps=7), episodes=2, fps=0, seed=0
    )
    result = play(cfg, events=lambda: [])
    assert result.lengths == [7, 7]  # truncated by the time limit, twice
    assert result.returns == [7.0, 7.0]
    assert len(result.actions) == 14 and set(result.actions) == {0}  # CartPole's no key: left


def test_play_continuous_env_is_refused(pygame) -> None:
    with pytest.raises(RlpipeError, match="continuous actions.*playable envs"):
        play(PlayConfig(env=EnvConfig(id="Pendulum-v1")), events=lambda: [])


def test_play_cli_pendulum(tmp_path: Path) -> None:
    proc = run_module("rlpipe.play", "env=pendulum", cwd=tmp_path)
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1, proc.stderr
    assert lines[0].startswith("rlpipe: error:")
    assert "env=cartpole_noop, env=cartpole or env=mountaincar" in lines[0]


def test_play_cli_bad_episodes(tmp_path: Path) -> None:
    proc = run_module("rlpipe.play", "episodes=-1", cwd=tmp_path)
    assert proc.returncode == 2
    assert "episodes must be >= 0" in proc.stderr
