"""The algorithm contract the shared runner drives (:class:`Algorithm`, every hook declared with
its default), and what the algorithms built on one env share (:class:`EnvAlgorithm`)."""

from __future__ import annotations

import math
from collections.abc import Collection, Iterator
from contextlib import contextmanager
from dataclasses import replace
from functools import partial
from typing import Any, ClassVar

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torch import nn
from torchrl.envs import EnvBase

from rlpipe.algos.collectors import CollectAction, make_collector
from rlpipe.algos.state import load_parts, save_parts, start_parts
from rlpipe.config import RUN_KEYS, AlgoConfig, Config, EnvConfig
from rlpipe.encoders import encoded
from rlpipe.envs import EnvFactory, Observation, make_env, observation_of
from rlpipe.envs.backends import backend_of
from rlpipe.errors import RlpipeError, check
from rlpipe.models import mlp, object_record, user_network
from rlpipe.registry import config_class

# Scalars are averaged over the runner's logging window; lists hold one value per event
# (e.g. one return per finished training episode) and are logged row by row.
Metrics = dict[str, float | list[float]]

# metric keys the runner reads
EPISODE_RETURN = "train/episode_return"  # one value per finished training episode
EPISODE_LENGTH = "train/episode_length"
LOSS = "train/loss"
# the frame each finished training episode ended at, in the order of the episodes' values: the
# step of their rows (not logged itself)
EPISODE_FRAMES = "train/episode_frame"
# what a replay buffer keeps of each transition (DQN, SAC)
TRANSITION_KEYS = (
    "observation",
    "action",
    ("next", "observation"),
    ("next", "reward"),
    ("next", "done"),
    ("next", "terminated"),
)


def annealed(start: float, end: float | None, frames: int, total: int | None) -> float:
    """A value annealed linearly from ``start`` to ``end`` over ``total`` frames (held there
    after); ``start`` throughout where ``end`` or ``total`` is None (e.g. DQN's ``lr_end``)."""
    if end is None or not total:
        return start
    return start + min(max(frames / total, 0.0), 1.0) * (end - start)  # held before frame 0


def batch_steps(env: EnvBase, frames: int) -> tuple[int, int]:
    """``(copies, steps)``: the env's copies, and the steps each takes for ``frames`` frames
    (rounded up to whole steps of all copies)."""
    copies = max(env.batch_size.numel(), 1)
    return copies, math.ceil(frames / copies)


