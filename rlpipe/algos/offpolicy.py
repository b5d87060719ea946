"""The off-policy loop that DQN, SAC and the next off-policy algorithm configure rather than copy:
collect, count, store, warm up, K gradient steps, target update (SB3's ``OffPolicyAlgorithm``
template, from TorchRL parts: a ReplayBuffer and a target updater; the collection of
:mod:`rlpipe.algos.collectors`)."""

from __future__ import annotations

from typing import Any

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.data import ReplayBuffer
from torchrl.envs import EnvBase
from torchrl.objectives import LossModule, SoftUpdate

from rlpipe.algos.base import LOSS, TRANSITION_KEYS, EnvAlgorithm, Metrics, episode_metrics
from rlpipe.algos.collectors import CollectAction
from rlpipe.algos.configs import OffPolicyConfig
from rlpipe.algos.storage import LeafStorage
from rlpipe.cadence import Cadence


class OffPolicy(EnvAlgorithm):
    """One off-policy iteration per :meth:`train_step`, on an :class:`OffPolicyConfig`.

    Collect ``cfg.frames_per_batch`` frames with the collecting policy, count them, store the
    transitions (:meth:`transitions`) in a replay buffer of ``cfg.buffer_size``; once
    ``cfg.learning_starts`` frames (and a minibatch) are in, run ``cfg.updates_per_batch``
    gradient steps on minibatches of ``cfg.batch_size``, each on :meth:`loss_of` the minibatch,
    then the target networks' update (:meth:`update_targets`): after every gradient step, or,
    with ``cfg.target_update_every``, once the frames pass a multiple of it.

    A subclass gives the maths. Its ``_build(env)`` sets ``self.policy`` (greedy), ``self.loss``
    (a TorchRL loss module, through :meth:`on_device`), ``self.optimizer`` and
    ``self.target_updater``, then calls :meth:`start_loop` with the collecting policy (and, for
    the lean collection, the same policy on plain tensors); it implements :meth:`loss_of`, and
    may override :meth:`follow_schedules`, :meth:`collect_metrics`, :meth:`transitions`,
    :meth:`clip_gradients` and :meth:`update_targets`. Checkpoints hold the loss module
    (networks and targets), the optimizer, the replay buffer and :attr:`updates`.
    """

    cfg: OffPolicyConfig
    state_attrs = ("loss", "optimizer", "buffer")
    compiled = ("loss",)
    # gradient steps so far; during one, its number (from 1), which loss_of and update_targets
    # read (e.g. TD3's delayed actor and target updates)
    updates: int = 0

    def on_device(self, loss: LossModule) -> LossModule:
        """``loss`` with its value estimator (γ: ``cfg.gamma``), moved onto the device with its
        buffers (TorchRL makes the estimator's γ on the CPU); before the optimizer and target
        updater take its tensors."""
        loss.make_value_estimator(gamma=self.cfg.gamma)
        return loss.to(self.device)

    def start_loop(
        self,
        env: EnvBase,
        collect_policy: TensorDictModuleBase,
        *,
        act: CollectAction | None = None,
    ) -> None:
        """The replay buffer, the target cadence and the collector (last in ``_build``);
        ``act``: the collecting policy on plain tensors (see
        :meth:`~rlpipe.algos.base.EnvAlgorithm.make_collector`)."""
        self.buffer = ReplayBuffer(  # sampled with an explicit size: a batch of minibatches
            storage=LeafStorage(self.cfg.buffer_size, device=self.device)
        )
        self._target_cadence = Cadence(self.cfg.target_update_every, 0)
        self.make_collector(env, collect_policy, self.cfg.frames_per_batch, act=act)

    def loss_of(self, sample: TensorDictBase) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """The loss to minimise on a sampled minibatch, and scalars to log (of the last step)."""
        raise NotImplementedError

    def follow_schedules(self) -> None:
        """After the frames of a batch are counted: set what follows them (ε, learning rate)."""

    def collect_metrics(self) -> Metrics:
        """Scalars of the collection to log with every iteration (e.g. DQN's ε)."""
        return {}

    def transitions(self, batch: TensorDictBase) -> TensorDictBase:
        """What the buffer stores of a collected ``[env copies, steps]`` batch: one row per
        transition, :data:`~rlpipe.algos.base.TRANSITION_KEYS`."""
        return batch.select(*TRANSITION_KEYS).reshape(-1)

    def clip_gradients(self) -> None:
        """Between ``backward`` and the optimizer's step (nothing by default)."""

    def update_targets(self) -> None:
        """After each gradient step (``cfg.target_update_every`` 0): the target networks'
        update, ``self.target_updater.step()``."""
        self.target_updater.step()

    def train_step(self) -> Metrics:
        cfg = self.cfg
        batch = self.collect()
        self.frames += batch.numel()
        self.iterations += 1
        self.follow_schedules()
        self.buffer.extend(self.transitions(batch))
        metrics = self.collect_metrics()
        metrics.update(episode_metrics(batch, self.frames))
        if len(self.buffer) < max(cfg.learning_starts, cfg.batch_size):
            return metrics
        losses, scalars = [], {}
        # every minibatch of the batch's updates in one draw (one sampler and storage call)
        draws = self.buffer.sample(cfg.updates_per_batch * cfg.batch_size)
        minibatches = (
            (draws,)
            if cfg.updates_per_batch == 1
            else draws.reshape(cfg.updates_per_batch, cfg.batch_size).unbind(0)
        )
        for minibatch in minibatches:
            self.updates += 1
            loss, scalars = self.loss_of(minibatch)
            self.optimizer.zero_grad(set_to_none=True)
            loss.backward()
            self.clip_gradients()
            self.optimizer.step()
            if not cfg.target_update_every:
                self.update_targets()
            losses.append(loss.detach())
        if losses:
            if self._target_cadence.due(self.frames):
                self.target_updater.step()
            # the mean loss and the last step's scalars in one tensor: one read of its values
            values = [torch.stack(losses).mean(), *(v.reshape(()) for v in scalars.values())]
            metrics.update(zip((LOSS, *scalars), torch.stack(values).tolist(), strict=True))
        self.sync_collector()
        return metrics

    def state_dict(self) -> dict[str, Any]:
        return {**super().state_dict(), "updates": self.updates}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.updates = int(state.get("updates", 0))  # a checkpoint from before it was counted
        super().load_state_dict(state)

    def _restored(self) -> None:
        self.follow_schedules()
        self._target_cadence = Cadence(self.cfg.target_update_every, self.frames)
        self.sync_collector()


class ForeachSoftUpdate(SoftUpdate):
    """TorchRL's ``SoftUpdate`` (target ← τ·online + (1 − τ)·target), each step one
    ``torch._foreach_lerp_`` over every target tensor instead of one op per parameter group."""

    def __init__(self, loss_module: LossModule, *, tau: float) -> None:
        super().__init__(loss_module, tau=tau)
        self._pairs: tuple[list[torch.Tensor], list[torch.Tensor]] | None = None

    @torch.no_grad()
    def step(self) -> None:
        if self._pairs is None:  # the same tensors for the whole run: loads copy into them
            super().step()  # the parent's checks (initialised, targets outside the graph)
            sources, targets = [], []
            for key, source in self._sources.items():
                target = self._targets.get(f"target_{key}")
                sources += [leaf.data for leaf in source.values(True, True)]
                targets += [leaf.data for leaf in target.values(True, True)]
            self._pairs = targets, sources
            return
        torch._foreach_lerp_(*self._pairs, 1 - self.eps)
