"""Greedy policies as plain torch modules: raw observations in, the actions rlpipe's evaluation
takes out (what ``python -m rlpipe.export`` writes).

:func:`greedy_policy` builds, from a trained algorithm, an ``nn.Module`` mapping a float32 batch
``[B, obs]`` of raw observations to the greedy actions ``[B]`` (discrete, int64) or
``[B, action dims]`` (continuous, float32), with no TensorDict or distribution inside: the
observation normaliser (ARS, PPO; MBRL's world model), the network, and the action head that
evaluation's deterministic mode applies (argmax of Q-values, the most probable action, the
Gaussian's mean clamped into the bounds, SAC's tanh of the mean scaled into them). MBRL's greedy
policy plans with its world model (:class:`FixedNoisePlanner`).
"""

from __future__ import annotations

import copy
from collections.abc import Callable
from typing import Any

import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModuleBase
from torch import nn
from torch.overrides import TorchFunctionMode
from torchrl.envs import ExplorationType, set_exploration_type

from rlpipe.algos.base import Algorithm
from rlpipe.errors import RlpipeError
from rlpipe.models import ArgmaxAction

# the random draws of MBRL's planner (torch functions), fixed by FixedNoisePlanner
DRAWS = (torch.rand, torch.randn)


class GreedyPolicy(nn.Module):
    """The network, then the action head: on the network's output, or on its output number
    ``output`` when it returns several (a Gaussian's location and scale: 0)."""

    def __init__(self, net: nn.Module, head: nn.Module, output: int | None = None) -> None:
        super().__init__()
        self.net, self.head, self.output = net, head, output

    def forward(self, observation: torch.Tensor) -> torch.Tensor:
        out = self.net(observation)
        return self.head(out if self.output is None else out[self.output])


class MostProbable(nn.Module):
    """The most probable action of a Categorical over ``logits``: its ``mode``."""

    def forward(self, logits: torch.Tensor) -> torch.Tensor:
        return torch.softmax(logits, -1).argmax(-1)


class TanhAction(nn.Module):
    """SAC's greedy action: the Gaussian's mean through TorchRL's safe tanh (kept off ±1 by the
    float's resolution), scaled from [-1, 1] into ``[low, high]`` (TanhNormal's deterministic
    sample)."""

    def __init__(self, low: torch.Tensor, high: torch.Tensor) -> None:
        super().__init__()
        self.register_buffer("center", (high + low) / 2)
        self.register_buffer("half_range", (high - low) / 2)

    def forward(self, loc: torch.Tensor) -> torch.Tensor:
        limit = 1.0 - torch.finfo(loc.dtype).resolution
        return self.center + self.half_range * loc.tanh().clamp(-limit, limit)


class _RecordDraws(TorchFunctionMode):
    """Inside it, the planner's random draws (:data:`DRAWS`) are also kept in ``draws``."""

    def __init__(self) -> None:
        super().__init__()
        self.draws: list[torch.Tensor] = []

    def __torch_function__(
        self, func: Callable, types: tuple, args: tuple = (), kwargs: dict | None = None
    ) -> Any:
        out = func(*args, **(kwargs or {}))
        if func in DRAWS:
            self.draws.append(out)
        return out


class _ReplayDraws(TorchFunctionMode):
    """Inside it, the planner's random draws return ``draws`` in turn, each (one observation's
    draw) expanded to the batch asked for."""

    def __init__(self, draws: torch.Tensor) -> None:
        super().__init__()
        self.draws = iter(draws)

    def __torch_function__(
        self, func: Callable, types: tuple, args: tuple = (), kwargs: dict | None = None
    ) -> Any:
        if func not in DRAWS:
            return func(*args, **(kwargs or {}))
        sized = isinstance(args[0], (tuple, list, torch.Size))
        shape = args[0] if sized else args  # rand(size) or rand(*size)
        return next(self.draws).expand(shape)


class FixedNoisePlanner(nn.Module):
    """MBRL's greedy model-predictive control as a module: its MPC policy, whose planner's
    random draws are the ones it makes for one observation, fixed.

    rlpipe's greedy MPC re-seeds its planner's noise on every call, so for one observation its
    action is a function of the observation. This module records the draws of one such call
    (they depend on the batch's size, not on the observation) and replays them, each expanded
    to the batch, whenever it plans: row ``i`` of a batch gets the action rlpipe's policy takes
    for observation ``i`` alone (on a batch, rlpipe's policy draws other noise for each row).
    It takes over ``mpc`` (:func:`greedy_policy` passes a copy): the world model's "can
    terminate" flag becomes a constant, as torch.export (ONNX) cannot branch on a buffer.
    """

    def __init__(self, mpc: nn.Module) -> None:
        super().__init__()
        self.mpc = mpc
        model = mpc.model
        can_terminate = bool(model.can_terminate)
        del model.can_terminate
        model.can_terminate = can_terminate
        recorder = _RecordDraws()
        with torch.no_grad(), recorder:
            mpc(torch.zeros(1, model.obs_norm.loc.numel()))
        self.register_buffer("noise", torch.cat(recorder.draws))

    def forward(self, observation: torch.Tensor) -> torch.Tensor:
        with set_exploration_type(ExplorationType.DETERMINISTIC), _ReplayDraws(self.noise):
            return self.mpc(observation)


