"""REINFORCE assembled from TorchRL parts: a ProbabilisticActor, whole episodes stepped on the
batched env into TensorDicts, and a hand-written policy-gradient objective over minibatches."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import (
    NormalParamExtractor,
    TensorDictModule,
    TensorDictModuleBase,
    TensorDictSequential,
    add_custom_mapping,
)
from torch import nn
from torchrl.data import Bounded
from torchrl.envs import EnvBase, ExplorationType, set_exploration_type
from torchrl.modules import IndependentNormal, ProbabilisticActor
from torchrl.objectives.value.functional import reward2go

from rlpipe.algos.base import Metrics, episode_metrics
from rlpipe.envs import is_discrete, num_actions, observation_size
from rlpipe.errors import RlpipeError, check
from rlpipe.models import mlp

add_custom_mapping("sigmoid", torch.sigmoid)  # the notebook's std in (0, 1)
_EPS = torch.finfo(torch.float32).eps


@dataclass
class ReinforceConfig:
    """REINFORCE hyper-parameters; the defaults are the REINFORCE/ARS notebook's."""

    name: str = "reinforce"
    hidden_sizes: list[int] = field(default_factory=list)  # []: a linear policy
    episodes_per_epoch: int = 100  # whole episodes collected per train_step
    updates_per_epoch: int = 50  # Adam steps per epoch, each on a random minibatch
    batch_size: int = 128
    gamma: float = 0.99
    lr: float = 1e-3
    weight_decay: float = 1e-4

    def __post_init__(self) -> None:
        check(
            self.episodes_per_epoch >= 1,
            f"algo.episodes_per_epoch must be >= 1, got {self.episodes_per_epoch}",
        )
        check(
            self.updates_per_epoch >= 1,
            f"algo.updates_per_epoch must be >= 1, got {self.updates_per_epoch}",
        )
        check(self.batch_size >= 1, f"algo.batch_size must be >= 1, got {self.batch_size}")
        check(0 < self.gamma <= 1, f"algo.gamma must be in (0, 1], got {self.gamma}")
        check(self.lr > 0, f"algo.lr must be > 0, got {self.lr}")
        check(self.weight_decay >= 0, f"algo.weight_decay must be >= 0, got {self.weight_decay}")
        check(
            all(h >= 1 for h in self.hidden_sizes),
            f"algo.hidden_sizes must be positive, got {self.hidden_sizes}",
        )


class Clip(nn.Module):
    """Clamp a tensor into ``[low, high]`` (element-wise bounds)."""

    def __init__(self, low: torch.Tensor, high: torch.Tensor) -> None:
        super().__init__()
        self.register_buffer("low", low)
        self.register_buffer("high", high)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return torch.clamp(x, self.low, self.high)


def make_policy(env: EnvBase, hidden_sizes: list[int]) -> tuple[TensorDictModuleBase, str]:
    """The stochastic policy and the key holding what its log-probability is taken of.

    Discrete actions: a Categorical over logits, sampled into ``action``. Box actions: a
    Gaussian with a mean and a sigmoid std in (0, 1) per dimension, as the notebook's; the raw
    sample goes to ``sample`` (the policy gradient's variable) and ``action`` is that sample
    clipped into the bounds. In deterministic mode: the argmax, or the clipped mean.
    """
    spec = env.action_spec_unbatched
    n_obs = observation_size(env)
    if is_discrete(env):
        net = mlp(n_obs, num_actions(env), hidden_sizes)
        module = TensorDictModule(net, in_keys=["observation"], out_keys=["logits"])
        actor = ProbabilisticActor(
            module,
            in_keys=["logits"],
            spec=spec,
            distribution_class=torch.distributions.Categorical,
        )
        return actor, "action"
    if not isinstance(spec, Bounded) or not spec.dtype.is_floating_point or len(spec.shape) != 1:
        raise RlpipeError(
            f"REINFORCE's policy needs discrete actions or a bounded flat box of continuous "
            f"actions, but this env's actions are {type(spec).__name__} of shape "
            f"{tuple(spec.shape)}"
        )
    net = nn.Sequential(
        mlp(n_obs, 2 * spec.shape[0], hidden_sizes), NormalParamExtractor(scale_mapping="sigmoid")
    )
    module = TensorDictModule(net, in_keys=["observation"], out_keys=["loc", "scale"])
    actor = ProbabilisticActor(
        module,
        in_keys=["loc", "scale"],
        out_keys=["sample"],
        distribution_class=IndependentNormal,
        distribution_kwargs={"upscale": 1.0},
    )
    clip = Clip(spec.space.low.clone(), spec.space.high.clone())
    return TensorDictSequential(actor, TensorDictModule(clip, ["sample"], ["action"])), "sample"


