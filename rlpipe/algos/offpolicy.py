"""The off-policy loop that DQN, SAC and the next off-policy algorithm configure rather than copy:
collect, count, store, warm up, K gradient steps, target update (SB3's ``OffPolicyAlgorithm``
template, from TorchRL parts: the Collector, a ReplayBuffer and a target updater)."""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.data import LazyTensorStorage, ReplayBuffer
from torchrl.envs import EnvBase

from rlpipe.algos.base import LOSS, TRANSITION_KEYS, EnvAlgorithm, Metrics, episode_metrics
from rlpipe.algos.configs import OffPolicyConfig
from rlpipe.cadence import Cadence


class OffPolicy(EnvAlgorithm):
    """One off-policy iteration per :meth:`train_step`, on an :class:`OffPolicyConfig`.

    Collect ``cfg.frames_per_batch`` frames with the collecting policy, count them, store the
    transitions (:meth:`transitions`) in a replay buffer of ``cfg.buffer_size``; once
    ``cfg.learning_starts`` frames (and a minibatch) are in, run ``cfg.updates_per_batch``
    gradient steps on minibatches of ``cfg.batch_size``, each on :meth:`loss_of` the minibatch,
    then the target networks' update: after every gradient step, or, with
    ``cfg.target_update_every``, once the frames pass a multiple of it.

    A subclass gives the maths. Its ``_build(env)`` sets ``self.policy`` (greedy),
    ``self.loss`` (a TorchRL loss module), ``self.optimizer`` and ``self.target_updater``, then
    calls :meth:`start_loop` with the collecting policy; it implements :meth:`loss_of`, and may
    override :meth:`follow_schedules`, :meth:`collect_metrics`, :meth:`transitions` and
    :meth:`clip_gradients`. Checkpoints hold the loss module (networks and targets), the
    optimizer and the replay buffer.
    """

    cfg: OffPolicyConfig
    state_attrs = ("loss", "optimizer", "buffer")

    def start_loop(self, env: EnvBase, collect_policy: TensorDictModuleBase) -> None:
        """The replay buffer, the target cadence and the collector (last in ``_build``)."""
        self.buffer = ReplayBuffer(
            storage=LazyTensorStorage(self.cfg.buffer_size, device=self.device),
            batch_size=self.cfg.batch_size,
        )
        self._target_cadence = Cadence(self.cfg.target_update_every, 0)
        self.make_collector(env, collect_policy, self.cfg.frames_per_batch)

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
        return batch.reshape(-1).select(*TRANSITION_KEYS)

    def clip_gradients(self) -> None:
        """Between ``backward`` and the optimizer's step (nothing by default)."""

    def train_step(self) -> Metrics:
        cfg = self.cfg
        batch = self.collect()
        self.frames += batch.numel()
        self.iterations += 1
        self.follow_schedules()
        self.buffer.extend(self.transitions(batch))
        metrics = self.collect_metrics()
        metrics.update(episode_metrics(batch))
        if len(self.buffer) < max(cfg.learning_starts, cfg.batch_size):
            return metrics
        losses, scalars = [], {}
        for _ in range(cfg.updates_per_batch):
            loss, scalars = self.loss_of(self.buffer.sample())
            self.optimizer.zero_grad(set_to_none=True)
            loss.backward()
            self.clip_gradients()
            self.optimizer.step()
            if not cfg.target_update_every:
                self.target_updater.step()
            losses.append(loss.detach())
        if losses:
            if self._target_cadence.due(self.frames):
                self.target_updater.step()
            metrics[LOSS] = float(torch.stack(losses).mean())
            metrics.update({key: float(value) for key, value in scalars.items()})
        self.sync_collector()
        return metrics

    def _restored(self) -> None:
        self.follow_schedules()
        self._target_cadence = Cadence(self.cfg.target_update_every, self.frames)
        self.collector.update_policy_weights_()
