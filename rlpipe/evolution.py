"""Augmented random search (ARS) for any TensorDictModule policy, usable without the runner.

The search evolves the policy's flat parameter vector θ: each iteration samples ``N`` Gaussian
directions δ, rolls out the ``2N`` perturbed policies θ ± ν·δ as one population (one batched
policy call per step over a population dimension), keeps the ``b`` directions with the best
``max(r+, r-)`` and moves θ by ``α / (b·σ) · Σ (r+ - r-)·δ``, σ being the std of the selected
returns (Mania et al., 2018). A :class:`Normalizer` inside the policy (ARS V2) standardises
observations with running statistics that are updated after each iteration and frozen in between.

Rollouts step the gymnasium copies under a :func:`rlpipe.make_env` env directly: a finished copy
is not stepped again, and TorchRL's per-step overhead (a third of BipedalWalker's physics) is
skipped. With ``workers > 1`` the population is cut into chunks that worker processes pull as they
free up (episode lengths vary a lot); each rolls out its chunk's members as one batch to the end
and sends back only returns and observation statistics.
"""

from __future__ import annotations

import multiprocessing as mp
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from functools import partial
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
from rlpipe.errors import check

__all__ = ["ARSSearch", "Normalizer", "PopulationPolicy", "ars_update", "batched_call", "rollout"]

# (num_envs=..., seed=...) -> a TorchRL env over a gymnasium SyncVectorEnv, e.g.
# functools.partial(rlpipe.make_env, EnvConfig(id="BipedalWalker-v3"))
EnvFactory = Callable[..., EnvBase]
CHUNKS_PER_WORKER = 4


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


def batched_call(module: nn.Module, params: dict[str, torch.Tensor]) -> Callable[..., Any]:
    """``module`` as a function of a population batch, member ``i`` using ``params[name][i]``.

    ``nn.Linear`` layers become one batched matmul and ``nn.Sequential`` chains (TorchRL's MLP)
    are followed layer by layer, parameter-free layers (activations) applied to the whole
    batch; any other module goes through ``torch.vmap`` over ``functional_call``.
    """
    if isinstance(module, nn.Linear):
        weight = params["weight"].transpose(1, 2)
        bias = params.get("bias")

        def linear(x: torch.Tensor) -> torch.Tensor:
            if bias is None:
                return torch.bmm(x.unsqueeze(1), weight).squeeze(1)
            return torch.baddbmm(bias.unsqueeze(1), x.unsqueeze(1), weight).squeeze(1)

        return linear
    if isinstance(module, nn.Sequential):
        layers = []
        for name, layer in module.named_children():
            prefix = f"{name}."
            own = {k[len(prefix) :]: v for k, v in params.items() if k.startswith(prefix)}
            layers.append(batched_call(layer, own) if own else layer)

        def chain(x: torch.Tensor) -> torch.Tensor:
            for layer in layers:
                x = layer(x)
            return x

        return chain
    vmapped = torch.vmap(lambda p, *args: torch.func.functional_call(module, p, args))
    return partial(vmapped, params)


class PopulationPolicy:
    """A TensorDictModule policy evaluated for a population of flat parameter vectors at once.

    Row ``i`` of ``flat`` (``[P, n]``, the layout of ``parameters_to_vector``) holds member
    ``i``'s parameters. The policy is a ``TensorDictModule`` or a ``TensorDictSequential`` of
    them (one output key each); calling this on a TensorDict whose batch is the population runs
    them in order, parameter-free ones (normaliser, action head) once on the whole batch and the
    others through :func:`batched_call`.
    """

    def __init__(self, policy: TensorDictModuleBase, flat: torch.Tensor) -> None:
        modules = policy.module if isinstance(policy, TensorDictSequential) else [policy]
        self.steps: list[tuple[Callable[..., Any], list[Any], Any]] = []
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
            call = batched_call(module.module, params) if params else module.module
            self.steps.append((call, module.in_keys, module.out_keys[0]))
        check(offset == flat.shape[-1], "flat parameters do not match the policy's parameters")

    def __call__(self, td: TensorDictBase) -> TensorDictBase:
        return td.update(self.outputs(dict(td.items(include_nested=True, leaves_only=True))))

    def outputs(self, values: dict[Any, torch.Tensor]) -> dict[Any, torch.Tensor]:
        """The same on a plain dict of tensors (the rollout's per-step fast path)."""
        for call, in_keys, out_key in self.steps:
            values[out_key] = call(*(values[key] for key in in_keys))
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


