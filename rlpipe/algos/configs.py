"""Every built-in algorithm's config dataclass: its hyper-parameters with their defaults and value
rules, its run length and cadence. Imports no torch, so the command line checks a config (and
prints ``--help``) before torch loads; each algorithm's module re-exports its own."""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Any, ClassVar

from rlpipe.config import AlgoConfig, checked
from rlpipe.errors import check, check_choice, check_fields

LOSSES = ("smooth_l1", "l2", "l1")
EPS_SCHEDULES = ("exp", "linear")
BASELINES = ("none", "value")
PLANNERS = ("cem", "random")
ARS_POLICIES = ("linear", "mlp")
ARS_BACKENDS = ("local", "ray")
ARS_FITNESS = ("returns", "ranks")
# the parameters that ARSSearch takes and ARSConfig holds under the same names, checked by
# check_search_params for both
SEARCH_PARAMS = (
    "num_directions",
    "num_best",
    "step_size",
    "noise",
    "bound_penalty",
    "episodes",
    "fitness",
    "workers",
    "backend",
)


@dataclass
class OffPolicyConfig(AlgoConfig):
    """What the off-policy loop (:class:`rlpipe.algos.offpolicy.OffPolicy`) reads: each iteration
    collects ``frames_per_batch`` frames into a replay buffer of ``buffer_size``, then, once
    ``learning_starts`` frames are in, runs ``updates_per_batch`` gradient steps on minibatches of
    ``batch_size``, the target networks following at rate ``tau``. DQN, SAC and any further
    off-policy algorithm extend it."""

    buffer_keys: ClassVar[tuple[str, ...]] = ("buffer_size",)

    lr: float = checked(3e-4, "positive")
    batch_size: int = checked(256, "at_least_one")
    buffer_size: int = 1_000_000
    gamma: float = checked(0.99, "discount")
    # soft target update: target <- tau * online + (1 - tau) * target
    tau: float = checked(0.005, "discount")
    # frames between target updates (0: after every gradient step); with tau=1, a hard copy
    # every N frames (SB3's target_update_interval)
    target_update_every: int = checked(0, "non_negative")
    frames_per_batch: int = checked(1, "at_least_one")  # env frames collected per iteration
    updates_per_batch: int = checked(1, "non_negative")  # gradient steps per iteration
    learning_starts: int = checked(100, "non_negative")  # frames collected before updates

    def __post_init__(self) -> None:
        super().__post_init__()
        check(
            self.buffer_size >= self.batch_size,
            f"algo.buffer_size ({self.buffer_size}) must be >= algo.batch_size ({self.batch_size})",
        )

    def for_copies(self, copies: int) -> OffPolicyConfig:
        """A batch holds whole steps of the env's copies: ``frames_per_batch`` rounds up to a
        multiple of ``copies`` and ``updates_per_batch`` scales with it, so the gradient steps
        per frame stay what the config says (e.g. 4 frames and 4 updates on 8 copies: 8 and 8)."""
        frames = math.ceil(self.frames_per_batch / copies) * copies
        if frames == self.frames_per_batch:
            return self
        updates = round(self.updates_per_batch * frames / self.frames_per_batch)
        return replace(self, frames_per_batch=frames, updates_per_batch=updates)