class Algorithm:
    """The base class of what the runner drives, with every hook the runner uses declared.

    Subclass it, set :attr:`policy`, and implement :meth:`train_step`, :meth:`state_dict` and
    :meth:`load_state_dict` (and :meth:`close` if it holds envs or workers).

    Every other member the runner uses is declared here with its default: the counters
    (:attr:`frames`, :attr:`iterations`), the algorithm's own :attr:`budget`, the metrics that
    must stay finite, the advice a divergence error ends with, the frame limit the runner sets
    (:meth:`limit_frames`), and a stop request (:meth:`request_stop`) that a long
    :meth:`train_step` may poll (:attr:`stop_requested`) to end its iteration early in a
    consistent state. Built as ``Algo(env_factory, cfg, device=..., network=...)``: the base
    constructor keeps those and calls :meth:`build`, where a subclass builds its parts;
    ``env_factory()`` builds the training env (a :data:`rlpipe.envs.EnvFactory`), which the
    algorithm owns and closes.
    """

    policy: TensorDictModuleBase  # deterministic/greedy policy used by evaluation and video
    frames: int = 0  # environment frames consumed so far
    iterations: int = 0  # train_step calls so far
    # the algorithm's own budget in iterations (REINFORCE epochs, ARS iterations); None: the
    # run's total_frames decides
    budget: int | None = None
    budget_key: ClassVar[str] = ""  # the config key that sets budget (``algo.iterations``)
    # the most frames that budget can take (None: not known); a run warns when its first
    # evaluation lies past it
    budget_frames: int | None = None
    finite_keys: ClassVar[tuple[str, ...]] = ()  # metrics that must stay finite (else: diverged)
    divergence_hint: ClassVar[str] = "try a smaller algo.lr"  # what a divergence error ends with
    # the modules (attribute names) whose forward compile=true|auto compiles: the loss
    compiled: ClassVar[tuple[str, ...]] = ()
    frame_limit: int | None = None  # the run's total_frames: collect no further (limit_frames)
    _stop = False  # request_stop's flag
    # what it was built from (None for an algorithm built otherwise): run_config reads them
    cfg: Any = None
    env_factory: EnvFactory | None = None
    user_network: nn.Module | None = None  # given in place of the default network

    def __init__(
        self,
        env_factory: EnvFactory | None = None,
        cfg: Any = None,
        *,
        device: str | torch.device = "cpu",
        network: nn.Module | None = None,
    ) -> None:
        self.cfg, self.env_factory, self.user_network = cfg, env_factory, network
        self.device = torch.device(device)
        self.build()

    def build(self) -> None:
        """Build what the algorithm needs from :attr:`env_factory` and :attr:`cfg` (called by
        ``__init__``, after the fields above are set; nothing by default)."""

    def train_step(self) -> Metrics:
        """Run one iteration (collect and update); advance ``frames``; return metrics."""
        raise NotImplementedError

    def state_dict(self) -> dict[str, Any]:
        """Everything a resume needs (tensors and plain containers)."""
        raise NotImplementedError

    def load_state_dict(self, state: dict[str, Any]) -> None:
        raise NotImplementedError

    def close(self) -> None:
        """Release the env the algorithm built and any workers or collectors it started."""

    def start_from(self, state: dict[str, Any], parts: Collection[str], parent: Any) -> None:
        """Begin a new run from another run's checkpoint (``state``: its ``"algo"`` entry, of a
        run with algorithm config ``parent``; ``init_from``): its networks and observation
        normaliser, and of ``parts`` (``"optimizer"``, ``"buffer"``) those too; counters,
        generators and every setting of the config stay this run's. None by default."""
        raise RlpipeError(
            f"{type(self).__name__} cannot start from another run (init_from): it implements no "
            "start_from; train it from scratch"
        )

    def limit_frames(self, total_frames: int | None) -> None:
        """The runner's ``total_frames``: an iteration collects no frames past it."""
        self.frame_limit = total_frames

    def restart_episodes(self) -> None:
        """Start fresh training episodes, their env seeds drawn from torch's generator: the
        runner calls it after each checkpoint and when a run resumes, so that a resumed run
        meets the episodes the uninterrupted one does (nothing by default: for an algorithm
        whose iterations start fresh episodes anyway)."""

    def request_stop(self, stop: bool = True) -> None:
        """Ask the current iteration to end early (SIGINT/SIGTERM); ``False`` clears it."""
        self._stop = stop

    @property
    def stop_requested(self) -> bool:
        """Whether a stop was requested: a long :meth:`train_step` polls it to end early."""
        return self._stop

    def run_config(self, **run: Any) -> Config | None:
        """The :class:`~rlpipe.config.Config` of a run of this algorithm, or None.

        Known when :attr:`cfg` is a registered algorithm config and :attr:`env_factory` was made
        as ``functools.partial(make_env, EnvConfig(...), seed=s)`` (``seed`` left out: torch's
        initial seed, what :func:`~rlpipe.seed_everything` set). ``run``: the runner's
        :data:`~rlpipe.config.RUN_KEYS`, ``keep_checkpoints`` and ``progress``.
        """
        factory = self.env_factory
        known = isinstance(self.cfg, AlgoConfig) and config_class(self.cfg.name) is type(self.cfg)
        by_make_env = isinstance(factory, partial) and factory.func is make_env
        if not (known and by_make_env and factory.args and isinstance(factory.args[0], EnvConfig)):
            return None
        env, options = factory.args[0], factory.keywords
        env = replace(env, backend=backend_of(env))  # the one its envs were built on
        if options.get("num_envs"):
            env = replace(env, num_envs=options["num_envs"])
        seed = options.get("seed")
        given = self.user_network
        network = {} if given is None else {"network": object_record(given)}
        return Config(
            env=env,
            algo=replace(self.cfg, **{key: run[key] for key in RUN_KEYS}, **network),
            seed=torch.initial_seed() % 2**32 if seed is None else seed,
            device=str(self.device),
            **run,
        )


