"""The EnvPool backend: EnvPool's C++ vectorised envs as a TorchRL env that steps exactly like
the gymnasium backend's (no autoreset filler, gymnasium's specs, seeds at build time)."""

from __future__ import annotations

import warnings
from typing import Any

import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.envs import EnvBase

from rlpipe.config import EnvConfig
from rlpipe.envs.backends import envpool_task
from rlpipe.envs.gymnasium_env import gymnasium_env

__all__ = ["EnvPoolEnv", "SEED_LIMIT"]

SEED_LIMIT = 2**31  # EnvPool's seeds are int32: copy i's seed is (seed + i) mod this


class EnvPoolEnv(EnvBase):
    """``num_envs`` copies of ``cfg.id`` in one EnvPool, seen as :func:`rlpipe.make_env`'s
    gymnasium env is seen: the same keys, specs and episodes' semantics.

    Written on ``EnvBase`` rather than as a subclass of TorchRL's ``MultiThreadedEnv``
    (torchrl 0.14.1), of which it would keep only the constructor: that wrapper takes its specs
    from EnvPool's declared spaces through the old ``gym`` package (and BipedalWalker's
    declared observation space is wrong: low 0, high 3.4e38), imports ``treevalue`` to reset,
    ignores ``set_seed``, and its ``step_and_maybe_reset`` relies on EnvPool's NEXT_STEP
    autoreset, whose next step ignores the action and returns the reset observation with
    reward 0 and no done flag: a filler transition that would reach replay buffers, returns
    and step counts.

    Here no filler exists: a step steps only the live copies (EnvPool's ``env_id=``), and a
    finished copy starts its next episode through EnvPool's own reset of its id (TorchRL's
    ``_reset`` mask, as ``step_and_maybe_reset``, collectors and rollouts send it). A finished
    copy stepped without a reset stays as it ended (its last observation, reward 0, done).
    Specs are gymnasium's declaration of the same id (one gymnasium copy is built for them).
    Copy ``i`` is seeded ``seed + i`` when the pool is built; :meth:`set_seed` rebuilds it.
    ``threads``: EnvPool's worker threads (at most one per copy). :meth:`reset_copies` and
    :meth:`step_copies` are the same resets and steps on NumPy arrays (what rlpipe's lean
    collection, :mod:`rlpipe.algos.collectors`, steps).
    """

    def __init__(
        self,
        cfg: EnvConfig,
        num_envs: int,
        *,
        seed: int | None = None,
        threads: int = 1,
        device: str | torch.device = "cpu",
    ) -> None:
        super().__init__(device=device, batch_size=[num_envs])
        self.cfg, self.task = cfg, envpool_task(cfg)
        self.threads = max(min(threads, num_envs), 1)
        probe = gymnasium_env(cfg, 1, vectorization="sync")
        try:
            for name in ("observation", "action", "reward", "done"):
                spec = getattr(probe, f"full_{name}_spec_unbatched")
                setattr(self, f"full_{name}_spec", spec.expand(num_envs).to(self.device))
        finally:
            probe.close()
        n = num_envs
        self._obs = np.zeros(self.observation_spec["observation"].shape, np.float32)
        self._terminated, self._truncated = np.zeros(n, bool), np.zeros(n, bool)
        self._live = np.zeros(n, bool)  # copies in an episode: the only ones a step steps
        self.pool: Any = None
        self._set_seed(seed)
        self.is_closed = False

    def make_pool(self, seeds: list[int] | np.ndarray, threads: int | None = None) -> Any:
        """A new EnvPool of ``len(seeds)`` copies of this env, copy ``i`` seeded ``seeds[i]``
        (used as is: the caller steps and closes it; ARS rolls out on such pools)."""
        import envpool

        seeds = [int(s) % SEED_LIMIT for s in seeds]
        limit = self.cfg.max_episode_steps
        options = {} if limit is None else {"max_episode_steps": limit}
        with warnings.catch_warnings():  # its spaces' float64 bounds, cast to float32
            warnings.filterwarnings("ignore", ".*precision lowered", UserWarning)
            pool = envpool.make(
                self.task,
                env_type="gymnasium",
                num_envs=len(seeds),
                seed=seeds,
                num_threads=max(min(threads or self.threads, len(seeds)), 1),
                **options,
            )
            pool.observation_space, pool.action_space  # noqa: B018  (built once, here)
        return pool

    def _set_seed(self, seed: int | None) -> None:
        if self.pool is not None:
            self.pool.close()
        start = int(np.random.randint(SEED_LIMIT)) if seed is None else seed
        self.pool = self.make_pool(start + np.arange(self.batch_size[0]))
        self._live[:] = False  # a new pool: every copy needs a reset

    def reset_copies(self, mask: np.ndarray | None = None) -> np.ndarray:
        """Start new episodes in the copies ``mask`` selects (None: all of them); the
        observations of every copy (the others' as they were)."""
        ids = self.pool.all_env_ids if mask is None else np.flatnonzero(mask).astype(np.int32)
        if len(ids):
            obs, info = self.pool.reset(env_id=ids)
            self._obs[info["env_id"]] = obs
        self._live[ids], self._terminated[ids], self._truncated[ids] = True, False, False
        return self._obs.copy()

    def step_copies(self, action: np.ndarray) -> tuple[np.ndarray, ...]:
        """Step the copies in an episode with their rows of ``action``; every copy's
        observation, reward, terminated and truncated (a finished copy's as it ended, reward 0)."""
        if self._live.all():
            obs, reward, terminated, truncated, info = self.pool.step(action)
        else:  # finished copies wait for their reset: EnvPool would autoreset them
            live = np.flatnonzero(self._live).astype(np.int32)
            obs, reward, terminated, truncated, info = self.pool.step(action[live], env_id=live)
        ids = info["env_id"]
        rewards = np.zeros(self.batch_size[0], np.float32)
        self._obs[ids], rewards[ids] = obs, reward
        self._terminated[ids], self._truncated[ids] = terminated, truncated
        self._live[ids] = ~(terminated | truncated)
        return self._obs.copy(), rewards, self._terminated.copy(), self._truncated.copy()

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs: Any) -> TensorDictBase:
        mask = None if tensordict is None else tensordict.get("_reset", None)
        obs = self.reset_copies(None if mask is None else mask.reshape(-1).cpu().numpy())
        no = torch.zeros((*self.batch_size, 1), dtype=torch.bool)
        return self._output(observation=obs, done=no, terminated=no, truncated=no)

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        obs, rewards, terminated, truncated = self.step_copies(
            tensordict.get("action").cpu().numpy()
        )
        term, trunc = (torch.from_numpy(x)[:, None] for x in (terminated, truncated))
        return self._output(
            observation=obs,
            reward=torch.from_numpy(rewards).unsqueeze(-1),
            done=term | trunc,
            terminated=term,
            truncated=trunc,
        )

    def _output(self, **values: Any) -> TensorDictBase:
        return TensorDict(values, batch_size=self.batch_size, device=self.device)

    def close(self, *, raise_if_closed: bool = True) -> None:
        """Close the pool."""
        if self.pool is not None:
            self.pool.close()
            self.pool = None
        self.is_closed = True
