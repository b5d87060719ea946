"""When the runner does things: metric windows between log flushes and frame cadences."""

from __future__ import annotations

import math
from collections import defaultdict


class Window:
    """Averages scalar metrics between two log flushes."""

    def __init__(self) -> None:
        self.sums: dict[str, float] = defaultdict(float)
        self.counts: dict[str, int] = defaultdict(int)

    def add(self, key: str, value: float) -> None:
        self.sums[key] += value
        self.counts[key] += 1

    def state(self) -> dict[str, dict[str, float]]:
        """The window's sums and counts, as plain data (a checkpoint keeps them)."""
        return {"sums": dict(self.sums), "counts": dict(self.counts)}

    def load(self, state: dict[str, dict[str, float]]) -> None:
        """Take back what :meth:`state` returned (an empty dict: an empty window)."""
        self.sums.clear()
        self.counts.clear()
        self.sums.update(state.get("sums", {}))
        self.counts.update(state.get("counts", {}))

    def pop(self) -> dict[str, float]:
        means = {k: self.sums[k] / self.counts[k] for k in self.sums}
        self.sums.clear()
        self.counts.clear()
        return means


class Cadence:
    """Something due every ``every`` frames: at the first multiple of ``every`` past the frames
    it last fired at (``every`` 0: never)."""

    def __init__(self, every: int, frames: int) -> None:
        self.every = every
        self._next = self._after(frames)

    def due(self, frames: int) -> bool:
        """Whether it is due at ``frames``; if so, the next time is set past ``frames``."""
        if frames < self._next:
            return False
        self._next = self._after(frames)
        return True

    def _after(self, frames: int) -> float:
        return (frames // self.every + 1) * self.every if self.every > 0 else math.inf
