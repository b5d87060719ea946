"""The small interface every algorithm exposes to the shared runner, and what they share."""

from __future__ import annotations

import math
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any, ClassVar, Protocol, runtime_checkable

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torch import nn
from torchrl.collectors import Collector
from torchrl.envs import EnvBase

from rlpipe.envs import EnvFactory
from rlpipe.models import mlp, user_network

# Scalars are averaged over the runner's logging window; lists hold one value per event
# (e.g. one return per finished training episode) and are logged row by row.
Metrics = dict[str, float | list[float]]

# metric keys the runner reads
EPISODE_RETURN = "train/episode_return"  # one value per finished training episode
EPISODE_LENGTH = "train/episode_length"
LOSS = "train/loss"
# what a replay buffer keeps of each transition (DQN, SAC)
TRANSITION_KEYS = (
    "observation",
    "action",
    ("next", "observation"),
    ("next", "reward"),
    ("next", "done"),
    ("next", "terminated"),
)


def batch_steps(env: EnvBase, frames: int) -> tuple[int, int]:
    """``(copies, steps)``: the env's copies, and the steps each takes for ``frames`` frames
    (rounded up to whole steps of all copies)."""
    copies = max(env.batch_size.numel(), 1)
    return copies, math.ceil(frames / copies)


@runtime_checkable
class Algorithm(Protocol):
    """What the runner needs: a greedy policy, a frame counter, one iteration, and state.

    Builders are called as ``Algo(env_factory, cfg, device=device)``: ``env_factory()`` builds
    the training env (a :data:`rlpipe.envs.EnvFactory`), which the algorithm owns and closes.
    """

    policy: TensorDictModuleBase  # deterministic/greedy policy used by evaluation and video
    frames: int  # environment frames consumed so far
    iterations: int  # train_step calls so far
    budget: int | None  # the algorithm's own budget in iterations (REINFORCE epochs, ARS
    # iterations); None: none, the run's total_frames decides
    finite_keys: ClassVar[tuple[str, ...]]  # metrics that must stay finite (else: diverged)
    # optional: `divergence_hint` (str), the advice a divergence error ends with, and
    # `should_stop` (a callable the runner sets: True once SIGINT/SIGTERM arrived), which a
    # long train_step may poll to end its iteration early in a consistent state, and
    # `frame_limit` (the runner sets its total_frames), where train_step stops collecting

    def train_step(self) -> Metrics:
        """Run one iteration (collect and update); advance ``frames``; return metrics."""
        ...

    def state_dict(self) -> dict[str, Any]: ...

    def load_state_dict(self, state: dict[str, Any]) -> None: ...

    def close(self) -> None:
        """Release the env the algorithm built and any workers or collectors it started."""
        ...


def episode_metrics(batch: TensorDictBase) -> Metrics:
    """Returns and lengths of the episodes that ended inside a collected batch."""
    done = batch["next", "done"]
    if not bool(done.any()):
        return {}
    return {
        EPISODE_RETURN: batch["next", "episode_reward"][done].tolist(),
        EPISODE_LENGTH: batch["next", "step_count"][done].float().tolist(),
    }


@contextmanager
def closing_on_error(env: EnvBase) -> Iterator[EnvBase]:
    """Close ``env`` if building the algorithm around it fails (it owns the env after that)."""
    try:
        yield env
    except BaseException:
        env.close()
        raise


class BatchCut:
    """A TorchRL collector interruptor that ends the next batch after ``steps`` env steps
    (``None``: the whole batch); see :meth:`EnvAlgorithm.collect`."""

    def __init__(self) -> None:
        self.steps: int | None = None

    def collection_stopped(self) -> bool:
        """Called by the collector after each env step of a batch."""
        if self.steps is None:
            return False
        self.steps -= 1
        return self.steps <= 0


