"""Augmented random search (ARS V2) as an rlpipe algorithm: a linear or MLP policy behind a
running observation normaliser, evolved by :class:`rlpipe.algos.ars.ARSSearch`."""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import partial
from typing import Any

import torch
from tensordict.nn import TensorDictModule, TensorDictSequential
from torch import nn
from torchrl.data import Bounded, Categorical
from torchrl.envs import EnvBase

from rlpipe.algos.ars.search import SEARCH_PARAMS, ARSSearch, check_search_params
from rlpipe.algos.base import Metrics
from rlpipe.config import AlgoConfig, checked
from rlpipe.envs import EnvFactory, is_discrete, num_actions, observation_size
from rlpipe.errors import RlpipeError
from rlpipe.models import ArgmaxAction, ClampAction, mlp, user_network
from rlpipe.normalizer import Normalizer

__all__ = ["ARS", "ARSConfig", "RayConfig", "make_ars_policy"]

POLICIES = ("linear", "mlp")
# the search's timing figures, which differ between identical runs: logged under time/
TIMINGS = ("steps_per_second", "rollout_cpu_seconds")


@dataclass
class RayConfig:
    """Where ``algo.backend=ray`` runs its rollout actors."""

    address: str | None = None  # null: start Ray on this machine; host:port or auto: a cluster
    num_cpus: int | None = None  # CPUs of a Ray started here (null: all the machine's)


@dataclass
class ARSConfig(AlgoConfig):
    """ARS hyper-parameters; the defaults are the workshop notebook's."""

    name: str = "ars"
    eval_every: int = 1_000_000  # frames between greedy evaluations (an iteration is 2N episodes)
    checkpoint_every: int = 1_000_000
    iterations: int = checked(1000, "at_least_one")  # the run's length, unless total_frames caps it
    num_directions: int = 16  # N: directions sampled per iteration (2N rollouts)
    num_best: int = 16  # b: directions kept for the update, by max(r+, r-)
    step_size: float = 0.02  # α
    noise: float = 0.03  # ν: perturbations are θ ± ν·δ
    # cap on training rollouts (the env's own limit still applies)
    episode_length: int = checked(2000, "at_least_one")
    reward_clip: bool = True  # clip training rewards to [-1, 1], as the notebook
    alive_bonus_offset: float = 0.0  # added to every training reward (RL Zoo: -0.1 for Bipedal)
    normalize_observations: bool = True  # ARS V2: running mean/variance, frozen for evaluation
    policy: str = checked("linear", choices=POLICIES)
    hidden_sizes: list[int] = checked([32, 32], "sizes")  # policy=mlp only
    workers: int = 0  # rollout workers; 0: one per CPU core (Ray: per CPU of the cluster)
    backend: str = "local"  # local: this process or worker processes; ray: Ray actors
    ray: RayConfig = field(default_factory=RayConfig)  # backend=ray only

    def __post_init__(self) -> None:
        super().__post_init__()
        check_search_params(self, "algo.")
        if isinstance(self.ray, dict):  # rebuilt from a run's config.yaml
            self.ray = RayConfig(**self.ray)


class ARS:
    """Augmented random search (ARS V2) as the runner's algorithm, on envs from ``env_factory``.

    ``env_factory`` is a :data:`rlpipe.envs.EnvFactory` over :func:`rlpipe.make_env`.

    One env copy is built for the specs and closed; the ``2N`` perturbed policies roll out on
    copies that ``env_factory(num_envs=n, seed=s, vectorization="sync")`` builds, spread over
    ``cfg.workers`` processes (``cfg.backend="ray"``: Ray actors, see ``cfg.ray``), which start
    with the first :meth:`train_step`. One :meth:`train_step` is one ARS iteration; ``frames``
    counts every step of every perturbed rollout. ARS runs on the CPU whatever ``device`` says:
    its per-step work is one small batched matmul, next to the env's physics.

    ``network`` (or ``cfg.network``) is your policy network in place of the linear map or MLP:
    normalised observations to one output per action (discrete: the argmax is taken) or per
    action dimension (continuous: clamped into the bounds); ARS searches its parameters (e.g. the
    LayerNorm MLP of ``examples/ars_layernorm.py``).
    """

    finite_keys = ()  # the runner checks the policy's parameters
    divergence_hint = "try a smaller algo.step_size or algo.noise"  # the end of its error

    def __init__(
        self,
        env_factory: EnvFactory,
        cfg: ARSConfig,
        *,
        device: str | torch.device = "cpu",
        network: nn.Module | None = None,
    ):
        self.cfg = cfg
        self.device = torch.device("cpu")
        self.frames = 0
        self.budget = cfg.iterations
        self.env_factory = env_factory
        self._network = network  # the user's, in place of the default (or cfg.network)
        probe = env_factory(num_envs=1, vectorization="sync")
        try:
            self.policy, normalizer = make_ars_policy(probe, cfg, network)
        finally:
            probe.close()
        seed = int(torch.randint(0, 2**31 - 1, ()))  # from the run's seeded torch generator
        self.search = ARSSearch(
            self.policy,
            partial(env_factory, vectorization="sync"),
            **{key: getattr(cfg, key) for key in SEARCH_PARAMS},  # the same names and checks
            max_steps=cfg.episode_length,
            reward_offset=cfg.alive_bonus_offset,
            reward_clip=1.0 if cfg.reward_clip else None,
            normalizer=normalizer if cfg.normalize_observations else None,
            ray_address=cfg.ray.address,
            ray_num_cpus=cfg.ray.num_cpus,
            seed=seed,
        )

    @property
    def iterations(self) -> int:
        """ARS iterations done (the search's counter)."""
        return self.search.iterations

    def train_step(self) -> Metrics:
        stats = self.search.step()
        self.frames += int(stats["env_steps"])  # every step of every perturbed rollout
        return {f"{'time' if key in TIMINGS else 'train'}/{key}": v for key, v in stats.items()}

    def state_dict(self) -> dict[str, Any]:
        # the search's keys beside frames: the layout ARS checkpoints have always had
        return {**self.search.state_dict(), "frames": self.frames}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.search.load_state_dict(state)
        self.frames = int(state["frames"])

    def close(self) -> None:
        """Stop the rollout workers (if they were started)."""
        self.search.close()


def make_ars_policy(
    env: EnvBase, cfg: ARSConfig, network: nn.Module | None = None
) -> tuple[TensorDictSequential, Normalizer]:
    """Normaliser -> ``network`` (or ``cfg.network``; by default a linear map, zero-initialised
    as the notebook's, or an MLP) -> action head."""
    size = observation_size(env)
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
