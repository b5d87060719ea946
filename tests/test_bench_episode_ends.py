"""benchmarks/episode_ends.py: each episode sorted by how it ended (a fall, another termination,
the time limit) on an env whose episodes end each way in turn, and the script on a tiny trained
run: one table row, its episodes saved and read back."""

from __future__ import annotations

import importlib
import subprocess
import sys

import gymnasium as gym
import numpy as np
import pytest
from conftest import benchmarks_importable
from trained_runs import BENCHMARKS, ResetCounter, check_runs_script

from rlpipe.config import EnvConfig
from rlpipe.envs import make_env
from rlpipe.evaluate import BASELINES

# (last reward, terminated, truncated, steps) of the episodes, in turn
ENDS = [(-100.0, True, False, 5), (1.0, True, False, 7), (1.0, False, True, 10)]


@pytest.fixture(scope="module")
def episode_ends():
    with benchmarks_importable():
        yield importlib.import_module("episode_ends")


class EndsInTurn(ResetCounter):
    """Episodes of reward 1 a step that end in turn in a fall (-100 at step 5), at a goal (step 7)
    and at the time limit (step 10)."""

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
    check_runs_script("episode_ends.py", run_copy, "ends-3-seed7.json", 8, tmp_path)


def test_a_run_dir_that_is_not_there_is_one_line(tmp_path):
    missing = tmp_path / "no-such-run"
    proc = subprocess.run(
        [sys.executable, str(BENCHMARKS / "episode_ends.py"), str(missing)],
        capture_output=True,
        text=True,
    )
    assert proc.returncode == 1, proc.stderr
    assert proc.stderr.strip() == f"episode_ends: run directory {missing} does not exist"
