"""Augmented random search (ARS) for any TensorDictModule policy, usable without the runner.

The search evolves the policy's flat parameter vector θ: each iteration samples ``N`` Gaussian
directions δ, rolls out the ``2N`` perturbed policies θ ± ν·δ as one population (one batched
policy call per step over a population dimension), keeps the ``b`` directions with the best
``max(r+, r-)`` and moves θ by ``α / (b·σ) · Σ (r+ - r-)·δ``, σ being the std of the selected
returns (Mania et al., 2018). A :class:`Normalizer` inside the policy (ARS V2) standardises
observations with running statistics that are updated after each iteration and frozen in between.

Rollouts step the gymnasium copies under a :func:`rlpipe.make_env` env directly: a finished copy
is not stepped again, and TorchRL's per-step overhead (a third of BipedalWalker's physics) is
skipped. With several workers (local processes, or Ray actors on this machine or a cluster) the
population is cut into chunks that the workers pull as they free up (episode lengths vary a
lot); each rolls out its chunk's members as one batch to the end and sends back only returns and
observation statistics.
"""

from __future__ import annotations

import math
import multiprocessing as mp
import os
import signal
import socket
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, fields
from multiprocessing.connection import wait
from typing import Any

import cloudpickle
import gymnasium as gym
import numpy as np
import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule, TensorDictModuleBase, TensorDictSequential
from torch import nn
from torch.nn.utils import parameters_to_vector, vector_to_parameters
from torchrl.envs import EnvBase

from rlpipe.envs import sub_envs
from rlpipe.errors import RlpipeError, check

__all__ = ["ARSSearch", "Normalizer", "PopulationPolicy", "ars_update", "batched_call", "rollout"]

# (num_envs=..., seed=...) -> a TorchRL env over a gymnasium SyncVectorEnv, e.g.
# functools.partial(rlpipe.make_env, EnvConfig(id="BipedalWalker-v3"))
EnvFactory = Callable[..., EnvBase]
CHUNKS_PER_WORKER = 8


class Normalizer(nn.Module):
    """Running mean and variance of observations; ``forward`` standardises with frozen values.

    The statistics (float64 count, mean and sum of squared deviations) grow by :meth:`merge`
    (Chan et al.'s parallel form of Welford's update); ``loc`` and ``scale`` used by ``forward``
    are refreshed only then. The variance is clipped at ``min_var`` (1e-2, as the notebook);
    before any observation the normaliser is the identity.
    """

    def __init__(self, size: int, min_var: float = 1e-2) -> None:
        super().__init__()
        self.min_var = min_var
        self.register_buffer("count", torch.zeros((), dtype=torch.float64))
        self.register_buffer("mean", torch.zeros(size, dtype=torch.float64))
        self.register_buffer("m2", torch.zeros(size, dtype=torch.float64))
        self.register_buffer("loc", torch.zeros(size))
        self.register_buffer("scale", torch.ones(size))

    def forward(self, observation: torch.Tensor) -> torch.Tensor:
        return (observation - self.loc) / self.scale

    def numpy_forward(self) -> Callable[[np.ndarray], np.ndarray]:
        """``forward`` as a NumPy function of a snapshot of the current ``loc`` and ``scale``
        (later merges do not change it, on any device)."""
        loc, scale = self.loc.cpu().numpy().copy(), self.scale.cpu().numpy().copy()
        return lambda observation: (observation - loc) / scale

    @torch.no_grad()
    def merge(self, count: float, mean: torch.Tensor, m2: torch.Tensor) -> None:
        """Fold in the statistics (count, mean, sum of squared deviations) of a batch."""
        if count == 0:
            return
        total = self.count + count
        delta = mean.double() - self.mean
        self.m2 += m2.double() + delta**2 * self.count * count / total
        self.mean += delta * count / total
        self.count.copy_(total)
        self.loc.copy_(self.mean)
        self.scale.copy_((self.m2 / self.count).clamp(min=self.min_var).sqrt())

    def observe(self, observations: torch.Tensor) -> None:
        """Fold in a batch of observations (rows)."""
        self.merge(*batch_stats(observations))


def batch_stats(observations: torch.Tensor) -> tuple[int, torch.Tensor, torch.Tensor]:
    """Count, mean and sum of squared deviations of a batch of observations (rows)."""
    x = observations.double().reshape(-1, observations.shape[-1])
    mean = x.mean(0) if len(x) else x.new_zeros(x.shape[-1])
    return len(x), mean, ((x - mean) ** 2).sum(0)


