"""DQN assembled from TorchRL parts: QValueActor, EGreedyModule, Collector, ReplayBuffer,
DQNLoss (Huber) and SoftUpdate."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import torch
from tensordict.nn import TensorDictSequential
from torchrl.data import LazyTensorStorage, ReplayBuffer
from torchrl.envs import EnvBase
from torchrl.modules import EGreedyModule, QValueActor
from torchrl.objectives import DQNLoss, SoftUpdate

from rlpipe.algos.base import LOSS, Metrics, closing_on_error, episode_metrics, make_collector
from rlpipe.config import AlgoConfig
from rlpipe.envs import EnvFactory, is_discrete, observation_size
from rlpipe.errors import RlpipeError, check, check_choice, check_fields
from rlpipe.models import mlp

LOSSES = ("smooth_l1", "l2", "l1")
EPS_SCHEDULES = ("exp", "linear")


@dataclass
class DQNConfig(AlgoConfig):
    """DQN hyper-parameters; the defaults are the workshop notebook's."""

    name: str = "dqn"
    total_frames: int | None = 60_000  # DQN has no budget of its own: the run's length
    hidden_sizes: list[int] = field(default_factory=lambda: [128, 128])
    lr: float = 1e-4
    weight_decay: float = 1e-2  # AdamW's default
    amsgrad: bool = True
    batch_size: int = 128
    buffer_size: int = 10_000
    gamma: float = 0.99
    tau: float = 0.005  # soft target update: target <- tau * online + (1 - tau) * target
    grad_clip_value: float = 100.0
    loss: str = "smooth_l1"  # Huber
    double_dqn: bool = False
    eps_start: float = 0.9
    eps_end: float = 0.05
    eps_schedule: str = "exp"  # exp: eps_end + (eps_start - eps_end) * exp(-t / eps_decay)
    eps_decay: int = 1000  # frames: time constant (exp) or annealing length (linear)
    frames_per_batch: int = 4  # env frames collected per iteration (across all envs) ...
    updates_per_batch: int = 4  # ... then as many gradient steps: one per frame, as the notebook
    learning_starts: int = 128  # frames collected before the first update

    def __post_init__(self) -> None:
        super().__post_init__()
        check_fields(
            self,
            "algo.",
            positive=("lr", "grad_clip_value"),
            non_negative=("weight_decay", "updates_per_batch", "learning_starts"),
            at_least_one=("batch_size", "eps_decay", "frames_per_batch"),
            discount=("gamma", "tau"),
            sizes=("hidden_sizes",),
        )
        check(
            self.buffer_size >= self.batch_size,
            f"algo.buffer_size ({self.buffer_size}) must be >= algo.batch_size ({self.batch_size})",
        )
        check_choice(self.eps_schedule, "algo.eps_schedule", EPS_SCHEDULES)
        check(
            0 <= self.eps_end <= self.eps_start <= 1,
            f"need 0 <= algo.eps_end <= algo.eps_start <= 1, got {self.eps_end}, {self.eps_start}",
        )
        check_choice(self.loss, "algo.loss", LOSSES)


_STORED_KEYS = (
    "observation",
    "action",
    ("next", "observation"),
    ("next", "reward"),
    ("next", "done"),
    ("next", "terminated"),
)


def epsilon(frames: int, cfg: DQNConfig) -> float:
    """Exploration rate after ``frames`` env frames (exponential or linear decay)."""
    if cfg.eps_schedule == "exp":
        return cfg.eps_end + (cfg.eps_start - cfg.eps_end) * math.exp(-frames / cfg.eps_decay)
    fraction = min(frames / cfg.eps_decay, 1.0)
    return cfg.eps_start + fraction * (cfg.eps_end - cfg.eps_start)


class DQN:
    """Deep Q-learning on a batched TorchRL env with a discrete action space.

    Each :meth:`train_step` collects ``cfg.frames_per_batch`` frames with the ε-greedy policy,
    stores them in the replay buffer and runs ``cfg.updates_per_batch`` gradient steps, each
    followed by a soft target update.
    """

    finite_keys = (LOSS,)

    def __init__(
        self, env_factory: EnvFactory, cfg: DQNConfig, *, device: str | torch.device = "cpu"
    ):
        with closing_on_error(env_factory()) as env:
            self._build(env, cfg, torch.device(device))

    def _build(self, env: EnvBase, cfg: DQNConfig, device: torch.device) -> None:
        if not is_discrete(env):
            raise RlpipeError(
                f"DQN needs a discrete action space, but this env's actions are "
                f"{type(env.action_spec_unbatched).__name__} (continuous); pick a discrete env "
                "(cartpole, mountaincar, lunarlander) or another algorithm"
            )
        self.cfg = cfg
        self.device = device
        self.frames = self.iterations = 0
        self.budget = None  # frames only: the run's total_frames
        spec = env.action_spec_unbatched.to(self.device)
        net = mlp(observation_size(env), spec.space.n, cfg.hidden_sizes).to(self.device)
        self.policy = QValueActor(net, in_keys=["observation"], spec=spec)
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
        self.target_updater = SoftUpdate(self.loss, tau=cfg.tau)
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
        self.collector = make_collector(
            env, TensorDictSequential(self.policy, self.exploration), cfg.frames_per_batch, device
        )
        self._batches = iter(self.collector)
        # On one device the collector steps this very policy; otherwise it holds a copy.
        self._copy_weights = self.device != torch.device(env.device)

    def train_step(self) -> Metrics:
        batch = next(self._batches)
        self.frames += batch.numel()
        self.iterations += 1
        self.exploration.eps.fill_(epsilon(self.frames, self.cfg))
        self.buffer.extend(batch.reshape(-1).select(*_STORED_KEYS))
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
            self.optimizer.step()
            self.target_updater.step()
            losses.append(loss.detach())
        if losses:
            metrics[LOSS] = float(torch.stack(losses).mean())
        if self._copy_weights:
            self.collector.update_policy_weights_()
        return metrics

    def state_dict(self) -> dict[str, Any]:
        return {
            "loss": self.loss.state_dict(),
            "optimizer": self.optimizer.state_dict(),
            "buffer": self.buffer.state_dict(),
            "frames": self.frames,
            "iterations": self.iterations,
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.loss.load_state_dict(state["loss"])
        self.optimizer.load_state_dict(state["optimizer"])
        self.buffer.load_state_dict(state["buffer"])
        self.frames = int(state["frames"])
        self.iterations = int(state["iterations"])
        self.exploration.eps.fill_(epsilon(self.frames, self.cfg))
        self.collector.update_policy_weights_()

    def close(self) -> None:
        """Stop the collector and close its env."""
        self.collector.shutdown()
