"""TorchRL's loss modules with their forward on plain tensors: the same parameters, state dict,
target updaters and maths, without moving every minibatch through TensorDicts and swapping the
parameters into a network for each call.

TorchRL's functional losses put their parameters into a meta copy of each network
(``to_module``) for every network call, and route every intermediate through a TensorDict: on
the small networks of classic-control tasks that costs more than the maths. Each loss here
subclasses TorchRL's, keeps its parameters, keys and value estimator, and computes its forward on
copies of the networks bound once to those parameters (:class:`Bound`); tests compare each with
TorchRL's forward (losses, gradients, priorities).
"""

from __future__ import annotations

import copy
import math
from typing import Any

import torch
import torch.nn.functional as F
from tensordict import TensorDict, TensorDictBase
from torch import nn
from torchrl._utils import _standardize
from torchrl.modules import MLP, TanhNormal
from torchrl.objectives import ClipPPOLoss, DQNLoss, SACLoss
from torchrl.objectives.utils import distance_loss

from rlpipe.models import TensorModule

LOG_SQRT_2PI = math.log(math.sqrt(2 * math.pi))  # of the Normal's log-density
# TorchRL's safetanh_noeps keeps tanh inside the open interval (-1, 1) by this margin
TANH_LIMIT = 1.0 - torch.finfo(torch.float32).resolution
# TorchRL's distance losses (distance_loss), each reducing its rows in the same op
DISTANCES = {"l2": F.mse_loss, "l1": F.l1_loss, "smooth_l1": F.smooth_l1_loss}


def inner_network(module: nn.Module) -> TensorModule:
    """The one :class:`~rlpipe.models.TensorModule` inside ``module`` (a TorchRL actor or value
    operator): the plain network the direct forwards call."""
    inner = [m for m in module.modules() if isinstance(m, TensorModule)]
    if len(inner) != 1:
        raise ValueError(f"a direct loss needs one TensorModule inside {type(module).__name__}")
    return inner[0]


def bind(module: nn.Module, params: TensorDictBase) -> nn.Module:
    """A copy of ``module`` (a loss's meta copy: no data is copied) whose parameters are the
    tensors of ``params`` for good; returns its plain network."""
    twin = copy.deepcopy(module)
    params.to_module(twin)
    return inner_network(twin).module


class Bound:
    """The networks a direct forward calls (``loss._networks()``), made at the first call and
    again after :meth:`reset` (the loss's ``_apply``: ``to()``, ``cuda()``, ``double()`` may
    put other tensors in its parameters' place); kept outside what ``nn.Module`` registers, so
    the state dict stays TorchRL's."""

    def __init__(self) -> None:
        self.nets: tuple = ()

    def reset(self) -> None:
        """Bind again at the next call."""
        self.nets = ()

    @torch.compiler.disable  # under compile=true the forward's graph starts after the binding
    def __call__(self, loss: nn.Module) -> tuple:
        if not self.nets:
            with torch.enable_grad():  # views of stacked parameters carry their gradients
                self.nets = loss._networks()
        return self.nets

    def __deepcopy__(self, memo: dict) -> Bound:  # a copy of the loss binds its own parameters
        return Bound()


class Binding(nn.Module):
    """What a direct loss mixes in: a :class:`Bound` (``_bound``) bound anew whenever
    ``_apply`` (a move or cast) runs, as TorchRL's losses erase their caches there."""

    _bound: Bound

    def _apply(self, *args: Any, **kwargs: Any) -> nn.Module:
        if "_bound" in self.__dict__:
            self._bound.reset()
        return super()._apply(*args, **kwargs)