class EnvAlgorithm:
    """What DQN, REINFORCE and MBRL share: built on one env from the factory (closed again if
    building fails), frame and iteration counters, and a state dict over named attributes.

    ``network`` (or ``cfg.network``) replaces the algorithm's default network (see
    :meth:`network`). Subclasses implement ``_build(env)`` (``self.cfg`` and ``self.device`` are
    set) and ``train_step``, and list in ``state_attrs`` the attributes a checkpoint holds:
    anything with ``state_dict``/``load_state_dict`` (modules, optimizers, replay buffers) or
    ``get_state``/``set_state`` (torch generators). ``_restored`` runs after a load.
    """

    finite_keys: ClassVar[tuple[str, ...]] = (LOSS,)
    state_attrs: ClassVar[tuple[str, ...]] = ()
    budget: int | None = None  # frames only: the run's total_frames
    activation: ClassVar[type[nn.Module]] = nn.ReLU  # of the default MLPs
    frame_limit: int | None = None  # the runner sets its total_frames: collect no further
    divergence_hint = "try a smaller algo.lr"

    @staticmethod
    def should_stop() -> bool:
        """Whether a signal asks the current iteration to end early (the runner replaces it)."""
        return False

    def __init__(
        self,
        env_factory: EnvFactory,
        cfg: Any,
        *,
        device: str | torch.device = "cpu",
        network: nn.Module | None = None,
    ):
        self.cfg = cfg
        self.device = torch.device(device)
        self.frames = self.iterations = 0
        self._network = network  # the user's, in place of the default (or cfg.network)
        self.env_factory = env_factory
        with closing_on_error(env_factory()) as env:
            self._build(env)

    def _build(self, env: EnvBase) -> None:
        raise NotImplementedError

    def network(self, in_features: int, out_features: int, outputs: str) -> nn.Module:
        """The user's network (``network=`` or ``cfg.network``, checked to map ``in_features``
        to ``out_features``), else the default: an MLP with ``cfg.hidden_sizes``."""
        given = user_network(
            self._network,
            self.cfg.network,
            in_features=in_features,
            out_features=out_features,
            outputs=outputs,
        )
        if given is not None:
            return given
        return mlp(in_features, out_features, self.cfg.hidden_sizes, self.activation)

    def make_collector(
        self, env: EnvBase, policy: TensorDictModuleBase, frames_per_batch: int
    ) -> None:
        """An endless TorchRL ``Collector`` (``self.collector``) of ``frames_per_batch`` frames per
        batch, rounded up to whole steps of the env's copies; policy and storage on the device."""
        self._copies, self._steps = batch_steps(env, frames_per_batch)
        self._cut = BatchCut()
        self.collector = Collector(
            env,
            policy,
            frames_per_batch=self._steps * self._copies,
            total_frames=-1,
            policy_device=self.device,
            storing_device=self.device,
            interruptor=self._cut,
        )
        self._batches = iter(self.collector)
        # on one device the collector steps the very policy; otherwise it holds a copy
        self._copy_weights = self.device != torch.device(env.device)

    def sync_collector(self) -> None:
        """After updates: the collector's copy of the policy takes the new weights."""
        if self._copy_weights:
            self.collector.update_policy_weights_()

    def close(self) -> None:
        """Stop the collector (:meth:`make_collector`) and close its env."""
        self.collector.shutdown()

    def collect(self, at_most: int | None = None) -> TensorDictBase:
        """The collector's next batch, ``[env copies, steps]``, cut short (whole steps of the
        copies) to hold at most ``at_most`` frames and to end at ``frame_limit``: a run's
        ``total_frames`` is exact when it is a multiple of the env's copies."""
        caps = [at_most, None if self.frame_limit is None else self.frame_limit - self.frames]
        frames = min((cap for cap in caps if cap is not None), default=None)
        steps = self._steps if frames is None else max(math.ceil(frames / self._copies), 1)
        self._cut.steps = steps if steps < self._steps else None
        return next(self._batches)[..., :steps]

    def state_dict(self) -> dict[str, Any]:
        state = {name: _save(getattr(self, name)) for name in self.state_attrs}
        return {**state, "frames": self.frames, "iterations": self.iterations}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        for name in self.state_attrs:
            _load(getattr(self, name), state[name])
        self.frames = int(state["frames"])
        self.iterations = int(state["iterations"])
        self._restored()

    def _restored(self) -> None:
        """Bring derived state (schedules, collector weights) in line after a load."""


def _save(part: Any) -> Any:
    return part.get_state() if isinstance(part, torch.Generator) else part.state_dict()


def _load(part: Any, state: Any) -> None:
    if isinstance(part, torch.Generator):
        part.set_state(state)
    else:
        part.load_state_dict(state)
