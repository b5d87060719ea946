"""What a run ends with: its result, or the errors that stop it (interrupted, diverged)."""

from __future__ import annotations

import signal
from dataclasses import dataclass
from pathlib import Path

from rlpipe.errors import RlpipeError


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
            f"final eval {self.eval_mean:.2f} ± {self.eval_std:.2f} over {self.eval_episodes} "
            f"episodes | {self.frames:,} frames | {self.wall_time:.1f} s | run dir {self.run_dir}"
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
