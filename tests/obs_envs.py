"""Tiny gymnasium envs with image, Dict and Tuple observations for tests/test_observations.py,
registered on import (env.id=obs_envs:rlpipe-test/Image-v0 with tests/ on PYTHONPATH)."""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np

SIZE = 16  # the images' height and width


class SideEnv(gym.Env):
    """A bright bar on the left or the right of a 16x16 RGB image; reward 1 for the action that
    names its side (discrete 0/1, or the sign of a continuous action); 8 steps an episode.
    ``kind``: image (the image alone), dict (a Dict of the image, the side as a Box and a
    Discrete, and a text mission) or tuple (a Tuple space, which rlpipe refuses)."""

    def __init__(self, kind: str = "image", continuous: bool = False) -> None:
        image = gym.spaces.Box(0, 255, (SIZE, SIZE, 3), np.uint8)
        spaces = {
            "image": image,
            "dict": gym.spaces.Dict(
                {
                    "pixels": gym.spaces.Box(0, 255, (8, 8, 3), np.uint8),
                    "side": gym.spaces.Box(-1.0, 1.0, (2,), np.float32),
                    "flag": gym.spaces.Discrete(3),
                    "mission": gym.spaces.Text(20),
                }
            ),
            "tuple": gym.spaces.Tuple((image, gym.spaces.Discrete(2))),
        }
        self.kind, self.observation_space = kind, spaces[kind]
        self.action_space = (
            gym.spaces.Box(-1.0, 1.0, (1,), np.float32) if continuous else gym.spaces.Discrete(2)
        )
        self.side = 0

    def _observation(self) -> Any:
        image = np.zeros((SIZE, SIZE, 3), np.uint8)
        start = 0 if self.side == 0 else 3 * SIZE // 4
        image[:, start : start + SIZE // 4] = 255
        if self.kind == "image":
            return image
        if self.kind == "tuple":
            return image, self.side
        side = np.array([1.0, 0.0] if self.side == 0 else [0.0, 1.0], np.float32)
        return {"pixels": image[::2, ::2], "side": side, "flag": self.side, "mission": "go"}

    def reset(self, *, seed: int | None = None, options: dict | None = None) -> tuple:
        super().reset(seed=seed)
        self.side = int(self.np_random.integers(2))
        return self._observation(), {}

    def step(self, action: Any) -> tuple:
        chosen = int(action) if np.ndim(action) == 0 else int(np.asarray(action)[0] > 0)
        reward = float(chosen == self.side)
        self.side = int(self.np_random.integers(2))
        return self._observation(), reward, False, False, {}


for _name, _kwargs in {
    "Image-v0": {"kind": "image"},
    "ImageContinuous-v0": {"kind": "image", "continuous": True},
    "Dict-v0": {"kind": "dict"},
    "DictContinuous-v0": {"kind": "dict", "continuous": True},
    "Tuple-v0": {"kind": "tuple"},
}.items():
    gym.register(f"rlpipe-test/{_name}", entry_point=SideEnv, kwargs=_kwargs, max_episode_steps=8)