@dataclass
class DQNConfig(OffPolicyConfig):
    """DQN hyper-parameters; the defaults are the workshop notebook's."""

    buffer_keys: ClassVar[tuple[str, ...]] = ("buffer_size", "n_steps")  # n-step transitions
    architecture: ClassVar[tuple[str, ...]] = ("hidden_sizes", "layer_norm", "network")

    name: str = "dqn"
    total_frames: int | None = 60_000  # DQN has no budget of its own: the run's length
    hidden_sizes: list[int] = checked([128, 128], "sizes")
    # a LayerNorm after each hidden layer of the default Q-network (keeps TD targets from
    # diverging: Gallici et al. 2024, https://arxiv.org/abs/2407.04811)
    layer_norm: bool = False
    lr: float = checked(1e-4, "positive")
    # null: a constant lr; a number: lr annealed linearly to it over algo.total_frames
    lr_end: float | None = None
    weight_decay: float = checked(1e-2, "non_negative")  # AdamW's default
    amsgrad: bool = True
    batch_size: int = checked(128, "at_least_one")
    buffer_size: int = 10_000
    # n-step returns (TorchRL's MultiStep on each collected batch): each stored transition
    # sums up to n discounted rewards and bootstraps from the state n steps on; a window stops
    # at an episode's end and at the batch's end (frames_per_batch / num_envs steps)
    n_steps: int = checked(1, "at_least_one")
    grad_clip_value: float = checked(100.0, "positive")  # each gradient element (the notebook's)
    max_grad_norm: float | None = None  # also clip the gradient's norm (SB3: 10); null: off
    loss: str = checked("smooth_l1", choices=LOSSES)  # Huber
    double_dqn: bool = False
    eps_start: float = 0.9
    eps_end: float = 0.05
    # exp: eps_end + (eps_start - eps_end) * exp(-t / eps_decay); linear: annealed over eps_decay
    eps_schedule: str = checked("exp", choices=EPS_SCHEDULES)
    eps_decay: int = checked(1000, "at_least_one")  # frames
    # εz-greedy: each random action held for n steps, P(n) ∝ n^-eps_zeta (e.g. 2); null: ε-greedy
    eps_zeta: float | None = None
    # the most any return can be (e.g. CartPole's 1/(1-γ) = 100 at γ 0.99): each TD target is
    # clamped to it, so Q-values cannot climb past it; null: unbounded
    q_max: float | None = None
    # frames collected per iteration (all env copies), then as many gradient steps (the notebook)
    frames_per_batch: int = checked(4, "at_least_one")
    updates_per_batch: int = checked(4, "non_negative")
    learning_starts: int = checked(128, "non_negative")  # frames collected before the first update

    def __post_init__(self) -> None:
        super().__post_init__()
        check(
            self.lr_end is None or 0 <= self.lr_end <= self.lr,
            f"algo.lr_end must be null or in [0, algo.lr], got {self.lr_end}",
        )
        check(
            self.max_grad_norm is None or self.max_grad_norm > 0,
            f"algo.max_grad_norm must be null or > 0, got {self.max_grad_norm}",
        )
        check(
            self.eps_zeta is None or self.eps_zeta > 1,
            f"algo.eps_zeta must be null or > 1, got {self.eps_zeta}",
        )
        check(
            0 <= self.eps_end <= self.eps_start <= 1,
            f"need 0 <= algo.eps_end <= algo.eps_start <= 1, got {self.eps_end}, {self.eps_start}",
        )


@dataclass
class SACConfig(OffPolicyConfig):
    """SAC hyper-parameters; the defaults are SB3's."""

    name: str = "sac"
    total_frames: int | None = 50_000  # SAC has no budget of its own: the run's length
    eval_every: int = 5_000
    hidden_sizes: list[int] = checked([256, 256], "sizes")  # actor's and each critic's
    alpha_init: float = checked(1.0, "positive")  # the entropy coefficient's start
    # true: alpha_init all run (SB3's ent_coef=<number>); false: tuned towards target_entropy
    fixed_alpha: bool = False
    target_entropy: float | None = None  # null: minus the action dimensions
    # exploration noise's colour: the collecting policy's Gaussian draws correlated in time with
    # a power spectrum 1/f^β: 0 white (independent draws, SAC's own), 1 pink, 2 red (Brownian,
    # like OU noise); each env copy's draws are sequences of noise_steps steps
    noise_color: float = checked(0.0, "non_negative")
    noise_steps: int = checked(1000, "at_least_one")

    def __post_init__(self) -> None:
        super().__post_init__()
        check(
            self.noise_steps >= 2 or not self.noise_color,
            f"algo.noise_steps must be >= 2 for coloured noise, got {self.noise_steps}",
        )


