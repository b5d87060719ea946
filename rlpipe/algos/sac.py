"""SAC assembled from TorchRL parts: a tanh-Gaussian ProbabilisticActor (collecting on plain
tensors), twin Q networks, a ReplayBuffer, SACLoss (automatic entropy tuning; its forward on plain
tensors) and a soft target update."""

from __future__ import annotations

import math
from collections.abc import Collection
from typing import Any

import torch
from tensordict import TensorDictBase
from tensordict.nn import NormalParamExtractor
from torch import nn
from torchrl.data import Bounded
from torchrl.envs import EnvBase
from torchrl.modules import MLP, ProbabilisticActor, TanhNormal

from rlpipe.algos.collectors import lean_collection
from rlpipe.algos.configs import SACConfig
from rlpipe.algos.direct import TANH_LIMIT, DirectSACLoss, inner_network
from rlpipe.algos.noise import ColoredNoise
from rlpipe.algos.offpolicy import ForeachSoftUpdate, OffPolicy
from rlpipe.encoders import EncodeFirst, encoder
from rlpipe.envs import is_discrete
from rlpipe.errors import RlpipeError
from rlpipe.models import TensorModule


def tanh_normal_sample(
    loc: torch.Tensor,
    scale: torch.Tensor,
    middle: torch.Tensor,
    half: torch.Tensor,
    draw: torch.Tensor | None = None,
) -> torch.Tensor:
    """The action :func:`~rlpipe.algos.direct.tanh_normal_rsample` draws (the same random draw
    and value) on bounds ``middle ± half``, without its log-probability and gradient: what
    collecting needs, at a fraction of the cost. ``draw``: the standard-normal draw to use
    (e.g. coloured noise's), instead of a fresh one."""
    if draw is None:
        draw = torch.empty_like(loc).normal_()  # Normal.rsample's draw
    preimage = loc + draw * scale
    return middle + half * preimage.tanh().clamp(-TANH_LIMIT, TANH_LIMIT)


class SAC(OffPolicy):
    """Soft actor-critic on a batched TorchRL env with continuous (bounded box) actions.

    The off-policy loop (:class:`~rlpipe.algos.offpolicy.OffPolicy`) with the sampling policy
    collecting and Adam steps on TorchRL's SACLoss (actor, twin Q critics and the entropy
    coefficient, tuned towards ``cfg.target_entropy``), each followed by a soft update of the
    target critics. The greedy policy is the tanh of the Gaussian's mean. With
    ``cfg.noise_color`` β > 0, the collecting policy's standard-normal draws are coloured noise
    (:class:`~rlpipe.algos.noise.ColoredNoise`, per env copy and action dimension), correlated in
    time: exploration that keeps a direction for a while, which sparse-reward envs such as
    MountainCarContinuous need; the losses keep their own independent draws.
    ``network`` (or ``cfg.network``): the actor's network, observations to a mean and a
    pre-softplus std per action dimension.
    """

    cfg: SACConfig

    def _build(self, env: EnvBase) -> None:
        cfg, spec = self.cfg, env.action_spec_unbatched
        if is_discrete(env) or not isinstance(spec, Bounded) or len(spec.shape) != 1:
            raise RlpipeError(
                f"SAC needs continuous actions (a bounded flat box), but this env's actions are "
                f"{type(spec).__name__} of shape {tuple(spec.shape)}; pick a continuous env "
                "(pendulum, bipedal, cartpole_continuous, mountaincar_continuous) or algo=dqn "
                "or algo=ppo"
            )
        size, n_obs = spec.shape[0], self.observation.in_features
        outputs = f"a mean and a pre-softplus std per action dimension ({size}), in that order"
        net = nn.Sequential(
            self.network(n_obs, 2 * size, outputs),
            NormalParamExtractor(scale_mapping="biased_softplus_1"),
        )
        # TensorModule: a TensorDictModule without its per-call lookups (see its docstring)
        self.policy = ProbabilisticActor(
            TensorModule(net, ["observation"], ["loc", "scale"]),
            in_keys=["loc", "scale"],
            spec=spec,
            distribution_class=TanhNormal,
            distribution_kwargs={"low": spec.space.low, "high": spec.space.high},
        ).to(self.device)
        first, features = encoder(self.observation)  # an image's CNN, ...; a vector: none
        critic = MLP(  # TorchRL's MLP concatenates its inputs: Q(s, a)
            in_features=features + size,
            out_features=1,
            num_cells=cfg.hidden_sizes,
            activation_class=nn.ReLU,
        )
        critic = critic if first is None else EncodeFirst(first, critic)
        qvalue = TensorModule(critic, ["observation", "action"], ["state_action_value"])
        qvalue = qvalue.to(self.device)
        self.loss = self.on_device(
            DirectSACLoss(  # SACLoss, its forward on plain tensors
                self.policy,
                qvalue,
                num_qvalue_nets=2,
                alpha_init=cfg.alpha_init,
                fixed_alpha=cfg.fixed_alpha,
                target_entropy=-float(size) if cfg.target_entropy is None else cfg.target_entropy,
                loss_function="l2",
                deactivate_vmap=True,  # the two critics in a loop: cheaper than torch.vmap on CPU
            )
        )
        self.target_updater = ForeachSoftUpdate(self.loss, tau=cfg.tau)
        self.optimizer = torch.optim.Adam(self.loss.parameters(), lr=cfg.lr, fused=True)
        self._actor = inner_network(self.policy).module
        low, high = (torch.as_tensor(b, device=self.device) for b in self.loss.bounds)
        self._bounds = (high + low) / 2, (high - low) / 2
        self._noise = None
        if cfg.noise_color:
            lean_collection(env, "algo.noise_color", "0")
            copies = (env.batch_size.numel(), size)
            self._noise = ColoredNoise(cfg.noise_color, copies, cfg.noise_steps, self.device)
        self.start_loop(env, self.policy, act=self._explore)

    def _explore(self, observation: torch.Tensor) -> dict[str, torch.Tensor]:
        """The collecting policy on plain tensors: a TanhNormal draw on the actor's network's
        ``(loc, scale)``, the one the ``ProbabilisticActor`` draws (or, with coloured noise,
        the next step of the noise)."""
        draw = None if self._noise is None else self._noise()
        return {"action": tanh_normal_sample(*self._actor(observation), *self._bounds, draw)}

    def start_from(self, state: dict[str, Any], parts: Collection[str], parent: Any) -> None:
        super().start_from(state, parts, parent)  # α is learned: it comes with the weights,
        if self.cfg.alpha_init != parent.alpha_init:  # unless this run asks for another start
            self.loss.log_alpha.data.fill_(math.log(self.cfg.alpha_init))

    def loss_of(self, sample: TensorDictBase) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        out = self.loss(sample)
        loss = out["loss_actor"] + out["loss_qvalue"] + out["loss_alpha"]
        q1, q2 = out["loss_qvalues"].unbind(0)
        return loss, {
            "train/alpha": out["alpha"],
            "train/actor_loss": out["loss_actor"].detach(),
            "train/q1_loss": q1,
            "train/q2_loss": q2,
            "train/alpha_loss": out["loss_alpha"].detach(),
            "train/entropy": out["entropy"],
        }
