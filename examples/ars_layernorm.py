"""An MLP with LayerNorm as ARS's policy network, given in the config (``algo.network``).

ARS searches every parameter of the network (LayerNorm's gain and bias too) behind its running
observation normaliser; the network maps normalised observations to one value per action (the
argmax is taken) or per action dimension (clamped into the bounds). From the command line::

    PYTHONPATH=examples python -m rlpipe algo=ars env=cartpole \\
        algo.network._target_=ars_layernorm.LayerNormMLP algo.network.hidden=16

From Python (this file)::

    python examples/ars_layernorm.py [total_frames]
"""

from __future__ import annotations

import sys

import torch
from torch import nn

from rlpipe import RunResult, compose_run, train


class LayerNormMLP(nn.Module):
    """Linear -> LayerNorm -> tanh -> linear; the output layer starts at zero, as ARS's linear
    policy does, so every direction starts from the same policy."""

    def __init__(self, in_features: int, out_features: int, hidden: int = 16) -> None:
        super().__init__()
        self.hidden = nn.Sequential(nn.Linear(in_features, hidden), nn.LayerNorm(hidden), nn.Tanh())
        self.out = nn.Linear(hidden, out_features)
        nn.init.zeros_(self.out.weight)
        nn.init.zeros_(self.out.bias)

    def forward(self, observation: torch.Tensor) -> torch.Tensor:
        return self.out(self.hidden(observation))


def main(total_frames: int = 100_000, run_dir: str = "runs/ars_layernorm") -> RunResult:
    """ARS on CartPole-v1 (the notebook's settings, two rollout workers) with this network."""
    cfg = compose_run(
        "algo=ars",
        "env=cartpole",
        "algo.workers=2",
        "algo.network._target_=ars_layernorm.LayerNormMLP",  # this module, on sys.path
        f"total_frames={total_frames}",
        f"eval_every={max(total_frames // 5, 1)}",
    )
    return train(cfg, run_dir)  # config.yaml holds the spec: evaluate and resume rebuild it


if __name__ == "__main__":  # ARS's rollout workers are processes: keep the guard
    print(main(*map(int, sys.argv[1:2])).summary_line())
