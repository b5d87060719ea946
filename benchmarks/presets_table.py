"""The presets benchmarks/presets.py measures: target, seeds (tuning and held-out), SB3's settings.

The protocol: a preset is tuned on any seeds below 100 (``tuned_on`` says which were used) and
published on its held-out seeds (100-109; ``sac_bipedal``, hours per seed: 100-102), which no
tuning run, sweep or trial may touch. Solved, per seed: the mean of the last three evals and
the final 100-episode greedy eval both ≥ the target. The target is the RL Zoo's figure where
the Zoo has one for that algorithm and env (its benchmark.md: one run, the deterministic policy),
else the aim the preset was tuned to (``target_from`` says which). ``floor``: a uniformly random
policy's mean over 100 episodes (``python -m rlpipe.evaluate policy=random env=<env>
episodes=100``), for scores normalised as (score - floor) / (target - floor).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

from rlpipe.errors import RlpipeError, check

HELD_OUT = tuple(range(100, 110))  # the seeds results are published on
NET_256 = dict(net_arch=[256, 256])
# overrides that change how a run executes, not what it learns: allowed on held-out seeds
NEUTRAL_KEYS = ("env.backend", "threads", "device")


@dataclass(frozen=True)
class Preset:
    """One tuned preset (``+experiment=<experiment>``), its target and its SB3 counterpart."""

    experiment: str
    env: str
    target: float
    target_from: str  # where the target comes from
    floor: float  # a random policy's 100-episode mean (the normalisation's 0)
    tuned_on: tuple[int, ...]  # the seeds its tuning runs used (all < 100)
    held_out: tuple[int, ...] = HELD_OUT
    final_episodes: int = 100  # episodes of the final greedy eval
    sb3: dict[str, Any] | None = None  # SB3 keyword arguments (RL Zoo's hyperparams/<algo>.yml)
    sb3_algo: str = "DQN"  # the SB3 (or sb3-contrib) class they are for
    sb3_policy: str = "MlpPolicy"
    sb3_envs: int = 1  # the Zoo's n_envs
    sb3_normalize: bool = False  # the Zoo's VecNormalize(norm_obs=True, norm_reward=False)
    no_sb3: str = ""  # why SB3 has no counterpart (sb3 is None)
    # hours-long presets: both sides save at every eval, and a call that finds an interrupted
    # run in --out continues it (rlpipe from its newest checkpoint, SB3 from its newest save)
    resumable: bool = False

    def normalised(self, score: float) -> float:
        """``score`` on the scale where the random policy is 0 and the target 1."""
        return (score - self.floor) / (self.target - self.floor)


class linear:  # noqa: N801 (named as the Zoo's lin_<start>)
    """The RL Zoo's ``lin_<start>`` schedule: ``start`` annealed linearly to 0 (picklable)."""

    def __init__(self, start: float) -> None:
        self.start = start

    def __call__(self, progress_remaining: float) -> float:
        return progress_remaining * self.start

    def __repr__(self) -> str:
        return f"lin_{self.start:g}"


# random-policy floors measured with python -m rlpipe.evaluate policy=random episodes=100
CARTPOLE, PENDULUM, BIPEDAL, CONTINUOUS_CARTPOLE = 21.0, -1257.9, -100.9, 31.1
ZOO = "RL Zoo's benchmark.md"

