"""Environment factory: gymnasium ids -> batched TorchRL envs with the standard transforms."""

from __future__ import annotations

from collections.abc import Callable

import gymnasium as gym
from gymnasium.envs.registration import load_env_creator
from gymnasium.vector import AutoresetMode
from torchrl.data import Categorical, OneHot
from torchrl.envs import (
    Compose,
    DoubleToFloat,
    EnvBase,
    GymWrapper,
    InitTracker,
    RewardSum,
    StepCounter,
    TransformedEnv,
)

from rlpipe.config import EnvConfig
from rlpipe.envs import cartpole  # noqa: F401  (registers rlpipe/CartPole*-v0 with gymnasium)
from rlpipe.errors import RlpipeError

__all__ = ["EnvFactory", "make_env", "observation_size", "is_discrete", "num_actions", "sub_envs"]

# What algorithms are built from: ``env_factory(**overrides) -> EnvBase``, e.g.
# ``functools.partial(rlpipe.make_env, EnvConfig(id="CartPole-v1"), seed=0)``. Called with no
# arguments for the training env; ARS also passes ``num_envs=``, ``seed=`` and
# ``vectorization="sync"`` (its rollouts step the gymnasium copies of a make_env env).
EnvFactory = Callable[..., EnvBase]


def make_env(
    cfg: EnvConfig,
    *,
    num_envs: int | None = None,
    seed: int | None = None,
    device: str = "cpu",
    render_mode: str | None = None,
    vectorization: str = "auto",
) -> TransformedEnv:
    """Build ``num_envs`` (default ``cfg.num_envs``) copies of ``cfg.id`` stepped as one batch.

    The copies live in a gymnasium vector env with autoreset DISABLED, wrapped by TorchRL's
    ``GymWrapper`` (partial resets go through gymnasium's ``reset_mask``), plus
    ``DoubleToFloat``, ``StepCounter``, ``InitTracker`` and ``RewardSum`` (``episode_reward``).
    Actions of discrete spaces are integer indices (``Categorical`` spec).

    ``vectorization``: ``"vector"`` is the id's own batched implementation (its gymnasium
    ``vector_entry_point``, which must support autoreset DISABLED, as rlpipe's CartPoles do and
    gymnasium's CartPole-v1 does not); ``"sync"`` a ``SyncVectorEnv`` of single envs (what
    :func:`sub_envs` needs); ``"auto"`` the former when the id has one and no ``render_mode``
    is asked for.
    """
    n = cfg.num_envs if num_envs is None else num_envs
    if n < 1:
        raise RlpipeError(f"num_envs must be >= 1, got {n}")
    if vectorization not in ("auto", "sync", "vector"):
        raise RlpipeError(f"vectorization must be auto, sync or vector, got {vectorization!r}")
    batched = vectorization != "sync" and _batched_entry_point(cfg.id)
    if vectorization == "vector" and not batched:
        raise RlpipeError(f"{cfg.id!r} has no vector implementation with autoreset disabled")
    kwargs = dict(cfg.kwargs)
    if cfg.max_episode_steps is not None:
        kwargs["max_episode_steps"] = cfg.max_episode_steps
    if render_mode is not None:
        kwargs["render_mode"] = render_mode
    try:
        if batched and (vectorization == "vector" or render_mode is None):
            venv = gym.make_vec(cfg.id, n, vectorization_mode="vector_entry_point", **kwargs)
        else:
            venv = gym.make_vec(
                cfg.id,
                num_envs=n,
                vectorization_mode="sync",
                vector_kwargs={"autoreset_mode": AutoresetMode.DISABLED},
                **kwargs,
            )
    except gym.error.Error as err:
        raise RlpipeError(
            f"cannot make gymnasium env {cfg.id!r}: {err} (pick a config from conf/env or "
            "set env.id to any registered gymnasium id)"
        ) from err
    except TypeError as err:
        raise RlpipeError(f"bad env.kwargs for {cfg.id!r}: {err}") from err
    except ModuleNotFoundError as err:  # env.id=module:Id, module not importable
        raise RlpipeError(
            f"env.id={cfg.id!r} names module {err.name or cfg.id.partition(':')[0]!r}, which "
            "cannot be imported; put the folder that holds it on PYTHONPATH "
            "(e.g. PYTHONPATH=. python -m rlpipe ...)"
        ) from err
    _check_spaces(cfg.id, venv)
    base = GymWrapper(venv, categorical_action_encoding=True, device=device)
    env = TransformedEnv(base, Compose(DoubleToFloat(), StepCounter(), InitTracker(), RewardSum()))
    if seed is not None:
        env.set_seed(seed)
    return env


