"""The notebooks' CartPole variants as gymnasium envs: continuous force, and a "no force" action.

Both reuse gymnasium's :class:`CartPoleEnv` (constants, seeding, reset, pygame rendering) and
only change how an action becomes a force, the failure limits and the reward. They are
registered on ``import rlpipe.envs`` as ``rlpipe/CartPoleContinuous-v0`` and
``rlpipe/CartPoleNoop-v0``.
"""

from __future__ import annotations

import math
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from gymnasium.envs.classic_control.cartpole import CartPoleEnv

__all__ = ["ContinuousCartPoleEnv", "NoopCartPoleEnv"]


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

    def step(self, action: Any) -> tuple[np.ndarray, float, bool, bool, dict]:
        assert self.state is not None, "call reset before step"
        x, x_dot, theta, theta_dot = self.state.tolist()
        cos, sin = math.cos(theta), math.sin(theta)
        temp = (self.force(action) + self.polemass_length * theta_dot**2 * sin) / self.total_mass
        theta_acc = (self.gravity * sin - cos * temp) / (
            self.length * (4.0 / 3.0 - self.masspole * cos**2 / self.total_mass)
        )
        x_acc = temp - self.polemass_length * theta_acc * cos / self.total_mass
        x, x_dot = x + self.tau * x_dot, x_dot + self.tau * x_acc
        theta, theta_dot = theta + self.tau * theta_dot, theta_dot + self.tau * theta_acc
        self.state = np.array((x, x_dot, theta, theta_dot))
        terminated = abs(x) > self.x_threshold or abs(theta) > self.theta_threshold_radians
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


for _id, _cls in (
    ("rlpipe/CartPoleContinuous-v0", ContinuousCartPoleEnv),
    ("rlpipe/CartPoleNoop-v0", NoopCartPoleEnv),
):
    if _id not in gym.registry:
        gym.register(_id, entry_point=_cls, max_episode_steps=500)
