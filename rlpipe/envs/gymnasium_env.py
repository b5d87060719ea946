"""The gymnasium backend: a gymnasium vector env with autoreset disabled under TorchRL's
``GymWrapper`` (what :func:`rlpipe.make_env` builds with ``env.backend=gymnasium``)."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
from gymnasium.envs.registration import load_env_creator
from gymnasium.vector import AutoresetMode
from torchrl.envs import GymWrapper

from rlpipe.config import EnvConfig
from rlpipe.envs import (
    cartpole,  # noqa: F401  (registers rlpipe/CartPole*-v0 with gymnasium)
    minigrid,  # noqa: F401  (registers rlpipe/MiniGrid-*-Pixels-v0)
)
from rlpipe.envs.observations import KeySlice, dict_observation
from rlpipe.errors import RlpipeError

__all__ = ["SUPPORTED_SPACES", "VectorCopies", "dict_layout", "gymnasium_env", "vector_env"]

SUPPORTED_SPACES = (
    gym.spaces.Box,
    gym.spaces.Discrete,
    gym.spaces.MultiDiscrete,
    gym.spaces.MultiBinary,
)


def gymnasium_env(
    cfg: EnvConfig,
    num_envs: int,
    *,
    device: str = "cpu",
    render_mode: str | None = None,
    vectorization: str = "auto",
) -> GymWrapper:
    """``num_envs`` copies of ``cfg.id`` in a gymnasium vector env with autoreset DISABLED,
    wrapped by TorchRL's ``GymWrapper`` (partial resets go through gymnasium's ``reset_mask``;
    discrete actions are integer indices; a Dict observation becomes one vector,
    :class:`~rlpipe.envs.observations.DictObservation`). ``vectorization``: see
    :func:`rlpipe.make_env`."""
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
            venv = gym.make_vec(cfg.id, num_envs, vectorization_mode="vector_entry_point", **kwargs)
        else:
            venv = gym.make_vec(
                cfg.id,
                num_envs=num_envs,
                vectorization_mode="sync",
                vector_kwargs={"autoreset_mode": AutoresetMode.DISABLED},
                wrappers=[dict_observation],  # a Dict observation as one vector
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
    return GymWrapper(venv, categorical_action_encoding=True, device=device)


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


def vector_env(base: object) -> gym.vector.VectorEnv | None:
    """The gymnasium vector env inside a :func:`gymnasium_env` env (None for any other env)."""
    # TorchRL's GymWrapper forwards attributes it lacks to the gymnasium env it wraps, whose
    # ``unwrapped`` is the vector env itself (under any vector wrappers)
    venv = base.unwrapped if isinstance(base, GymWrapper) else None
    return venv if isinstance(venv, gym.vector.VectorEnv) else None


def dict_layout(base: object) -> tuple[KeySlice, ...] | None:
    """Where each key of a Dict observation lies in a :func:`gymnasium_env` env's vector (None:
    its observations are no Dict)."""
    venv = vector_env(base)
    envs = venv.envs if isinstance(venv, gym.vector.SyncVectorEnv) else [None]
    return getattr(envs[0], "layout", None)


class VectorCopies:
    """The copies of a :func:`gymnasium_env` env stepped on NumPy arrays, as TorchRL's
    ``GymWrapper`` steps them: the same calls on the same vector env (what rlpipe's lean
    collection, :mod:`rlpipe.algos.collectors`, steps), so the same seeds give the same
    episodes."""

    def __init__(self, base: GymWrapper) -> None:
        self.venv = base._env  # what GymWrapper steps (it keeps it private)

    @classmethod
    def of(cls, base: object) -> VectorCopies | None:
        """The copies of ``base`` when it is a :func:`gymnasium_env` env (autoreset disabled)."""
        if type(base) is not GymWrapper:
            return None
        mode = getattr(base._env, "autoreset_mode", None)
        return cls(base) if mode == AutoresetMode.DISABLED else None

    def reset_copies(self, mask: np.ndarray | None = None) -> np.ndarray:
        """Start new episodes in the copies ``mask`` selects (None: all of them, as a full reset
        does); the observations of every copy."""
        if mask is None:
            obs, _ = self.venv.reset()
        else:
            obs, _ = self.venv.reset(options={"reset_mask": mask})
        return obs

    def step_copies(self, action: np.ndarray) -> tuple[np.ndarray, ...]:
        """One step of every copy; their observations, rewards, terminated and truncated."""
        obs, reward, terminated, truncated, _ = self.venv.step(action)
        return obs, reward, terminated, truncated