@dataclass
class PPOConfig(AlgoConfig):
    """PPO hyper-parameters; the defaults are SB3's."""

    name: str = "ppo"
    total_frames: int | None = 100_000  # PPO has no budget of its own: the run's length
    eval_every: int = 10_000
    hidden_sizes: list[int] = checked([64, 64], "sizes")  # actor's and critic's (tanh MLPs)
    lr: float = checked(3e-4, "positive")
    anneal_lr: bool = False  # linearly to 0 over algo.total_frames
    anneal_clip: bool = False  # clip_epsilon, likewise (the RL Zoo's lin_0.2)
    frames_per_batch: int = checked(2048, "at_least_one")  # one rollout (across all env copies)
    epochs: int = checked(10, "at_least_one")  # passes over each rollout
    minibatch_size: int = checked(64, "at_least_one")
    gamma: float = checked(0.99, "discount")
    gae_lambda: float = checked(0.95, "discount")
    clip_epsilon: float = 0.2
    entropy_coef: float = checked(0.0, "non_negative")
    critic_coef: float = checked(0.5, "positive")
    max_grad_norm: float = checked(0.5, "positive")
    normalize_observations: bool = False  # a running mean/std in front of actor and critic
    ortho_init: bool = True  # SB3's initialisation of the default networks (see PPO)

    def __post_init__(self) -> None:
        super().__post_init__()
        check(
            self.clip_epsilon > 0,
            f"algo.clip_epsilon must be > 0 (the ratio's clip range), got {self.clip_epsilon}",
        )
        check(
            self.minibatch_size <= self.frames_per_batch,
            f"algo.minibatch_size ({self.minibatch_size}) must be <= algo.frames_per_batch "
            f"({self.frames_per_batch}), the frames of one rollout",
        )


@dataclass
class ReinforceConfig(AlgoConfig):
    """REINFORCE hyper-parameters; the defaults are the REINFORCE/ARS notebook's."""

    architecture: ClassVar[tuple[str, ...]] = (
        "hidden_sizes",
        "network",
        "baseline",
        "value_hidden_sizes",
    )

    name: str = "reinforce"
    eval_every: int = 5_000  # about one evaluation per epoch on the continuous CartPole
    eval_episodes: int = 20  # the notebook's test episodes
    epochs: int = checked(20, "at_least_one")  # the run's length, unless total_frames caps it
    hidden_sizes: list[int] = checked([], "sizes")  # []: a linear policy
    episodes_per_epoch: int = checked(100, "at_least_one")  # whole episodes per train_step
    updates_per_epoch: int = checked(50, "at_least_one")  # Adam steps, each on a random minibatch
    batch_size: int = checked(128, "at_least_one")
    gamma: float = checked(0.99, "discount")
    lr: float = checked(1e-3, "positive")
    weight_decay: float = checked(1e-4, "non_negative")
    # none: the notebook's weights; value: returns minus a learned V(s)
    baseline: str = checked("none", choices=BASELINES)
    value_hidden_sizes: list[int] = checked([64], "sizes")  # V(s)'s network
    value_lr: float = checked(1e-2, "positive")  # V(s)'s Adam learning rate (same weight decay)


def check_search_params(params: Any, prefix: str) -> None:
    """Value checks of the :data:`SEARCH_PARAMS` that ``params`` holds as attributes; errors
    name the key as ``<prefix><name>`` (``"algo."`` for :class:`ARSConfig`, ``""`` for
    :class:`rlpipe.algos.ars.ARSSearch`)."""
    check_fields(
        params,
        prefix,
        at_least_one=("num_directions", "episodes"),
        positive=("step_size", "noise"),
        non_negative=("workers", "bound_penalty"),
    )
    check(
        1 <= params.num_best <= params.num_directions,
        f"{prefix}num_best ({params.num_best}) must be between 1 and {prefix}num_directions "
        f"({params.num_directions})",
    )
    check_choice(params.fitness, f"{prefix}fitness", ARS_FITNESS)
    check_choice(params.backend, f"{prefix}backend", ARS_BACKENDS)


