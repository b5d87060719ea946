"""SAC from TorchRL parts: the tanh-Gaussian actor, twin critics and entropy tuning, bad input."""

from __future__ import annotations

from functools import partial

import torch
from conftest import TINY
from torchrl.envs import ExplorationType, set_exploration_type

from rlpipe.algos import SAC, Algorithm, SACConfig
from rlpipe.config import EnvConfig
from rlpipe.envs import make_env

SMALL = dict(
    batch_size=16,
    buffer_size=256,
    learning_starts=16,
    frames_per_batch=8,
    updates_per_batch=2,
    hidden_sizes=[16],
)
PENDULUM = EnvConfig(id="Pendulum-v1", num_envs=2)


def sac() -> SAC:
    torch.manual_seed(0)
    return SAC(partial(make_env, PENDULUM, seed=0), SACConfig(**SMALL))


def test_actions_in_bounds_and_greedy_is_deterministic():
    algo = sac()
    assert isinstance(algo, Algorithm)
    td = make_env(PENDULUM, seed=1).reset()
    sampled = algo.policy(td.clone())["action"]
    assert sampled.shape == (2, 1) and sampled.abs().max() <= 2.0  # tanh into [-2, 2]
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        first, second = algo.policy(td.clone())["action"], algo.policy(td.clone())["action"]
    assert torch.equal(first, second)
    algo.close()


def test_updates_move_actor_critics_and_alpha_and_the_targets_follow():
    algo = sac()
    before = {name: p.detach().clone() for name, p in algo.loss.named_parameters()}
    target = algo.loss.target_qvalue_network_params.clone()
    metrics = {}
    while "train/loss" not in metrics:
        metrics = algo.train_step()
    after = dict(algo.loss.named_parameters())
    assert all(not torch.equal(before[name], after[name]) for name in before)
    assert (algo.loss.target_qvalue_network_params != target).any()  # soft-updated
    assert metrics["train/alpha"] != 1.0 and torch.isfinite(torch.tensor(metrics["train/loss"]))
    algo.close()


def test_discrete_env_is_one_line(rlpipe_cli):
    done = rlpipe_cli(*TINY, "algo=sac", "env=cartpole")
    assert done.returncode == 2
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and "SAC needs continuous actions" in lines[0], lines


def test_cli_trains_sac(rlpipe_cli):
    done = rlpipe_cli(
        *TINY,
        "algo=sac",
        "env=pendulum",
        "algo.hidden_sizes=[16]",
        "algo.learning_starts=50",
        "algo.batch_size=32",
    )
    assert done.returncode == 0, done.stderr
    assert "200 frames" in done.stdout
