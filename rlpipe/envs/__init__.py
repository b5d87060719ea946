"""Environment factory: gymnasium ids -> batched TorchRL envs with the standard transforms, on
the gymnasium or the EnvPool backend."""

from __future__ import annotations

from collections.abc import Callable
from typing import Protocol

import gymnasium as gym
import numpy as np
from torchrl.data import Categorical, OneHot
from torchrl.envs import (
    Compose,
    DoubleToFloat,
    EnvBase,
    InitTracker,
    RewardSum,
    StepCounter,
    TransformedEnv,
)

from rlpipe.config import EnvConfig
from rlpipe.envs.backends import backend_of
from rlpipe.envs.envpool_env import EnvPoolEnv
from rlpipe.envs.gymnasium_env import VectorCopies, dict_layout, gymnasium_env, vector_env
from rlpipe.envs.observations import Observation, image_transforms, observation_of
from rlpipe.errors import RlpipeError

__all__ = [
    "EnvCopies",
    "EnvFactory",
    "Observation",
    "env_copies",
    "envpool_env",
    "episode_limit",
    "is_discrete",
    "make_env",
    "num_actions",
    "observation_of",
    "observation_size",
    "sub_envs",
]

# What algorithms are built from: ``env_factory(**overrides) -> EnvBase``, e.g.
# ``functools.partial(rlpipe.make_env, EnvConfig(id="CartPole-v1"), seed=0)``. Called with no
# arguments for the training env; ARS also passes ``num_envs=``, ``seed=`` and
# ``vectorization="sync"`` (its rollouts step the gymnasium copies of a make_env env, or the
# EnvPool behind it, then also ``threads=``).
EnvFactory = Callable[..., EnvBase]

# what make_env puts over either backend, in this order
TRANSFORMS = (DoubleToFloat, StepCounter, InitTracker, RewardSum)
# the observation keys of a make_env env: the backend's, then StepCounter's, InitTracker's and
# RewardSum's
OBSERVATION_KEYS = {"observation", "step_count", "is_init", "episode_reward"}


class EnvCopies(Protocol):
    """A :func:`make_env` env's copies on NumPy arrays: its backend's resets and steps without
    TorchRL's per-step TensorDicts (:func:`env_copies`)."""

    def reset_copies(self, mask: np.ndarray | None = None) -> np.ndarray:
        """New episodes in the copies ``mask`` selects (None: all); every copy's observation."""
        ...

    def step_copies(self, action: np.ndarray) -> tuple[np.ndarray, ...]:
        """One step; every copy's observation, reward, terminated and truncated."""
        ...


def make_env(
    cfg: EnvConfig,
    *,
    num_envs: int | None = None,
    seed: int | None = None,
    device: str = "cpu",
    render_mode: str | None = None,
    vectorization: str = "auto",
    threads: int = 1,
) -> TransformedEnv:
    """Build ``num_envs`` (default ``cfg.num_envs``) copies of ``cfg.id`` stepped as one batch.

    ``cfg.backend`` picks the engine (:func:`rlpipe.envs.backends.backend_of`; rendering is
    always gymnasium's). gymnasium: the copies live in a gymnasium vector env with autoreset
    DISABLED, wrapped by TorchRL's ``GymWrapper`` (partial resets go through gymnasium's
    ``reset_mask``). EnvPool: an :class:`~rlpipe.envs.envpool_env.EnvPoolEnv` with
    ``threads`` worker threads, which behaves the same. Either way ``DoubleToFloat``,
    ``StepCounter``, ``InitTracker`` and ``RewardSum`` (``episode_reward``) follow, and
    actions of discrete spaces are integer indices (``Categorical`` spec). A Dict observation
    is one vector (:class:`~rlpipe.envs.observations.DictObservation`); images get TorchRL's
    image transforms and frame stacking after those
    (:func:`~rlpipe.envs.observations.image_transforms`; such envs leave the lean collection
    path for TorchRL's collector).

    ``vectorization`` (gymnasium only): ``"vector"`` is the id's own batched implementation
    (its gymnasium ``vector_entry_point``, which must support autoreset DISABLED, as rlpipe's
    CartPoles do and gymnasium's CartPole-v1 does not); ``"sync"`` a ``SyncVectorEnv`` of
    single envs (what :func:`sub_envs` needs); ``"auto"`` the former when the id has one and no
    ``render_mode`` is asked for.
    """
    n = cfg.num_envs if num_envs is None else num_envs
    if n < 1:
        raise RlpipeError(f"num_envs must be >= 1, got {n}")
    if vectorization not in ("auto", "sync", "vector"):
        raise RlpipeError(f"vectorization must be auto, sync or vector, got {vectorization!r}")
    if backend_of(cfg, render_mode) == "envpool":
        base = EnvPoolEnv(cfg, n, seed=seed, threads=threads, device=device)
    else:
        base = gymnasium_env(
            cfg, n, device=device, render_mode=render_mode, vectorization=vectorization
        )
    spec = base.observation_spec_unbatched.get("observation", None)
    extra = [] if spec is None else image_transforms(cfg, spec)
    env = TransformedEnv(base, Compose(*(transform() for transform in TRANSFORMS), *extra))
    if cfg.dict_obs == "keys":  # what the networks' per-key encoders read
        env.observation_layout = dict_layout(base)
    if seed is not None and not isinstance(base, EnvPoolEnv):  # EnvPool's is set at build
        env.set_seed(seed)
    return env