def ars_update(
    theta: torch.Tensor,
    deltas: torch.Tensor,
    returns_plus: torch.Tensor,
    returns_minus: torch.Tensor,
    num_best: int,
    step_size: float,
) -> torch.Tensor:
    """The ARS step: θ + α / (b·σ) · Σ_top-b (r+ - r-)·δ, top-b by max(r+, r-).

    ``deltas`` is ``[N, len(theta)]``; σ is the std of the ``2b`` selected returns.
    """
    top = torch.maximum(returns_plus, returns_minus).topk(num_best).indices
    plus, minus = returns_plus[top], returns_minus[top]
    sigma = torch.cat([plus, minus]).std(unbiased=False).clamp(min=1e-8)
    step = ((plus - minus).unsqueeze(-1) * deltas[top]).sum(0)
    return theta + step_size / (num_best * sigma) * step


# NumPy forms of common parameter-free layers (any other runs through torch, see numpy_layer)
_NUMPY_ACTIVATIONS: dict[type[nn.Module], Callable[[np.ndarray], np.ndarray]] = {
    nn.ReLU: lambda x: np.maximum(x, 0),
    nn.Tanh: np.tanh,
    nn.Identity: lambda x: x,
}


def numpy_layer(module: nn.Module) -> Callable[..., np.ndarray]:
    """A parameter-free ``module`` as a function of NumPy arrays.

    Modules with a ``numpy_forward()`` method (rlpipe's normaliser and action heads) give their
    own NumPy form, common activations have one here; anything else is called through torch
    (zero-copy conversions; module hooks are not run).
    """
    if hasattr(module, "numpy_forward"):
        return module.numpy_forward()
    if type(module) in _NUMPY_ACTIVATIONS:
        return _NUMPY_ACTIVATIONS[type(module)]
    return lambda *xs: module.forward(*map(torch.from_numpy, xs)).numpy()


def batched_call(module: nn.Module, params: dict[str, torch.Tensor]) -> Callable[..., np.ndarray]:
    """``module`` as a NumPy function of a population batch, member ``i`` using ``params[name][i]``.

    ``nn.Linear`` layers become one batched matmul and ``nn.Sequential`` chains (TorchRL's MLP)
    are followed layer by layer, parameter-free layers through :func:`numpy_layer`; any other
    module goes through ``torch.vmap`` over ``functional_call``. ``params`` are CPU tensors.
    """
    if isinstance(module, nn.Linear):
        weight = params["weight"].detach().transpose(1, 2).numpy()  # [P, in, out]
        bias = params.get("bias")
        bias = None if bias is None else bias.detach().numpy()

        def linear(x: np.ndarray) -> np.ndarray:
            y = np.matmul(x[:, None, :], weight)[:, 0]
            return y if bias is None else y + bias

        return linear
    if isinstance(module, nn.Sequential):
        layers = []
        for name, layer in module.named_children():
            prefix = f"{name}."
            own = {k[len(prefix) :]: v for k, v in params.items() if k.startswith(prefix)}
            layers.append(batched_call(layer, own) if own else numpy_layer(layer))

        def chain(x: np.ndarray) -> np.ndarray:
            for layer in layers:
                x = layer(x)
            return x

        return chain
    vmapped = torch.vmap(lambda p, *args: torch.func.functional_call(module, p, args))
    return lambda *xs: vmapped(params, *map(torch.from_numpy, xs)).numpy()


