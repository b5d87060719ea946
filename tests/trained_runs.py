"""Helpers of the tests of benchmarks that evaluate trained runs: an env that counts its resets,
and a script's run on a trained run, its figures saved and read back."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import gymnasium as gym
import numpy as np

BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"


class ResetCounter(gym.Env):
    """Zero observations of shape (2,), one action in [-1, 1]; ``resets`` counts the resets and
    ``t`` the steps since the last (a subclass's ``step`` decides what an episode does)."""

    observation_space = gym.spaces.Box(-1.0, 1.0, (2,), np.float32)
    action_space = gym.spaces.Box(-1.0, 1.0, (1,), np.float32)

    def __init__(self) -> None:
        self.resets, self.t = 0, 0

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.resets, self.t = self.resets + 1, 0
        return np.zeros(2, np.float32), {}


def check_runs_script(script: str, run: Path, saved: str, cells: int, tmp_path: Path) -> None:
    """``benchmarks/<script> <run> --episodes 3 --append <md>`` publishes one table row of
    ``cells`` cells and saves its figures in ``<run>/evaluation/<saved>``; a second call reads
    them back (the file untouched) and prints the same row."""
    command = [sys.executable, str(BENCHMARKS / script), str(run), "--episodes", "3"]
    out = tmp_path / "BENCH.md"
    proc = subprocess.run([*command, "--append", str(out)], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    rows = [line for line in out.read_text().splitlines() if line.startswith("| `")]
    assert len(rows) == 1 and rows[0].count("|") == cells + 1, out.read_text()
    stamp = (run / "evaluation" / saved).stat().st_mtime_ns
    again = subprocess.run(command, capture_output=True, text=True)
    assert again.returncode == 0 and rows[0] in again.stdout, again.stderr
    assert (run / "evaluation" / saved).stat().st_mtime_ns == stamp
