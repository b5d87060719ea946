"""Population rollouts: one episode per member, stepping the gymnasium copies or an EnvPool
directly.

A finished copy is not stepped again, and TorchRL's per-step overhead is skipped: the loop
steps the envs under a :func:`rlpipe.make_env` env (the gymnasium copies under their
bookkeeping wrappers, or a fresh EnvPool per population) and calls the policy as a
:class:`PopulationPolicy` on plain NumPy arrays.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, fields
from typing import Any

import gymnasium as gym
import numpy as np
import torch
from tensordict.nn import TensorDictModuleBase

from rlpipe.algos.ars.population import PopulationPolicy
from rlpipe.envs import EnvFactory, envpool_env, sub_envs
from rlpipe.envs.envpool_env import EnvPoolEnv
from rlpipe.normalizer import batch_stats

__all__ = ["RolloutResult", "Rollouts", "pool_rollout", "rollout"]


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
    bound_penalty: float = 0.0,
) -> RolloutResult:
    """One episode per member: ``envs[i]``, reset with ``seeds[i]``, runs parameters ``flat[i]``.

    Every step calls the policy once on the observations of the members still running (a
    :class:`PopulationPolicy` on a plain dict of NumPy arrays: a TensorDict per step would
    cost more than the policy itself); finished copies are not stepped again. An episode ends
    at ``max_steps`` or the env's own time limit, whichever comes first.
    Training rewards are ``clip(r + reward_offset, -reward_clip, reward_clip)``, less
    ``bound_penalty × Σ|policy_output - action|`` a step (raw outputs past the action bounds).
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
    seen, penalties = [], np.zeros(size)
    for _ in range(max_steps):
        seen.append(obs)
        actions = _act(forward, obs, running, penalties, bound_penalty)
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
    return _result(np.subtract(returns, penalties).tolist(), raw_returns, lengths, cpu, seen)


@torch.inference_mode()
def pool_rollout(
    policy: TensorDictModuleBase,
    env: EnvPoolEnv,
    flat: torch.Tensor,
    seeds: Sequence[int],
    *,
    max_steps: int,
    reward_offset: float = 0.0,
    reward_clip: float | None = None,
    bound_penalty: float = 0.0,
) -> RolloutResult:
    """:func:`rollout` on EnvPool: one episode per member on a fresh pool of ``len(flat)``
    copies of ``env``'s env (:meth:`EnvPoolEnv.make_pool`), copy ``i`` seeded ``seeds[i]``.

    Each step calls the policy once on the members still running and steps only their copies
    (``env_id=``), so a finished copy never reaches EnvPool's autoreset. EnvPool cannot reseed
    an env at reset, hence the fresh pool (about 10 ms for 64 BipedalWalkers): an episode is
    then decided by its seed and parameters alone.
    """
    cpu = time.process_time()
    size = len(flat)
    pool = env.make_pool(seeds)
    try:
        obs, info = pool.reset()
        obs = obs[np.argsort(info["env_id"])].astype(np.float32)
        returns, raw_returns = np.zeros(size), np.zeros(size)
        lengths = np.zeros(size, np.int64)
        low, high = (-math.inf, math.inf) if reward_clip is None else (-reward_clip, reward_clip)
        running = pool.all_env_ids  # the member of each row of obs, ascending
        forward = PopulationPolicy(policy, flat)
        seen, penalties = [], np.zeros(size)
        for _ in range(max_steps):
            seen.append(obs)
            actions = _act(forward, obs, running, penalties, bound_penalty)
            step = pool.step(actions, env_id=running)
            order = np.argsort(step[4]["env_id"])  # the rows in member order
            obs, reward, terminated, truncated = (part[order] for part in step[:4])
            raw_returns[running] += reward
            returns[running] += np.clip(reward + reward_offset, low, high)
            lengths[running] += 1
            still = ~(terminated | truncated) & (lengths[running] < max_steps)
            if not still.any():
                break
            if not still.all():  # rows (and parameters) of finished members drop out
                obs, running = obs[still], running[still]
                forward = PopulationPolicy(policy, flat[running])
    finally:
        pool.close()
    returns -= penalties
    return _result(returns.tolist(), raw_returns.tolist(), lengths.tolist(), cpu, seen)


