"""DQN assembled from TorchRL parts: QValueActor, EGreedyModule (collecting on plain tensors),
ReplayBuffer, DQNLoss (Huber; DirectDQNLoss) and SoftUpdate (HardUpdate for tau=1)."""

from __future__ import annotations

import math

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictSequential
from torchrl.data.postprocs import MultiStep
from torchrl.envs import EnvBase
from torchrl.modules import EGreedyModule, QValueActor
from torchrl.objectives import HardUpdate

from rlpipe.algos.base import TRANSITION_KEYS, Metrics, annealed, batch_steps
from rlpipe.algos.collectors import lean_collection
from rlpipe.algos.configs import DQNConfig
from rlpipe.algos.direct import DirectDQNLoss, inner_network
from rlpipe.algos.offpolicy import ForeachSoftUpdate, OffPolicy
from rlpipe.envs import is_discrete
from rlpipe.errors import RlpipeError, check
from rlpipe.models import TensorModule


def epsilon(frames: int, cfg: DQNConfig) -> float:
    """Exploration rate after ``frames`` env frames (exponential or linear decay)."""
    if cfg.eps_schedule == "exp":
        return cfg.eps_end + (cfg.eps_start - cfg.eps_end) * math.exp(-frames / cfg.eps_decay)
    fraction = min(frames / cfg.eps_decay, 1.0)
    return cfg.eps_start + fraction * (cfg.eps_end - cfg.eps_start)


def learning_rate(frames: int, cfg: DQNConfig) -> float:
    """The learning rate after ``frames`` env frames (linear to ``lr_end`` over
    ``total_frames``, or constant)."""
    return annealed(cfg.lr, cfg.lr_end, frames, cfg.total_frames)


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


class HeldActions:
    """εz-greedy (Dabney et al. 2021, "Temporally-extended ε-greedy exploration"): a random
    action, once drawn, is repeated for n steps, n from a zeta distribution (P(n) ∝ n^-μ,
    n ≤ 10,000), one hold per env copy; between holds, ε-greedy's choice."""

    def __init__(self, mu: float, copies: int, device: torch.device, longest: int = 10_000):
        weights = torch.arange(1, longest + 1, dtype=torch.float64).pow(-mu)
        self._cdf = (weights.cumsum(0) / weights.sum()).float().to(device)
        self._left = torch.zeros(copies, dtype=torch.long, device=device)  # steps still held
        self._action = torch.zeros(copies, dtype=torch.long, device=device)

    def __call__(
        self, explore: torch.Tensor, random: torch.Tensor, greedy: torch.Tensor
    ) -> torch.Tensor:
        """This step's actions: a held one where a hold goes on, a new hold where ``explore``
        draws one, else ``greedy``."""
        holding = self._left > 0
        start = explore & ~holding
        draws = torch.rand(start.shape, device=start.device)
        steps = torch.searchsorted(self._cdf, draws, right=True) + 1  # n >= 1
        steps = steps.clamp_max(len(self._cdf))  # float rounding at the top
        self._action = torch.where(start, random, self._action)
        self._left = torch.where(start, steps, self._left) - (holding | start).long()
        return torch.where(holding | start, self._action, greedy)


