"""SAC from TorchRL parts: the tanh-Gaussian actor, twin critics, entropy tuning, coloured
exploration noise, bad input."""

from __future__ import annotations

from functools import partial

import pytest
import torch
from conftest import TINY, torchrl_stepped
from torchrl.envs import ExplorationType, set_exploration_type

from rlpipe.algos import SAC, Algorithm, SACConfig
from rlpipe.algos.noise import ColoredNoise, powerlaw_noise
from rlpipe.config import EnvConfig
from rlpipe.envs import make_env
from rlpipe.errors import RlpipeError

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


def test_fixed_alpha_stays_at_its_start():
    torch.manual_seed(0)
    algo = SAC(
        partial(make_env, PENDULUM, seed=0), SACConfig(**SMALL, alpha_init=0.1, fixed_alpha=True)
    )
    metrics = {}
    while "train/loss" not in metrics:
        metrics = algo.train_step()
    metrics = algo.train_step()
    assert abs(metrics["train/alpha"] - 0.1) < 1e-6
    assert "log_alpha" not in dict(algo.loss.named_parameters())
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


def lag_one_correlation(draws: torch.Tensor) -> float:
    """The correlation of ``[steps, ...]`` draws with the next step's, over every entry."""
    centred = draws - draws.mean(0)
    return float((centred[1:] * centred[:-1]).mean() / centred.square().mean())


def test_coloured_noise_has_unit_variance_and_correlates_more_as_beta_grows():
    torch.manual_seed(0)
    lags = []
    for beta in (0.0, 1.0, 2.0):
        draws = powerlaw_noise(beta, (400,), 500)
        assert draws.shape == (400, 500)
        assert abs(draws.var(dim=-1).mean().item() - 1) < 0.05  # unit variance about its mean
        lags.append(lag_one_correlation(draws.T))
    assert abs(lags[0]) < 0.02 and 0.6 < lags[1] < 0.9 and lags[2] > 0.95, lags
    noise = ColoredNoise(1.0, (3, 2), steps=4)
    steps = [noise() for _ in range(9)]  # two sequences of 4 used up, the third begun
    assert all(step.shape == (3, 2) for step in steps)
    assert not torch.equal(torch.stack(steps[:4]), torch.stack(steps[4:8]))


def test_coloured_noise_colours_the_collecting_draws_only():
    torch.manual_seed(0)
    algo = SAC(partial(make_env, PENDULUM, seed=0), SACConfig(**SMALL, noise_color=2.0))
    obs = make_env(PENDULUM, seed=1).reset()["observation"]
    with torch.no_grad():
        actions = torch.stack([algo._explore(obs)["action"] for _ in range(200)])
    assert actions.shape == (200, 2, 1) and actions.abs().max() <= 2.0
    assert lag_one_correlation(actions) > 0.8  # white draws: about 0
    algo.close()


def test_coloured_noise_on_torchrl_s_collector_is_one_line():
    scaled_env = torchrl_stepped(PENDULUM)
    SAC(scaled_env, SACConfig(**SMALL)).close()  # white noise: fine on any env
    with pytest.raises(RlpipeError, match="algo.noise_color needs an env made by rlpipe.make_env"):
        SAC(scaled_env, SACConfig(**SMALL, noise_color=1.0))
    with pytest.raises(RlpipeError, match="algo.noise_steps must be >= 2"):
        SACConfig(**SMALL, noise_color=1.0, noise_steps=1)
