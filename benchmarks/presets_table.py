"""The presets benchmarks/presets.py measures (presets.yaml) and the held-out seed protocol.

The protocol: a preset is tuned on any seeds below 100 or from 1000 up (``tuned_on`` says which were
used) and published on its held-out seeds (100-109; ``sac_bipedal``, hours per seed: 100-102), which
no tuning run, sweep or trial may touch; 110-999 stay untouched, for others' checks of the published
figures. Solved, per seed: the mean of the last three evals and the final 100-episode greedy eval
both ≥ the target. The target is the RL Zoo's figure where the Zoo has one for that algorithm and
env (its benchmark.md: one run, the deterministic policy), else the aim the preset was tuned to
(``target_from`` says which). ``floor``: a uniformly random policy's mean over 100 episodes, for
scores normalised as (score - floor) / (target - floor). Each preset's entry, with SB3's settings,
is data in ``presets.yaml``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

from rlpipe.errors import RlpipeError, check

HELD_OUT = tuple(range(100, 110))  # the seeds results are published on
RESERVED = range(100, 1000)  # held-out seeds and checks of them: never a tuning seed
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
    tuned_on: tuple[int, ...]  # the seeds its tuning runs used (< 100 or >= 1000)
    held_out: tuple[int, ...] = HELD_OUT
    final_episodes: int = 100  # episodes of the final greedy eval
    sb3: dict[str, Any] | None = None  # SB3 keyword arguments (RL Zoo's hyperparams/<algo>.yml)
    sb3_algo: str = ""  # the SB3 (or sb3-contrib) class they are for
    sb3_policy: str = "MlpPolicy"
    sb3_envs: int = 1  # the Zoo's n_envs
    sb3_normalize: bool = False  # the Zoo's VecNormalize(norm_obs=True, norm_reward=False)
    no_sb3: str = ""  # why SB3 has no counterpart (sb3 is None)
    # hours-long presets: both sides save at every eval, and a call that finds an interrupted
    # run in --out continues it (rlpipe from its newest checkpoint, SB3 from its newest save)
    resumable: bool = False
    # where the preset stays short of 8 of 10 held-out seeds: why, in a sentence (what was tried:
    # its section of docs/tuning.md)
    short_of: str = ""
    # where its time to the target stays above SPEED_TARGET x SB3's: why, in a sentence
    slow: str = ""

    @property
    def fell_below(self) -> float:
        """An eval below this, once one reached the target, fell back: the target less a tenth of
        target - floor."""
        return self.target - 0.1 * (self.target - self.floor)

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


def schedule(value: Any) -> Any:
    """A Zoo value as SB3 takes it: ``lin_<x>`` is :class:`linear` from x."""
    if isinstance(value, str) and value.startswith("lin_"):
        return linear(float(value[4:]))
    return value


TABLE = Path(__file__).with_name("presets.yaml")


def load(path: Path = TABLE) -> dict[str, Preset]:
    """The presets of ``presets.yaml`` (its header says what each key means)."""
    table = yaml.safe_load(path.read_text())
    presets = {}
    for name, entry in table.items():
        sb3 = entry.pop("sb3", None) or {}
        for key in ("tuned_on", "held_out"):
            entry[key] = tuple(entry.get(key, HELD_OUT))
        presets[name] = Preset(
            name,
            **entry,
            sb3={k: schedule(v) for k, v in sb3["kwargs"].items()} if sb3 else None,
            sb3_algo=sb3.get("algo", ""),
            sb3_policy=sb3.get("policy", "MlpPolicy"),
            sb3_envs=sb3.get("n_envs", 1),
            sb3_normalize=sb3.get("normalize", False),
        )
    return presets


PRESETS = load()


def seeds_for(
    presets: Sequence[Preset], seeds: Sequence[int] | None, tune: bool, overrides: Sequence[str]
) -> dict[str, tuple[int, ...]]:
    """Each preset's seeds under the protocol: its held-out seeds by default; ``--tune`` runs
    only seeds outside 100-999 (and must name them); a published run only held-out seeds, and
    no override that changes what a run learns."""
    if tune:
        check(seeds is not None, "--tune needs --seeds: the tuning seeds, below 100 or >= 1000")
        touched = sorted({s for s in seeds if s in RESERVED})
        check(
            not touched,
            f"--tune refuses held-out seeds ({', '.join(map(str, touched))}): seeds 100-999 "
            "are for the published table and its checks only; tune on seeds below 100 or "
            "from 1000 up",
        )
        return {p.experiment: tuple(dict.fromkeys(seeds)) for p in presets}
    learning = [o for o in overrides if o.lstrip("+~").split("=")[0] not in NEUTRAL_KEYS]
    check(
        not learning,
        f"--override {' '.join(learning)} changes the preset: that is tuning, so add --tune "
        "and tuning seeds (below 100 or from 1000 up); held-out runs take only "
        + ", ".join(f"{k}=" for k in NEUTRAL_KEYS),
    )
    chosen = {}
    for p in presets:
        wanted = p.held_out if seeds is None else tuple(dict.fromkeys(seeds))
        outside = [s for s in wanted if s not in p.held_out]
        if outside:
            raise RlpipeError(
                f"seed(s) {', '.join(map(str, outside))}: not {p.experiment}'s held-out seeds "
                f"({p.held_out[0]}-{p.held_out[-1]}): add --tune to run tuning seeds "
                "(< 100 or >= 1000)"
            )
        chosen[p.experiment] = wanted
    return chosen
