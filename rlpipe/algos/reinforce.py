"""REINFORCE assembled from TorchRL parts: a ProbabilisticActor, whole episodes stepped on the
batched env into TensorDicts, a hand-written policy-gradient objective over minibatches and,
optionally, a learned state-value baseline whose targets TorchRL's TD(1) estimator computes."""

from __future__ import annotations

import math
from collections.abc import Callable

import torch
from tensordict import TensorDictBase
from tensordict.nn import (
    TensorDictModuleBase,
)
from torchrl.envs import EnvBase, ExplorationType, set_exploration_type
from torchrl.objectives.value import TD1Estimator
from torchrl.objectives.value.functional import reward2go

from rlpipe.algos.base import LOSS, EnvAlgorithm, Metrics, episode_metrics
from rlpipe.algos.configs import ReinforceConfig
from rlpipe.envs import observation_size
from rlpipe.episodes import episode_quotas
from rlpipe.models import TensorModule, make_policy, mlp

_EPS = torch.finfo(torch.float32).eps


def normalized_returns(batch: TensorDictBase, gamma: float) -> torch.Tensor:
    """Discounted returns of concatenated whole episodes, normalised within each episode.

    The per-episode sums run on the CPU: on CUDA, ``bincount`` with weights adds atomically in
    no fixed order, and two runs with one seed would part ways."""
    done = batch["next", "done"]
    on_device = reward2go(batch["next", "reward"], done, gamma).squeeze(-1)
    returns = on_device.cpu()
    done = done.squeeze(-1).long().cpu()
    episode = torch.cumsum(done, 0) - done  # 0, 0, ..., 1, 1, ...: which episode each frame is
    counts = torch.bincount(episode).to(returns.dtype)
    mean = torch.bincount(episode, returns) / counts
    centered = returns - mean[episode]
    var = torch.bincount(episode, centered.square()) / (counts - 1).clamp(min=1)
    return (centered / (var.sqrt()[episode] + _EPS)).to(on_device.device)


class Stopped(Exception):
    """``should_stop`` ended :func:`collect_episodes` before its episodes were done."""


@torch.no_grad()
def collect_episodes(
    policy: TensorDictModuleBase,
    env: EnvBase,
    episodes: int,
    *,
    frame_limit: int | None = None,
    should_stop: Callable[[], bool] | None = None,
) -> tuple[TensorDictBase, int]:
    """``episodes`` whole episodes of ``policy`` (sampling) and the env frames it took.

    The env's ``n`` copies start fresh and run in lock-step; copy ``i`` contributes its first
    ``episodes // n`` (+1 for the first ``episodes % n`` copies) episodes, so every episode
    is on-policy and short ones are not over-represented; frames stepped past a copy's quota
    are counted but not kept. Stepping stops once ``frame_limit`` frames are stepped (whole
    steps of the copies); the episodes it cuts are not kept. ``should_stop``, polled after every
    step, ends the collection with :class:`Stopped`. Episodes are concatenated along the single
    batch dimension, each ending at a ``("next", "done")`` flag.
    """
    n = env.batch_size.numel()
    remaining = episode_quotas(n, episodes)
    device = next(policy.parameters()).device
    td, steps, kept = env.reset(), [], []
    limit = frame_limit if frame_limit is not None else math.inf
    with set_exploration_type(ExplorationType.RANDOM):
        while bool((remaining > 0).any()) and n * len(steps) < limit:
            td = policy(td) if device == env.device else policy(td.to(device)).to(env.device)
            td, td_next = env.step_and_maybe_reset(td)
            steps.append(td)
            kept.append(remaining > 0)
            remaining -= td["next", "done"].reshape(n).long() * (remaining > 0)
            if should_stop is not None and should_stop():
                raise Stopped
            td = td_next
    rollout = torch.stack(steps, 1)  # [n, time]: each copy's episodes in order
    done = rollout["next", "done"].reshape(n, len(steps))
    ended = done.flip(1).cumsum(1).flip(1) > 0  # up to each copy's last episode end
    return rollout[torch.stack(kept, 1) & ended], n * len(steps)


