"""The ARS search loop on any TensorDictModule policy, usable without the runner, and its
update rule."""

from __future__ import annotations

import time
from functools import partial
from typing import Any

import torch
from tensordict.nn import TensorDictModuleBase
from torch.nn.utils import parameters_to_vector, vector_to_parameters

from rlpipe.algos.ars.backends import BACKENDS, Backend, start_backend
from rlpipe.envs import EnvFactory
from rlpipe.errors import check, check_choice, check_fields
from rlpipe.normalizer import Normalizer

__all__ = ["SEARCH_PARAMS", "ARSSearch", "ars_update", "check_search_params"]

# the parameters that ARSSearch takes and ARSConfig holds under the same names, checked by
# check_search_params for both
SEARCH_PARAMS = ("num_directions", "num_best", "step_size", "noise", "workers", "backend")


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

    The backend (env copies, worker processes or actors) starts with the first :meth:`step`, or
    :meth:`start`: a search built only to hold its policy, or to load a state, starts nothing.

    Each direction's episode seed comes from the search's generator, shared by θ+νδ and θ-νδ
    (both start from the same state, so r+ - r- measures the direction, not two starts' luck),
    so for the same ``seed`` every backend and worker count gives the same rollouts and the
    same θ, for envs whose
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
        self.num_directions = num_directions
        self.num_best = num_directions if num_best is None else num_best
        self.step_size, self.noise = step_size, noise
        self.max_steps, self.workers, self.backend = max_steps, workers, backend
        check_search_params(self, "")
        check_fields(self, "", at_least_one=("max_steps",))
        self.policy, self.normalizer = policy, normalizer
        self.generator = torch.Generator().manual_seed(seed)
        self.iterations = 0
        options = dict(max_steps=max_steps, reward_offset=reward_offset, reward_clip=reward_clip)
        self._start_backend = partial(
            start_backend,
            policy,
            env_factory,
            2 * num_directions,
            backend=backend,
            workers=workers,
            seed=seed,
            options=options,
            ray_address=ray_address,
            ray_num_cpus=ray_num_cpus,
        )
        self._backend: Backend | None = None

    @property
    def theta(self) -> torch.Tensor:
        """The policy's current flat parameter vector (a copy)."""
        return parameters_to_vector(self.policy.parameters()).detach().clone()

    @theta.setter
    def theta(self, value: torch.Tensor) -> None:
        vector_to_parameters(value, self.policy.parameters())

    def start(self) -> None:
        """Start the backend now (the first :meth:`step` does, if it has not started)."""
        if self._backend is None:
            self._backend = self._start_backend()

    def step(self) -> dict[str, float | list[float]]:
        """One iteration: roll out θ ± ν·δ for N fresh directions, update θ and the normaliser.

        Returns the env's (unshaped) returns of the ``2N`` rollouts, their mean and max, the
        env steps taken, steps/s and the CPU seconds the rollouts took over all processes.
        """
        self.start()
        start = time.perf_counter()
        theta = self.theta
        deltas = torch.randn(self.num_directions, theta.numel(), generator=self.generator)
        flat = torch.cat([theta + self.noise * deltas, theta - self.noise * deltas])
        # each direction's episode seed comes from the search's generator (the same results
        # whichever worker runs it); θ+νδ and θ-νδ start from the same state, so r+ - r- measures
        # the direction, not the luck of two starts
        seeds = torch.randint(2**31 - 1, (self.num_directions,), generator=self.generator)
        seeds = seeds.repeat(2)
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

    def state_dict(self) -> dict[str, Any]:
        """θ and the normaliser (the policy's state dict), iterations and the generator."""
        return {
            "policy": self.policy.state_dict(),
            "iterations": self.iterations,
            "generator": self.generator.get_state(),
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.policy.load_state_dict(state["policy"])
        self.iterations = int(state["iterations"])
        self.generator.set_state(state["generator"])

    def close(self) -> None:
        """Stop the workers (or close the local envs), if they were started."""
        if self._backend is not None:
            backend, self._backend = self._backend, None
            backend.close()


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


def check_search_params(params: Any, prefix: str) -> None:
    """Value checks of the :data:`SEARCH_PARAMS` that ``params`` holds as attributes; errors
    name the key as ``<prefix><name>`` (``"algo."`` for :class:`rlpipe.algos.ars.ARSConfig`,
    ``""`` for :class:`ARSSearch`)."""
    check_fields(
        params,
        prefix,
        at_least_one=("num_directions",),
        positive=("step_size", "noise"),
        non_negative=("workers",),
    )
    check(
        1 <= params.num_best <= params.num_directions,
        f"{prefix}num_best ({params.num_best}) must be between 1 and {prefix}num_directions "
        f"({params.num_directions})",
    )
    check_choice(params.backend, f"{prefix}backend", BACKENDS)