@dataclass
class RayConfig:
    """Where ``algo.backend=ray`` runs its rollout actors."""

    address: str | None = None  # null: start Ray on this machine; host:port or auto: a cluster
    num_cpus: int | None = None  # CPUs of a Ray started here (null: all the machine's)


@dataclass
class ARSConfig(AlgoConfig):
    """ARS hyper-parameters; the defaults are the workshop notebook's."""

    architecture: ClassVar[tuple[str, ...]] = ("policy", "hidden_sizes", "network")

    name: str = "ars"
    eval_every: int = 1_000_000  # frames between greedy evaluations (an iteration is 2N episodes)
    checkpoint_every: int = 1_000_000
    iterations: int = checked(1000, "at_least_one")  # the run's length, unless total_frames caps it
    num_directions: int = 16  # N: directions sampled per iteration (2N rollouts)
    num_best: int = 16  # b: directions kept for the update, by max(r+, r-)
    step_size: float = 0.02  # α
    # null: a constant α; a number: α annealed linearly to it over total_frames (or iterations)
    # so that the policy settles as the budget ends, rather than being caught mid-jump
    step_size_end: float | None = None
    noise: float = 0.03  # ν: perturbations are θ ± ν·δ
    # null: a constant ν; in (0, noise]: ν annealed linearly to it, as step_size_end does α
    # (a finer search near the end, where a walker that nearly walks is easily tipped over)
    noise_end: float | None = None
    # cap on training rollouts (the env's own limit still applies)
    episode_length: int = checked(2000, "at_least_one")
    # training rewards clipped to [-1, 1] (true: the notebook's), to [-c, c] (a number c: a
    # fall's -100 counts as -c) or not at all (false)
    reward_clip: bool | int | float = True
    # null: the clip bound stays; a number: the bound moves linearly from reward_clip's to it over
    # total_frames (or iterations), after the first reward_clip_from of them: e.g. 1 -> 10 from
    # 0.5, falls cost little while the walker learns to move and more once it walks
    reward_clip_end: float | None = None
    reward_clip_from: float = 0.0  # the fraction of the run before the bound starts to move
    alive_bonus_offset: float = 0.0  # added to every training reward (RL Zoo: -0.1 for Bipedal)
    # continuous actions: c x the sum of |raw output - clamped action| taken off every training
    # reward, so that the search stays where a perturbation changes the actions (0: none)
    bound_penalty: float = 0.0
    # what weighs the directions: returns (the ARS paper's), or ranks (each of the 2N training
    # returns replaced by its centred rank in [-0.5, 0.5], as OpenAI's ES does: a rollout that
    # falls ranks last, but no longer outweighs the other directions by the reward it lost)
    fitness: str = "returns"
    # episodes a perturbed policy runs per iteration, returns averaged (one before episodes_from)
    episodes: int = 1
    episodes_from: float = checked(0.0, "fraction")
    # several starts searched in turn, the worse half dropped at each of ceil(log2(starts))
    # rungs, one left after the first starts_until of the run (rlpipe/algos/ars/starts.py)
    starts: int = checked(1, "at_least_one")
    starts_until: float = 0.375
    normalize_observations: bool = True  # ARS V2: running mean/variance, frozen for evaluation
    policy: str = checked("linear", choices=ARS_POLICIES)
    hidden_sizes: list[int] = checked([32, 32], "sizes")  # policy=mlp only
    workers: int = 0  # rollout workers; 0: one per CPU core (Ray: per CPU of the cluster)
    backend: str = "local"  # local: this process or worker processes; ray: Ray actors
    ray: RayConfig = field(default_factory=RayConfig)  # backend=ray only

    def __post_init__(self) -> None:
        super().__post_init__()
        check_search_params(self, "algo.")
        check(
            self.step_size_end is None or 0 <= self.step_size_end <= self.step_size,
            f"algo.step_size_end must be null or in [0, algo.step_size ({self.step_size})], got "
            f"{self.step_size_end}: lower it, or set algo.step_size_end=null for a constant α",
        )
        check(
            self.noise_end is None or 0 < self.noise_end <= self.noise,
            f"algo.noise_end must be null or in (0, algo.noise ({self.noise})], got "
            f"{self.noise_end}: lower it, or set algo.noise_end=null for a constant ν",
        )
        check(
            isinstance(self.reward_clip, bool) or 0 < self.reward_clip < math.inf,
            f"algo.reward_clip must be true, false or a number > 0, got {self.reward_clip}",
        )
        check(
            self.reward_clip_end is None
            or (self.reward_bound is not None and 0 < self.reward_clip_end < math.inf),
            f"algo.reward_clip_end must be null, or a number > 0 with algo.reward_clip true or a "
            f"number, got {self.reward_clip_end} (algo.reward_clip="
            f"{str(self.reward_clip).lower()}): set algo.reward_clip_end=null for a fixed bound",
        )
        check(
            0 <= self.reward_clip_from < 1,
            f"algo.reward_clip_from must be in [0, 1) (the fraction of the run before the clip "
            f"bound moves), got {self.reward_clip_from}",
        )
        check(
            0 < self.starts_until < 1,
            f"algo.starts_until must be in (0, 1) (the fraction of the run after which one start "
            f"remains), got {self.starts_until}",
        )
        if isinstance(self.ray, dict):  # rebuilt from a run's config.yaml
            self.ray = RayConfig(**self.ray)

    def stepped_copies(self, num_envs: int) -> int:
        """The population's 2N episodes, stepped together whatever ``env.num_envs`` says."""
        return 2 * self.num_directions

    @property
    def reward_bound(self) -> float | None:
        """The bound training rewards are clipped to (None: not clipped)."""
        if isinstance(self.reward_clip, bool):
            return 1.0 if self.reward_clip else None
        return float(self.reward_clip)