class DQN(OffPolicy):
    """Deep Q-learning on a batched TorchRL env with a discrete action space.

    The off-policy loop (:class:`~rlpipe.algos.offpolicy.OffPolicy`) with the ε-greedy policy
    collecting, (n-step) transitions stored, TorchRL's ``DQNLoss`` (Huber by default, double DQN
    optionally) with gradients clipped by value (and norm), and a soft target update (a hard
    copy with ``tau=1``). ε and, with ``cfg.lr_end``, the learning rate follow the frames.
    ``network`` (or ``cfg.network``) is your Q-network in place of the MLP: observations to one
    value per action (e.g. the dueling network of ``examples/dueling_dqn.py``).
    """

    cfg: DQNConfig

    def _build(self, env: EnvBase) -> None:
        cfg = self.cfg
        if not is_discrete(env):
            raise RlpipeError(
                f"DQN needs a discrete action space, but this env's actions are "
                f"{type(env.action_spec_unbatched).__name__} (continuous); pick a discrete env "
                "(cartpole, mountaincar, lunarlander, acrobot) or another algorithm"
            )
        spec = env.action_spec_unbatched.to(self.device)
        n = spec.space.n
        net = self.network(
            self.observation.in_features,
            n,
            f"one Q-value per action ({n})",
            layer_norm=cfg.layer_norm,
        )
        net = net.to(self.device)
        # TensorModule: a TensorDictModule without its per-call lookup (see its docstring)
        self.policy = QValueActor(TensorModule(net, ["observation"], ["action_value"]), spec=spec)
        self.exploration = EGreedyModule(
            spec, eps_init=cfg.eps_start, eps_end=cfg.eps_end, device=self.device
        )
        self.exploration.eps.fill_(epsilon(0, cfg))
        self.loss = self.on_device(
            DirectDQNLoss(  # DQNLoss, its forward on plain tensors
                self.policy,
                loss_function=cfg.loss,
                delay_value=True,
                double_dqn=cfg.double_dqn,
                action_space=spec,
                q_max=cfg.q_max,
            )
        )
        self.target_updater = (  # tau 1: copy (TorchRL's SoftUpdate wants tau <= 0.5)
            HardUpdate(self.loss, value_network_update_interval=0)  # 0: copy at every step()
            if cfg.tau == 1.0
            else ForeachSoftUpdate(self.loss, tau=cfg.tau)
        )
        self.optimizer = torch.optim.AdamW(
            self.loss.parameters(),
            lr=cfg.lr,
            weight_decay=cfg.weight_decay,
            amsgrad=cfg.amsgrad,
            fused=True,  # one kernel for all parameters: a third of the step time on CPU
        )
        copies, steps = batch_steps(env, cfg.frames_per_batch)
        check(  # a window stops at the batch's end: more steps than a batch holds never happen
            cfg.n_steps <= steps,
            f"algo.n_steps ({cfg.n_steps}) is more than the {steps} steps each env copy takes "
            f"per batch (algo.frames_per_batch / env.num_envs); raise algo.frames_per_batch to "
            f"at least {cfg.n_steps * copies}",
        )
        self.multistep = MultiStep(cfg.gamma, cfg.n_steps) if cfg.n_steps > 1 else None
        self._q_network = inner_network(self.policy).module
        self._held = None
        if cfg.eps_zeta is not None:
            lean_collection(env, "algo.eps_zeta", "null")
            self._held = HeldActions(cfg.eps_zeta, env.batch_size.numel(), self.device)
        self.start_loop(env, TensorDictSequential(self.policy, self.exploration), act=self._explore)

    def _explore(self, observation: torch.Tensor) -> dict[str, torch.Tensor]:
        """The collecting policy on plain tensors, ``EGreedyModule``'s ε-greedy with its random
        draws: with probability ε (``self.exploration.eps``) a uniformly random action, else the
        Q-network's argmax; with ``cfg.eps_zeta``, each random action then held for a duration
        of its own (:class:`HeldActions`)."""
        values = self._q_network(observation)
        greedy = values.argmax(-1)
        explore = torch.rand(greedy.shape, device=greedy.device) < self.exploration.eps
        random = torch.randint_like(greedy, values.shape[-1])  # drawn in EGreedyModule's order
        if self._held is not None:
            return {"action": self._held(explore, random, greedy)}
        return {"action": torch.where(explore, random, greedy)}

    def follow_schedules(self) -> None:
        self.exploration.eps.fill_(epsilon(self.frames, self.cfg))
        for group in self.optimizer.param_groups:
            group["lr"] = learning_rate(self.frames, self.cfg)

    def collect_metrics(self) -> Metrics:
        return {"train/epsilon": float(self.exploration.eps)}

    def transitions(self, batch: TensorDictBase) -> TensorDictBase:
        if self.multistep is None:
            return super().transitions(batch)
        stored = n_step_transitions(batch, self.multistep)
        return stored.select(*TRANSITION_KEYS, "steps_to_next_obs").reshape(-1)

    def loss_of(self, sample: TensorDictBase) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        out = self.loss(sample)
        return out["loss"], {"train/q_mean": out["q_mean"]}

    def clip_gradients(self) -> None:
        params = self.optimizer.param_groups[0]["params"]  # the loss's, listed once
        torch.nn.utils.clip_grad_value_(params, self.cfg.grad_clip_value)
        if self.cfg.max_grad_norm is not None:
            torch.nn.utils.clip_grad_norm_(params, self.cfg.max_grad_norm)
