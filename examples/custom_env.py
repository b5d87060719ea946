"""A gymnasium env of your own, registered by its module and trained from the command line.

Importing this module registers ``GoalLine-v0``: a point on a line starts at 0 and must reach
the goal at +1 within 50 steps (actions: left, stay, right; reward -0.01 per step, +1 at the
goal). gymnasium's ``module:Id`` form makes rlpipe import the module first::

    PYTHONPATH=examples python -m rlpipe env=gym env.id=custom_env:GoalLine-v0 \\
        total_frames=5000 eval_every=1000

Any algorithm that fits the action space works (DQN here, the default); ``env.kwargs.<key>=``
passes constructor arguments (e.g. ``env.kwargs.goal=0.5``). A run dir of such an env holds
code to import: ``python -m rlpipe.evaluate run_dir=<dir> allow_env_import=true``.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np


class GoalLine(gym.Env):
    """Walk a point from 0 to ``goal`` in steps of 0.1."""

    metadata = {"render_modes": []}

    def __init__(self, goal: float = 1.0) -> None:
        self.goal = goal
        self.observation_space = gym.spaces.Box(-2.0, 2.0, shape=(2,), dtype=np.float32)
        self.action_space = gym.spaces.Discrete(3)
        self.position = 0.0

    def _observation(self) -> np.ndarray:
        return np.array([self.position, self.goal - self.position], dtype=np.float32)

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        super().reset(seed=seed)
        self.position = float(self.np_random.uniform(-0.05, 0.05))
        return self._observation(), {}

    def step(self, action: int) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        self.position = float(np.clip(self.position + 0.1 * (int(action) - 1), -2.0, 2.0))
        reached = self.position >= self.goal - 1e-6
        return self._observation(), 1.0 if reached else -0.01, reached, False, {}


gym.register(id="GoalLine-v0", entry_point=GoalLine, max_episode_steps=50)