def normalized_returns(batch: TensorDictBase, gamma: float) -> torch.Tensor:
    """Discounted returns of concatenated whole episodes, normalised within each episode."""
    done = batch["next", "done"]
    returns = reward2go(batch["next", "reward"], done, gamma).squeeze(-1)
    done = done.squeeze(-1).long()
    episode = torch.cumsum(done, 0) - done  # 0, 0, ..., 1, 1, ...: which episode each frame is
    counts = torch.bincount(episode).to(returns.dtype)
    mean = torch.bincount(episode, returns) / counts
    centered = returns - mean[episode]
    var = torch.bincount(episode, centered.square()) / (counts - 1).clamp(min=1)
    return centered / (var.sqrt()[episode] + _EPS)


@torch.no_grad()
def collect_episodes(
    policy: TensorDictModuleBase, env: EnvBase, episodes: int
) -> tuple[TensorDictBase, int]:
    """``episodes`` whole episodes of ``policy`` (sampling) and the env frames it took.

    The env's ``n`` copies start fresh and run in lock-step; copy ``i`` contributes its first
    ``episodes // n`` (+1 for the first ``episodes % n`` copies) episodes, so every episode
    is on-policy and short ones are not over-represented; frames stepped past a copy's quota
    are counted but not kept. Episodes are concatenated along the single batch dimension,
    each ending at a ``("next", "done")`` flag.
    """
    n = env.batch_size.numel()
    remaining = torch.tensor([episodes // n + (i < episodes % n) for i in range(n)])
    device = next(policy.parameters()).device
    td, steps, kept = env.reset(), [], []
    with set_exploration_type(ExplorationType.RANDOM):
        while bool((remaining > 0).any()):
            td = policy(td) if device == env.device else policy(td.to(device)).to(env.device)
            td, td_next = env.step_and_maybe_reset(td)
            steps.append(td)
            kept.append(remaining > 0)
            remaining -= td["next", "done"].reshape(n).long() * (remaining > 0)
            td = td_next
    rollout = torch.stack(steps, 1)  # [n, time]: each copy's episodes in order
    return rollout[torch.stack(kept, 1)], n * len(steps)


class Reinforce:
    """REINFORCE (Monte-Carlo policy gradient) on a batched TorchRL env, discrete or continuous.

    Each :meth:`train_step` is one epoch: :func:`collect_episodes` runs
    ``cfg.episodes_per_epoch`` fresh episodes with the sampling policy, returns are discounted
    and normalised per episode, then ``cfg.updates_per_epoch`` Adam steps maximise
    ``log pi(a|s) * G`` on random minibatches of ``cfg.batch_size`` frames.
    """

    def __init__(self, env: EnvBase, cfg: ReinforceConfig, *, device: str | torch.device = "cpu"):
        self.cfg = cfg
        self.device = torch.device(device)
        self.frames = 0
        self.policy, self._sample_key = make_policy(env, cfg.hidden_sizes)
        self.policy.to(self.device)
        self._actor = self.policy if self._sample_key == "action" else self.policy[0]
        self.optimizer = torch.optim.Adam(
            self.policy.parameters(),
            lr=cfg.lr,
            weight_decay=cfg.weight_decay,
            fused=True,  # one kernel for all parameters
        )
        self.env = env

    def train_step(self) -> Metrics:
        batch, frames = collect_episodes(self.policy, self.env, self.cfg.episodes_per_epoch)
        self.frames += frames
        batch = batch.to(self.device)
        observation, sample = batch["observation"], batch[self._sample_key]
        weight = normalized_returns(batch, self.cfg.gamma)
        losses = []
        for _ in range(self.cfg.updates_per_epoch):
            idx = torch.randint(len(weight), (self.cfg.batch_size,), device=self.device)
            minibatch = TensorDict(observation=observation[idx], batch_size=[len(idx)])
            log_prob = self._actor.get_dist(minibatch).log_prob(sample[idx])
            loss = -(log_prob * weight[idx]).mean()
            self.optimizer.zero_grad(set_to_none=True)
            loss.backward()
            self.optimizer.step()
            losses.append(loss.detach())
        metrics: Metrics = {"train/loss": float(torch.stack(losses).mean())}
        metrics.update(episode_metrics(batch))
        return metrics

    def state_dict(self) -> dict[str, Any]:
        return {
            "policy": self.policy.state_dict(),
            "optimizer": self.optimizer.state_dict(),
            "frames": self.frames,
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.policy.load_state_dict(state["policy"])
        self.optimizer.load_state_dict(state["optimizer"])
        self.frames = int(state["frames"])

    def close(self) -> None:
        """Close the env."""
        self.env.close()
