"""Several ARS starts searched in turn and halved to the best until one remains (successive
halving over restarts): a walker stuck in a slow gait is dropped early rather than refined."""

from __future__ import annotations

import copy
import math
from typing import Any

from torch import nn

__all__ = ["Starts"]


class Starts:
    """``count`` candidate states of one policy (θ and its normaliser), stepped in turn.

    Before each iteration :meth:`next_turn` loads the live candidate that has taken the fewest
    env steps into ``policy``; after it :meth:`record` stores that candidate's new state with
    the iteration's figures, halves the live candidates at each rung, and loads the leader back
    (the candidate with the best score), so that evaluation, videos and checkpoints see the
    policy the run would return now. A candidate's score is the mean env return of its
    ``window`` latest iterations' perturbed rollouts: free of extra env steps, since the
    search rolls them out anyway.

    Rungs split ``[0, until]`` of the run (a fraction of its frames, or iterations) into
    ``ceil(log2(count))`` equal parts; at the end of each, the best ``ceil(live / 2)`` stay. All
    candidates begin from the policy's state at the first :meth:`next_turn` (``init_from``
    included) and part as soon as they draw their own directions.
    """

    def __init__(self, count: int, until: float, window: int = 3) -> None:
        self.count, self.until, self.window = count, until, window
        self.rungs = max(1, math.ceil(math.log2(count)))
        self.states: list[dict[str, Any]] = []  # filled at the first turn
        self.returns: list[list[float]] = [[] for _ in range(count)]
        self.steps = [0] * count
        self.live = list(range(count))
        self.halvings = 0
        self.turn = 0

    def next_turn(self, policy: nn.Module) -> None:
        """Load the live candidate with the fewest env steps into ``policy``."""
        if not self.states:
            self.states = [copy.deepcopy(policy.state_dict()) for _ in range(self.count)]
        self.turn = min(self.live, key=lambda k: (self.steps[k], k))
        policy.load_state_dict(self.states[self.turn])

    def record(self, policy: nn.Module, return_mean: float, steps: int, done: float) -> list[int]:
        """Keep the stepped candidate's state and figures; halve at a rung passed (``done``:
        the fraction of the run behind); load the leader into ``policy``. Returns the
        candidates dropped by this call (none mostly)."""
        k, dropped = self.turn, []
        self.states[k] = copy.deepcopy(policy.state_dict())
        self.returns[k] = (self.returns[k] + [return_mean])[-self.window :]
        self.steps[k] += steps
        while self.halvings < self.rungs and done >= self.until * (self.halvings + 1) / self.rungs:
            keep = math.ceil(len(self.live) / 2)
            ranked = sorted(self.live, key=self.score, reverse=True)
            self.live, dropped = ranked[:keep], dropped + ranked[keep:]
            self.halvings += 1
        for gone in dropped:
            self.states[gone] = {}  # a dropped candidate's state is not kept
        policy.load_state_dict(self.states[self.leader])
        return dropped

    def score(self, k: int) -> float:
        """Candidate ``k``'s mean return over its latest iterations (-inf before its first)."""
        recent = self.returns[k]
        return sum(recent) / len(recent) if recent else -math.inf

    @property
    def leader(self) -> int:
        """The live candidate with the best score (the first live one before any score)."""
        return max(self.live, key=lambda k: (self.score(k), -k))

    def state_dict(self) -> dict[str, Any]:
        """A copy of the candidates' states, figures and rung progress."""
        keys = ("states", "returns", "steps", "live", "halvings")
        return copy.deepcopy({key: getattr(self, key) for key in keys})

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore a :meth:`state_dict`."""
        for key, value in copy.deepcopy(state).items():
            setattr(self, key, value)