@torch.no_grad()
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

    Every step calls the policy once for the members still running (a :class:`PopulationPolicy`
    on their observations, a plain dict of tensors: building a TensorDict per step would cost
    about a tenth of a BipedalWalker step); finished copies are not stepped again.
    Training rewards are ``clip(r + reward_offset, -reward_clip, reward_clip)``.
    """
    cpu = time.process_time()
    size = len(envs)
    seeds = [None] * len(envs) if seeds is None else seeds
    obs = np.stack([env.reset(seed=seed)[0] for env, seed in zip(envs, seeds)])
    obs = obs.astype(np.float32)
    returns, raw_returns, lengths = [0.0] * size, [0.0] * size, [0] * size
    running = list(range(size))  # members still in their episode; the policy sees only them
    forward = PopulationPolicy(policy, flat)
    seen = []
    for _ in range(max_steps):
        observation = torch.from_numpy(obs[running])
        seen.append(observation)
        actions = forward.outputs({"observation": observation})["action"].numpy()
        still = []
        for i, action in zip(running, actions):
            obs[i], reward, terminated, truncated, _ = envs[i].step(action)
            raw_returns[i] += reward
            reward += reward_offset
            if reward_clip is not None:
                reward = min(max(reward, -reward_clip), reward_clip)
            returns[i] += reward
            lengths[i] += 1
            if not (terminated or truncated):
                still.append(i)
        if not still:
            break
        if len(still) < len(running):
            running = still
            forward = PopulationPolicy(policy, flat[running])
    count, mean, m2 = batch_stats(torch.cat(seen))
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
    """A share of the population: its env copies and the policy, stepped in this process."""

    def __init__(self, policy: TensorDictModuleBase, env: EnvBase, options: dict[str, Any]):
        self.policy, self.env, self.envs, self.options = policy, env, sub_envs(env), options

    def run(
        self, state: dict[str, torch.Tensor] | None, flat: torch.Tensor, seeds: list[int]
    ) -> RolloutResult:
        if state is not None:
            self.policy.load_state_dict(state)
        return rollout(self.policy, self.envs[: len(flat)], flat, seeds, **self.options)


def _worker(conn: Any, payload: bytes) -> None:
    torch.set_num_threads(1)
    policy, env_factory, num_envs, seed, options = cloudpickle.loads(payload)
    rollouts = _Rollouts(policy, env_factory(num_envs=num_envs, seed=seed), options)
    conn.send(None)  # ready
    try:
        while (message := conn.recv()) is not None:
            conn.send(rollouts.run(*message))
    except EOFError:  # the parent exited without close()
        pass
    finally:
        rollouts.env.close()


class ARSSearch:
    """Augmented random search on ``policy``'s parameters, one :meth:`step` per iteration.

    ``env_factory(num_envs=n, seed=s)`` builds the rollout envs (a TorchRL env over a gymnasium
    ``SyncVectorEnv``, such as ``functools.partial(rlpipe.make_env, env_cfg)``). ``policy`` maps
    ``"observation"`` to ``"action"``; a ``normalizer`` inside it is updated from the
    observations of every iteration's rollouts. ``workers`` processes share the ``2N``
    members, in chunks (1: everything in this process, as one batch).
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
        check(workers >= 1, f"workers must be >= 1, got {workers}")
        self.policy, self.normalizer = policy, normalizer
        self.num_directions, self.num_best = num_directions, num_best
        self.step_size, self.noise = step_size, noise
        self.generator = torch.Generator().manual_seed(seed)
        self.iterations = 0
        population = 2 * num_directions
        workers = min(workers, population)
        # Episode lengths are heavy-tailed, so workers pull small chunks of members as they free
        # up instead of owning a fixed half: about four chunks per worker.
        chunk = -(-population // (CHUNKS_PER_WORKER * workers)) if workers > 1 else population
        self._chunks = list(torch.arange(population).split(chunk))
        options = dict(max_steps=max_steps, reward_offset=reward_offset, reward_clip=reward_clip)
        self._local: _Rollouts | None = None
        self._conns: list[Any] = []
        self._procs: list[Any] = []
        if workers == 1:
            env = env_factory(num_envs=population, seed=seed)
            self._local = _Rollouts(policy, env, options)
            return
        ctx = mp.get_context("spawn")
        for w in range(workers):
            parent, child = ctx.Pipe()
            payload = cloudpickle.dumps((policy, env_factory, chunk, seed + w, options))
            proc = ctx.Process(target=_worker, args=(child, payload), daemon=True)
            proc.start()
            child.close()
            self._conns.append(parent)
            self._procs.append(proc)
        for conn in self._conns:
            conn.recv()  # wait until every worker has built its envs

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
        results = self._roll_out(flat, seeds)
        returns, raw, lengths = (torch.empty(len(flat), dtype=torch.float64) for _ in range(3))
        for share, result in zip(self._chunks, results):
            returns[share] = result.returns
            raw[share] = result.raw_returns
            lengths[share] = result.lengths.double()
        plus, minus = returns.float().chunk(2)
        self.theta = ars_update(theta, deltas, plus, minus, self.num_best, self.step_size)
        if self.normalizer is not None:
            for result in results:
                self.normalizer.merge(result.obs_count, result.obs_mean, result.obs_m2)
        self.iterations += 1
        steps = int(lengths.sum())
        return {
            "return_mean": float(raw.mean()),
            "return_max": float(raw.max()),
            "env_steps": float(steps),
            "steps_per_second": steps / (time.perf_counter() - start),
            "rollout_cpu_seconds": sum(result.cpu_seconds for result in results),
            "episode_return": raw.tolist(),  # one per perturbed rollout
            "episode_length": lengths.tolist(),
        }

    def _roll_out(self, flat: torch.Tensor, seeds: torch.Tensor) -> list[RolloutResult]:
        if self._local is not None:
            return [self._local.run(None, flat, seeds.tolist())]
        state = self.policy.state_dict()
        pending = list(range(len(self._chunks)))
        results: list[Any] = [None] * len(self._chunks)
        busy: dict[Any, int] = {}

        def give(conn: Any) -> None:
            if pending:
                busy[conn] = pending.pop(0)
                chunk = self._chunks[busy[conn]]
                conn.send((state, flat[chunk], seeds[chunk].tolist()))

        for conn in self._conns:
            give(conn)
        while busy:
            for conn in wait(list(busy)):
                results[busy.pop(conn)] = conn.recv()
                give(conn)
        return results

    def close(self) -> None:
        """Stop the worker processes (or close the local envs)."""
        if self._local is not None and not self._local.env.is_closed:
            self._local.env.close()
        for conn in self._conns:
            conn.send(None)
            conn.close()
        for proc in self._procs:
            proc.join(timeout=10)
        self._conns, self._procs = [], []