class DirectDQNLoss(Binding, DQNLoss):
    """``DQNLoss`` (a ``QValueActor`` over one :class:`~rlpipe.models.TensorModule`, a
    categorical action space, TorchRL's TD(0) value estimator) whose :meth:`forward` computes
    what ``DQNLoss.forward`` computes: the chosen action's value, double DQN's online argmax and
    target value or the target's max, ``r + γ^k (1 - terminated) V'``, the distance loss, the
    ``td_error`` priority; and ``q_mean``, the mean value of the chosen actions (for logging).
    ``q_max`` (not DQNLoss's): each target clamped to at most it, the returns' ceiling."""

    def __init__(self, value_network: nn.Module, q_max: float | None = None, **kwargs) -> None:
        super().__init__(value_network, **kwargs)
        self.q_max = q_max
        if self.action_space != "categorical":
            raise ValueError("DirectDQNLoss needs a categorical action space")
        self.in_key = inner_network(self.value_network).in_keys[0]
        self._bound = Bound()

    def _networks(self) -> tuple[nn.Module, nn.Module]:
        params = self.value_network_params, self.target_value_network_params
        return tuple(bind(self.value_network, p) for p in params)

    def forward(self, tensordict: TensorDictBase) -> TensorDict:
        online, target = self._bound(self)
        action = tensordict.get(self.tensor_keys.action)
        values = online(tensordict.get(self.in_key))
        if action.ndim != values.ndim:
            action = action.unsqueeze(-1)
        chosen = values.gather(-1, action).squeeze(-1)
        with torch.no_grad():
            next_obs = tensordict.get(("next", self.in_key))
            next_values = target(next_obs)
            if self.double_dqn:
                best = online(next_obs).argmax(-1, keepdim=True)
                next_value = next_values.gather(-1, best)
            else:
                next_value = next_values.max(-1, keepdim=True).values
            target_value = td0_target(self, tensordict, next_value).squeeze(-1)
            if self.q_max is not None:
                target_value = target_value.clamp(max=self.q_max)
            priority = (chosen - target_value).pow(2).unsqueeze(-1)
        tensordict.set(self.tensor_keys.priority, priority, inplace=True)
        weights = None
        if self.use_prioritized_weights in (True, "auto"):
            weights = tensordict.get(self.tensor_keys.priority_weight, None)
        loss = reduced_distance(self, chosen, target_value, tensordict, weights)
        return TensorDict(loss=loss, q_mean=chosen.detach().mean())


def td0_target(loss: nn.Module, tensordict: TensorDictBase, next_value: torch.Tensor):
    """TorchRL's TD(0) value estimate of ``loss``'s estimator: ``r + γ^k (1 - terminated) V'``
    (``k``: the n-step transitions' ``steps_to_next_obs``, else 1); a terminal state's ``V'``
    counts as 0 whatever it holds."""
    estimator = loss.value_estimator
    keys, nxt = estimator.tensor_keys, tensordict.get("next")
    reward = nxt.get(keys.reward)
    gamma = estimator.gamma.to(reward.device)
    steps = tensordict.get(keys.steps_to_next_obs, None)
    if steps is not None:
        gamma = gamma.pow(steps.view_as(reward))
    return reward + gamma * next_value.masked_fill(nxt.get(keys.terminated), 0.0)


def reduced_distance(
    loss: nn.Module,
    predicted: torch.Tensor,
    target: torch.Tensor,
    tensordict: TensorDictBase,
    weights: torch.Tensor | None,
) -> torch.Tensor:
    """``loss._reduce_loss(distance_loss(predicted, target, loss.loss_function), ...)``: one
    reducing op where no weights and no mask (``loss``'s mask keys) touch the rows."""
    fused = DISTANCES.get(loss.loss_function)
    masked = any(tensordict.get(key, None) is not None for key in loss._loss_mask_keys())
    if fused is None or weights is not None or masked or loss.reduction == "none":
        distance = distance_loss(predicted, target, loss.loss_function)
        return loss._reduce_loss(distance, tensordict, weights=weights)
    if predicted.shape != target.shape:  # distance_loss's check
        raise RuntimeError(f"shapes {predicted.shape} and {target.shape} differ")
    return fused(predicted, target, reduction=loss.reduction)


