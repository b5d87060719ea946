"""Baseline policies for ``python -m rlpipe.evaluate policy=random|heuristic``.

``heuristic`` is the agent-templates notebook's hand-written BipedalWalker controller: while a
knee folds fast (joint speed below -0.5) it eases that leg's hip and knee back; otherwise, and
whenever both feet are on the ground, it tries a uniformly random torque. A floor to beat, not
a walker.
"""

from __future__ import annotations

import torch
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.data import TensorSpec
from torchrl.envs import EnvBase

from rlpipe.envs import is_discrete, observation_size
from rlpipe.errors import check

# BipedalWalker-v3 observation layout (first 14 of 24: hull, then leg 1 and leg 2 joints)
KNEE_1_SPEED, LEG_1_CONTACT, KNEE_2_SPEED, LEG_2_CONTACT = 7, 8, 12, 13
FOLD_SPEED = -0.5
EASE_BACK = (-0.05, -0.2)  # hip and knee torque for a folding leg


class RandomActions(nn.Module):
    """Uniform samples from an action spec, one per observation in the batch."""

    def __init__(self, spec: TensorSpec) -> None:
        super().__init__()
        self.spec = spec

    def forward(self, observation: torch.Tensor) -> torch.Tensor:
        return self.spec.rand(observation.shape[:-1])


class WalkerHeuristic(nn.Module):
    """The notebook's BipedalWalker controller, batched: observations (..., 24) -> torques."""

    def forward(self, observation: torch.Tensor) -> torch.Tensor:
        action = torch.rand(*observation.shape[:-1], 4) * 2 - 1
        ease = torch.tensor(EASE_BACK)
        both_down = (observation[..., LEG_1_CONTACT] == 1) & (observation[..., LEG_2_CONTACT] == 1)
        fold_1 = ~both_down & (observation[..., KNEE_1_SPEED] < FOLD_SPEED)
        fold_2 = ~both_down & ~fold_1 & (observation[..., KNEE_2_SPEED] < FOLD_SPEED)
        for fold, leg in ((fold_1, slice(0, 2)), (fold_2, slice(2, 4))):
            eased = torch.zeros(4)
            eased[leg] = ease
            action = torch.where(fold.unsqueeze(-1), eased, action)
        return action


def random_policy(env: EnvBase) -> TensorDictModule:
    """Uniformly random actions for ``env`` (any action space)."""
    return TensorDictModule(
        RandomActions(env.action_spec_unbatched), in_keys=["observation"], out_keys=["action"]
    )


def heuristic_policy(env: EnvBase) -> TensorDictModule:
    """The hand-written BipedalWalker controller; a clear error on any other env."""
    check(
        not is_discrete(env)
        and observation_size(env) == 24
        and env.action_spec_unbatched.shape == (4,),
        "policy=heuristic is the hand-written BipedalWalker controller: it needs BipedalWalker's "
        "24 observations and 4 torques (env=bipedal or bipedal_hardcore); use policy=random here",
    )
    return TensorDictModule(WalkerHeuristic(), in_keys=["observation"], out_keys=["action"])
