"""What a run ends with: its result, or the errors that stop it (interrupted, diverged)."""

from __future__ import annotations

import math
import signal
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from rlpipe.errors import RlpipeError


def counted(number: int, noun: str) -> str:
    """``number`` and ``noun``, plural unless one: "1 episode", "20 episodes"."""
    return f"{number:,} {noun}{'' if number == 1 else 's'}"


@dataclass
class RunResult:
    """What a finished run reports (also written to ``summary.json`` in the run dir)."""

    eval_mean: float
    eval_std: float
    eval_episodes: int
    frames: int
    wall_time: float
    run_dir: str

    def summary_line(self) -> str:
        return (
            f"final eval {self.eval_mean:.2f} ± {self.eval_std:.2f} over "
            f"{counted(self.eval_episodes, 'episode')} | {self.frames:,} frames | "
            f"{self.wall_time:.1f} s | run dir {self.run_dir}"
        )


class Interrupted(RlpipeError):
    """SIGINT or SIGTERM stopped the run after a final checkpoint (``exit_code``: 128 + signal)."""

    def __init__(self, signum: int, frames: int, checkpoint: Path) -> None:
        name = self.signal_name = signal.Signals(signum).name
        super().__init__(
            f"{name} received: stopped at {frames:,} frames, checkpoint {checkpoint}; "
            f"resume with the same command plus resume={checkpoint.parent.parent}"
        )
        self.exit_code = 128 + signum


class Diverged(RlpipeError):
    """A loss or a parameter became NaN or infinite; no checkpoint is written after it."""


def not_finite(
    metrics: Mapping[str, Any] | None, keys: Iterable[str], parameters: Iterable[Any]
) -> str | None:
    """What diverged: the first of ``keys`` whose value (a number or a list) in ``metrics`` is
    not finite, or, with ``metrics`` None, ``"policy parameters"`` when a tensor of
    ``parameters`` is not (None: all finite)."""
    if metrics is None:
        finite = all(bool(p.isfinite().all()) for p in parameters)
        return None if finite else "policy parameters"
    for key in keys:
        value = metrics.get(key, 0.0)
        if not all(math.isfinite(v) for v in (value if isinstance(value, list) else [value])):
            return key
    return None
