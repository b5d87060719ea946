"""Augmented random search (ARS V2) as an rlpipe algorithm: a linear or MLP policy behind a
running observation normaliser, evolved by :class:`rlpipe.algos.ars.ARSSearch`."""

from __future__ import annotations

import math
import os
from collections.abc import Collection
from functools import partial
from typing import Any

import torch
from tensordict.nn import TensorDictModule, TensorDictSequential
from torch import nn
from torchrl.data import Bounded, Categorical
from torchrl.envs import EnvBase

from rlpipe.algos.ars.search import ARSSearch
from rlpipe.algos.ars.starts import Starts
from rlpipe.algos.base import Algorithm, Metrics, annealed
from rlpipe.algos.configs import SEARCH_PARAMS, ARSConfig, RayConfig
from rlpipe.console import say
from rlpipe.envs import envpool_env, episode_limit, is_discrete, num_actions, observation_size
from rlpipe.errors import RlpipeError, check
from rlpipe.models import ArgmaxAction, ClampAction, mlp, user_network
from rlpipe.normalizer import Normalizer

__all__ = ["ARS", "ARSConfig", "RayConfig", "make_ars_policy"]

# the search's timing figures, which differ between identical runs: logged under time/
TIMINGS = ("steps_per_second", "rollout_cpu_seconds")


