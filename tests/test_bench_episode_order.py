"""benchmarks/episode_order.py: early falls counted by each copy's episode number on an env that
falls at once after its third reset, and the script on a tiny trained run: one table row, its
figures saved and read back."""

from __future__ import annotations

import importlib

import gymnasium as gym
import numpy as np
import pytest
from conftest import benchmarks_importable
from trained_runs import ResetCounter, check_runs_script

from rlpipe.config import EnvConfig
from rlpipe.envs import make_env
from rlpipe.episodes import EvalResult
from rlpipe.evaluate import BASELINES


@pytest.fixture(scope="module")
def episode_order():
    with benchmarks_importable():
        yield importlib.import_module("episode_order")


class ThirdFalls(ResetCounter):
    """10 steps of reward 1 an episode, except after the env's third reset: one step of reward
    -100 (BipedalWalker's Box2D world after its third reset, caricatured)."""

    def step(self, action):
        self.t += 1
        if self.resets == 3:
            return np.zeros(2, np.float32), -100.0, True, False, {}
        return np.zeros(2, np.float32), 1.0, False, self.t >= 10, {}


def test_early_falls_counts_short_negative_episodes(episode_order):
    result = EvalResult(returns=[-99.0, 250.0, -50.0, -1.0], lengths=[58, 1600, 400, 200])
    assert episode_order.early_falls(result) == 2


def test_falls_by_order_finds_the_third_episode(episode_order):
    if "rlpipe-test/ThirdFalls-v0" not in gym.registry:
        gym.register("rlpipe-test/ThirdFalls-v0", entry_point=ThirdFalls)
    cfg = EnvConfig(id="rlpipe-test/ThirdFalls-v0", backend="gymnasium")
    probe = make_env(cfg, num_envs=1)
    try:
        policy = BASELINES["random"](probe)
    finally:
        probe.close()
    n = episode_order.COPIES  # seeding resets each gymnasium copy once (TorchRL's set_seed),
    # so a copy's third reset starts its second episode
    assert episode_order.falls_by_order(policy, cfg, seed=0) == [0, n, 0, 0]


def test_episode_order_script_on_a_trained_run(run_copy, tmp_path):
    check_runs_script("episode_order.py", run_copy, "order-3-seed7.json", 7, tmp_path)