def env_copies(env: EnvBase) -> EnvCopies | None:
    """The copies of a :func:`make_env` env on arrays: a gymnasium env's
    :class:`~rlpipe.envs.gymnasium_env.VectorCopies`, or the
    :class:`~rlpipe.envs.envpool_env.EnvPoolEnv` itself; None for any other env (other
    transforms, keys or backends), which only TorchRL knows how to step."""
    if not isinstance(env, TransformedEnv) or env.batch_dims != 1:
        return None
    transforms = list(env.transform) if isinstance(env.transform, Compose) else [env.transform]
    if tuple(type(t) for t in transforms) != TRANSFORMS or transforms[1].max_steps is not None:
        return None
    keys = set(env.observation_spec.keys(True, True)), env.reward_keys, set(env.done_keys)
    if keys != (OBSERVATION_KEYS, ["reward"], {"done", "terminated", "truncated"}):
        return None
    base = env.base_env
    return base if isinstance(base, EnvPoolEnv) else VectorCopies.of(base)


def observation_size(env: EnvBase, algo: str = "this algorithm") -> int:
    """Length of the flat observation vector; one line naming what to do for an image (or any
    other non-vector) observation, ``algo`` naming the algorithm that refuses it."""
    observation = observation_of(env)
    if not observation.flat:
        what = "image" if observation.image else f"shape {observation.shape}"
        raise RlpipeError(
            f"{algo} takes flat vector observations, but this env observes {what}: use algo=dqn, "
            "algo=ppo or algo=sac (they encode images and Dict keys), or flatten the "
            "observation (gymnasium.wrappers.FlattenObservation; env.dict_obs=flatten)"
        )
    return observation.size


def is_discrete(env: EnvBase) -> bool:
    """Whether the env's action space is a finite set of actions."""
    return isinstance(env.action_spec_unbatched, (Categorical, OneHot))


def num_actions(env: EnvBase) -> int:
    """Number of discrete actions (only for discrete action spaces)."""
    return int(env.action_spec_unbatched.space.n)


def envpool_env(env: EnvBase) -> EnvPoolEnv | None:
    """The :class:`~rlpipe.envs.envpool_env.EnvPoolEnv` inside a :func:`make_env` env built on
    the EnvPool backend (None for any other env)."""
    base = env.base_env if isinstance(env, TransformedEnv) else env
    return base if isinstance(base, EnvPoolEnv) else None


def episode_limit(env: EnvBase) -> int | None:
    """The time limit of a :func:`make_env` env's episodes (None: none), on either backend."""
    pool = envpool_env(env)
    if pool is not None:
        return pool.cfg.max_episode_steps or gym.spec(pool.cfg.id).max_episode_steps
    return sub_envs(env)[0].spec.max_episode_steps


def sub_envs(env: EnvBase) -> list[gym.Env]:
    """The gymnasium copies inside a :func:`make_env` env (``vectorization="sync"``), for loops
    that step them directly."""
    venv = vector_env(env.base_env if isinstance(env, TransformedEnv) else env)
    if not isinstance(venv, gym.vector.SyncVectorEnv):
        raise RlpipeError(
            f"expected an env built on a gymnasium SyncVectorEnv (rlpipe.make_env with "
            f"env.backend=gymnasium and vectorization='sync'), got {venv or env!r}"
        )
    return list(venv.envs)
