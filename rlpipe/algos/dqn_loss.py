"""TorchRL's DQNLoss with its forward on plain tensors: the same parameters and maths, without
swapping the parameters into the network three times per minibatch."""

from __future__ import annotations

import copy

import torch
from tensordict import TensorDict, TensorDictBase
from torch import nn
from torchrl.objectives import DQNLoss
from torchrl.objectives.utils import distance_loss

from rlpipe.models import TensorModule


class DirectDQNLoss(DQNLoss):
    """``DQNLoss`` (a ``QValueActor`` over a :class:`~rlpipe.models.TensorModule`, a categorical
    action space, TorchRL's TD(0) value estimator) whose :meth:`forward` computes what
    ``DQNLoss.forward`` computes (the chosen action's value, double DQN's online argmax and
    target value or the target's max, ``r + γ^k (1 - terminated) V'``, the distance loss, the
    ``td_error`` priority) on two copies of the network bound once to the loss's own online and
    target parameters. ``DQNLoss.forward`` puts the parameters into a meta copy of the network
    with ``to_module`` for each of its three network calls, which costs more than the maths on
    a small network. Parameters, state dict, target updaters and value estimator are
    ``DQNLoss``'s: the bound copies are views of the same tensors, not registered modules.
    """

    def __init__(self, value_network: nn.Module, **kwargs) -> None:
        super().__init__(value_network, **kwargs)
        inner = [m for m in self.value_network.modules() if isinstance(m, TensorModule)]
        if len(inner) != 1 or self.action_space != "categorical":
            raise ValueError("DirectDQNLoss needs a QValueActor over one TensorModule")
        self.in_key = inner[0].in_keys[0]

    def _networks(self) -> tuple[nn.Module, nn.Module]:
        """The network bound to the online parameters and to the target ones, made at the first
        call and again for a copy of the loss (whose parameters are other tensors); kept outside
        what ``nn.Module`` registers, so the state dict stays ``DQNLoss``'s."""
        params = self.value_network_params, self.target_value_network_params
        owner = tuple(id(p) for p in params)
        if self.__dict__.get("_owner") != owner:
            self.__dict__["_nets"] = tuple(self._bound(p) for p in params)
            self.__dict__["_owner"] = owner
        return self.__dict__["_nets"]

    def _bound(self, params: TensorDictBase) -> nn.Module:
        """The network, its parameters those of ``params`` (the same tensors, for good)."""
        actor = copy.deepcopy(self.value_network)  # a meta copy: no data is copied
        params.to_module(actor)
        return next(m for m in actor.modules() if isinstance(m, TensorModule)).module

    def forward(self, tensordict: TensorDictBase) -> TensorDict:
        online, target = self._networks()
        action = tensordict.get(self.tensor_keys.action)
        values = online(tensordict.get(self.in_key))
        if action.ndim != values.ndim:
            action = action.unsqueeze(-1)
        chosen = values.gather(-1, action).squeeze(-1)
        estimator, nxt = self.value_estimator, tensordict.get("next")
        with torch.no_grad():
            next_obs = nxt.get(self.in_key)
            next_values = target(next_obs)
            if self.double_dqn:
                best = online(next_obs).argmax(-1, keepdim=True)
                next_value = next_values.gather(-1, best)
            else:
                next_value = next_values.max(-1, keepdim=True).values
            reward = nxt.get(estimator.tensor_keys.reward)
            gamma = estimator.gamma.to(reward.device)
            steps = tensordict.get(estimator.tensor_keys.steps_to_next_obs, None)
            if steps is not None:
                gamma = gamma ** steps.view_as(reward)
            terminated = nxt.get(estimator.tensor_keys.terminated)
            target_value = (reward + gamma * (~terminated).int() * next_value).squeeze(-1)
            priority = (chosen - target_value).pow(2).unsqueeze(-1)
        tensordict.set(self.tensor_keys.priority, priority, inplace=True)
        loss = distance_loss(chosen, target_value, self.loss_function)
        weights = None
        if self.use_prioritized_weights in (True, "auto"):
            weights = tensordict.get(self.tensor_keys.priority_weight, None)
        return TensorDict(loss=self._reduce_loss(loss, tensordict=tensordict, weights=weights))
