"""The algorithms: the registry (``ALGORITHMS``, :func:`make_algorithm`) and each algorithm's
class and config, imported on first use so that ``import rlpipe.algos`` loads no torch."""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

from rlpipe.registry import ALGORITHMS

if TYPE_CHECKING:
    import torch
    from torch import nn

    from rlpipe.algos.base import Algorithm
    from rlpipe.envs import EnvFactory

# public name -> the module that defines it (imported when the name is first used)
_LAZY = {
    "ARS": "rlpipe.algos.ars",
    "MBRL": "rlpipe.algos.mbrl",
    "DQN": "rlpipe.algos.dqn",
    "PPO": "rlpipe.algos.ppo",
    "Reinforce": "rlpipe.algos.reinforce",
    "SAC": "rlpipe.algos.sac",
    "Algorithm": "rlpipe.algos.base",
    "Metrics": "rlpipe.algos.base",
    **dict.fromkeys(
        ("ARSConfig", "DQNConfig", "MBRLConfig", "PPOConfig", "ReinforceConfig", "SACConfig"),
        "rlpipe.algos.configs",
    ),
}

__all__ = ["ALGORITHMS", "make_algorithm", *_LAZY]


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def make_algorithm(
    env_factory: EnvFactory,
    cfg: Any,
    *,
    device: str | torch.device = "cpu",
    network: nn.Module | None = None,
    threads: int | str = "auto",
    compile: bool | str = False,
) -> Algorithm:
    """Build the algorithm named by ``cfg.name`` on envs from ``env_factory``.

    ``network``: your module in place of the algorithm's default network. ``threads``: torch's
    intra-op threads, set process-wide first (a run's ``threads`` key: ``"auto"`` is 1 on a CPU
    device, ``0`` torch's default, ``N`` N). ``compile``: ``torch.compile`` the algorithm's loss
    (``True``, or ``"auto"``: where torch can compile here; :mod:`rlpipe.algos.compiling`)."""
    import torch  # with the algorithm: importing this package loads no torch

    from rlpipe.algos.compiling import compile_algorithm, wants_compile
    from rlpipe.runtime import set_threads

    set_threads(threads, torch.device(device))
    compiling = wants_compile(compile, torch.device(device))  # before anything is built
    extra = {} if network is None else {"network": network}
    algo = ALGORITHMS.builder(cfg.name)(env_factory, cfg, device=device, **extra)
    if compiling:
        try:
            compile_algorithm(algo, strict=compile is True)
        except BaseException:
            algo.close()  # its env and workers
            raise
    return algo