class PopulationPolicy:
    """A TensorDictModule policy evaluated for a population of flat parameter vectors at once.

    Row ``i`` of ``flat`` (``[P, n]``, the layout of ``parameters_to_vector``) holds member
    ``i``'s parameters. The policy is a ``TensorDictModule`` or a ``TensorDictSequential`` of
    them (one output key each); calling this on a TensorDict whose batch is the population runs
    them in order, as NumPy functions of the current parameters and statistics: parameter-free
    ones (normaliser, action head) through :func:`numpy_layer`, the others through
    :func:`batched_call`. A rollout step calls the policy on a few members right after the
    physics has evicted torch's dispatch code from the caches: measured there on BipedalWalker
    (two members), the torch form of the policy took about 70 µs per call, this one about 18.
    """

    def __init__(self, policy: TensorDictModuleBase, flat: torch.Tensor) -> None:
        modules = policy.module if isinstance(policy, TensorDictSequential) else [policy]
        self.steps: list[tuple[Callable[..., np.ndarray], list[Any], Any]] = []
        offset = 0
        for module in modules:
            check(
                isinstance(module, TensorDictModule) and len(module.out_keys) == 1,
                f"the policy must be made of TensorDictModules with one output, got {module}",
            )
            params = {}
            for name, param in module.module.named_parameters():
                params[name] = flat[:, offset : offset + param.numel()].view(-1, *param.shape)
                offset += param.numel()
            call = batched_call(module.module, params) if params else numpy_layer(module.module)
            self.steps.append((call, module.in_keys, module.out_keys[0]))
        check(offset == flat.shape[-1], "flat parameters do not match the policy's parameters")

    @torch.no_grad()
    def __call__(self, td: TensorDictBase) -> TensorDictBase:
        values = {k: v.cpu().numpy() for k, v in td.items(include_nested=True, leaves_only=True)}
        values = self.outputs(values)
        return td.update({key: torch.from_numpy(values[key]) for _, _, key in self.steps})

    def outputs(self, values: dict[Any, np.ndarray]) -> dict[Any, np.ndarray]:
        """The same on a plain dict of NumPy arrays (the rollout's per-step fast path)."""
        for call, in_keys, out_key in self.steps:
            values[out_key] = call(*[values[key] for key in in_keys])
        return values


@dataclass
class RolloutResult:
    """Per-member returns of one population rollout and the statistics of what it observed."""

    returns: torch.Tensor  # shaped (offset, clipped) returns, what the update ranks
    raw_returns: torch.Tensor  # the env's own returns
    lengths: torch.Tensor
    cpu_seconds: float  # CPU time of the process that rolled out
    obs_count: int
    obs_mean: torch.Tensor
    obs_m2: torch.Tensor

    def __reduce__(self) -> tuple[Any, tuple[Any, ...]]:
        # pickled as NumPy arrays: on a multiprocessing pipe torch's own reducer would move every
        # tensor through a new shared-memory file (about half a millisecond each)
        return _rollout_result, tuple(_numpy(getattr(self, f.name)) for f in fields(self))


def _numpy(value: Any) -> Any:
    return value.numpy() if isinstance(value, torch.Tensor) else value


def _rollout_result(*values: Any) -> RolloutResult:
    return RolloutResult(*(torch.as_tensor(v) if isinstance(v, np.ndarray) else v for v in values))


# wrappers that only check call order or count steps: a rollout steps the env inside them
# and ends the episode at the time limit itself
_BOOKKEEPING_WRAPPERS = (
    gym.wrappers.TimeLimit,
    gym.wrappers.OrderEnforcing,
    gym.wrappers.PassiveEnvChecker,
)


def _inner_env(env: gym.Env) -> tuple[gym.Env, int | None]:
    """The env under ``env``'s bookkeeping wrappers and its time limit (when only those wrap it).

    Each wrapper layer costs a few µs per step; an env with any other wrapper is stepped as is.
    """
    limit, inner = None, env
    while isinstance(inner, _BOOKKEEPING_WRAPPERS):
        if isinstance(inner, gym.wrappers.TimeLimit):
            limit = inner._max_episode_steps
        inner = inner.env
    return (inner, limit) if not isinstance(inner, gym.Wrapper) else (env, None)


