"""DQN assembled from TorchRL parts: QValueActor, EGreedyModule, Collector, ReplayBuffer,
DQNLoss (Huber) and SoftUpdate (HardUpdate for tau=1)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictSequential
from torchrl.data import LazyTensorStorage, ReplayBuffer
from torchrl.data.postprocs import MultiStep
from torchrl.envs import EnvBase
from torchrl.modules import EGreedyModule, QValueActor
from torchrl.objectives import DQNLoss, HardUpdate, SoftUpdate

from rlpipe.algos.base import (
    LOSS,
    TRANSITION_KEYS,
    EnvAlgorithm,
    Metrics,
    batch_steps,
    episode_metrics,
)
from rlpipe.cadence import Cadence
from rlpipe.config import AlgoConfig, checked
from rlpipe.envs import is_discrete, observation_size
from rlpipe.errors import RlpipeError, check
from rlpipe.models import TensorModule

LOSSES = ("smooth_l1", "l2", "l1")
EPS_SCHEDULES = ("exp", "linear")


@dataclass
class DQNConfig(AlgoConfig):
    """DQN hyper-parameters; the defaults are the workshop notebook's."""

    name: str = "dqn"
    total_frames: int | None = 60_000  # DQN has no budget of its own: the run's length
    hidden_sizes: list[int] = checked([128, 128], "sizes")
    lr: float = checked(1e-4, "positive")
    # null: a constant lr; a number: lr annealed linearly to it over algo.total_frames
    lr_end: float | None = None
    weight_decay: float = checked(1e-2, "non_negative")  # AdamW's default
    amsgrad: bool = True
    batch_size: int = checked(128, "at_least_one")
    buffer_size: int = 10_000
    gamma: float = checked(0.99, "discount")
    # n-step returns (TorchRL's MultiStep on each collected batch): each stored transition
    # sums up to n discounted rewards and bootstraps from the state n steps on; a window stops
    # at an episode's end and at the batch's end (frames_per_batch / num_envs steps)
    n_steps: int = checked(1, "at_least_one")
    # soft target update: target <- tau * online + (1 - tau) * target
    tau: float = checked(0.005, "discount")
    # frames between target updates (0: after every gradient step); with tau=1, a hard copy
    # every N frames (SB3's target_update_interval)
    target_update_every: int = checked(0, "non_negative")
    grad_clip_value: float = checked(100.0, "positive")  # each gradient element (the notebook's)
    max_grad_norm: float | None = None  # also clip the gradient's norm (SB3: 10); null: off
    loss: str = checked("smooth_l1", choices=LOSSES)  # Huber
    double_dqn: bool = False
    eps_start: float = 0.9
    eps_end: float = 0.05
    # exp: eps_end + (eps_start - eps_end) * exp(-t / eps_decay); linear: annealed over eps_decay
    eps_schedule: str = checked("exp", choices=EPS_SCHEDULES)
    eps_decay: int = checked(1000, "at_least_one")  # frames
    # env frames collected per iteration (across all envs), then as many gradient steps: one
    # per frame, as the notebook
    frames_per_batch: int = checked(4, "at_least_one")
    updates_per_batch: int = checked(4, "non_negative")
    learning_starts: int = checked(128, "non_negative")  # frames collected before the first update

    def __post_init__(self) -> None:
        super().__post_init__()
        check(
            self.buffer_size >= self.batch_size,
            f"algo.buffer_size ({self.buffer_size}) must be >= algo.batch_size ({self.batch_size})",
        )
        check(
            self.lr_end is None or 0 <= self.lr_end <= self.lr,
            f"algo.lr_end must be null or in [0, algo.lr], got {self.lr_end}",
        )
        check(
            self.max_grad_norm is None or self.max_grad_norm > 0,
            f"algo.max_grad_norm must be null or > 0, got {self.max_grad_norm}",
        )
        check(
            0 <= self.eps_end <= self.eps_start <= 1,
            f"need 0 <= algo.eps_end <= algo.eps_start <= 1, got {self.eps_end}, {self.eps_start}",
        )


def epsilon(frames: int, cfg: DQNConfig) -> float:
    """Exploration rate after ``frames`` env frames (exponential or linear decay)."""
    if cfg.eps_schedule == "exp":
        return cfg.eps_end + (cfg.eps_start - cfg.eps_end) * math.exp(-frames / cfg.eps_decay)
    fraction = min(frames / cfg.eps_decay, 1.0)
    return cfg.eps_start + fraction * (cfg.eps_end - cfg.eps_start)


def learning_rate(frames: int, cfg: DQNConfig) -> float:
    """The learning rate after ``frames`` env frames (linear to ``lr_end`` over
    ``total_frames``, or constant)."""
    if cfg.lr_end is None or not cfg.total_frames:
        return cfg.lr
    fraction = min(frames / cfg.total_frames, 1.0)
    return cfg.lr + fraction * (cfg.lr_end - cfg.lr)


def n_step_transitions(batch: TensorDictBase, multistep: MultiStep) -> TensorDictBase:
    """``batch`` (``[env copies, steps]``) with n-step rewards, next observations and
    ``steps_to_next_obs`` (TorchRL's :class:`MultiStep`), and with the end-of-episode flags of
    each window's last step, so that a window reaching a terminal state does not bootstrap."""
    out = multistep(batch)
    steps = torch.arange(batch.shape[-1], device=batch.device)
    last = (steps + out["steps_to_next_obs"] - 1).unsqueeze(-1)  # each window's last step
    for key in ("done", "terminated", "truncated"):
        if ("next", key) in batch.keys(True):
            out["next", key] = batch["next", key].gather(1, last)
    return out