@dataclass
class MBRLConfig(AlgoConfig):
    """Model-based RL hyper-parameters; the defaults are a PETS-like recipe for Pendulum-v1."""

    architecture: ClassVar[tuple[str, ...]] = ("hidden_sizes", "ensemble_size", "network")
    buffer_keys: ClassVar[tuple[str, ...]] = ("buffer_size",)

    name: str = "mbrl"
    total_frames: int | None = 15_000  # MBRL has no budget of its own: the run's length
    eval_every: int = 2_000  # every greedy eval step plans (eval_episodes x episode length)
    checkpoint_every: int = 5_000
    # models
    ensemble_size: int = checked(5, "at_least_one")  # dynamics MLPs, each on its own minibatches
    hidden_sizes: list[int] = checked([64, 64], "sizes")
    lr: float = checked(1e-3, "positive")
    weight_decay: float = checked(1e-4, "non_negative")
    batch_size: int = checked(256, "at_least_one")
    fit_steps: int = checked(200, "at_least_one")  # Adam steps on the models after each batch
    # transitions held out for the logged validation losses
    validation_fraction: float = checked(0.1, "fraction")
    buffer_size: int = checked(100_000, "at_least_one")
    # loop
    # uniformly random actions before the first fit
    warmup_frames: int = checked(400, "non_negative")
    frames_per_batch: int = checked(200, "at_least_one")  # env frames collected between two fits
    # planner
    planner: str = checked("cem", choices=PLANNERS)  # cem | random (random shooting)
    horizon: int = checked(15, "at_least_one")
    num_candidates: int = checked(100, "at_least_one")
    cem_iterations: int = checked(5, "at_least_one")  # CEM rounds (random shooting: 1)
    elites: int = 10
    gamma: float = checked(0.99, "discount")
    init_std: float = checked(0.5, "positive")  # CEM's first std, in half action ranges

    def __post_init__(self) -> None:
        super().__post_init__()
        check(
            1 <= self.elites <= self.num_candidates,
            f"algo.elites must be in [1, algo.num_candidates={self.num_candidates}], "
            f"got {self.elites}",
        )
