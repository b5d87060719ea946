"""benchmarks/episode_ends.py: each episode sorted by how it ended (a fall, another termination,
the time limit) on an env whose episodes end each way in turn, and the script on a tiny trained
run: one table row, its episodes saved and read back."""

from __future__ import annotations

import importlib
import subprocess
import sys
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
from conftest import benchmarks_importable

from rlpipe.config import EnvConfig
from rlpipe.envs import make_env
from rlpipe.evaluate import BASELINES

BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"
# (last reward, terminated, truncated, steps) of the episodes, in turn
ENDS = [(-100.0, True, False, 5), (1.0, True, False, 7), (1.0, False, True, 10)]


@pytest.fixture(scope="module")
def episode_ends():
    with benchmarks_importable():
        yield importlib.import_module("episode_ends")


class EndsInTurn(gym.Env):
    """Episodes of reward 1 a step that end in turn in a fall (-100 at step 5), at a goal (step 7)
    and at the time limit (step 10)."""

    observation_space = gym.spaces.Box(-1.0, 1.0, (2,), np.float32)
    action_space = gym.spaces.Box(-1.0, 1.0, (1,), np.float32)

    def __init__(self) -> None:
        self.resets, self.t = 0, 0

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.resets, self.t = self.resets + 1, 0
        return np.zeros(2, np.float32), {}

    def step(self, action):
        self.t += 1
        last, terminated, truncated, steps = ENDS[self.resets % len(ENDS)]
        if self.t < steps:
            return np.zeros(2, np.float32), 1.0, False, False, {}
        return np.zeros(2, np.float32), last, terminated, truncated, {}


def test_each_episode_is_sorted_by_its_end(episode_ends):
    if "rlpipe-test/EndsInTurn-v0" not in gym.registry:
        gym.register("rlpipe-test/EndsInTurn-v0", entry_point=EndsInTurn)
    env = make_env(EnvConfig(id="rlpipe-test/EndsInTurn-v0", backend="gymnasium"), num_envs=1)
    try:
        ends = episode_ends.episode_ends(BASELINES["random"](env), env, 3, fall_reward=-100.0)
    finally:
        env.close()
    got = sorted((e["end"], e["steps"], e["return"]) for e in ends)
    assert got == [("fall", 5, -96.0), ("terminated", 7, 7.0), ("time limit", 10, 10.0)]


def test_episode_ends_script_on_a_trained_run(run_copy, tmp_path):
    command = [sys.executable, str(BENCHMARKS / "episode_ends.py"), str(run_copy)]
    command += ["--episodes", "3"]
    out = tmp_path / "BENCH.md"
    proc = subprocess.run([*command, "--append", str(out)], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    rows = [line for line in out.read_text().splitlines() if line.startswith("| `")]
    assert len(rows) == 1 and rows[0].count("|") == 9, out.read_text()
    saved = run_copy / "evaluation" / "ends-3-seed7.json"
    stamp = saved.stat().st_mtime_ns
    again = subprocess.run(command, capture_output=True, text=True)
    assert again.returncode == 0 and rows[0] in again.stdout, again.stderr
    assert saved.stat().st_mtime_ns == stamp