class Reinforce(EnvAlgorithm):
    """REINFORCE (Monte-Carlo policy gradient) on a batched TorchRL env, discrete or continuous.

    Each :meth:`train_step` is one epoch: :func:`collect_episodes` runs
    ``cfg.episodes_per_epoch`` fresh episodes (env seeds drawn from torch's generator, so a
    resumed run is the uninterrupted one) with the sampling policy, every frame gets a weight
    (``baseline="none"``: its discounted return normalised within its episode, the notebook's;
    ``"value"``: TorchRL's TD(1) advantage, the discounted return minus a learned ``V(s)``, which
    bootstraps on ``V`` where the time limit cut an episode), then ``cfg.updates_per_epoch`` Adam
    steps on random minibatches of ``cfg.batch_size`` frames minimise ``-log pi(a|s) * weight``
    (plus, with the baseline, ``V``'s squared error to the epoch's TD(1) targets). An epoch
    that reaches the run's ``total_frames`` (:meth:`limit_frames`) stops there and learns from
    the episodes that ended; a stop request (SIGINT/SIGTERM) ends it within an env step, undone
    (its random draws given back, so the checkpoint is the previous epoch's end).
    ``network`` (or ``cfg.network``) is your policy network in place of the MLP: observations to
    logits, or to a mean and a pre-sigmoid std per continuous action dimension.
    """

    budget_key = "algo.epochs"

    cfg: ReinforceConfig

    def _build(self, env: EnvBase) -> None:
        cfg = self.cfg
        self.budget = cfg.epochs
        n_obs = observation_size(env, "REINFORCE")
        self.policy, self._actor, self._sample_key = make_policy(
            env, self.network, algo="REINFORCE"
        )
        self.policy.to(self.device)
        groups = [{"params": list(self.policy.parameters())}]
        self.value: TensorModule | None = None
        self.state_attrs = ("policy", "optimizer")
        if cfg.baseline == "value":
            net = mlp(n_obs, 1, cfg.value_hidden_sizes)
            self.value = TensorModule(net, ["observation"], ["state_value"]).to(self.device)
            self._estimator = TD1Estimator(gamma=cfg.gamma, value_network=self.value)
            groups.append({"params": list(self.value.parameters()), "lr": cfg.value_lr})
            self.state_attrs += ("value",)
        self.optimizer = torch.optim.Adam(
            groups,
            lr=cfg.lr,
            weight_decay=cfg.weight_decay,
            fused=True,  # one kernel for all parameters
        )
        self.env = env

    @torch.no_grad()
    def weigh(self, batch: TensorDictBase) -> None:
        """Write each frame's ``weight`` of ``log pi`` into ``batch`` (with the baseline, TorchRL's
        TD(1) estimator also writes V's ``value_target``)."""
        if self.value is None:
            batch["weight"] = normalized_returns(batch, self.cfg.gamma)
        else:
            self._estimator(batch)
            batch["weight"] = batch["advantage"].squeeze(-1)

    def loss(self, minibatch: TensorDictBase) -> torch.Tensor:
        """The policy-gradient loss on a minibatch of frames (plus V's when there is a baseline)."""
        log_prob = self._actor.get_dist(minibatch).log_prob(minibatch[self._sample_key])
        loss = -(log_prob * minibatch["weight"]).mean()
        if self.value is not None:
            error = self.value(minibatch)["state_value"] - minibatch["value_target"]
            loss = loss + error.square().mean()
        return loss

    def train_step(self) -> Metrics:
        # each epoch's episodes start from env seeds drawn from torch's generator, which
        # checkpoints hold: a resumed run collects the episodes the uninterrupted one would have
        generator = torch.get_rng_state()
        self.env.set_seed(int(torch.randint(2**31 - 1, ())))
        limit = None if self.frame_limit is None else self.frame_limit - self.frames
        try:
            batch, frames = collect_episodes(
                self.policy,
                self.env,
                self.cfg.episodes_per_epoch,
                frame_limit=limit,
                should_stop=lambda: self.stop_requested,
            )
        except Stopped:  # a signal: the epoch did not happen (its draws are given back)
            torch.set_rng_state(generator)
            return {}
        self.frames += frames
        self.iterations += 1
        if not len(batch):  # the budget ended before any episode did
            return {}
        batch = batch.to(self.device)
        self.weigh(batch)
        data = batch.select("observation", self._sample_key, "weight", "value_target", strict=False)
        losses = []
        for _ in range(self.cfg.updates_per_epoch):
            idx = torch.randint(len(data), (self.cfg.batch_size,), device=self.device)
            loss = self.loss(data[idx])
            self.optimizer.zero_grad(set_to_none=True)
            loss.backward()
            self.optimizer.step()
            losses.append(loss.detach())
        metrics: Metrics = {LOSS: float(torch.stack(losses).mean())}
        metrics.update(episode_metrics(batch))
        return metrics

    def restart_episodes(self) -> None:
        """Nothing: every epoch starts fresh episodes, seeded from torch's generator."""

    def close(self) -> None:
        """Close the env."""
        self.env.close()
