"""Algorithm registry: config class and builder for each ``algo`` option."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import torch
from torch import nn

from rlpipe.algos.ars import ARS, ARSConfig
from rlpipe.algos.base import Algorithm, Metrics
from rlpipe.algos.dqn import DQN, DQNConfig
from rlpipe.algos.mbrl import MBRL, MBRLConfig
from rlpipe.algos.ppo import PPO, PPOConfig
from rlpipe.algos.reinforce import Reinforce, ReinforceConfig
from rlpipe.algos.sac import SAC, SACConfig
from rlpipe.envs import EnvFactory
from rlpipe.errors import check_choice

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
    "PPO",
    "PPOConfig",
    "SAC",
    "SACConfig",
    "Reinforce",
    "ReinforceConfig",
    "make_algorithm",
]

# name -> (config dataclass, builder(env_factory, cfg, device=...) -> Algorithm)
ALGORITHMS: dict[str, tuple[type, Callable[..., Algorithm]]] = {
    "dqn": (DQNConfig, DQN),
    "reinforce": (ReinforceConfig, Reinforce),
    "ars": (ARSConfig, ARS),
    "mbrl": (MBRLConfig, MBRL),
    "ppo": (PPOConfig, PPO),
    "sac": (SACConfig, SAC),
}


def make_algorithm(
    env_factory: EnvFactory,
    cfg: Any,
    *,
    device: str | torch.device = "cpu",
    network: nn.Module | None = None,
) -> Algorithm:
    """Build the algorithm named by ``cfg.name`` on envs from ``env_factory``.

    ``network``: your module in place of the algorithm's default network."""
    check_choice(cfg.name, "algo.name", ALGORITHMS)
    extra = {} if network is None else {"network": network}
    return ALGORITHMS[cfg.name][1](env_factory, cfg, device=device, **extra)