PRESETS: dict[str, Preset] = {
    "dqn_cartpole": Preset(
        "dqn_cartpole",
        "CartPole-v1",
        target=500.0,
        target_from=f"{ZOO}, DQN, 50k steps",
        floor=CARTPOLE,
        tuned_on=(0, 1, 2, 3, 4),
        sb3=dict(
            learning_rate=2.3e-3,
            batch_size=64,
            buffer_size=100_000,
            learning_starts=1000,
            gamma=0.99,
            target_update_interval=10,
            train_freq=256,
            gradient_steps=128,
            exploration_fraction=0.16,
            exploration_final_eps=0.04,
            policy_kwargs=NET_256,
        ),
    ),
    "dqn_mountaincar": Preset(
        "dqn_mountaincar",
        "MountainCar-v0",
        target=-100.8,
        target_from=f"{ZOO}, DQN, 120k steps",
        floor=-200.0,
        tuned_on=(0, 1, 2, 3, 4, 5),
        sb3=dict(
            learning_rate=4e-3,
            batch_size=128,
            buffer_size=10_000,
            learning_starts=1000,
            gamma=0.98,
            target_update_interval=600,
            train_freq=16,
            gradient_steps=8,
            exploration_fraction=0.2,
            exploration_final_eps=0.07,
            policy_kwargs=NET_256,
        ),
    ),
    "dqn_lunarlander": Preset(
        "dqn_lunarlander",
        "LunarLander-v3",
        target=154.4,
        target_from=f"{ZOO}, DQN, 100k steps, measured on LunarLander-v2",
        floor=-187.7,
        tuned_on=(0, 1, 2),
        sb3=dict(
            learning_rate=6.3e-4,
            batch_size=128,
            buffer_size=50_000,
            learning_starts=0,
            gamma=0.99,
            target_update_interval=250,
            train_freq=4,
            gradient_steps=-1,
            exploration_fraction=0.12,
            exploration_final_eps=0.1,
            policy_kwargs=NET_256,
        ),
    ),
    "reinforce_cartpole": Preset(
        "reinforce_cartpole",
        "rlpipe/CartPoleContinuous-v0",
        target=50.0,
        target_from="the 50-step horizon, the aim of conf/tuned/reinforce_cartpole_continuous.yaml",
        floor=CONTINUOUS_CARTPOLE,
        tuned_on=tuple(range(9)),
        no_sb3="SB3 has no REINFORCE",
    ),
    "ars_cartpole": Preset(
        "ars_cartpole",
        "CartPole-v1",
        target=500.0,
        target_from=f"{ZOO}, ARS, 50k steps",
        floor=CARTPOLE,
        tuned_on=(0, 1, 2),
        sb3=dict(n_delta=2),
        sb3_algo="ARS",
        sb3_policy="LinearPolicy",
    ),
    "ars_pendulum": Preset(
        "ars_pendulum",
        "Pendulum-v1",
        target=-212.5,
        target_from=f"{ZOO}, ARS, 2M steps",
        floor=PENDULUM,
        tuned_on=(0, 1, 2),
        sb3=dict(
            learning_rate=0.018,
            n_delta=4,
            n_top=1,
            delta_std=0.1,
            zero_policy=False,
            policy_kwargs=dict(net_arch=[16]),
        ),
        sb3_algo="ARS",
        sb3_normalize=True,
    ),
    "ars_bipedal": Preset(
        "ars_bipedal",
        "BipedalWalker-v3",
        target=300.0,
        target_from="BipedalWalker-v3's 'solved' (the Zoo has no ARS figure for it), the aim of "
        "conf/tuned/ars_bipedal.yaml",
        floor=BIPEDAL,
        tuned_on=(0, 1, 2),
        sb3=dict(
            learning_rate=0.02,
            delta_std=0.0075,
            n_delta=64,
            n_top=32,
            alive_bonus_offset=-0.1,
            policy_kwargs=dict(net_arch=[16]),
        ),
        sb3_algo="ARS",
        sb3_normalize=True,
        resumable=True,  # SB3's ARS steps one env: hours per seed at 30 M frames
    ),
    "mbrl_pendulum": Preset(
        "mbrl_pendulum",
        "Pendulum-v1",
        target=-250.0,
        target_from="the target of benchmarks/mbrl_sample_efficiency.py",
        floor=PENDULUM,
        tuned_on=(0, 1, 2),
        no_sb3="SB3 has no model-based RL",
    ),
    "mbrl_cartpole": Preset(
        "mbrl_cartpole",
        "rlpipe/CartPoleContinuous-v0",
        target=50.0,
        target_from="the 50-step horizon (benchmarks/mbrl_sample_efficiency.py's target)",
        floor=CONTINUOUS_CARTPOLE,
        tuned_on=(0, 1, 2),
        no_sb3="SB3 has no model-based RL",
    ),
    "ppo_cartpole": Preset(
        "ppo_cartpole",
        "CartPole-v1",
        target=500.0,
        target_from=f"{ZOO}, PPO, 100k steps",
        floor=CARTPOLE,
        tuned_on=(0, 1, 2),
        sb3=dict(
            n_steps=32,
            batch_size=256,
            gae_lambda=0.8,
            gamma=0.98,
            n_epochs=20,
            ent_coef=0.0,
            learning_rate=linear(1e-3),
            clip_range=linear(0.2),
        ),
        sb3_algo="PPO",
        sb3_envs=8,
    ),
    "sac_pendulum": Preset(
        "sac_pendulum",
        "Pendulum-v1",
        target=-157.0,
        target_from=f"{ZOO}, SAC, 20k steps",
        floor=PENDULUM,
        tuned_on=(0, 1, 2),
        sb3=dict(learning_rate=1e-3),
        sb3_algo="SAC",
    ),
    "sac_bipedal": Preset(
        "sac_bipedal",
        "BipedalWalker-v3",
        target=297.7,
        target_from=f"{ZOO}, SAC, 500k steps",
        floor=BIPEDAL,
        tuned_on=(0, 1, 2),
        held_out=(100, 101, 102),  # ~2.5 h of training per seed and side on 2 cores
        sb3=dict(
            learning_rate=7.3e-4,
            buffer_size=300_000,
            batch_size=256,
            ent_coef="auto",
            gamma=0.98,
            tau=0.02,
            train_freq=64,
            gradient_steps=64,
            learning_starts=10_000,
            use_sde=True,
            policy_kwargs=dict(log_std_init=-3, net_arch=[400, 300]),
        ),
        sb3_algo="SAC",
        resumable=True,
    ),
}


def seeds_for(
    presets: Sequence[Preset], seeds: Sequence[int] | None, tune: bool, overrides: Sequence[str]
) -> dict[str, tuple[int, ...]]:
    """Each preset's seeds under the protocol: its held-out seeds by default; ``--tune`` runs
    only seeds below 100 (and must name them); a published run only held-out seeds, and no
    override that changes what a run learns."""
    if tune:
        check(seeds is not None, "--tune needs --seeds: the tuning seeds, all below 100")
        touched = sorted({s for s in seeds if s >= 100})
        check(
            not touched,
            f"--tune refuses held-out seeds ({', '.join(map(str, touched))}): seeds 100 and "
            "above are for the published table only; tune on seeds below 100",
        )
        return {p.experiment: tuple(dict.fromkeys(seeds)) for p in presets}
    learning = [o for o in overrides if o.lstrip("+~").split("=")[0] not in NEUTRAL_KEYS]
    check(
        not learning,
        f"--override {' '.join(learning)} changes the preset: that is tuning, so add --tune "
        "and tuning seeds (below 100); held-out runs take only "
        + ", ".join(f"{k}=" for k in NEUTRAL_KEYS),
    )
    chosen = {}
    for p in presets:
        wanted = p.held_out if seeds is None else tuple(dict.fromkeys(seeds))
        outside = [s for s in wanted if s not in p.held_out]
        if outside:
            raise RlpipeError(
                f"seed(s) {', '.join(map(str, outside))}: not {p.experiment}'s held-out seeds "
                f"({p.held_out[0]}-{p.held_out[-1]}): add --tune to run tuning seeds (< 100)"
            )
        chosen[p.experiment] = wanted
    return chosen