@torch.inference_mode()
def rollout(
    policy: TensorDictModuleBase,
    envs: Sequence[gym.Env],
    flat: torch.Tensor,
    seeds: Sequence[int] | None = None,
    *,
    max_steps: int,
    reward_offset: float = 0.0,
    reward_clip: float | None = None,
) -> RolloutResult:
    """One episode per member: ``envs[i]``, reset with ``seeds[i]``, runs parameters ``flat[i]``.

    Every step calls the policy once on the observations of the members still running (a
    :class:`PopulationPolicy` on a plain dict of NumPy arrays: building a TensorDict per step
    would cost about a tenth of a BipedalWalker step); finished copies are not stepped again. An
    episode ends at ``max_steps`` or the env's own time limit, whichever comes first.
    Training rewards are ``clip(r + reward_offset, -reward_clip, reward_clip)``.
    """
    cpu = time.process_time()
    size = len(envs)
    seeds = [None] * len(envs) if seeds is None else seeds
    inner = [_inner_env(env) for env in envs]
    steps = [env.step for env, _ in inner]
    limits = [max_steps if limit is None else min(limit, max_steps) for _, limit in inner]
    obs = np.stack([env.reset(seed=seed)[0] for (env, _), seed in zip(inner, seeds)])
    obs = obs.astype(np.float32)
    returns, raw_returns, lengths = [0.0] * size, [0.0] * size, [0] * size
    low, high = (-math.inf, math.inf) if reward_clip is None else (-reward_clip, reward_clip)
    running = list(range(size))  # the member of each row of obs: those still in their episode
    forward = PopulationPolicy(policy, flat)
    seen = []
    for _ in range(max_steps):
        seen.append(obs)
        actions = forward.outputs({"observation": obs})["action"]
        obs, still = np.empty_like(obs), []
        for row, (i, action) in enumerate(zip(running, actions)):
            obs[row], reward, terminated, truncated, _ = steps[i](action)
            raw_returns[i] += reward
            returns[i] += min(max(reward + reward_offset, low), high)
            lengths[i] += 1
            if not (terminated or truncated) and lengths[i] < limits[i]:
                still.append(row)
        if not still:
            break
        if len(still) < len(running):  # rows (and parameters) of finished members drop out
            obs, running = obs[still], [running[row] for row in still]
            forward = PopulationPolicy(policy, flat[running])
    count, mean, m2 = batch_stats(torch.from_numpy(np.concatenate(seen)))
    return RolloutResult(
        torch.tensor(returns, dtype=torch.float64),
        torch.tensor(raw_returns, dtype=torch.float64),
        torch.tensor(lengths),
        time.process_time() - cpu,
        count,
        mean,
        m2,
    )


class _Rollouts:
    """A share of the population: its env copies and the policy, stepped in one process.

    Every backend's unit of work: used in this process, in each worker process, and as the Ray
    actor class (each actor builds its own env copies from ``env_factory``).
    """

    def __init__(
        self,
        policy: TensorDictModuleBase,
        env_factory: EnvFactory,
        num_envs: int,
        seed: int,
        options: dict[str, Any],
    ) -> None:
        self.policy, self.options = policy, options
        self.env = env_factory(num_envs=num_envs, seed=seed)
        self.envs = sub_envs(self.env)

    def run(
        self, state: dict[str, Any] | None, flat: torch.Tensor | np.ndarray, seeds: list[int]
    ) -> RolloutResult:
        """Roll out ``flat``'s members, after loading the policy ``state`` when one is given
        (tensors or NumPy arrays: the worker backends send arrays, which pickle fast)."""
        if state is not None:
            self.policy.load_state_dict({key: torch.as_tensor(v) for key, v in state.items()})
        flat = torch.as_tensor(flat)
        return rollout(self.policy, self.envs[: len(flat)], flat, seeds, **self.options)

    def close(self) -> None:
        if not self.env.is_closed:
            self.env.close()


# what a backend's roll_out returns: (member indices, their result) pairs covering the population
Shares = list[tuple[torch.Tensor, RolloutResult]]


class _InProcess:
    """The rollout backend that steps the whole population as one batch in this process."""

    def __init__(self, rollouts: _Rollouts, population: int) -> None:
        self.rollouts, self.members = rollouts, torch.arange(population)

    def roll_out(self, flat: torch.Tensor, seeds: torch.Tensor) -> Shares:
        return [(self.members, self.rollouts.run(None, flat, seeds.tolist()))]

    def close(self) -> None:
        self.rollouts.close()