def episode_metrics(batch: TensorDictBase, ended_by: int | None = None) -> Metrics:
    """Returns and lengths of the episodes that ended inside a collected batch; with
    ``ended_by`` (the frames counted once the ``[env copies, steps]`` batch is), also the frame
    each ended at (:data:`EPISODE_FRAMES`), the episodes in the order they ended."""
    done = batch["next", "done"]
    if not bool(done.any()):
        return {}
    returns = batch["next", "episode_reward"][done]
    lengths = batch["next", "step_count"][done].float()
    if ended_by is None or batch.ndim != 2:
        return {EPISODE_RETURN: returns.tolist(), EPISODE_LENGTH: lengths.tolist()}
    copies, steps = batch.shape
    behind = torch.arange(steps - 1, -1, -1, device=done.device).expand(copies, steps)
    frames = (ended_by - behind * copies)[done.reshape(copies, steps)]
    order = torch.argsort(frames, stable=True)
    return {
        EPISODE_RETURN: returns[order].tolist(),
        EPISODE_LENGTH: lengths[order].tolist(),
        EPISODE_FRAMES: frames[order].tolist(),
    }


@contextmanager
def closing_on_error(env: EnvBase) -> Iterator[EnvBase]:
    """Close ``env`` if building the algorithm around it fails (it owns the env after that)."""
    try:
        yield env
    except BaseException:
        env.close()
        raise


