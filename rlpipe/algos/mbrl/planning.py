"""Learned world models and a model-predictive planner over them (used by ``algo=mbrl``).

:class:`WorldModel` holds an ensemble of MLPs predicting the (normalised) state change, a reward
model and a termination model; :class:`Planner` searches action sequences on it by random
shooting or the cross-entropy method, every candidate rolled out on every ensemble member in
one batched matrix product per step.

Why not TorchRL's ``CEMPlanner`` over a ``ModelBasedEnvBase``: in 0.14.1 it samples its noise
from the global generator (a greedy policy that is not a function of the observation, and state
a checkpoint cannot hold), sums rewards undiscounted, handles continuous actions only, and
steps the model through ``EnvBase.rollout``, which builds, checks and moves a TensorDict per
simulated step; an ensemble dimension would have to be folded into the env's batch by hand.
The planner is called once per env step in training and in every greedy evaluation step, so on
2 CPU cores the per-step Python overhead matters: here a simulated step is one ``baddbmm`` per
layer over (members, envs × candidates) rows, with no TensorDicts inside the loop.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
import torch.nn.functional as F
from torch import nn

from rlpipe.models import mlp
from rlpipe.normalizer import Normalizer


class EnsembleMLP(nn.Module):
    """``members`` independent ReLU MLPs evaluated as one batch: ``[E, N, in] -> [E, N, out]``.

    The weights of each layer are one ``[E, in, out]`` tensor, so a forward pass is one
    ``baddbmm`` per layer instead of ``E`` module calls (or a ``vmap`` over copies of
    :func:`rlpipe.models.mlp`, whose per-call overhead dominates at planning sizes).
    """

    def __init__(
        self, members: int, in_features: int, out_features: int, hidden_sizes: Sequence[int]
    ) -> None:
        super().__init__()
        sizes = [in_features, *hidden_sizes, out_features]
        self.weights = nn.ParameterList()
        self.biases = nn.ParameterList()
        for fan_in, fan_out in zip(sizes[:-1], sizes[1:]):
            bound = 1 / math.sqrt(fan_in)  # nn.Linear's default initialisation
            self.weights.append(nn.Parameter(torch.empty(members, fan_in, fan_out)))
            self.biases.append(nn.Parameter(torch.empty(members, 1, fan_out)))
            nn.init.uniform_(self.weights[-1], -bound, bound)
            nn.init.uniform_(self.biases[-1], -bound, bound)

    @property
    def members(self) -> int:
        return self.weights[0].shape[0]

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        last = len(self.weights) - 1
        for i, (weight, bias) in enumerate(zip(self.weights, self.biases)):
            x = torch.baddbmm(bias, x, weight)
            if i < last:
                x = torch.relu(x)
        return x


class WorldModel(nn.Module):
    """Dynamics ensemble, reward model and termination model over encoded actions.

    - dynamics: ``members`` MLPs on (normalised observation, action) predicting the normalised
      change ``next_observation - observation``;
    - reward: one MLP on (observation, action, next observation), all normalised;
    - termination: one MLP on the normalised next observation giving the logit of
      ``terminated``; it is trained and used only once a terminal transition has been seen
      (``can_terminate``), so envs that only truncate (Pendulum) skip it. Terminal transitions
      are rare: the fit weights them to balance the classes, erring towards predicting falls.

    The normalisers (:class:`rlpipe.normalizer.Normalizer`) grow with every stored transition
    (:meth:`observe`) and are part of the state dict.
    """

    def __init__(
        self, obs_size: int, action_size: int, hidden_sizes: Sequence[int], members: int
    ) -> None:
        super().__init__()
        self.obs_norm = Normalizer(obs_size)
        self.delta_norm = Normalizer(obs_size, min_var=1e-8)
        self.reward_norm = Normalizer(1)
        self.dynamics = EnsembleMLP(members, obs_size + action_size, obs_size, hidden_sizes)
        self.reward = mlp(2 * obs_size + action_size, 1, hidden_sizes)
        self.termination = mlp(obs_size, 1, hidden_sizes)
        self.register_buffer("can_terminate", torch.zeros((), dtype=torch.bool))

    @torch.no_grad()
    def observe(
        self,
        observation: torch.Tensor,
        next_observation: torch.Tensor,
        reward: torch.Tensor,
        terminated: torch.Tensor,
    ) -> None:
        """Fold a batch of transitions into the normalisation statistics."""
        self.obs_norm.observe(observation)
        self.delta_norm.observe(next_observation - observation)
        self.reward_norm.observe(reward.reshape(-1, 1))
        self.can_terminate |= terminated.any()

    def step(
        self, observation: torch.Tensor, action: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """``[E, N, ...]`` observations and encoded actions -> next observation, reward ``[E, N]``
        and termination probability ``[E, N]`` (zeros until ``can_terminate``)."""
        obs = self.obs_norm(observation)
        delta = self.dynamics(torch.cat([obs, action], -1))
        next_observation = observation + self.delta_norm.loc + self.delta_norm.scale * delta
        next_obs = self.obs_norm(next_observation)
        reward = self.reward(torch.cat([obs, action, next_obs], -1)).squeeze(-1)
        reward = self.reward_norm.loc + self.reward_norm.scale * reward
        if bool(self.can_terminate):
            p_done = torch.sigmoid(self.termination(next_obs).squeeze(-1))
        else:
            p_done = torch.zeros_like(reward)
        return next_observation, reward, p_done

    def losses(
        self,
        observation: torch.Tensor,
        action: torch.Tensor,
        next_observation: torch.Tensor,
        reward: torch.Tensor,
        terminated: torch.Tensor,
        terminal_weight: float = 1.0,
    ) -> dict[str, torch.Tensor]:
        """Normalised-MSE dynamics (mean over members) and reward losses, BCE termination loss
        with terminal transitions weighted by ``terminal_weight``.

        Inputs are ``[E, N, ...]``: member ``e`` is trained on row ``e`` (its own minibatch);
        the reward and termination models use every row.
        """
        obs, next_obs = self.obs_norm(observation), self.obs_norm(next_observation)
        target = (next_observation - observation - self.delta_norm.loc) / self.delta_norm.scale
        delta = self.dynamics(torch.cat([obs, action], -1))
        predicted = self.reward(torch.cat([obs, action, next_obs], -1)).squeeze(-1)
        losses = {
            "dynamics": F.mse_loss(delta, target),
            "reward": F.mse_loss(predicted, self.reward_norm(reward.unsqueeze(-1)).squeeze(-1)),
        }
        if bool(self.can_terminate):
            logits = self.termination(next_obs).squeeze(-1)
            weight = torch.tensor(terminal_weight, device=logits.device)
            losses["termination"] = F.binary_cross_entropy_with_logits(
                logits, terminated.float(), pos_weight=weight
            )
        return losses


class ActionCoder:
    """Env actions <-> the planner's encoding: [-1, 1] per dimension for a bounded box, one-hot
    for a discrete set (``num_actions`` given)."""

    def __init__(
        self,
        *,
        low: torch.Tensor | None = None,
        high: torch.Tensor | None = None,
        num_actions: int | None = None,
    ) -> None:
        self.discrete = num_actions is not None
        self.num_actions = num_actions
        self.low, self.high = low, high
        self.size = num_actions if self.discrete else int(low.numel())

    def encode(self, action: torch.Tensor) -> torch.Tensor:
        """Env actions (indices, or values in the bounds) -> model inputs."""
        if self.discrete:
            return F.one_hot(action.long(), self.num_actions).float()
        return 2 * (action - self.low) / (self.high - self.low) - 1

    def decode(self, code: torch.Tensor) -> torch.Tensor:
        """Planner samples (indices, or values in [-1, 1]) -> env actions."""
        if self.discrete:
            return code
        return self.low + (code + 1) * (self.high - self.low) / 2


class Planner:
    """Model-predictive control on a :class:`WorldModel`: returns the first action of the best
    action sequence found for each observation.

    ``method="random"`` (random shooting): ``candidates`` sequences of ``horizon`` actions drawn
    uniformly (from the action set, or the box), the one with the highest predicted return wins.
    ``method="cem"`` (cross-entropy method): ``iterations`` rounds of sampling ``candidates``
    sequences from a per-step Gaussian (box: mean 0 and ``init_std`` in [-1, 1] units, clipped)
    or categorical (discrete: uniform at first), refitting it to the ``elites`` best; the action
    is the final mean (box) or most probable action (discrete) of the first step.

    A sequence's predicted return is the discounted sum of predicted rewards, each weighted by
    the predicted probability that the episode has not terminated before it, averaged over the
    ensemble members (every candidate is rolled out on every member).
    """

    def __init__(
        self,
        model: WorldModel,
        coder: ActionCoder,
        *,
        method: str,
        horizon: int,
        candidates: int,
        iterations: int,
        elites: int,
        gamma: float,
        init_std: float,
    ) -> None:
        self.model, self.coder, self.method = model, coder, method
        self.horizon, self.candidates, self.elites = horizon, candidates, elites
        self.iterations = iterations if method == "cem" else 1
        self.init_std = init_std
        self.discounts = gamma ** torch.arange(horizon, dtype=torch.float32)

    @torch.no_grad()
    def returns(self, observation: torch.Tensor, codes: torch.Tensor) -> torch.Tensor:
        """Predicted returns ``[B, N]`` of encoded action sequences ``[B, N, H, A]`` from
        observations ``[B, obs]``, averaged over the ensemble."""
        batch, n = codes.shape[:2]
        members = self.model.dynamics.members
        state = observation.unsqueeze(1).expand(batch, n, -1).reshape(1, batch * n, -1)
        state = state.expand(members, -1, -1)
        codes = codes.reshape(1, batch * n, self.horizon, -1).expand(members, -1, -1, -1)
        alive = torch.ones(members, batch * n, device=observation.device)
        total = torch.zeros_like(alive)
        discounts = self.discounts.to(observation.device)
        for t in range(self.horizon):
            state, reward, p_done = self.model.step(state, codes[:, :, t])
            total += discounts[t] * alive * reward
            alive = alive * (1 - p_done)
        return total.mean(0).reshape(batch, n)

    @torch.no_grad()
    def plan(self, observation: torch.Tensor, generator: torch.Generator) -> torch.Tensor:
        """Env actions ``[B, ...]`` for observations ``[B, obs]``, sampling with ``generator``."""
        if self.coder.discrete:
            return self._plan_discrete(observation, generator)
        return self._plan_box(observation, generator)

    def _plan_box(self, observation: torch.Tensor, generator: torch.Generator) -> torch.Tensor:
        batch, device = observation.shape[0], observation.device
        shape = (batch, self.candidates, self.horizon, self.coder.size)
        if self.method == "random":
            codes = torch.rand(shape, generator=generator).to(device) * 2 - 1
            best = self.returns(observation, codes).argmax(1)
            return self.coder.decode(codes[torch.arange(batch), best, 0])
        mean = torch.zeros(batch, 1, self.horizon, self.coder.size, device=device)
        std = torch.full_like(mean, self.init_std)
        for _ in range(self.iterations):
            noise = torch.randn(shape, generator=generator).to(device)
            codes = (mean + std * noise).clamp(-1, 1)
            elite = self._elites(observation, codes)
            mean, std = elite.mean(1, keepdim=True), elite.std(1, keepdim=True)
        return self.coder.decode(mean[:, 0, 0])

    def _plan_discrete(self, observation: torch.Tensor, generator: torch.Generator) -> torch.Tensor:
        batch, device, n = observation.shape[0], observation.device, self.coder.num_actions
        probs = torch.full((batch, 1, self.horizon, n), 1 / n, device=device)
        for _ in range(self.iterations):
            u = torch.rand(batch, self.candidates, self.horizon, 1, generator=generator)
            index = (probs.cumsum(-1) < u.to(device)).sum(-1).clamp(max=n - 1)
            codes = F.one_hot(index, n).float()
            if self.method == "random":
                best = self.returns(observation, codes).argmax(1)
                return index[torch.arange(batch), best, 0]
            probs = self._elites(observation, codes).mean(1, keepdim=True)
        return probs[:, 0, 0].argmax(-1)

    def _elites(self, observation: torch.Tensor, codes: torch.Tensor) -> torch.Tensor:
        """The ``elites`` highest-return sequences ``[B, K, H, A]`` among ``codes``."""
        top = self.returns(observation, codes).topk(self.elites, dim=1).indices
        return codes.gather(1, top[:, :, None, None].expand(-1, -1, *codes.shape[2:]))
