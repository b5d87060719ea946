"""Greedy policies as plain torch modules: raw observations in, the actions rlpipe's evaluation
takes out (what ``python -m rlpipe.export`` writes).

:func:`greedy_policy` builds, from a trained algorithm, an ``nn.Module`` mapping a float32 batch
``[B, obs]`` of raw observations to the greedy actions ``[B]`` (discrete, int64) or
``[B, action dims]`` (continuous, float32), with no TensorDict, distribution or rlpipe inside:
the observation normaliser (ARS, PPO; MBRL's world model), the network, and the action head that
evaluation's deterministic mode applies (argmax of Q-values, the most probable action, the
Gaussian's mean clamped into the bounds, SAC's tanh of the mean scaled into them). MBRL's greedy
policy plans with its world model (:class:`FixedNoisePlanner`).
"""

from __future__ import annotations

import copy
from collections.abc import Callable

import torch
import torch.nn.functional as F
from tensordict import TensorDict
from tensordict.nn import TensorDictModuleBase
from torch import nn
from torchrl.envs import ExplorationType, set_exploration_type

from rlpipe.algos.base import Algorithm
from rlpipe.algos.mbrl.planning import Planner
from rlpipe.errors import RlpipeError
from rlpipe.models import ArgmaxAction

# the seed rlpipe's greedy MPC policy re-seeds its planner's noise with on every call
# (rlpipe.algos.mbrl.algorithm._EVAL_SEED)
PLANNER_SEED = 0


class GreedyPolicy(nn.Module):
    """``observation -> net -> (its output number output) -> head``: the greedy action."""

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


class FixedNoisePlanner(nn.Module):
    """MBRL's greedy model-predictive control as a module: the planner's search on the world
    model, with the noise drawn once, as rlpipe's greedy policy draws it for one observation.

    rlpipe's greedy MPC re-seeds its planner with :data:`PLANNER_SEED` on every call, so for one
    observation its action is a function of the observation; this module holds that noise
    (CEM: ``iterations`` draws of ``[candidates, horizon, action]``; random shooting: one) and
    plans every row of a batch with it, so row ``i`` of a batch gets the action rlpipe's policy
    takes for observation ``i`` alone (on a batch, rlpipe's policy draws other noise per row).
    """

    def __init__(self, planner: Planner) -> None:
        super().__init__()
        self.model, self.planner = planner.model, planner  # owned: greedy_policy passes a copy
        # whether the model predicts terminations, as a constant: torch.export (ONNX) cannot
        # branch on a buffer's value (it changes only while training)
        can_terminate = bool(self.model.can_terminate)
        del self.model.can_terminate
        self.model.can_terminate = can_terminate
        coder = planner.coder
        shape = (planner.candidates, planner.horizon, 1 if coder.discrete else coder.size)
        gaussian = not coder.discrete and planner.method == "cem"
        generator = torch.Generator().manual_seed(PLANNER_SEED)
        # the planner's draws for one observation, one per iteration (random shooting: one)
        noise = torch.stack(
            [
                (torch.randn if gaussian else torch.rand)((1, *shape), generator=generator)[0]
                for _ in range(planner.iterations)
            ]
        )
        if not coder.discrete and planner.method == "random":
            noise = noise * 2 - 1  # uniform action codes in [-1, 1]
        self.register_buffer("noise", noise)

    def forward(self, observation: torch.Tensor) -> torch.Tensor:
        if self.planner.coder.discrete:
            return self._discrete(observation)
        return self._box(observation)

    def _box(self, observation: torch.Tensor) -> torch.Tensor:
        planner = self.planner
        if planner.method == "random":
            codes = self.noise[0].expand(observation.shape[0], -1, -1, -1)
            best = planner.returns(observation, codes).argmax(1)
            first = codes[torch.arange(observation.shape[0]), best, 0]
        else:
            mean = observation.new_zeros(observation.shape[0], 1, *self.noise.shape[2:])
            std = torch.full_like(mean, planner.init_std)
            for noise in self.noise:
                elite = planner._elites(observation, (mean + std * noise).clamp(-1, 1))
                mean, std = elite.mean(1, keepdim=True), elite.std(1, keepdim=True)
            first = mean[:, 0, 0]
        return planner.coder.decode(first)

    def _discrete(self, observation: torch.Tensor) -> torch.Tensor:
        planner, n = self.planner, self.planner.coder.num_actions
        rows = observation.shape[0]
        probs = observation.new_full((rows, 1, planner.horizon, n), 1 / n)
        for uniform in self.noise:  # inverse-CDF samples of the per-step categoricals
            index = (probs.cumsum(-1) < uniform).sum(-1).clamp(max=n - 1)
            codes = F.one_hot(index, n).float()
            if planner.method == "random":
                best = planner.returns(observation, codes).argmax(1)
                return index[torch.arange(rows), best, 0]
            probs = planner._elites(observation, codes).mean(1, keepdim=True)
        return probs[:, 0, 0].argmax(-1)


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
    return FixedNoisePlanner(_inner(policy, "action").planner)


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
    """A plain ``nn.Module`` (eval mode) mapping raw float32 observations ``[B, obs]`` to the
    greedy actions ``algo.policy`` takes in evaluation, built from a copy of the policy (later
    training does not change it). MBRL: see :class:`FixedNoisePlanner`."""
    name = algo.cfg.name
    if name not in BUILDERS:
        raise RlpipeError(
            f"cannot export algo={name}: rlpipe knows the greedy policy of "
            f"{', '.join(BUILDERS)}; build a torch module from its policy by hand"
        )
    return BUILDERS[name](copy.deepcopy(algo.policy)).eval()


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