class EnvAlgorithm(Algorithm):
    """What DQN, REINFORCE, MBRL, PPO and SAC share: built on one env from the factory (closed
    again if building fails), and a state dict over named attributes.

    ``network`` (or ``cfg.network``) replaces the algorithm's default network (see
    :meth:`network`). Subclasses implement ``_build(env)`` (``self.cfg`` and ``self.device`` are
    set) and ``train_step``, and list in ``state_attrs`` the attributes a checkpoint holds:
    anything with ``state_dict``/``load_state_dict`` (modules, optimizers, replay buffers) or
    ``get_state``/``set_state`` (torch generators). ``_restored`` runs after a load.
    """

    finite_keys: ClassVar[tuple[str, ...]] = (LOSS,)
    state_attrs: ClassVar[tuple[str, ...]] = ()
    activation: ClassVar[type[nn.Module]] = nn.ReLU  # of the default MLPs

    observation: Observation  # what the networks see (set before ``_build``)

    def build(self) -> None:
        """One env from the factory (closed again if building fails), then ``_build(env)``."""
        with closing_on_error(self.env_factory()) as env:
            self.observation = observation_of(env)
            self._build(env)

    def _build(self, env: EnvBase) -> None:
        raise NotImplementedError

    def network(
        self,
        in_features: int | tuple[int, ...],
        out_features: int,
        outputs: str,
        *,
        layer_norm: bool = False,
    ) -> nn.Module:
        """The user's network (``network=`` or ``cfg.network``, checked to map observations of
        ``in_features``, a size or a shape, to ``out_features``), else :meth:`default_network`
        (``layer_norm``: with a LayerNorm after each hidden layer; refused beside a user's)."""
        given = user_network(
            self.user_network,
            self.cfg.network,
            in_features=in_features,
            out_features=out_features,
            outputs=outputs,
        )
        if given is not None:
            check(
                not layer_norm,
                f"algo.layer_norm shapes {self.cfg.name}'s default network, not one you bring "
                "(put the LayerNorm in your network, or drop algo.layer_norm)",
            )
            return given
        return self.default_network(in_features, out_features, layer_norm=layer_norm)

    def default_network(
        self,
        in_features: int | tuple[int, ...],
        out_features: int,
        hidden_sizes: list[int] | None = None,
        *,
        layer_norm: bool = False,
    ) -> nn.Module:
        """An MLP (``hidden_sizes``, default ``cfg.hidden_sizes``; ``layer_norm``: see
        :func:`rlpipe.models.mlp`) on a flat observation of ``in_features``; on any other, the
        MLP after the observation's encoder (:func:`rlpipe.encoders.encoded`: a CNN for images,
        one per key for Dict keys)."""
        sizes = self.cfg.hidden_sizes if hidden_sizes is None else hidden_sizes
        if self.observation.flat:
            return mlp(int(in_features), out_features, sizes, self.activation, layer_norm)
        return encoded(
            self.observation, lambda n: mlp(n, out_features, sizes, self.activation, layer_norm)
        )

    def make_collector(
        self,
        env: EnvBase,
        policy: TensorDictModuleBase,
        frames_per_batch: int,
        *,
        act: CollectAction | None = None,
    ) -> None:
        """What :meth:`collect` draws from (``self.collector``): batches of ``frames_per_batch``
        frames, rounded up to whole steps of the env's copies, stored on the device.

        On a :func:`rlpipe.make_env` env, the lean loop of
        :class:`~rlpipe.algos.collectors.ArrayCollector`, choosing actions with ``act`` (the
        sampling policy on plain tensors, e.g. DQN's ε-greedy) or, without one, with ``policy``
        on a reused TensorDict; on any other env (or with a policy that reads more than the
        observation), TorchRL's ``Collector`` running ``policy``
        (:class:`~rlpipe.algos.collectors.TorchRLCollector`). Either way the batches are the
        same ``[env copies, steps]`` TensorDicts (``act`` must compute what ``policy`` does).
        """
        self._copies, self._steps = batch_steps(env, frames_per_batch)
        self.collector = make_collector(env, policy, self._steps, self.device, act)

    def sync_collector(self) -> None:
        """After updates: a collector's copy of the policy (TorchRL's, on another device than
        the env's) takes the new weights."""
        self.collector.sync()

    def close(self) -> None:
        """Stop the collector (:meth:`make_collector`) and close its env."""
        self.collector.close()

    def restart_episodes(self) -> None:
        """Cut the collector's episodes: every env copy reset, seeded from torch's generator."""
        self.collector.restart(int(torch.randint(2**31 - 1, ())))

    def collect(self, at_most: int | None = None) -> TensorDictBase:
        """The collector's next batch, ``[env copies, steps]``, cut short (whole steps of the
        copies) to hold at most ``at_most`` frames and to end at ``frame_limit``: a run's
        ``total_frames`` is exact when it is a multiple of the env's copies."""
        caps = [at_most, None if self.frame_limit is None else self.frame_limit - self.frames]
        frames = min((cap for cap in caps if cap is not None), default=None)
        steps = self._steps if frames is None else max(math.ceil(frames / self._copies), 1)
        return self.collector.batch(min(steps, self._steps))

    def state_dict(self) -> dict[str, Any]:
        state = save_parts(self, self.state_attrs)
        return {**state, "frames": self.frames, "iterations": self.iterations}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        load_parts(self, self.state_attrs, state)
        self.frames = int(state["frames"])
        self.iterations = int(state["iterations"])
        self._restored()

    def _restored(self) -> None:
        """Bring derived state (schedules, collector weights) in line after a load."""

    def start_from(self, state: dict[str, Any], parts: Collection[str], parent: Any) -> None:
        """:meth:`Algorithm.start_from` over :attr:`state_attrs` by kind
        (:func:`~rlpipe.algos.state.start_parts`), then ``_restored``."""
        start_parts(self, self.state_attrs, state, parts)
        self._restored()
