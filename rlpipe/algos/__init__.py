"""Algorithm registry: config class and builder for each ``algo`` option."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import torch
from torchrl.envs import EnvBase

from rlpipe.algos.ars import ARS, ARSConfig
from rlpipe.algos.base import Algorithm, Metrics
from rlpipe.algos.dqn import DQN, DQNConfig
from rlpipe.algos.mbrl import MBRL, MBRLConfig
from rlpipe.algos.reinforce import Reinforce, ReinforceConfig
from rlpipe.errors import RlpipeError

__all__ = [
    "ALGORITHMS",
    "ARS",
    "ARSConfig",
    "Algorithm",
    "Metrics",
    "DQN",
    "DQNConfig",
    "MBRL",
    "MBRLConfig",
    "Reinforce",
    "ReinforceConfig",
    "make_algorithm",
]

# name -> (config dataclass, builder(env, cfg, device) -> Algorithm)
ALGORITHMS: dict[str, tuple[type, Callable[..., Algorithm]]] = {
    "dqn": (DQNConfig, DQN),
    "reinforce": (ReinforceConfig, Reinforce),
    "ars": (ARSConfig, ARS),
    "mbrl": (MBRLConfig, MBRL),
}


def make_algorithm(env: EnvBase, cfg: Any, *, device: str | torch.device = "cpu") -> Algorithm:
    """Build the algorithm named by ``cfg.name`` on ``env``."""
    if cfg.name not in ALGORITHMS:
        raise RlpipeError(f"unknown algorithm {cfg.name!r}; choose one of {', '.join(ALGORITHMS)}")
    return ALGORITHMS[cfg.name][1](env, cfg, device=device)
