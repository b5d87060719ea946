"""benchmarks/env_backends.py's walking start: the committed policy loads into ars_bipedal's ARS
policy and walks (its steps/s are those of walking episodes, not of falls)."""

from __future__ import annotations

import importlib

import torch
from conftest import benchmarks_importable

from rlpipe import compose_run, make_env
from rlpipe.algos.ars import make_ars_policy
from rlpipe.config import EnvConfig
from rlpipe.episodes import evaluate


def test_the_walking_start_walks():
    cfg = compose_run("+experiment=ars_bipedal")
    env_cfg = EnvConfig(id=cfg.env.id, backend="gymnasium")
    policy, normalizer = make_ars_policy(make_env(env_cfg, num_envs=1), cfg.algo)
    with benchmarks_importable():
        importlib.import_module("env_backends").load_walker(policy)
    assert normalizer.count > 1e6 and torch.count_nonzero(policy[1].module.weight) == 4 * 24
    result = evaluate(policy, make_env(env_cfg, num_envs=2, seed=5), episodes=2)
    # it walks (about 300; a zero policy stands at about -90), though some episodes fall
    assert max(result.returns) > 250


def test_off_policy_presets_are_timed_past_their_random_action_start(monkeypatch):
    """A DQN preset's clock starts at its learning_starts: the window holds its updates."""
    with benchmarks_importable():
        module = importlib.import_module("env_backends")
    monkeypatch.setitem(module.PRESETS, "dqn_cartpole", ("CartPole-v1 ×16, DQN", ("frames", 256)))
    result = module.measure("dqn_cartpole", "gymnasium")
    starts = compose_run("+experiment=dqn_cartpole").algo.learning_starts
    assert result["from"] >= starts == 1000 and 256 <= result["steps"] < 256 + 128
