"""The ARS search loop on any TensorDictModule policy, usable without the runner, and its
update rule."""

from __future__ import annotations

import copy
import time
from functools import partial
from typing import Any

import torch
from tensordict.nn import TensorDictModuleBase
from torch.nn.utils import parameters_to_vector, vector_to_parameters

from rlpipe.algos.ars.backends import Backend, start_backend
from rlpipe.algos.configs import check_search_params
from rlpipe.envs import EnvFactory
from rlpipe.errors import check, check_fields
from rlpipe.normalizer import Normalizer

__all__ = ["ARSSearch", "ars_update", "centered_ranks"]


class ARSSearch:
    """Augmented random search on ``policy``'s flat parameters θ, one :meth:`step` per iteration.

    Each iteration samples ``num_directions`` (N) Gaussian directions δ, rolls out the ``2N``
    policies θ ± ν·δ (ν: ``noise``) for ``episodes`` episodes each (their returns averaged),
    keeps the ``num_best`` (b) directions with the best ``max(r+, r-)`` and moves θ by
    ``α / (b·σ) · Σ (r+ - r-)·δ`` (α: ``step_size``, σ: the std of the ``2b`` kept returns;
    :func:`ars_update`). θ is ``parameters_to_vector(policy.parameters())``, read and set
    through :attr:`theta`.

    Args:
        policy: a CPU ``TensorDictModule``, or a ``TensorDictSequential`` of them with one
            output key each, mapping ``"observation"`` to ``"action"`` (what the gymnasium env's
            ``step`` takes). Every parameter is searched; buffers (a :class:`Normalizer`'s
            statistics) are not. The search changes this object's parameters in place.
        env_factory: ``env_factory(num_envs=n, seed=s)`` builds ``n`` rollout env copies: a
            TorchRL env over a gymnasium ``SyncVectorEnv``, such as
            ``functools.partial(rlpipe.make_env, env_cfg, vectorization="sync")``, or a
            :func:`rlpipe.make_env` env on the EnvPool backend (its rollouts then step a pool
            of the same env, ``threads`` as the env was built with).
        num_directions: N, directions sampled per iteration (``2N`` rollouts). Default 16.
        num_best: b, directions kept for the update, between 1 and N. Default None: N.
        step_size: α, the update's step size (> 0). Default 0.02.
        noise: ν, the perturbations' scale (> 0). Default 0.03.
        max_steps: a rollout's episode ends after this many steps (at least 1), or earlier at
            the env's own time limit or termination. Default 1000.
        reward_offset: added to every reward of the training returns that rank and weigh the
            directions (the ARS paper's alive-bonus offset; the RL Zoo uses -0.1 on
            BipedalWalker). Default 0.0.
        reward_clip: training rewards (after the offset) are clipped to
            ``[-reward_clip, reward_clip]``; None: not clipped (the default). The offset and
            the clip shape only the update: :meth:`step` reports the env's own returns.
            ``step_size``, ``noise`` and ``reward_clip`` are attributes too, read by every
            :meth:`step`: set them between steps to anneal them (the :class:`rlpipe.algos.ars.ARS`
            runner does, for ``algo.step_size_end``, ``algo.noise_end`` and
            ``algo.reward_clip_end``).
        bound_penalty: c (>= 0): ``c × Σ|policy_output - action|`` is taken off every step's
            training reward, where ``policy_output`` is the policy's raw output and ``action``
            that output clamped into the action bounds, so that the search keeps away from
            outputs far past the bounds (a bang-bang policy that a perturbation hardly
            changes). Continuous actions only. Default 0.0: none.
        episodes: episodes each perturbed policy runs per iteration (at least 1, the default),
            from as many episode seeds per direction (θ+νδ and θ-νδ sharing each); their
            training returns are averaged before ranking and weighing, so that one episode's
            luck (a fall on one terrain) weighs less. An attribute, read by every :meth:`step`.
        fitness: ``"returns"`` (the default: the ARS paper's update on the training returns)
            or ``"ranks"``: the ``2N`` training returns replaced by their centred ranks
            (:func:`centered_ranks`) before the top-b selection and the update, so that one
            rollout's fall weighs no more than its place.
        normalizer: the :class:`Normalizer` inside ``policy`` whose statistics the search
            updates after every iteration (below). Default None: no statistics are kept.
        workers: ``"local"``: processes rolling out the members in chunks (1, the default: all
            in this process, as one batch; 0: one per CPU core); ``"ray"``: Ray actors (0: one
            per CPU of the cluster). Never more than ``2N``. With 2 or more local workers keep
            scripts' ``if __name__ == "__main__":`` guard (workers may be spawned).
        backend: ``"local"`` (the default) or ``"ray"`` (the ``ray`` extra).
        ray_address: ``backend="ray"`` only: None (the default) starts Ray on this machine,
            ``host:port``, ``ray://host:port`` or ``"auto"`` joins that cluster. A Ray already
            initialised in this process is used as it is.
        ray_num_cpus: ``backend="ray"`` only: CPUs of a Ray started here (None: all).
        seed: seeds the search's generator, which draws the directions and each direction's
            episode seed, and the env copies (worker ``w`` builds its copies with ``seed + w``).
            Default 0.

    A bad ``num_directions``, ``num_best``, ``step_size``, ``noise``, ``max_steps``,
    ``bound_penalty``, ``fitness``, ``workers`` or ``backend`` raises
    :class:`rlpipe.RlpipeError` naming it. The backend (env copies, worker processes or
    actors) starts with the first :meth:`step`, or :meth:`start`: a search built only to hold
    its policy, or to load a state, starts nothing. :meth:`close` stops it.

    The normaliser (ARS V2) goes in two places, as one and the same object: as a module inside
    ``policy``, ahead of the layers that read its output (so that every rollout standardises
    observations with its statistics, frozen during an iteration: worker processes and actors
    get them with each iteration's first chunk), and as ``normalizer=`` (so that after every
    iteration the search merges in the statistics of all the observations the ``2N`` perturbed
    policies acted on: their count, mean and squared deviations). The rollouts of iteration
    ``k`` use the statistics of iterations ``1 .. k-1``. Inside the policy only, it stays what
    it was built as (a new one: the identity), as if there were no normaliser. As
    ``normalizer=`` only, its statistics grow but no rollout ever uses them, and
    :meth:`state_dict` (the policy's state) does not hold them. ``make_ars_policy`` in
    :mod:`rlpipe.algos.ars` builds such a pair for any env.

    :meth:`state_dict` and :meth:`load_state_dict` checkpoint and resume exactly: a fresh
    search, built with the same arguments and loaded with a saved state, continues with the
    same directions, episodes, returns, θ and statistics as the search that was saved (for
    envs whose ``reset(seed=...)`` fixes the episode; see below). The state is a copy: the
    search going on does not change it, so ``torch.save`` it or keep it in memory.

    Each direction's episode seed comes from the search's generator, shared by θ+νδ and θ-νδ
    (both start from the same state, so r+ - r- measures the direction, not two starts' luck),
    so for the same ``seed`` every backend and worker count gives the same rollouts and the
    same θ, for envs whose ``reset(seed=...)`` fixes the episode. Box2D envs (BipedalWalker,
    LunarLander) keep their world across resets, so there an episode also depends on what its
    env copy ran before: worker counts, and a resumed search's fresh env copies, change the
    episodes. On EnvPool (``env_factory`` on the ``envpool`` backend) every rollout runs on a
    fresh pool whose copies are seeded with the members' episode seeds, so an episode depends on
    its seed and parameters alone, Box2D included (EnvPool cannot reseed at reset; its episodes
    for a seed are not gymnasium's).
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
        bound_penalty: float = 0.0,
        episodes: int = 1,
        fitness: str = "returns",
        normalizer: Normalizer | None = None,
        workers: int = 1,
        backend: str = "local",
        ray_address: str | None = None,
        ray_num_cpus: int | None = None,
        seed: int = 0,
    ) -> None:
        self.num_directions = num_directions
        self.num_best = num_directions if num_best is None else num_best
        self.step_size, self.noise, self.reward_clip = step_size, noise, reward_clip
        self.max_steps, self.workers, self.backend = max_steps, workers, backend
        self.bound_penalty, self.fitness, self.episodes = bound_penalty, fitness, episodes
        check_search_params(self, "")
        check_fields(self, "", at_least_one=("max_steps",))
        check(
            not bound_penalty or {"policy_output", "action"} <= set(policy.out_keys),
            "bound_penalty needs a policy that writes 'policy_output' (its raw outputs) and "
            "'action' (them clamped into the bounds), as make_ars_policy's does",
        )
        self.policy, self.normalizer = policy, normalizer
        self.generator = torch.Generator().manual_seed(seed)
        self.iterations = 0
        options = {
            "max_steps": max_steps,
            "reward_offset": reward_offset,
            "bound_penalty": bound_penalty,
        }
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

        Returns the iteration's figures (returns are the env's own, without ``reward_offset``
        or ``reward_clip``):

        - ``"return_mean"``, ``"return_max"``: mean and max return of the iteration's rollouts
          (``2N`` a round of episodes);
        - ``"env_steps"``: env steps taken by those rollouts (a float);
        - ``"steps_per_second"``: ``env_steps`` over this call's wall-clock seconds;
        - ``"rollout_cpu_seconds"``: CPU seconds of the rollouts, summed over all processes;
        - ``"episode_return"``, ``"episode_length"``: lists of ``2N`` floats per episode round,
          one per rollout: θ+νδ for the N directions, then θ-νδ in the same order.
        """
        self.start()
        start = time.perf_counter()
        theta = self.theta
        deltas = torch.randn(self.num_directions, theta.numel(), generator=self.generator)
        flat = torch.cat([theta + self.noise * deltas, theta - self.noise * deltas])
        # each direction's episode seed comes from the search's generator (the same results
        # whichever worker runs it); θ+νδ and θ-νδ start from the same state, so r+ - r- measures
        # the direction, not the luck of two starts
        seeds = torch.randint(
            2**31 - 1, (self.episodes, self.num_directions), generator=self.generator
        )
        shares = []  # every round's, merged into the normaliser after the last
        # per round: training returns, env returns and lengths of the 2N members
        figures = torch.empty(len(seeds), 3, len(flat), dtype=torch.float64)
        for round_figures, round_seeds in zip(figures, seeds, strict=True):
            round_shares = self._backend.roll_out(flat, round_seeds.repeat(2), self.reward_clip)
            for members, result in round_shares:
                round_figures[0, members] = result.returns
                round_figures[1, members] = result.raw_returns
                round_figures[2, members] = result.lengths.double()
            shares += round_shares
        returns, raw, lengths = figures[:, 0].mean(0), figures[:, 1], figures[:, 2]
        weights = centered_ranks(returns) if self.fitness == "ranks" else returns
        plus, minus = weights.float().chunk(2)
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
            "episode_return": raw.flatten().tolist(),  # one per perturbed rollout
            "episode_length": lengths.flatten().tolist(),
        }

    def state_dict(self) -> dict[str, Any]:
        """A copy of what resumes the search: ``"policy"`` (the policy's state dict: θ, and the
        normaliser inside the policy), ``"iterations"`` and ``"generator"`` (its state)."""
        return {
            # a copy: the normaliser's buffers change in place with every step
            "policy": copy.deepcopy(self.policy.state_dict()),
            "iterations": self.iterations,
            "generator": self.generator.get_state(),
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore a :meth:`state_dict` (θ, normaliser, iterations, generator) into this search;
        the next :meth:`step` is the one that followed the saved state."""
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


def centered_ranks(values: torch.Tensor) -> torch.Tensor:
    """Each value's rank among ``values`` (a 1-D tensor), scaled to ``[-0.5, 0.5]``: the
    lowest -0.5, the highest 0.5 (ties in the order they come)."""
    ranks = torch.empty_like(values)
    ranks[values.argsort(stable=True)] = torch.arange(len(values), dtype=values.dtype)
    return ranks / max(len(values) - 1, 1) - 0.5
