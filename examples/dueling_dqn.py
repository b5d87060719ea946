"""A dueling Q-network (Wang et al., 2016) for rlpipe's DQN, from Python and from the CLI.

The network maps observations to one Q-value per action, as DQN's default MLP does; DQN takes
any module with that contract. From the command line (``in_features``/``out_features`` are
filled from the env)::

    PYTHONPATH=examples python -m rlpipe +experiment=dqn_cartpole \\
        algo.network._target_=dueling_dqn.DuelingQNet algo.network.hidden=128

From Python (this file: the preset, the network passed as an object)::

    python examples/dueling_dqn.py [total_frames]
"""

from __future__ import annotations

import sys

import torch
from torch import nn

from rlpipe import RunResult, compose_run, train


class DuelingQNet(nn.Module):
    """Q(s, a) = V(s) + A(s, a) - mean over a of A(s, a), on a shared ReLU trunk."""

    def __init__(self, in_features: int, out_features: int, hidden: int = 128) -> None:
        super().__init__()
        self.trunk = nn.Sequential(
            nn.Linear(in_features, hidden), nn.ReLU(), nn.Linear(hidden, hidden), nn.ReLU()
        )
        self.value = nn.Linear(hidden, 1)
        self.advantage = nn.Linear(hidden, out_features)

    def forward(self, observation: torch.Tensor) -> torch.Tensor:
        features = self.trunk(observation)
        advantage = self.advantage(features)
        return self.value(features) + advantage - advantage.mean(-1, keepdim=True)


def main(total_frames: int = 50_000, run_dir: str = "runs/dueling_dqn") -> RunResult:
    """Train DQN with the dueling network on CartPole-v1: the ``dqn_cartpole`` preset."""
    cfg = compose_run("+experiment=dqn_cartpole", f"total_frames={total_frames}")
    # a module object: config.yaml records the preset; pass the network again to load_run
    return train(cfg, run_dir, network=DuelingQNet(in_features=4, out_features=2))


if __name__ == "__main__":
    print(main(*map(int, sys.argv[1:2])).summary_line())
