"""PPO from TorchRL parts: policies and critic, the clipped loss, GAE, learning, bad input."""

from __future__ import annotations

from functools import partial

import pytest
import torch
from conftest import TINY, assert_auto_chose
from torchrl.envs import ExplorationType, set_exploration_type

from rlpipe.algos import PPO, Algorithm, PPOConfig
from rlpipe.config import EnvConfig
from rlpipe.envs import make_env
from rlpipe.episodes import evaluate
from rlpipe.errors import RlpipeError

SMALL = dict(frames_per_batch=64, minibatch_size=16, epochs=2)


def ppo(env_id: str, **kwargs) -> PPO:
    torch.manual_seed(0)
    return PPO(partial(make_env, EnvConfig(id=env_id, num_envs=2), seed=0), PPOConfig(**kwargs))


@pytest.mark.parametrize(("env_id", "shape"), [("CartPole-v1", (3,)), ("Pendulum-v1", (3, 1))])
def test_policy_samples_in_bounds_and_greedy_is_deterministic(env_id, shape):
    algo = ppo(env_id, **SMALL)
    assert isinstance(algo, Algorithm)
    td = make_env(EnvConfig(id=env_id, num_envs=3), seed=1).reset()
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        first, second = algo.policy(td.clone())["action"], algo.policy(td.clone())["action"]
    assert first.shape == shape and torch.equal(first, second)
    if env_id == "Pendulum-v1":
        sampled = algo.policy(td.clone())["action"]
        assert sampled.abs().max() <= 2.0  # clipped into the bounds
        assert any(isinstance(m, torch.nn.Tanh) for m in algo.policy.modules())
    algo.close()


def test_a_step_computes_advantages_and_moves_actor_and_critic():
    algo = ppo("Pendulum-v1", **SMALL)
    before = [p.detach().clone() for p in algo.loss.parameters()]
    metrics = algo.train_step()
    assert algo.frames == 64 and torch.isfinite(torch.tensor(metrics["train/loss"]))
    moved = [not torch.equal(a, b) for a, b in zip(before, algo.loss.parameters())]
    assert all(moved)  # actor, free log-std and critic all trained
    algo.close()


def test_schedules_anneal_lr_and_clip_range_over_the_run_and_resume():
    algo = ppo("CartPole-v1", **SMALL, lr=1e-3, anneal_lr=True, anneal_clip=True, total_frames=256)
    algo.train_step()
    algo.train_step()  # half the run: both at half their start
    assert algo.optimizer.param_groups[0]["lr"] == pytest.approx(5e-4)
    assert float(algo.loss.clip_epsilon) == pytest.approx(0.1)
    other = ppo("CartPole-v1", **SMALL, anneal_clip=True, total_frames=256)
    other.load_state_dict(algo.state_dict())
    assert float(other.loss.clip_epsilon) == pytest.approx(0.1)
    algo.close()
    other.close()


def test_default_networks_start_orthogonal_and_a_users_network_is_left_alone():
    algo = ppo("CartPole-v1", **SMALL)
    linears = [m for m in algo.policy.modules() if isinstance(m, torch.nn.Linear)]
    first, last = linears[0].weight, linears[-1].weight
    gram = first.T @ first  # [64, 4]: orthogonal columns, gain √2
    assert torch.allclose(gram, 2.0 * torch.eye(4), atol=1e-4)
    assert last.norm(dim=1).max() <= 0.011 and not linears[0].bias.any()
    algo.close()
    torch.manual_seed(0)
    mine = torch.nn.Linear(4, 2)
    kept = mine.weight.detach().clone()
    algo = PPO(
        partial(make_env, EnvConfig(id="CartPole-v1", num_envs=2), seed=0),
        PPOConfig(**SMALL),
        network=mine,
    )
    assert torch.equal(mine.weight, kept)
    algo.close()


def test_observation_normaliser_follows_the_rollouts_and_is_saved():
    algo = ppo("Pendulum-v1", **SMALL, normalize_observations=True)
    algo.train_step()
    assert algo.normalizer.count == 64
    state = algo.state_dict()
    other = ppo("Pendulum-v1", **SMALL, normalize_observations=True)
    other.load_state_dict(state)
    assert torch.equal(other.normalizer.loc, algo.normalizer.loc) and other.frames == 64
    algo.close()
    other.close()


def test_learns_cartpole():
    algo = ppo("CartPole-v1", frames_per_batch=1024, minibatch_size=128, epochs=10, lr=1e-3)
    while algo.frames < 12_000:
        algo.train_step()
    env = make_env(EnvConfig(id="CartPole-v1", num_envs=5), seed=123)
    result = evaluate(algo.policy, env, 10)
    assert result.mean > 150, result.returns  # the untrained policy: about 20
    algo.close()


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["algo.clip_epsilon=0"], "algo.clip_epsilon must be > 0"),
        (
            ["algo.minibatch_size=4096"],
            "algo.minibatch_size (4096) must be <= algo.frames_per_batch",
        ),
        (["env=gym", "env.id=MultiDiscreteNope-v0"], "cannot make gymnasium env"),
    ],
)
def test_cli_bad_input_is_one_line(rlpipe_cli, args, message):
    done = rlpipe_cli(*TINY, "algo=ppo", *args)
    assert done.returncode == 2
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and message in lines[0], lines


def test_cli_trains_ppo(rlpipe_cli):
    done = rlpipe_cli(*TINY, "algo=ppo", "algo.frames_per_batch=100", "algo.minibatch_size=50")
    assert done.returncode == 0, done.stderr
    assert "200 frames" in done.stdout
    assert_auto_chose(done.stdout, copies=1)


def test_bad_clip_is_refused_from_python():
    with pytest.raises(RlpipeError, match="clip_epsilon"):
        PPOConfig(clip_epsilon=-0.1)