class DQN(EnvAlgorithm):
    """Deep Q-learning on a batched TorchRL env with a discrete action space.

    Each :meth:`train_step` collects ``cfg.frames_per_batch`` frames with the ε-greedy policy,
    stores them in the replay buffer and runs ``cfg.updates_per_batch`` gradient steps, each
    followed by a soft target update (or, with ``cfg.target_update_every``, one update each time
    the frames pass a multiple of it). ε and, with ``cfg.lr_end``, the learning rate follow the
    frames. ``network`` (or ``cfg.network``) is your Q-network in place of the MLP: observations
    to one value per action (e.g. the dueling network of ``examples/dueling_dqn.py``).
    """

    cfg: DQNConfig
    state_attrs = ("loss", "optimizer", "buffer")

    def _build(self, env: EnvBase) -> None:
        cfg = self.cfg
        if not is_discrete(env):
            raise RlpipeError(
                f"DQN needs a discrete action space, but this env's actions are "
                f"{type(env.action_spec_unbatched).__name__} (continuous); pick a discrete env "
                "(cartpole, mountaincar, lunarlander) or another algorithm"
            )
        spec = env.action_spec_unbatched.to(self.device)
        n = spec.space.n
        net = self.network(observation_size(env), n, f"one Q-value per action ({n})")
        net = net.to(self.device)
        # TensorModule: a TensorDictModule without its per-call lookup (see its docstring)
        self.policy = QValueActor(TensorModule(net, ["observation"], ["action_value"]), spec=spec)
        self.exploration = EGreedyModule(
            spec, eps_init=cfg.eps_start, eps_end=cfg.eps_end, device=self.device
        )
        self.exploration.eps.fill_(epsilon(0, cfg))
        self.loss = DQNLoss(
            self.policy,
            loss_function=cfg.loss,
            delay_value=True,
            double_dqn=cfg.double_dqn,
            action_space=spec,
        )
        self.loss.make_value_estimator(gamma=cfg.gamma)
        self.target_updater = (  # tau 1: copy (TorchRL's SoftUpdate wants tau <= 0.5)
            HardUpdate(self.loss, value_network_update_interval=0)  # 0: copy at every step()
            if cfg.tau == 1.0
            else SoftUpdate(self.loss, tau=cfg.tau)
        )
        self._target_cadence = Cadence(cfg.target_update_every, 0)
        self.optimizer = torch.optim.AdamW(
            self.loss.parameters(),
            lr=cfg.lr,
            weight_decay=cfg.weight_decay,
            amsgrad=cfg.amsgrad,
            fused=True,  # one kernel for all parameters: a third of the step time on CPU
        )
        self.buffer = ReplayBuffer(
            storage=LazyTensorStorage(cfg.buffer_size, device=self.device),
            batch_size=cfg.batch_size,
        )
        copies, steps = batch_steps(env, cfg.frames_per_batch)
        check(  # a window stops at the batch's end: more steps than a batch holds never happen
            cfg.n_steps <= steps,
            f"algo.n_steps ({cfg.n_steps}) is more than the {steps} steps each env copy takes "
            f"per batch (algo.frames_per_batch / env.num_envs); raise algo.frames_per_batch to "
            f"at least {cfg.n_steps * copies}",
        )
        self.multistep = MultiStep(cfg.gamma, cfg.n_steps) if cfg.n_steps > 1 else None
        self.make_collector(
            env, TensorDictSequential(self.policy, self.exploration), cfg.frames_per_batch
        )

    def train_step(self) -> Metrics:
        batch = self.collect()
        self.frames += batch.numel()
        self.iterations += 1
        self._follow_schedules()
        if self.multistep is None:
            self.buffer.extend(batch.reshape(-1).select(*TRANSITION_KEYS))
        else:
            stored = n_step_transitions(batch, self.multistep)
            self.buffer.extend(stored.reshape(-1).select(*TRANSITION_KEYS, "steps_to_next_obs"))
        metrics: Metrics = {"train/epsilon": float(self.exploration.eps)}
        metrics.update(episode_metrics(batch))
        if len(self.buffer) < max(self.cfg.learning_starts, self.cfg.batch_size):
            return metrics
        losses = []
        for _ in range(self.cfg.updates_per_batch):
            loss = self.loss(self.buffer.sample())["loss"]
            self.optimizer.zero_grad(set_to_none=True)
            loss.backward()
            torch.nn.utils.clip_grad_value_(self.loss.parameters(), self.cfg.grad_clip_value)
            if self.cfg.max_grad_norm is not None:
                torch.nn.utils.clip_grad_norm_(self.loss.parameters(), self.cfg.max_grad_norm)
            self.optimizer.step()
            if not self.cfg.target_update_every:
                self.target_updater.step()
            losses.append(loss.detach())
        if losses:
            if self._target_cadence.due(self.frames):
                self.target_updater.step()
            metrics[LOSS] = float(torch.stack(losses).mean())
        self.sync_collector()
        return metrics

    def _follow_schedules(self) -> None:
        self.exploration.eps.fill_(epsilon(self.frames, self.cfg))
        for group in self.optimizer.param_groups:
            group["lr"] = learning_rate(self.frames, self.cfg)

    def _restored(self) -> None:
        self._follow_schedules()
        self._target_cadence = Cadence(self.cfg.target_update_every, self.frames)
        self.collector.update_policy_weights_()
