"""The notebooks' CartPole variants as gymnasium envs: continuous force, and a "no force" action.

Both reuse gymnasium's :class:`CartPoleEnv` (constants, seeding, reset, pygame rendering) and
only change how an action becomes a force, the failure limits and the reward. They are
registered on ``import rlpipe.envs`` as ``rlpipe/CartPoleContinuous-v0`` and
``rlpipe/CartPoleNoop-v0``, each with a NumPy-batched twin as its ``vector_entry_point``
(``gym.make_vec(id, num_envs=n, vectorization_mode="vector_entry_point")``): the same physics,
seeding and time limit on all copies at once, with autoreset disabled.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import Any, TypeVar

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from gymnasium.envs.classic_control.cartpole import CartPoleEnv
from gymnasium.envs.classic_control.utils import maybe_parse_reset_bounds
from gymnasium.utils import seeding
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space

__all__ = [
    "ContinuousCartPoleEnv",
    "NoopCartPoleEnv",
    "ContinuousCartPoleVectorEnv",
    "NoopCartPoleVectorEnv",
]

F = TypeVar("F", float, np.ndarray)  # one copy's value, or the values of a batch of copies


class _ForceCartPole(CartPoleEnv):
    """Cart-pole physics driven by ``force(action)``; reward 1 per step survived, 0 on failure."""

    def __init__(
        self,
        *,
        action_space: spaces.Space,
        theta_degrees: float,
        half_length: float = 0.5,
        render_mode: str | None = None,
    ) -> None:
        super().__init__(render_mode=render_mode)
        self.length = half_length
        self.polemass_length = self.masspole * self.length
        self.theta_threshold_radians = math.radians(theta_degrees)
        # twice the failure limits, so the failing observation is still inside the space
        big = np.finfo(np.float32).max
        high = np.array(
            [2 * self.x_threshold, big, 2 * self.theta_threshold_radians, big], dtype=np.float32
        )
        self.observation_space = spaces.Box(-high, high, dtype=np.float32)
        self.action_space = action_space

    def force(self, action: Any) -> float:
        """Newtons pushing the cart to the right for ``action``."""
        raise NotImplementedError

    def forces(self, actions: np.ndarray) -> np.ndarray:
        """:meth:`force` of each action of a batch (float64, one per copy)."""
        raise NotImplementedError

    def advance(
        self, state: Sequence[F], force: F, cos: Callable[[F], F], sin: Callable[[F], F]
    ) -> tuple[tuple[F, F, F, F], F]:
        """One Euler step of ``state`` (x, x_dot, theta, theta_dot) under ``force``, and whether
        it failed. Floats with ``math``'s cos and sin, or arrays of copies with NumPy's: only
        correctly rounded arithmetic, so both give the same bits."""
        x, x_dot, theta, theta_dot = state
        c, s = cos(theta), sin(theta)
        temp = (force + self.polemass_length * (theta_dot * theta_dot) * s) / self.total_mass
        theta_acc = (self.gravity * s - c * temp) / (
            self.length * (4.0 / 3.0 - self.masspole * (c * c) / self.total_mass)
        )
        x_acc = temp - self.polemass_length * theta_acc * c / self.total_mass
        x, x_dot = x + self.tau * x_dot, x_dot + self.tau * x_acc
        theta, theta_dot = theta + self.tau * theta_dot, theta_dot + self.tau * theta_acc
        failed = (abs(x) > self.x_threshold) | (abs(theta) > self.theta_threshold_radians)
        return (x, x_dot, theta, theta_dot), failed

    def step(self, action: Any) -> tuple[np.ndarray, float, bool, bool, dict]:
        assert self.state is not None, "call reset before step"
        state, terminated = self.advance(
            self.state.tolist(), self.force(action), math.cos, math.sin
        )
        self.state = np.array(state)
        if self.render_mode == "human":
            self.render()
        return self.state.astype(np.float32), 0.0 if terminated else 1.0, terminated, False, {}


class ContinuousCartPoleEnv(_ForceCartPole):
    """CartPole with a force ``10 N * a`` for ``a`` in [-1, 1] (clipped); fails at 20° or 2.4 m."""

    def __init__(self, render_mode: str | None = None) -> None:
        super().__init__(
            action_space=spaces.Box(-1.0, 1.0, shape=(1,), dtype=np.float32),
            theta_degrees=20.0,
            render_mode=render_mode,
        )

    def force(self, action: Any) -> float:
        return self.force_mag * min(max(float(np.asarray(action).flat[0]), -1.0), 1.0)

    def forces(self, actions: np.ndarray) -> np.ndarray:
        first = np.asarray(actions, dtype=np.float64).reshape(len(actions), -1)[:, 0]
        return self.force_mag * np.clip(first, -1.0, 1.0)


class NoopCartPoleEnv(_ForceCartPole):
    """CartPole a person can play: left / no force / right, a 2 m pole, failure at 24°."""

    def __init__(self, render_mode: str | None = None) -> None:
        super().__init__(
            action_space=spaces.Discrete(3),
            theta_degrees=24.0,
            half_length=1.0,
            render_mode=render_mode,
        )

    def force(self, action: Any) -> float:
        return self.force_mag * (int(action) - 1)

    def forces(self, actions: np.ndarray) -> np.ndarray:
        return self.force_mag * (np.asarray(actions, dtype=np.int64).reshape(-1) - 1)


class _ForceCartPoleVector(VectorEnv):
    """``num_envs`` copies of :attr:`single_env` stepped as NumPy arrays (no rendering).

    Transitions equal those of a ``SyncVectorEnv`` of single copies, each under a
    ``max_episode_steps`` time limit, with autoreset DISABLED: ``reset`` restarts the copies in
    ``options["reset_mask"]`` (default all), each drawing from its own generator, seeded like
    the single env's by ``seed`` (an int seeds copy ``i`` with ``seed + i``; or a list).
    """

    metadata = {"autoreset_mode": AutoresetMode.DISABLED}
    single_env: type[_ForceCartPole]

    def __init__(self, num_envs: int = 1, max_episode_steps: int | None = None) -> None:
        self.physics = self.single_env()  # constants, spaces and the action-to-force rule
        self.num_envs = num_envs
        self.autoreset_mode = AutoresetMode.DISABLED  # where TorchRL's GymWrapper looks
        self.max_episode_steps = max_episode_steps
        self.single_observation_space = self.physics.observation_space
        self.single_action_space = self.physics.action_space
        self.observation_space = batch_space(self.single_observation_space, num_envs)
        self.action_space = batch_space(self.single_action_space, num_envs)
        self.state = np.zeros((4, num_envs))  # one row per state variable: contiguous copies
        self.steps = np.zeros(num_envs, dtype=np.int64)
        self.generators: list[np.random.Generator | None] = [None] * num_envs

    def reset(
        self, *, seed: int | list[int | None] | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        options = dict(options or {})
        mask = options.pop("reset_mask", np.ones(self.num_envs, dtype=np.bool_))
        if not isinstance(seed, list):
            seed = [None if seed is None else seed + i for i in range(self.num_envs)]
        low, high = maybe_parse_reset_bounds(options, -0.05, 0.05)
        for i in np.flatnonzero(mask):
            if seed[i] is not None or self.generators[i] is None:
                self.generators[i], _ = seeding.np_random(seed[i])
            self.state[:, i] = self.generators[i].uniform(low=low, high=high, size=(4,))
        self.steps[mask] = 0
        return self.state.T.astype(np.float32), {}

    def step(
        self, actions: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]:
        forces = self.physics.forces(actions)
        state, terminated = self.physics.advance(self.state, forces, np.cos, np.sin)
        self.state = np.stack(state)
        self.steps += 1
        limit = math.inf if self.max_episode_steps is None else self.max_episode_steps
        reward = np.where(terminated, 0.0, 1.0)
        return self.state.T.astype(np.float32), reward, terminated, self.steps >= limit, {}


class ContinuousCartPoleVectorEnv(_ForceCartPoleVector):
    """Batched :class:`ContinuousCartPoleEnv`."""

    single_env = ContinuousCartPoleEnv


class NoopCartPoleVectorEnv(_ForceCartPoleVector):
    """Batched :class:`NoopCartPoleEnv`."""

    single_env = NoopCartPoleEnv


for _id, _cls, _vector_cls in (
    ("rlpipe/CartPoleContinuous-v0", ContinuousCartPoleEnv, ContinuousCartPoleVectorEnv),
    ("rlpipe/CartPoleNoop-v0", NoopCartPoleEnv, NoopCartPoleVectorEnv),
):
    if _id not in gym.registry:
        gym.register(_id, entry_point=_cls, vector_entry_point=_vector_cls, max_episode_steps=500)