def _writer(policy: nn.Module, key: str) -> nn.Module | None:
    """The tensor module inside ``policy`` whose first output is ``key`` (the ``module`` of a
    ``TensorModule`` or ``TensorDictModule``), or None."""
    for module in policy.modules():
        inner = getattr(module, "module", None)
        keys = getattr(module, "out_keys", None) or [None]
        if isinstance(inner, nn.Module) and not isinstance(inner, nn.ModuleList) and keys[0] == key:
            return inner
    return None


def _inner(policy: nn.Module, key: str) -> nn.Module:
    found = _writer(policy, key)
    if found is None:
        raise RlpipeError(f"the policy {type(policy).__name__} has no module writing {key!r}")
    return found


def _q_values(policy: TensorDictModuleBase) -> nn.Module:
    """DQN: the argmax of the Q-values."""
    return GreedyPolicy(_inner(policy, "action_value"), ArgmaxAction())


def _gaussian_or_categorical(policy: TensorDictModuleBase) -> nn.Module:
    """REINFORCE's and PPO's (:func:`rlpipe.models.make_policy`): the most probable action, or
    the Gaussian's mean clamped into the bounds."""
    logits = _writer(policy, "logits")
    if logits is not None:
        return GreedyPolicy(logits, MostProbable())
    return GreedyPolicy(_inner(policy, "loc"), _inner(policy, "action"), output=0)


def _tanh_gaussian(policy: TensorDictModuleBase) -> nn.Module:
    """SAC: the tanh of the Gaussian's mean, scaled into the bounds."""
    space = policy.spec["action"].space
    return GreedyPolicy(_inner(policy, "loc"), TanhAction(space.low, space.high), output=0)


def _normalized_search(policy: TensorDictModuleBase) -> nn.Module:
    """ARS: normaliser, network, then its argmax or clamp."""
    keys = ("observation_norm", "policy_output", "action")
    normalizer, net, head = (_inner(policy, key) for key in keys)
    return GreedyPolicy(nn.Sequential(normalizer, net), head)


def _planner(policy: TensorDictModuleBase) -> nn.Module:
    """MBRL: its model-predictive control with the greedy noise fixed."""
    return FixedNoisePlanner(_inner(policy, "action"))


# algorithm name -> the greedy module of its (copied) policy
BUILDERS: dict[str, Callable[[TensorDictModuleBase], nn.Module]] = {
    "dqn": _q_values,
    "reinforce": _gaussian_or_categorical,
    "ppo": _gaussian_or_categorical,
    "sac": _tanh_gaussian,
    "ars": _normalized_search,
    "mbrl": _planner,
}


def greedy_policy(algo: Algorithm) -> nn.Module:
    """The algorithm's greedy policy as a plain ``nn.Module``.

    It maps raw float32 observations ``[B, obs]`` to the greedy actions ``algo.policy`` takes in
    evaluation: built from a copy of the policy (later training does
    not change it), in eval mode, its parameters without gradients. MBRL: see
    :class:`FixedNoisePlanner`."""
    name = algo.cfg.name
    observation = getattr(algo, "observation", None)
    if observation is not None and observation.image:
        raise RlpipeError(
            f"cannot export this {name} policy: it sees images through make_env's image "
            "transforms and frame stacking, which a standalone file does not carry; evaluate it "
            "with python -m rlpipe.evaluate, or save its network (algo.policy) with torch.save"
        )
    if name not in BUILDERS:
        raise RlpipeError(
            f"cannot export algo={name}: rlpipe knows the greedy policy of "
            f"{', '.join(BUILDERS)}; build a torch module from its policy by hand"
        )
    return BUILDERS[name](copy.deepcopy(algo.policy)).eval().requires_grad_(False)


@torch.no_grad()
def policy_actions(
    policy: TensorDictModuleBase, observations: torch.Tensor, *, rows_alone: bool = False
) -> torch.Tensor:
    """What ``policy`` (an rlpipe policy) does with ``observations`` ``[B, obs]`` in
    evaluation's deterministic mode; ``rows_alone``: one row at a time (MBRL's planner draws
    its noise per batch)."""
    batches = observations.split(1) if rows_alone else [observations]
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        return torch.cat(
            [policy(TensorDict(observation=o, batch_size=o.shape[:1]))["action"] for o in batches]
        )
