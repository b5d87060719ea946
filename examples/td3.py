"""TD3 (Fujimoto et al., 2018) as a plug-in: an algorithm from outside rlpipe, on its loop.

TorchRL's ``TD3Loss`` (twin critics, clipped double Q, target policy smoothing) on rlpipe's
off-policy loop (collect, store, warm up, gradient steps, soft target updates); this file adds
TD3's own maths: the delayed actor and target updates, the smoothing noise in action ranges,
the exploration noise and SB3's uniformly random warm-up. Importing it registers ``td3`` with
its config folder ``conf/`` beside it (``tuned/td3_pendulum.yaml``: the RL Zoo's settings), so
it then works wherever a built-in algorithm does. From the command line (this folder on
``PYTHONPATH``, the module named in ``RLPIPE_PLUGINS``)::

    PYTHONPATH=examples RLPIPE_PLUGINS=td3 python -m rlpipe algo=td3 env=pendulum
    PYTHONPATH=examples RLPIPE_PLUGINS=td3 python -m rlpipe.evaluate run_dir=<run dir>

From Python (this file: the same run, with any overrides)::

    python examples/td3.py [seed=1 ...]
"""

from __future__ import annotations

import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictSequential
from torch import nn
from torchrl.data import Bounded
from torchrl.envs import EnvBase
from torchrl.modules import TanhModule
from torchrl.objectives import TD3Loss

import rlpipe
from rlpipe import RunResult, compose_run, train
from rlpipe.algos.configs import OffPolicyConfig
from rlpipe.algos.offpolicy import ForeachSoftUpdate, OffPolicy
from rlpipe.config import checked
from rlpipe.envs import is_discrete, observation_size
from rlpipe.models import TensorModule, mlp


@dataclass
class TD3Config(OffPolicyConfig):
    """TD3's hyper-parameters; the defaults are SB3's, the exploration noise the RL Zoo's.

    Noise is in half action ranges (SB3 scales actions to [-1, 1]): 0.1 on Pendulum's torque
    range [-2, 2] is a std of 0.2."""

    name: str = "td3"
    total_frames: int | None = 50_000  # TD3 has no budget of its own: the run's length
    eval_every: int = 5_000
    hidden_sizes: list[int] = checked([400, 300], "sizes")  # the actor's and each critic's
    lr: float = checked(1e-3, "positive")
    policy_delay: int = checked(2, "at_least_one")  # gradient steps per actor and target update
    target_noise: float = checked(0.2, "non_negative")  # std of the target policy's smoothing
    target_noise_clip: float = checked(0.5, "non_negative")  # ... clipped to ± this
    exploration_noise: float = checked(0.1, "non_negative")  # std added to collected actions


class Exploration(nn.Module):
    """The collected actions: uniformly random while ``warming_up()`` (SB3's warm-up, the first
    ``learning_starts`` frames), then the actor's plus Gaussian noise of ``std`` half ranges,
    clipped to the bounds."""

    def __init__(
        self, low: torch.Tensor, high: torch.Tensor, std: float, warming_up: Callable[[], bool]
    ) -> None:
        super().__init__()
        self.register_buffer("low", low)
        self.register_buffer("high", high)
        self.std, self.warming_up = std, warming_up

    def forward(self, action: torch.Tensor) -> torch.Tensor:
        if self.warming_up():
            return self.low + (self.high - self.low) * torch.rand_like(action)
        noise = self.std * (self.high - self.low) / 2 * torch.randn_like(action)
        return (action + noise).clamp(self.low, self.high)


class TD3(OffPolicy):
    """Twin delayed DDPG on a batched TorchRL env with continuous (bounded box) actions.

    The greedy policy is the actor: its network (``network=`` or ``cfg.network``, observations
    to one value per action dimension) squashed by a tanh into the action bounds. Every
    gradient step fits the twin critics to the smoothed target; every ``cfg.policy_delay``-th
    also steps the actor up the first critic and soft-updates the targets.
    """

    cfg: TD3Config

    def _build(self, env: EnvBase) -> None:
        cfg, spec = self.cfg, env.action_spec_unbatched
        if is_discrete(env) or not isinstance(spec, Bounded) or len(spec.shape) != 1:
            raise rlpipe.RlpipeError(
                f"TD3 acts in a bounded flat box of continuous actions, and this env's are "
                f"{type(spec).__name__} of shape {tuple(spec.shape)}; pick a continuous env "
                "(pendulum, bipedal, cartpole_continuous)"
            )
        size, n_obs = spec.shape[0], observation_size(env)
        net = self.network(n_obs, size, f"one value per action dimension ({size}), pre-tanh")
        self.policy = TensorDictSequential(
            TensorModule(net, ["observation"], ["action"]), TanhModule(["action"], spec=spec)
        ).to(self.device)
        critic = mlp(n_obs + size, 1, cfg.hidden_sizes)  # Q(s, a): TorchRL's MLP concatenates
        low, high = (bound.to(self.device) for bound in (spec.space.low, spec.space.high))
        half = (high - low) / 2
        self.loss = self.on_device(
            TD3Loss(
                self.policy,
                TensorModule(critic, ["observation", "action"], ["state_action_value"]),
                action_spec=spec,
                policy_noise=cfg.target_noise * half,  # TorchRL's noise is in action units
                noise_clip=cfg.target_noise_clip * half,
                loss_function="l2",
                deactivate_vmap=True,  # the two critics in a loop: cheaper than torch.vmap on CPU
            )
        )
        self.target_updater = ForeachSoftUpdate(self.loss, tau=cfg.tau)
        self.optimizer = torch.optim.Adam(self.loss.parameters(), lr=cfg.lr, fused=True)
        explore = Exploration(
            low, high, cfg.exploration_noise, lambda: self.frames < cfg.learning_starts
        )
        self.start_loop(
            env, TensorDictSequential(self.policy, TensorModule(explore, ["action"], ["action"]))
        )

    def actor_step(self) -> bool:
        """Whether this gradient step also updates the actor and the targets."""
        return self.updates % self.cfg.policy_delay == 0

    def loss_of(self, sample: TensorDictBase) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        critic_loss, _ = self.loss.value_loss(sample)
        scalars = {"train/critic_loss": critic_loss.detach()}
        if not self.actor_step():
            return critic_loss, scalars
        # the actor's loss reads detached critics: its gradient reaches only the actor
        actor_loss, _ = self.loss.actor_loss(sample)
        scalars["train/actor_loss"] = actor_loss.detach()
        return critic_loss + actor_loss, scalars

    def update_targets(self) -> None:
        if self.actor_step():
            super().update_targets()


rlpipe.register("td3", TD3Config, TD3, conf=Path(__file__).parent / "conf")


def main(*overrides: str, run_dir: str = "runs/td3") -> RunResult:
    """Train TD3 on Pendulum-v1 with the RL Zoo's settings (``conf/tuned/td3_pendulum.yaml``)
    and ``overrides`` (the command line's ``key=value``)."""
    return train(compose_run("algo=td3", "env=pendulum", *overrides), run_dir)


if __name__ == "__main__":
    print(main(*sys.argv[1:]).summary_line())
