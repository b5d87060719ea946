"""How finely worker processes share an ARS population: chunk sizes from measured costs.

With ``W`` workers each taking ``n`` chunks of the ``P`` members per iteration, a worker makes
about ``n`` policy calls per env step (one per chunk) and ``P / W`` member-steps of the env. Small
chunks balance heavy-tailed episode lengths, but every call costs about as much for one member
as for several (NumPy's per-call overhead; far more through ``torch.vmap`` for a module without a
NumPy form). So ``n`` is the most chunks (at most :data:`MAX_CHUNKS`) whose policy calls stay
within :data:`OVERHEAD` of the worker's env steps, from a policy call and an env step timed (the
fastest of a few rounds, so that a busy machine reads the costs, not its preemptions) when the
workers start.
"""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np
from tensordict.nn import TensorDictModuleBase
from torch.nn.utils import parameters_to_vector
from torchrl.envs import EnvBase

from rlpipe.algos.ars.population import PopulationPolicy
from rlpipe.envs import EnvFactory, envpool_env, sub_envs

__all__ = ["MAX_CHUNKS", "OVERHEAD", "chunks_per_worker", "measured_costs"]

MAX_CHUNKS = 8  # per worker and iteration
OVERHEAD = 0.25  # a worker's policy calls may cost this share of its env steps, at most
_ENV_STEPS, _CALLS, _ROUNDS = 64, 32, 4  # what is timed: the fastest of 4 rounds


def measured_costs(
    policy: TensorDictModuleBase, env_factory: EnvFactory, members: int, seed: int
) -> tuple[float, float]:
    """Seconds of one population call of ``policy`` on ``members`` members and of one env step
    (random actions on one copy from ``env_factory``)."""
    env = env_factory(num_envs=1, seed=seed)
    try:
        step, observation = _random_steps(env, seed)
        env_step = _per_call(step, _ENV_STEPS)
    finally:
        env.close()
    flat = parameters_to_vector(policy.parameters()).detach().expand(members, -1).clone()
    forward = PopulationPolicy(policy, flat)
    batch = np.repeat(np.asarray(observation, np.float32)[None], members, axis=0)
    forward.outputs({"observation": batch.copy()})  # first-call set-up off the clock
    return _per_call(lambda: forward.outputs({"observation": batch.copy()}), _CALLS), env_step


def _per_call(call: Callable[[], object], calls: int) -> float:
    """Seconds per call of ``call``: the fastest of :data:`_ROUNDS` rounds of ``calls`` calls (a
    round that another process preempted reads slow; the fastest is the cost itself)."""
    best = float("inf")
    for _ in range(_ROUNDS):
        start = time.perf_counter()
        for _ in range(calls):
            call()
        best = min(best, (time.perf_counter() - start) / calls)
    return best


def _random_steps(env: EnvBase, seed: int) -> tuple[Callable[[], np.ndarray], np.ndarray]:
    """A function that steps one copy of ``env``'s env with a random action (a new episode
    after the last) and returns the observation, and the first observation."""
    pooled = envpool_env(env)
    if pooled is not None:  # its pool resets a finished copy itself
        pool = pooled.pool
        space = pool.action_space
        space.seed(seed)
        return lambda: pool.step(np.asarray(space.sample())[None])[0][0], pool.reset()[0][0]
    inner = sub_envs(env)[0]
    inner.action_space.seed(seed)

    def step() -> np.ndarray:
        observation, _, terminated, truncated, _ = inner.step(inner.action_space.sample())
        return inner.reset()[0] if terminated or truncated else observation

    return step, inner.reset(seed=seed)[0]


def chunks_per_worker(
    policy: TensorDictModuleBase, env_factory: EnvFactory, population: int, workers: int, seed: int
) -> int:
    """Chunks per worker and iteration: the most, up to :data:`MAX_CHUNKS`, whose policy calls
    cost at most :data:`OVERHEAD` of the worker's env steps (at least one). On EnvPool, one:
    every chunk steps a fresh pool of its own, each step a hand-off to the pool's threads that
    costs as much for one copy as for many (BipedalWalker on 2 workers: 2 chunks a worker took
    6-18% longer an iteration than 1, 4 chunks 26%)."""
    if _pooled(env_factory, seed):
        return 1
    members = max(population // (MAX_CHUNKS * workers), 1)
    call, env_step = measured_costs(policy, env_factory, members, seed)
    affordable = OVERHEAD * population * env_step / (workers * call)
    return int(min(max(affordable, 1), MAX_CHUNKS))


def _pooled(env_factory: EnvFactory, seed: int) -> bool:
    """Whether ``env_factory`` builds its copies on EnvPool."""
    env = env_factory(num_envs=1, seed=seed)
    try:
        return envpool_env(env) is not None
    finally:
        env.close()
