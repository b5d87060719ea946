"""Algorithm registry: config class and builder for each ``algo`` option."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import torch
from torchrl.envs import EnvBase

from rlpipe.algos.base import Algorithm, Metrics
from rlpipe.algos.dqn import DQN, DQNConfig
from rlpipe.errors import RlpipeError

__all__ = ["ALGORITHMS", "Algorithm", "Metrics", "DQN", "DQNConfig", "make_algorithm"]

# name -> (config dataclass, builder(env, cfg, device) -> Algorithm)
ALGORITHMS: dict[str, tuple[type, Callable[..., Algorithm]]] = {
    "dqn": (DQNConfig, DQN),
}


def make_algorithm(env: EnvBase, cfg: Any, *, device: str | torch.device = "cpu") -> Algorithm:
    """Build the algorithm named by ``cfg.name`` on ``env``."""
    if cfg.name not in ALGORITHMS:
        raise RlpipeError(f"unknown algorithm {cfg.name!r}; choose one of {', '.join(ALGORITHMS)}")
    return ALGORITHMS[cfg.name][1](env, cfg, device=device)