SUPPORTED_SPACES = (
    gym.spaces.Box,
    gym.spaces.Discrete,
    gym.spaces.MultiDiscrete,
    gym.spaces.MultiBinary,
    gym.spaces.Dict,
)


def _check_spaces(env_id: str, venv: gym.vector.VectorEnv) -> None:
    """Refuse observation/action spaces TorchRL's wrapper cannot batch (Tuple, Sequence, ...)."""
    for what, space in (
        ("observation", venv.single_observation_space),
        ("action", venv.single_action_space),
    ):
        if not isinstance(space, SUPPORTED_SPACES):
            venv.close()
            raise RlpipeError(
                f"{env_id!r} has a {type(space).__name__} {what} space, which rlpipe cannot "
                "batch; wrap the env (e.g. gymnasium.wrappers.FlattenObservation) and register "
                "the wrapped id"
            )


def _batched_entry_point(env_id: str) -> bool:
    """Whether ``env_id`` is registered with a vector entry point that disables autoreset."""
    spec = gym.registry.get(env_id)
    entry = None if spec is None else spec.vector_entry_point
    if entry is None:
        return False
    creator = load_env_creator(entry) if isinstance(entry, str) else entry
    return getattr(creator, "metadata", {}).get("autoreset_mode") == AutoresetMode.DISABLED


def observation_size(env: EnvBase, key: str = "observation") -> int:
    """Length of the flat observation vector; a clear error for image or dict observations."""
    spec = env.observation_spec_unbatched
    if key not in spec.keys() or len(spec[key].shape) != 1:
        shapes = {k: tuple(v.shape) for k, v in spec.items(include_nested=True, leaves_only=True)}
        raise RlpipeError(
            f"this algorithm needs a flat vector observation under {key!r}; the env gives {shapes}"
        )
    return int(spec[key].shape[0])


def is_discrete(env: EnvBase) -> bool:
    """Whether the env's action space is a finite set of actions."""
    return isinstance(env.action_spec_unbatched, (Categorical, OneHot))


def num_actions(env: EnvBase) -> int:
    """Number of discrete actions (only for discrete action spaces)."""
    return int(env.action_spec_unbatched.space.n)


def _vector_env(env: EnvBase) -> gym.vector.VectorEnv:
    """The gymnasium vector env inside a :func:`make_env` env."""
    base = env.base_env if isinstance(env, TransformedEnv) else env
    # TorchRL's GymWrapper forwards attributes it lacks to the gymnasium env it wraps, whose
    # ``unwrapped`` is the vector env itself (under any vector wrappers)
    venv = base.unwrapped if isinstance(base, GymWrapper) else None
    if not isinstance(venv, gym.vector.VectorEnv):
        raise RlpipeError(f"expected an env built by rlpipe.make_env, got {env!r}")
    return venv


def sub_envs(env: EnvBase) -> list[gym.Env]:
    """The gymnasium copies inside a :func:`make_env` env (``vectorization="sync"``), for loops
    that step them directly."""
    venv = _vector_env(env)
    if not isinstance(venv, gym.vector.SyncVectorEnv):
        raise RlpipeError(
            f"expected an env built on a gymnasium SyncVectorEnv (rlpipe.make_env with "
            f"vectorization='sync'), got {venv!r}"
        )
    return list(venv.envs)