class ARS(Algorithm):
    """Augmented random search (ARS V2) as the runner's algorithm, on envs from ``env_factory``.

    ``env_factory`` is a :data:`rlpipe.envs.EnvFactory` over :func:`rlpipe.make_env`.

    One env copy is built for the specs and closed; the ``2N`` perturbed policies roll out on
    copies that ``env_factory(num_envs=n, seed=s, vectorization="sync")`` builds, spread over
    ``cfg.workers`` processes (``cfg.backend="ray"``: Ray actors, see ``cfg.ray``), which start
    with the first :meth:`train_step`. On the EnvPool backend (``env.backend``) each local
    worker steps its share of the ``2N`` on a pool of its own, the cores shared out as the
    pools' threads (one worker: all ``2N`` on one pool in this process). One :meth:`train_step`
    is one ARS iteration; ``frames`` counts every step of every perturbed rollout. ARS runs on
    the CPU whatever ``device`` says: its per-step work is one small batched matmul, next to the
    env's physics.

    ``network`` (or ``cfg.network``) is your policy network in place of the linear map or MLP:
    normalised observations to one output per action (discrete: the argmax is taken) or per
    action dimension (continuous: clamped into the bounds); ARS searches its parameters (e.g. the
    LayerNorm MLP of ``examples/ars_layernorm.py``).
    """

    budget_key = "algo.iterations"

    divergence_hint = "try a smaller algo.step_size or algo.noise"  # the end of its error

    cfg: ARSConfig

    def build(self) -> None:
        """The policy (from one env copy's specs) and the search; ARS runs on the CPU."""
        cfg, env_factory = self.cfg, self.env_factory
        self.device = torch.device("cpu")
        self.budget = cfg.iterations
        probe = env_factory(num_envs=1, vectorization="sync")
        try:
            self.policy, normalizer = make_ars_policy(probe, cfg, self.user_network)
            check(
                not (cfg.bound_penalty and is_discrete(probe)),
                f"algo.bound_penalty ({cfg.bound_penalty}) applies to continuous (Box) actions; "
                "this env's actions are discrete: set algo.bound_penalty=0",
            )
            pooled, steps = envpool_env(probe) is not None, episode_limit(probe)
        finally:
            probe.close()
        limit = min(cfg.episode_length, steps or cfg.episode_length)
        self.budget_frames = cfg.iterations * 2 * cfg.num_directions * limit  # at most
        seed = int(torch.randint(0, 2**31 - 1, ()))  # from the run's seeded torch generator
        params = {key: getattr(cfg, key) for key in SEARCH_PARAMS}  # the same names and checks
        rollout_factory = partial(env_factory, vectorization="sync")
        if pooled and cfg.backend == "local":  # the cores shared out as each worker's threads
            cores = os.cpu_count() or 1
            workers = min(cfg.workers or cores, 2 * cfg.num_directions)
            rollout_factory = partial(rollout_factory, threads=max(cores // workers, 1))
        self.search = ARSSearch(
            self.policy,
            rollout_factory,
            **params,
            max_steps=cfg.episode_length,
            reward_offset=cfg.alive_bonus_offset,
            reward_clip=cfg.reward_bound,
            normalizer=normalizer if cfg.normalize_observations else None,
            ray_address=cfg.ray.address,
            ray_num_cpus=cfg.ray.num_cpus,
            seed=seed,
        )
        self.starts = Starts(cfg.starts, cfg.starts_until) if cfg.starts > 1 else None

    @property
    def iterations(self) -> int:
        """ARS iterations done (the search's counter)."""
        return self.search.iterations

    def _progress(self) -> tuple[int, int, str]:
        """The run's progress as (done, total, unit): frames, or iterations without a frame
        budget."""
        if self.cfg.total_frames:
            return self.frames, self.cfg.total_frames, "frames"
        return self.iterations, self.cfg.iterations, "iterations"

    def train_step(self) -> Metrics:
        cfg = self.cfg  # α's, ν's and the clip's schedules span the run's frames (or iterations)
        done, total, _ = self._progress()
        self.search.step_size = annealed(cfg.step_size, cfg.step_size_end, done, total)
        self.search.noise = annealed(cfg.noise, cfg.noise_end, done, total)
        self.search.episodes = cfg.episodes if done >= cfg.episodes_from * total else 1
        if cfg.reward_bound is not None:  # the clip's bound moves after its first part
            begin = cfg.reward_clip_from * total
            self.search.reward_clip = annealed(
                cfg.reward_bound, cfg.reward_clip_end, done - begin, total - begin
            )
        if self.starts is not None:
            self.starts.next_turn(self.policy)
        stats = self.search.step()
        self.frames += int(stats["env_steps"])  # every step of every perturbed rollout
        metrics = {f"{'time' if k in TIMINGS else 'train'}/{k}": v for k, v in stats.items()}
        if self.starts is not None:  # the leader goes back into the policy
            done, total, unit = self._progress()
            dropped = self.starts.record(
                self.policy, stats["return_mean"], int(stats["env_steps"]), done / total
            )
            if dropped:
                say(self._halving_line(dropped, f"{done:,} {unit}"))
            metrics["train/starts_live"] = len(self.starts.live)
        return metrics

    def _halving_line(self, dropped: list[int], when: str) -> str:
        """The console's line on a halving of the starts: who stays, who goes, on what scores."""
        starts = self.starts
        scores = ([starts.score(k) for k in ks] for ks in (starts.live, dropped))
        # a start the budget ended before its first turn has no return to show
        kept, gone = ([f"{x:.1f}" if x > -math.inf else "not run" for x in xs] for xs in scores)
        return (
            f"rlpipe: ARS starts: {len(kept)} of {len(kept) + len(gone)} kept at {when} "
            f"(recent returns {', '.join(kept)}; dropped {', '.join(gone)})"
        )

    def state_dict(self) -> dict[str, Any]:
        # the search's keys beside frames: the layout ARS checkpoints have always had
        state = {**self.search.state_dict(), "frames": self.frames}
        if self.starts is not None:
            state["starts"] = self.starts.state_dict()
        return state

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.search.load_state_dict(state)
        self.frames = int(state["frames"])
        if self.starts is not None:
            self.starts.load_state_dict(state["starts"])

    def start_from(self, state: dict[str, Any], parts: Collection[str], parent: Any) -> None:
        """θ and the normaliser's statistics of another run's checkpoint (``init_from``);
        iterations and the search's generator stay this run's. ARS has no optimizer or buffer."""
        if parts:
            part = sorted(parts)[0]
            raise RlpipeError(
                f"init_{part}=true, but ARS keeps no optimizer or replay buffer (its state is θ "
                f"and the normaliser, which init_from loads): drop init_{part}"
            )
        self.search.policy.load_state_dict(state["policy"])

    def close(self) -> None:
        """Stop the rollout workers (if they were started)."""
        self.search.close()


def make_ars_policy(
    env: EnvBase, cfg: ARSConfig, network: nn.Module | None = None
) -> tuple[TensorDictSequential, Normalizer]:
    """Normaliser -> ``network`` (or ``cfg.network``; by default a linear map, zero-initialised
    as the notebook's, or an MLP) -> action head."""
    size = observation_size(env, "ARS")
    spec = env.action_spec_unbatched
    if is_discrete(env) and isinstance(spec, Categorical):
        outputs, head = num_actions(env), ArgmaxAction()
    elif isinstance(spec, Bounded) and len(spec.shape) == 1:
        outputs, head = spec.shape[0], ClampAction(spec.space.low, spec.space.high)
    else:
        raise RlpipeError(
            f"ARS needs a discrete (Discrete) or a flat bounded continuous (Box) action space; "
            f"this env's actions are {type(spec).__name__} of shape {tuple(spec.shape)}"
        )
    what = "one value per action dimension (clamped into the bounds)"
    if isinstance(head, ArgmaxAction):
        what = "one value per action (the argmax is taken)"
    net = user_network(network, cfg.network, in_features=size, out_features=outputs, outputs=what)
    if net is None and cfg.policy == "linear":
        net = nn.Linear(size, outputs, bias=False)
        nn.init.zeros_(net.weight)
    elif net is None:
        net = mlp(size, outputs, cfg.hidden_sizes)
    normalizer = Normalizer(size)  # the identity until statistics are merged in
    policy = TensorDictSequential(
        TensorDictModule(normalizer, in_keys=["observation"], out_keys=["observation_norm"]),
        TensorDictModule(net, in_keys=["observation_norm"], out_keys=["policy_output"]),
        TensorDictModule(head, in_keys=["policy_output"], out_keys=["action"]),
    )
    return policy, normalizer
