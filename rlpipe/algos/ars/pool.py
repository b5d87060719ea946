"""What every multi-worker ARS backend shares: the units each worker is built from, and the pool
of workers that pull chunks of the population as they free up (worker processes in
:mod:`~rlpipe.algos.ars.backends`, Ray actors in :mod:`~rlpipe.algos.ars.ray_actors`)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import torch
from tensordict.nn import TensorDictModuleBase

from rlpipe.algos.ars.chunking import chunks_per_worker
from rlpipe.algos.ars.rollout import RolloutResult
from rlpipe.envs import EnvFactory

RAY_INSTALL = 'pip install "rlpipe[ray]"'
# what a backend's roll_out returns: (member indices, their result) pairs covering the population
Shares = list[tuple[torch.Tensor, RolloutResult]]


@dataclass
class Units:
    """What each worker's :class:`Rollouts` is built from (worker ``w``'s envs: ``seed + w``)."""

    policy: TensorDictModuleBase
    env_factory: EnvFactory
    seed: int
    options: dict[str, Any]

    def args(self, worker: int, num_envs: int) -> tuple[Any, ...]:
        """``Rollouts``' arguments for ``worker``, with ``num_envs`` env copies."""
        return self.policy, self.env_factory, num_envs, self.seed + worker, self.options


class Pool:
    """A rollout backend of workers that pull chunks of the population as they free up.

    Episode lengths are heavy-tailed, so each worker takes small chunks (up to eight per worker
    and iteration, as many as the policy's measured call cost allows:
    :func:`rlpipe.algos.ars.chunking.chunks_per_worker`) rather than owning a fixed share; one
    worker takes everything as one chunk.
    A chunk carries its members' parameters and episode seeds, the iteration's reward clip, and
    the policy's state (the normaliser changes every iteration) when it is the worker's first of
    the iteration, all as NumPy arrays; only its :class:`RolloutResult` comes back. Subclasses
    fill ``workers`` and say how a chunk is sent to a worker (:meth:`_submit`, returning a
    handle), how to wait until some handles are done (:meth:`_wait`) and how to collect one
    (:meth:`_collect`).
    """

    def __init__(self, units: Units, population: int, workers: int) -> None:
        self.policy = units.policy
        if workers > 1:
            chunks = chunks_per_worker(
                units.policy, units.env_factory, population, workers, units.seed
            )
            self.chunk_size = -(-population // (chunks * workers))
        else:
            self.chunk_size = population
        self.chunks = list(torch.arange(population).split(self.chunk_size))
        self.workers: list[Any] = []

    def roll_out(
        self, flat: torch.Tensor, seeds: torch.Tensor, reward_clip: float | None = None
    ) -> Shares:
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
                    reward_clip,
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
