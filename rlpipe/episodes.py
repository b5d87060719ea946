"""Greedy evaluation of a policy over a fixed number of complete episodes."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import torch
from tensordict.nn import TensorDictModuleBase
from torchrl.envs import EnvBase, ExplorationType, set_exploration_type

from rlpipe import faults

MAX_EVAL_ENVS = 32  # env copies an evaluation steps in lock-step, at most
EVALUATION, FINAL = 0, 1  # episodes_seed's purposes: a run's evaluations; a benchmark's final eval


def episodes_seed(seed: int, purpose: int, n: int = 0) -> int:
    """The seed of a batch of episodes (an env seeded ``s`` starts copy ``i`` from ``s + i``).

    numpy's SeedSequence hashes the run's ``seed``, a ``purpose`` and ``n`` (an evaluation's
    frames) into 32 bits, so the evaluations of one run, and those of runs with adjacent seeds,
    meet fresh episode starts (consecutive seeds would share all copies but one), and the same
    (seed, purpose, n) the same starts: a resumed run's evaluations are the uninterrupted run's.
    """
    return int(np.random.SeedSequence(seed, spawn_key=(purpose, n)).generate_state(1)[0])


def eval_envs(episodes: int) -> int:
    """How many env copies to evaluate ``episodes`` episodes on: one each, capped."""
    return min(episodes, MAX_EVAL_ENVS)


def episode_quotas(n: int, episodes: int) -> torch.Tensor:
    """How many of ``episodes`` each of ``n`` lock-step env copies contributes.

    ``episodes // n`` each, +1 for the first ``episodes % n`` copies: a fixed share per copy
    keeps short episodes (which finish first) from being over-represented.
    """
    return torch.tensor([episodes // n + (i < episodes % n) for i in range(n)])


@dataclass
class EvalResult:
    """Returns and lengths of the evaluated episodes."""

    returns: list[float] = field(default_factory=list)
    lengths: list[int] = field(default_factory=list)

    @property
    def mean(self) -> float:
        return float(torch.tensor(self.returns).mean())

    @property
    def std(self) -> float:
        return float(torch.tensor(self.returns).std(unbiased=False))

    def metrics(self, prefix: str = "eval/") -> dict[str, float]:
        """Summary statistics, named for the logger."""
        returns = torch.tensor(self.returns)
        return {
            f"{prefix}return_mean": self.mean,
            f"{prefix}return_std": self.std,
            f"{prefix}return_min": float(returns.min()),
            f"{prefix}return_max": float(returns.max()),
            f"{prefix}length_mean": float(torch.tensor(self.lengths, dtype=torch.float).mean()),
        }


class EvalStopped(Exception):
    """``should_stop`` ended an evaluation before its episodes were done."""


@torch.no_grad()
def evaluate(
    policy: TensorDictModuleBase,
    env: EnvBase,
    episodes: int,
    should_stop: Callable[[], bool] | None = None,
) -> EvalResult:
    """Run ``episodes`` complete episodes of ``policy`` in deterministic mode on ``env``.

    The env's batch of ``n`` copies runs in lock-step; each contributes its first
    :func:`episode_quotas` episodes. Finished copies are reset and their extra episodes ignored.
    ``should_stop``, polled after every step, aborts the evaluation with :class:`EvalStopped`.
    """
    n = env.batch_size.numel()
    remaining = episode_quotas(n, episodes)
    result = EvalResult()
    policy_device = next(policy.parameters(), torch.empty(0)).device
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        td = env.reset()
        while bool((remaining > 0).any()):
            td = policy(td.to(policy_device)).to(env.device)
            td, td_next = env.step_and_maybe_reset(td)
            counted = td["next", "done"].reshape(n) & (remaining > 0)
            if bool(counted.any()):
                result.returns += td["next", "episode_reward"].reshape(n)[counted].tolist()
                result.lengths += td["next", "step_count"].reshape(n)[counted].tolist()
                remaining -= counted.long()
            td = td_next
            faults.point("eval")
            if should_stop is not None and should_stop():
                raise EvalStopped
    return result
