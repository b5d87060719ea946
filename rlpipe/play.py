"""``python -m rlpipe.play [env=cartpole_noop|cartpole|mountaincar] [episodes=N] [fps=N]``.

Keyboard play, as the hackathon notebook did: ``a`` pushes left, ``d`` pushes right, no key is
the no-op (no force for ``cartpole_noop`` and ``mountaincar``; CartPole-v1 has none, so left).
The window shows the episode and its return; Esc or closing the window stops. ``episodes=0``
(default) plays until then.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import gymnasium as gym
import numpy as np
from hydra.core.config_store import ConfigStore

from rlpipe.cli import compose_config, run_entry_point
from rlpipe.config import EnvConfig
from rlpipe.errors import RlpipeError, check
from rlpipe.video import check_display


@dataclass(frozen=True)
class KeyMap:
    """Discrete actions for ``a`` (left), ``d`` (right) and no key."""

    left: int
    right: int
    noop: int


# env id -> keys; the conf/env options: cartpole, cartpole_noop, mountaincar
PLAYABLE = {
    "CartPole-v1": KeyMap(left=0, right=1, noop=0),
    "rlpipe/CartPoleNoop-v0": KeyMap(left=0, right=2, noop=1),
    "MountainCar-v0": KeyMap(left=0, right=2, noop=1),
}
PLAYABLE_OPTIONS = "env=cartpole_noop, env=cartpole or env=mountaincar"


@dataclass
class PlayConfig:
    """``conf/play.yaml``: the env (a ``conf/env`` option) and how long to play."""

    env: EnvConfig = field(default_factory=lambda: EnvConfig(id="rlpipe/CartPoleNoop-v0"))
    episodes: int = 0  # 0: until Esc or the window is closed
    fps: int | None = None  # steps per second; null: the env's render_fps; 0: no limit
    seed: int | None = None  # null: a new game every time

    def __post_init__(self) -> None:
        check(self.episodes >= 0, f"episodes must be >= 0, got {self.episodes}")
        check(self.fps is None or self.fps >= 0, f"fps must be >= 0 or null, got {self.fps}")


@dataclass
class PlayResult:
    """What was played: each finished episode's return and length, and every action taken."""

    returns: list[float] = field(default_factory=list)
    lengths: list[int] = field(default_factory=list)
    actions: list[int] = field(default_factory=list)


def key_map(env: gym.Env) -> KeyMap:
    """The keys for ``env``; a clear error for continuous or unmapped action spaces."""
    env_id = env.spec.id if env.spec else type(env).__name__
    check(
        isinstance(env.action_space, gym.spaces.Discrete),
        f"env {env_id} has continuous actions ({env.action_space}), which a/d keys cannot "
        f"play; playable envs: {PLAYABLE_OPTIONS}",
    )
    check(
        env_id in PLAYABLE,
        f"env {env_id} has no keyboard mapping; playable envs: {PLAYABLE_OPTIONS}",
    )
    return PLAYABLE[env_id]


def play(cfg: PlayConfig, events: Callable[[], Sequence[Any]] | None = None) -> PlayResult:
    """Play ``cfg.env`` from the keyboard in a pygame window until Esc or ``cfg.episodes``.

    ``events`` replaces ``pygame.event.get`` (tests inject key presses through it).
    """
    try:
        env = gym.make(cfg.env.id, render_mode="rgb_array", **_make_kwargs(cfg.env))
    except gym.error.Error as err:
        raise RlpipeError(f"cannot make gymnasium env {cfg.env.id!r}: {err}") from err
    try:
        keys = key_map(env)
        check_display("keyboard play")
        return _loop(env, keys, cfg, events)
    finally:
        env.close()


def _make_kwargs(cfg: EnvConfig) -> dict[str, Any]:
    kwargs = dict(cfg.kwargs)
    if cfg.max_episode_steps is not None:
        kwargs["max_episode_steps"] = cfg.max_episode_steps
    return kwargs


def _loop(
    env: gym.Env, keys: KeyMap, cfg: PlayConfig, events: Callable[[], Sequence[Any]] | None
) -> PlayResult:
    os.environ.setdefault("PYGAME_HIDE_SUPPORT_PROMPT", "1")
    import pygame

    pygame.display.init()
    pygame.font.init()
    try:
        env.reset(seed=cfg.seed)
        frame = env.render()
        try:
            screen = pygame.display.set_mode((frame.shape[1], frame.shape[0]))
        except pygame.error as err:
            raise RlpipeError(f"cannot open a window: {err}") from err
        pygame.display.set_caption(f"rlpipe play {env.spec.id}: a = left, d = right, Esc = quit")
        font, clock = pygame.font.Font(None, 30), pygame.time.Clock()
        fps = env.metadata.get("render_fps", 30) if cfg.fps is None else cfg.fps
        held: list[int] = []  # keys down, most recent last
        result, episode_return, steps = PlayResult(), 0.0, 0
        while True:
            for event in (events or pygame.event.get)():
                if event.type == pygame.QUIT or (
                    event.type == pygame.KEYDOWN and event.key == pygame.K_ESCAPE
                ):
                    return result
                if event.type == pygame.KEYDOWN and event.key in (pygame.K_a, pygame.K_d):
                    held.append(event.key)
                elif event.type == pygame.KEYUP and event.key in held:
                    held.remove(event.key)
            action = {pygame.K_a: keys.left, pygame.K_d: keys.right}.get(
                held[-1] if held else None, keys.noop
            )
            _, reward, terminated, truncated, _ = env.step(action)
            result.actions.append(action)
            episode_return, steps = episode_return + float(reward), steps + 1
            episode = len(result.returns) + 1
            _draw(screen, font, env.render(), f"episode {episode}   return {episode_return:.0f}")
            if terminated or truncated:
                print(f"episode {episode}: return {episode_return:.0f} in {steps} steps")
                result.returns.append(episode_return)
                result.lengths.append(steps)
                if cfg.episodes and len(result.returns) >= cfg.episodes:
                    return result
                env.reset()
                episode_return, steps = 0.0, 0
            clock.tick(fps)
    finally:
        pygame.quit()


def _draw(screen: Any, font: Any, frame: np.ndarray, text: str) -> None:
    import pygame

    screen.blit(pygame.surfarray.make_surface(frame.swapaxes(0, 1)), (0, 0))
    screen.blit(font.render(text, True, (0, 0, 0), (255, 255, 255)), (10, 10))
    pygame.display.flip()


def main(argv: Sequence[str] | None = None) -> None:
    """``python -m rlpipe.play key=value ...``; user errors: one line, exit 2."""
    run_entry_point(__doc__, argv, _play)


def _play(args: list[str]) -> None:
    result = play(compose_config("play", args))
    if result.returns:
        mean = sum(result.returns) / len(result.returns)
        print(f"rlpipe: played {len(result.returns)} episode(s), mean return {mean:.1f}")


ConfigStore.instance().store(name="play_schema", node=PlayConfig)

if __name__ == "__main__":
    main()
