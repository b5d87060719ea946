"""SAC assembled from TorchRL parts: a tanh-Gaussian ProbabilisticActor, twin Q ValueOperators,
the Collector, a ReplayBuffer, SACLoss (automatic entropy tuning) and SoftUpdate."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from tensordict.nn import NormalParamExtractor, TensorDictModule
from torch import nn
from torchrl.data import Bounded, LazyTensorStorage, ReplayBuffer
from torchrl.envs import EnvBase
from torchrl.modules import MLP, ProbabilisticActor, TanhNormal, ValueOperator
from torchrl.objectives import SACLoss, SoftUpdate

from rlpipe.algos.base import LOSS, TRANSITION_KEYS, EnvAlgorithm, Metrics, episode_metrics
from rlpipe.config import AlgoConfig, checked
from rlpipe.envs import is_discrete, observation_size
from rlpipe.errors import RlpipeError, check


@dataclass
class SACConfig(AlgoConfig):
    """SAC hyper-parameters; the defaults are SB3's."""

    name: str = "sac"
    total_frames: int | None = 50_000  # SAC has no budget of its own: the run's length
    eval_every: int = 5_000
    hidden_sizes: list[int] = checked([256, 256], "sizes")  # actor's and each critic's
    lr: float = checked(3e-4, "positive")  # actor, critics and the entropy coefficient
    batch_size: int = checked(256, "at_least_one")
    buffer_size: int = 1_000_000
    gamma: float = checked(0.99, "discount")
    tau: float = checked(0.005, "discount")  # target critics: tau * online + (1 - tau) * target
    frames_per_batch: int = checked(1, "at_least_one")  # env frames collected per iteration
    updates_per_batch: int = checked(1, "non_negative")  # gradient steps per iteration
    learning_starts: int = checked(100, "non_negative")  # frames collected before updates
    alpha_init: float = checked(1.0, "positive")  # the entropy coefficient's start
    target_entropy: float | None = None  # null: minus the action dimensions

    def __post_init__(self) -> None:
        super().__post_init__()
        check(
            self.buffer_size >= self.batch_size,
            f"algo.buffer_size ({self.buffer_size}) must be >= algo.batch_size ({self.batch_size})",
        )


class SAC(EnvAlgorithm):
    """Soft actor-critic on a batched TorchRL env with continuous (bounded box) actions.

    Each :meth:`train_step` collects ``cfg.frames_per_batch`` frames with the sampling policy
    into the replay buffer, then (once ``cfg.learning_starts`` frames are in) runs
    ``cfg.updates_per_batch`` Adam steps on TorchRL's SACLoss (actor, twin Q critics and the
    entropy coefficient, tuned towards ``cfg.target_entropy``), each followed by a soft update
    of the target critics. The greedy policy is the tanh of the Gaussian's mean.
    ``network`` (or ``cfg.network``): the actor's network, observations to a mean and a
    pre-softplus std per action dimension.
    """

    cfg: SACConfig
    state_attrs = ("loss", "optimizer", "buffer")

    def _build(self, env: EnvBase) -> None:
        cfg, spec = self.cfg, env.action_spec_unbatched
        if is_discrete(env) or not isinstance(spec, Bounded) or len(spec.shape) != 1:
            raise RlpipeError(
                f"SAC needs continuous actions (a bounded flat box), but this env's actions are "
                f"{type(spec).__name__} of shape {tuple(spec.shape)}; pick a continuous env "
                "(pendulum, bipedal, cartpole_continuous) or algo=dqn or algo=ppo"
            )
        size, n_obs = spec.shape[0], observation_size(env)
        outputs = f"a mean and a pre-softplus std per action dimension ({size}), in that order"
        net = nn.Sequential(
            self.network(n_obs, 2 * size, outputs),
            NormalParamExtractor(scale_mapping="biased_softplus_1"),
        )
        self.policy = ProbabilisticActor(
            TensorDictModule(net, in_keys=["observation"], out_keys=["loc", "scale"]),
            in_keys=["loc", "scale"],
            spec=spec,
            distribution_class=TanhNormal,
            distribution_kwargs={"low": spec.space.low, "high": spec.space.high},
        ).to(self.device)
        qvalue = ValueOperator(  # TorchRL's MLP concatenates its inputs: Q(s, a)
            MLP(
                in_features=n_obs + size,
                out_features=1,
                num_cells=cfg.hidden_sizes,
                activation_class=nn.ReLU,
            ),
            in_keys=["observation", "action"],
        ).to(self.device)
        self.loss = SACLoss(
            self.policy,
            qvalue,
            num_qvalue_nets=2,
            alpha_init=cfg.alpha_init,
            target_entropy=-float(size) if cfg.target_entropy is None else cfg.target_entropy,
            loss_function="l2",
            deactivate_vmap=True,  # the two critics in a loop: cheaper than torch.vmap on CPU
        )
        self.loss.make_value_estimator(gamma=cfg.gamma)
        self.target_updater = SoftUpdate(self.loss, tau=cfg.tau)
        self.optimizer = torch.optim.Adam(self.loss.parameters(), lr=cfg.lr, fused=True)
        self.buffer = ReplayBuffer(
            storage=LazyTensorStorage(cfg.buffer_size, device=self.device),
            batch_size=cfg.batch_size,
        )
        self.make_collector(env, self.policy, cfg.frames_per_batch)

    def train_step(self) -> Metrics:
        batch = self.collect()
        self.frames += batch.numel()
        self.iterations += 1
        self.buffer.extend(batch.reshape(-1).select(*TRANSITION_KEYS))
        metrics: Metrics = episode_metrics(batch)
        if len(self.buffer) < max(self.cfg.learning_starts, self.cfg.batch_size):
            return metrics
        losses = []
        for _ in range(self.cfg.updates_per_batch):
            out = self.loss(self.buffer.sample())
            loss = out["loss_actor"] + out["loss_qvalue"] + out["loss_alpha"]
            self.optimizer.zero_grad(set_to_none=True)
            loss.backward()
            self.optimizer.step()
            self.target_updater.step()
            losses.append(loss.detach())
        if losses:
            metrics[LOSS] = float(torch.stack(losses).mean())
            metrics["train/alpha"] = float(out["alpha"])
        self.sync_collector()
        return metrics

    def _restored(self) -> None:
        self.collector.update_policy_weights_()