def _act(
    forward: PopulationPolicy,
    obs: np.ndarray,
    running: Any,
    penalties: np.ndarray,
    bound_penalty: float,
) -> np.ndarray:
    """The actions of the ``running`` members for ``obs``; with a ``bound_penalty``, each one's
    ``bound_penalty × Σ|policy_output - action|`` is added to its ``penalties``."""
    outputs = forward.outputs({"observation": obs})
    if bound_penalty:
        excess = np.abs(outputs["policy_output"] - outputs["action"]).sum(-1)
        penalties[running] += bound_penalty * excess
    return outputs["action"]


def _result(
    returns: list[float], raw_returns: list[float], lengths: list[int], cpu: float, seen: list
) -> RolloutResult:
    """A rollout's :class:`RolloutResult`: ``cpu`` is the process time it started at, ``seen``
    the observations its policy acted on."""
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


@dataclass
class RolloutResult:
    """Per-member returns of one population rollout and the statistics of what it observed."""

    returns: torch.Tensor  # shaped (offset, clipped, penalised) returns, what the update ranks
    raw_returns: torch.Tensor  # the env's own returns
    lengths: torch.Tensor
    cpu_seconds: float  # CPU time of the process that rolled out
    obs_count: int
    obs_mean: torch.Tensor
    obs_m2: torch.Tensor

    def __reduce__(self) -> tuple[Any, tuple[Any, ...]]:
        # pickled as NumPy arrays: on a multiprocessing pipe torch's own reducer would move every
        # tensor through a new shared-memory file
        return _rollout_result, tuple(_numpy(getattr(self, f.name)) for f in fields(self))


def _numpy(value: Any) -> Any:
    return value.numpy() if isinstance(value, torch.Tensor) else value


def _rollout_result(*values: Any) -> RolloutResult:
    return RolloutResult(*map(_tensor, values))


def _tensor(value: Any) -> Any:
    if not isinstance(value, np.ndarray):
        return value
    # arrays from Ray's object store are read-only: copied, else torch warns
    return torch.as_tensor(value if value.flags.writeable else value.copy())


# wrappers that only check call order or count steps: a rollout steps the env inside them
# and ends the episode at the time limit itself
_BOOKKEEPING_WRAPPERS = (
    gym.wrappers.TimeLimit,
    gym.wrappers.OrderEnforcing,
    gym.wrappers.PassiveEnvChecker,
)


def _inner_env(env: gym.Env) -> tuple[gym.Env, int | None]:
    """The env under ``env``'s bookkeeping wrappers and its time limit (when only those wrap it).

    Every wrapper layer adds a Python call per step; an env with any other wrapper is stepped
    as is.
    """
    limit, inner = None, env
    while isinstance(inner, _BOOKKEEPING_WRAPPERS):
        if isinstance(inner, gym.wrappers.TimeLimit):
            limit = inner._max_episode_steps
        inner = inner.env
    return (inner, limit) if not isinstance(inner, gym.Wrapper) else (env, None)


class Rollouts:
    """A share of the population: its env copies and the policy, stepped in one process.

    Every backend's unit of work (:mod:`rlpipe.algos.ars.backends`): used in this process, in
    each worker process, and as the Ray actor class (each actor builds its own env copies from
    ``env_factory(num_envs=..., seed=...)``). An env on the EnvPool backend rolls out with
    :func:`pool_rollout` (its own pool is the template of each population's fresh one).
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
        self.pool = envpool_env(self.env)
        self.envs = sub_envs(self.env) if self.pool is None else []

    def run(
        self,
        state: dict[str, Any] | None,
        flat: torch.Tensor | np.ndarray,
        seeds: list[int],
        reward_clip: float | None = None,
    ) -> RolloutResult:
        """Roll out ``flat``'s members, after loading the policy ``state`` when one is given
        (tensors or NumPy arrays: the worker backends send arrays, which pickle fast), training
        rewards clipped to ``[-reward_clip, reward_clip]`` (None: not clipped)."""
        if state is not None:
            self.policy.load_state_dict({key: torch.as_tensor(v) for key, v in state.items()})
        flat, options = torch.as_tensor(flat), {**self.options, "reward_clip": reward_clip}
        if self.pool is not None:
            return pool_rollout(self.policy, self.pool, flat, seeds, **options)
        return rollout(self.policy, self.envs[: len(flat)], flat, seeds, **options)

    def close(self) -> None:
        if not self.env.is_closed:
            self.env.close()