class DirectSACLoss(Binding, SACLoss):
    """``SACLoss`` (version 2: no state-value network; a ``ProbabilisticActor`` and the Q
    network each over one :class:`~rlpipe.models.TensorModule`) whose :meth:`forward` computes
    what ``SACLoss.forward`` computes, drawing its random actions in the same order: the target
    ``r + γ (1 - terminated) (min Q'(s', a') - α log π(a'|s'))``, the critics' summed distance
    losses and ``td_error``, the actor's ``α log π(a|s) - min Q(s, a)`` through critics held
    fixed, and the entropy coefficient's loss; and ``loss_qvalues``, each critic's distance loss
    (for logging). Critics that are TorchRL MLPs run all at once on their stacked parameters
    (:class:`Stacked`)."""

    def __init__(self, actor_network: nn.Module, qvalue_network: nn.Module, **kwargs) -> None:
        super().__init__(actor_network, qvalue_network, **kwargs)
        if self._version != 2:
            raise ValueError("DirectSACLoss computes SAC version 2 (no value network)")
        head = next(m for m in self.actor_network.modules() if hasattr(m, "distribution_class"))
        kwargs = head.distribution_kwargs
        if head.distribution_class is not TanhNormal or set(kwargs) - {"low", "high"}:
            raise ValueError(
                "DirectSACLoss needs a TanhNormal actor (low and high its only kwargs)"
            )
        self.bounds = kwargs.get("low", -1.0), kwargs.get("high", 1.0)
        self.obs_key = inner_network(self.actor_network).in_keys[0]
        self._bound = Bound()

    def _networks(self) -> tuple:
        """The actor; the critics (all at once) on their parameters, on detached ones, on the
        targets."""
        critics = tuple(
            self._critics(params)
            for params in (
                self.qvalue_network_params,
                self.qvalue_network_params.detach(),
                self.target_qvalue_network_params,
            )
        )
        return bind(self.actor_network, self.actor_network_params), *critics

    def _critics(self, params: TensorDictBase):
        """``[copies, batch, 1]`` from ``(obs, action)``: a TorchRL MLP's copies at once
        (:class:`Stacked`); any other critic (an encoder first) one copy after another."""
        q = inner_network(self.qvalue_network).module
        if type(q) is MLP:
            return Stacked(q, params["module"])
        copies = [bind(self.qvalue_network, params[i]) for i in range(self.num_qvalue_nets)]
        return lambda *inputs: torch.stack([copy(*inputs) for copy in copies])

    def _act(self, actor: nn.Module, obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """A reparametrised action of the policy at ``obs`` and its log-probability."""
        return tanh_normal_rsample(*actor(obs), *self.bounds)

    def forward(self, tensordict: TensorDictBase) -> TensorDict:
        actor, critics, fixed, targets = self._bound(self)
        obs, action = tensordict.get(self.obs_key), tensordict.get(self.tensor_keys.action)
        alpha = self._alpha
        with torch.no_grad():
            next_obs = tensordict.get(("next", self.obs_key))
            next_action, next_log_prob = self._act(actor, next_obs)
            next_q = targets(next_obs, next_action)
            next_value = (next_q - alpha * next_log_prob.unsqueeze(-1)).min(0)[0]
            target = td0_target(self, tensordict, next_value).squeeze(-1)
        predicted = critics(obs, action).squeeze(-1)
        loss_q = distance_loss(predicted, target.expand_as(predicted), self.loss_function)
        each = loss_q.detach().mean(-1)  # of each critic, for logging
        weights = self._maybe_get_priority_weight(tensordict)
        loss_q = self._reduce_loss(loss_q.sum(0), tensordict=tensordict, weights=weights)
        new_action, log_prob = self._act(actor, obs)
        new_q = fixed(obs, new_action).min(0)[0].squeeze(-1)
        loss_actor = self._reduce_loss(
            alpha * log_prob - new_q, tensordict=tensordict, weights=weights
        )
        log_prob = log_prob.detach()
        loss_alpha = self._reduce_loss(
            self._alpha_loss(log_prob), tensordict=tensordict, weights=weights
        )
        td_error = (predicted - target).abs().detach().max(0)[0]
        tensordict.set(self.tensor_keys.priority, td_error)
        return TensorDict(
            loss_actor=loss_actor,
            loss_qvalue=loss_q,
            loss_alpha=loss_alpha,
            alpha=alpha,
            entropy=-log_prob.mean(),
            loss_qvalues=each,
        )


def tanh_normal_rsample(
    loc: torch.Tensor, scale: torch.Tensor, low: torch.Tensor | float, high: torch.Tensor | float
) -> tuple[torch.Tensor, torch.Tensor]:
    """What TorchRL's ``TanhNormal(loc, scale, low=low, high=high).rsample_and_log_prob()``
    returns (the same random draw, the same maths), without building the distribution and its
    transforms: an action ``(high + low)/2 + (high - low)/2 · tanh(u)``, ``u ~ N(loc, scale)``
    reparametrised, and its log-probability summed over the action's dimensions."""
    low, high = torch.as_tensor(low, device=loc.device), torch.as_tensor(high, device=loc.device)
    preimage = loc + torch.empty_like(loc).normal_() * scale  # Normal.rsample's draw
    half = (high - low) / 2
    # TorchRL's safetanh_noeps (tanh kept inside (-1, 1), its gradient 1 - tanh²) in torch's
    # own ops: an autograd Function costs a Python call in each backward
    squashed = preimage.tanh()
    squashed = squashed + (squashed.clamp(-TANH_LIMIT, TANH_LIMIT) - squashed).detach()
    action = (high + low) / 2 + half * squashed
    log_normal = -((preimage - loc) ** 2) / (2 * scale**2) - scale.log() - LOG_SQRT_2PI
    log_det = 2.0 * (math.log(2.0) - preimage - F.softplus(-2.0 * preimage)) + half.abs().log()
    return action, (log_normal - log_det).sum(-1)


class DirectPPOLoss(ClipPPOLoss):
    """``ClipPPOLoss`` (``functional=False``: the modules' own parameters; advantages computed
    beforehand; no delayed actor, value clipping or importance-ratio cap; an actor over one
    :class:`~rlpipe.models.TensorModule` and one distribution) whose :meth:`forward` computes
    what ``ClipPPOLoss.forward`` computes: the clipped surrogate on standardised advantages,
    the weighted entropy bonus and the weighted critic distance loss. It always reports the
    diagnostics PPO logs: clip fraction, approximate KL, entropy and explained variance."""

    def __init__(self, actor_network: nn.Module, critic_network: nn.Module, **kwargs) -> None:
        super().__init__(actor_network, critic_network, functional=False, **kwargs)
        if self.delay_actor or self.clip_value or self.max_importance_ratio is not None:
            raise ValueError("DirectPPOLoss computes the plain clipped objective")
        if self.advantage_norm is not None:
            raise ValueError("DirectPPOLoss standardises advantages per minibatch only")
        head = next(m for m in actor_network.modules() if hasattr(m, "distribution_class"))
        self.distribution = head.distribution_class, head.dist_keys, head.distribution_kwargs
        # not registered as a submodule: the state dict stays ClipPPOLoss's
        object.__setattr__(self, "actor_net", inner_network(actor_network))

    def forward(self, tensordict: TensorDictBase) -> TensorDict:
        keys, (distribution, dist_keys, kwargs) = self.tensor_keys, self.distribution
        advantage = tensordict.get(keys.advantage)
        if self.normalize_advantage and advantage.numel() > 1:
            advantage = _standardize(advantage, self.normalize_advantage_exclude_dims)
        obs = tensordict.get(self.actor_net.in_keys[0])
        params = self.actor_net.module(obs)
        params = params if isinstance(params, tuple) else (params,)
        old_log_prob = tensordict.get(keys.sample_log_prob)
        action = tensordict.get(keys.action)
        if distribution is torch.distributions.Categorical and not kwargs:
            log_prob, entropy = categorical_log_prob_entropy(*params, action)
        else:
            dist = distribution(**dict(zip(dist_keys, params, strict=True)), **kwargs)
            log_prob, entropy = dist.log_prob(action), dist.entropy()
        log_weight = (log_prob - old_log_prob).unsqueeze(-1)
        clipped = log_weight.clamp(*self._clip_bounds)
        gain = torch.minimum(log_weight.exp() * advantage, clipped.exp() * advantage)
        entropy = entropy.unsqueeze(-1)
        value = self.critic_network.module(obs)
        target = tensordict.get(keys.value_target)
        loss_value = distance_loss(target, value, loss_function=self.loss_critic_type)
        out = {
            "loss_objective": self._reduce_loss(-gain, tensordict),
            "loss_critic": self._reduce_loss(self.critic_coeff * loss_value, tensordict),
        }
        if self.entropy_bonus:
            out["loss_entropy"] = self._reduce_loss(-self.entropy_coeff * entropy, tensordict)
        with torch.no_grad():
            residual = torch.var(target - value, correction=0, dim=0)
            total = torch.var(target, correction=0, dim=0) + torch.finfo(target.dtype).eps
            diagnostics = {
                "clip_fraction": (clipped != log_weight).to(log_weight.dtype).mean(),
                "kl_approx": (old_log_prob - log_prob).mean(),
                "entropy": entropy.mean(),
                "explained_variance": 1.0 - residual / total,
            }
        return TensorDict({**out, **diagnostics})


def categorical_log_prob_entropy(
    logits: torch.Tensor, action: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """What ``torch.distributions.Categorical(logits=logits)`` gives as ``log_prob(action)`` and
    ``entropy()`` (the same maths), without building and validating the distribution."""
    log_probs = logits - logits.logsumexp(-1, keepdim=True)
    log_prob = log_probs.gather(-1, action.long().unsqueeze(-1)).squeeze(-1)
    smallest = torch.finfo(log_probs.dtype).min  # Categorical's clamp: 0 · log 0 counts as 0
    entropy = -(log_probs.clamp(min=smallest) * log_probs.exp()).sum(-1)
    return log_prob, entropy


class Stacked:
    """The copies of a TorchRL ``MLP`` whose parameters are stacked (a loss's critics: a leading
    dimension, one per copy), all run at once: each ``Linear`` one batched matmul over the copies
    (what TorchRL's vmap over the copies computes), the rest as they are."""

    def __init__(self, mlp: nn.Sequential, params: TensorDictBase) -> None:
        self.layers = [
            (params[name]["weight"].transpose(-1, -2), params[name]["bias"].unsqueeze(-2))
            if isinstance(layer, nn.Linear)
            else layer
            for name, layer in mlp.named_children()
        ]
        self.copies = params.batch_size[0]

    def __call__(self, *inputs: torch.Tensor) -> torch.Tensor:
        """``[copies, batch, out]``: every copy on the concatenated ``inputs`` (``[batch, in]``)."""
        x = torch.cat(inputs, -1).expand(self.copies, *inputs[0].shape[:-1], -1)
        for layer in self.layers:
            x = torch.baddbmm(layer[1], x, layer[0]) if isinstance(layer, tuple) else layer(x)
        return x