class _Pool:
    """A rollout backend of workers that pull chunks of the population as they free up.

    Episode lengths are heavy-tailed, so each worker takes small chunks (about eight per worker
    and iteration) rather than owning a fixed share; one worker takes everything as one chunk.
    A chunk carries its members' parameters and episode seeds, and the policy's state (the
    normaliser changes every iteration) when it is the worker's first of the iteration, all as
    NumPy arrays; only its :class:`RolloutResult` comes back. Subclasses fill
    ``workers`` and say how a chunk is sent to a worker (:meth:`_submit`, returning a handle), how
    to wait until some handles are done (:meth:`_wait`) and how to collect one (:meth:`_collect`).
    """

    def __init__(self, policy: TensorDictModuleBase, population: int, workers: int) -> None:
        self.policy = policy
        self.chunk_size = (
            -(-population // (CHUNKS_PER_WORKER * workers)) if workers > 1 else population
        )
        self.chunks = list(torch.arange(population).split(self.chunk_size))
        self.workers: list[Any] = []

    def roll_out(self, flat: torch.Tensor, seeds: torch.Tensor) -> Shares:
        state = {key: value.numpy() for key, value in self.policy.state_dict().items()}
        flat_np = flat.numpy()
        pending = list(range(len(self.chunks)))
        results: list[Any] = [None] * len(self.chunks)
        busy: dict[Any, tuple[int, Any]] = {}  # handle -> (chunk index, worker)
        updated: set[int] = set()  # workers that have this iteration's policy state

        def give(worker: Any) -> None:
            if pending:
                index = pending.pop(0)
                members = self.chunks[index]
                fresh = id(worker) not in updated
                updated.add(id(worker))
                handle = self._submit(
                    worker,
                    state if fresh else None,
                    flat_np[members.numpy()],
                    seeds[members].tolist(),
                )
                busy[handle] = index, worker

        for worker in self.workers:
            give(worker)
        while busy:
            for handle in self._wait(list(busy)):
                index, worker = busy.pop(handle)
                results[index] = self._collect(handle)
                give(worker)
        return list(zip(self.chunks, results))

    def _submit(self, worker: Any, *message: Any) -> Any:
        raise NotImplementedError

    def _wait(self, handles: list[Any]) -> list[Any]:
        raise NotImplementedError

    def _collect(self, handle: Any) -> RolloutResult:
        raise NotImplementedError


def _worker(conn: Any, payload: bytes) -> None:
    # Ctrl-C reaches the whole process group: the parent checkpoints and stops the workers
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    torch.set_num_threads(1)
    rollouts = _Rollouts(*cloudpickle.loads(payload))
    conn.send(None)  # ready
    try:
        while (message := conn.recv()) is not None:
            conn.send(rollouts.run(*message))
    except (EOFError, BrokenPipeError):  # the parent exited (or was killed) without close()
        pass
    finally:
        rollouts.close()


def _start_method() -> str:
    """``fork`` where it is safe (a worker is up in milliseconds), else ``spawn``.

    ``spawn`` re-imports torch and TorchRL in every worker (seconds); ``fork`` cannot be used
    once CUDA is initialised in this process.
    """
    if "fork" in mp.get_all_start_methods() and not torch.cuda.is_initialized():
        return "fork"
    return "spawn"


class _Processes(_Pool):
    """Worker processes on this machine, one pipe each."""

    def __init__(
        self,
        policy: TensorDictModuleBase,
        env_factory: EnvFactory,
        population: int,
        workers: int,
        seed: int,
        options: dict[str, Any],
    ) -> None:
        super().__init__(policy, population, workers)
        ctx = mp.get_context(_start_method())
        self._procs: list[Any] = []
        for w in range(workers):
            parent, child = ctx.Pipe()
            payload = cloudpickle.dumps((policy, env_factory, self.chunk_size, seed + w, options))
            proc = ctx.Process(target=_worker, args=(child, payload), daemon=True)
            proc.start()
            child.close()
            self.workers.append(parent)
            self._procs.append(proc)
        for conn in self.workers:
            conn.recv()  # wait until every worker has built its envs

    def _submit(self, worker: Any, *message: Any) -> Any:
        worker.send(message)
        return worker

    def _wait(self, handles: list[Any]) -> list[Any]:
        return wait(handles)

    def _collect(self, handle: Any) -> RolloutResult:
        return handle.recv()

    def close(self) -> None:
        for conn in self.workers:
            conn.send(None)
            conn.close()
        for proc in self._procs:
            proc.join(timeout=10)
        self.workers, self._procs = [], []


RAY_INSTALL = 'pip install "rlpipe[ray]"'
RAY_PORT = 6379  # the port of a Ray head's GCS when an address names none


def _check_reachable(address: str) -> None:
    """Fail in one line, within seconds, when nothing listens at a ``host:port`` Ray address.

    ``ray.init`` would retry an unreachable address for minutes.
    """
    host, _, port = address.removeprefix("ray://").rpartition(":")
    if not host:
        host, port = port, str(RAY_PORT)
    check(port.isdigit(), f"Ray address {address!r} must be host:port, ray://host:port or auto")
    try:
        socket.create_connection((host, int(port)), timeout=5).close()
    except OSError as err:
        raise RlpipeError(
            f"cannot reach a Ray cluster at {address} ({err.strerror or err}); start one with "
            "`ray start --head` there, or fix the address"
        ) from err


def _connect_ray(address: str | None, num_cpus: int | None) -> bool:
    """Start Ray here (``address`` None, ``num_cpus`` CPUs) or join the cluster at ``address``.

    Returns whether this call initialised Ray (and so should shut it down); a Ray the caller
    already initialised is used as it is.
    """
    try:
        import ray
    except ImportError as err:
        raise RlpipeError(f"the Ray backend needs Ray; install it with: {RAY_INSTALL}") from err
    if ray.is_initialized():
        return False
    if address not in (None, "auto"):
        _check_reachable(address)
    try:
        ray.init(
            address=address,
            num_cpus=num_cpus if address is None else None,
            include_dashboard=False,
            log_to_driver=False,
        )
    except ConnectionError as err:
        message = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        raise RlpipeError(f"cannot connect to Ray at {address}: {message}") from err
    return True


class _RayActors(_Pool):
    """Ray actors of one CPU each, on this machine or anywhere in a Ray cluster.

    Each actor is a :class:`_Rollouts` holding its own env copies; ``workers`` 0 starts one per
    CPU of the cluster.
    """

    def __init__(
        self,
        policy: TensorDictModuleBase,
        env_factory: EnvFactory,
        population: int,
        workers: int,
        seed: int,
        options: dict[str, Any],
        *,
        address: str | None,
        num_cpus: int | None,
    ) -> None:
        self._owns_ray = _connect_ray(address, num_cpus)
        import ray

        self._ray = ray
        cpus = int(ray.cluster_resources().get("CPU", 0))
        workers = min(workers or cpus, population)
        super().__init__(policy, population, max(workers, 1))
        try:
            check(
                1 <= workers <= cpus,
                f"{workers} Ray workers need as many CPUs, but the Ray cluster has {cpus}",
            )
            actor = ray.remote(num_cpus=1)(_Rollouts)
            self.workers = [
                actor.remote(policy, env_factory, self.chunk_size, seed + w, options)
                for w in range(workers)
            ]
            # every actor has built its envs (ray.get raises the error of one that could not)
            ray.get([worker.__ray_ready__.remote() for worker in self.workers])
        except BaseException:
            self.close()
            raise

    def _submit(self, worker: Any, *message: Any) -> Any:
        return worker.run.remote(*message)

    def _wait(self, handles: list[Any]) -> list[Any]:
        return self._ray.wait(handles, num_returns=1)[0]

    def _collect(self, handle: Any) -> RolloutResult:
        return self._ray.get(handle)

    def close(self) -> None:
        for worker in self.workers:
            self._ray.kill(worker)
        self.workers = []
        if self._owns_ray and self._ray.is_initialized():
            self._ray.shutdown()


BACKENDS = ("local", "ray")


class ARSSearch:
    """Augmented random search on ``policy``'s parameters, one :meth:`step` per iteration.

    ``env_factory(num_envs=n, seed=s)`` builds the rollout envs (a TorchRL env over a gymnasium
    ``SyncVectorEnv``, such as ``functools.partial(rlpipe.make_env, env_cfg)``). ``policy`` maps
    ``"observation"`` to ``"action"``; a ``normalizer`` inside it is updated from the
    observations of every iteration's rollouts.

    Where the ``2N`` rollouts run is the ``backend``'s business; the update is the same:

    - ``"local"``: ``workers`` processes on this machine share the members in chunks
      (1: everything in this process, as one batch; 0: one process per core);
    - ``"ray"``: ``workers`` Ray actors (0: one per CPU of the cluster), on a Ray started here
      with ``ray_num_cpus`` CPUs (all when None) or on the cluster at ``ray_address``
      (``host:port``, ``ray://host:port`` or ``auto``).

    Each member's episode seed comes from the search's generator, so for the same ``seed`` every
    backend and worker count gives the same rollouts and the same θ, for envs whose
    ``reset(seed=...)`` fixes the episode (Box2D envs keep their world across resets, so there
    an episode also depends on what its env copy ran before).
    """

    def __init__(
        self,
        policy: TensorDictModuleBase,
        env_factory: EnvFactory,
        *,
        num_directions: int = 16,
        num_best: int | None = None,
        step_size: float = 0.02,
        noise: float = 0.03,
        max_steps: int = 1000,
        reward_offset: float = 0.0,
        reward_clip: float | None = None,
        normalizer: Normalizer | None = None,
        workers: int = 1,
        backend: str = "local",
        ray_address: str | None = None,
        ray_num_cpus: int | None = None,
        seed: int = 0,
    ) -> None:
        num_best = num_directions if num_best is None else num_best
        check(num_directions >= 1, f"num_directions must be >= 1, got {num_directions}")
        check(
            1 <= num_best <= num_directions,
            f"num_best ({num_best}) must be between 1 and num_directions ({num_directions})",
        )
        check(step_size > 0, f"step_size must be > 0, got {step_size}")
        check(noise > 0, f"noise must be > 0, got {noise}")
        check(max_steps >= 1, f"max_steps must be >= 1, got {max_steps}")
        check(workers >= 0, f"workers must be >= 0, got {workers}")
        check(backend in BACKENDS, f"backend must be one of {', '.join(BACKENDS)}; got {backend!r}")
        self.policy, self.normalizer = policy, normalizer
        self.num_directions, self.num_best = num_directions, num_best
        self.step_size, self.noise = step_size, noise
        self.generator = torch.Generator().manual_seed(seed)
        self.iterations = 0
        population = 2 * num_directions
        options = dict(max_steps=max_steps, reward_offset=reward_offset, reward_clip=reward_clip)
        args = (policy, env_factory, population)
        self._backend: _InProcess | _Pool
        if backend == "ray":
            self._backend = _RayActors(
                *args, workers, seed, options, address=ray_address, num_cpus=ray_num_cpus
            )
            return
        workers = min(workers or os.cpu_count() or 1, population)
        if workers == 1:
            self._backend = _InProcess(_Rollouts(*args, seed, options), population)
        else:
            self._backend = _Processes(*args, workers, seed, options)

    @property
    def theta(self) -> torch.Tensor:
        """The policy's current flat parameter vector (a copy)."""
        return parameters_to_vector(self.policy.parameters()).detach().clone()

    @theta.setter
    def theta(self, value: torch.Tensor) -> None:
        vector_to_parameters(value, self.policy.parameters())

    def step(self) -> dict[str, float | list[float]]:
        """One iteration: roll out θ ± ν·δ for N fresh directions, update θ and the normaliser.

        Returns the env's (unshaped) returns of the ``2N`` rollouts, their mean and max, the
        env steps taken, steps/s and the CPU seconds the rollouts took over all processes.
        """
        start = time.perf_counter()
        theta = self.theta
        deltas = torch.randn(self.num_directions, theta.numel(), generator=self.generator)
        flat = torch.cat([theta + self.noise * deltas, theta - self.noise * deltas])
        # each member's episode seed comes from the search's generator: the same results
        # whichever worker runs it
        seeds = torch.randint(2**31 - 1, (len(flat),), generator=self.generator)
        shares = self._backend.roll_out(flat, seeds)
        returns, raw, lengths = (torch.empty(len(flat), dtype=torch.float64) for _ in range(3))
        for members, result in shares:
            returns[members] = result.returns
            raw[members] = result.raw_returns
            lengths[members] = result.lengths.double()
        plus, minus = returns.float().chunk(2)
        self.theta = ars_update(theta, deltas, plus, minus, self.num_best, self.step_size)
        if self.normalizer is not None:
            for _, result in shares:
                self.normalizer.merge(result.obs_count, result.obs_mean, result.obs_m2)
        self.iterations += 1
        steps = int(lengths.sum())
        return {
            "return_mean": float(raw.mean()),
            "return_max": float(raw.max()),
            "env_steps": float(steps),
            "steps_per_second": steps / (time.perf_counter() - start),
            "rollout_cpu_seconds": sum(result.cpu_seconds for _, result in shares),
            "episode_return": raw.tolist(),  # one per perturbed rollout
            "episode_length": lengths.tolist(),
        }

    def close(self) -> None:
        """Stop the workers (or close the local envs)."""
        self._backend.close()
