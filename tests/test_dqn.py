"""DQN from TorchRL parts: shapes, the loss, the exploration schedule, one iteration."""

from __future__ import annotations

import math
from functools import partial

import pytest
import torch
from conftest import torchrl_stepped
from tensordict import TensorDict
from torchrl.data.postprocs import MultiStep

from rlpipe.algos import DQN, Algorithm, DQNConfig
from rlpipe.algos.dqn import HeldActions, epsilon, learning_rate, n_step_transitions
from rlpipe.config import EnvConfig
from rlpipe.envs import make_env
from rlpipe.errors import RlpipeError
from rlpipe.rundir import RunDir

SMALL = dict(
    batch_size=8, buffer_size=64, learning_starts=8, frames_per_batch=8, updates_per_batch=2
)


@pytest.fixture
def dqn():
    torch.manual_seed(0)
    algo = DQN(partial(make_env, EnvConfig(num_envs=2), seed=0), DQNConfig(**SMALL))
    yield algo
    algo.close()


def test_is_an_algorithm_with_notebook_network(dqn):
    assert isinstance(dqn, Algorithm)
    linears = [m for m in dqn.policy.modules() if isinstance(m, torch.nn.Linear)]
    assert [(m.in_features, m.out_features) for m in linears] == [(4, 128), (128, 128), (128, 2)]
    assert dqn.cfg.loss == "smooth_l1"


def test_layer_norm_follows_each_hidden_layer_of_the_q_network_and_trains():
    cfg = DQNConfig(**SMALL, hidden_sizes=[16, 8], layer_norm=True)
    algo = DQN(partial(make_env, EnvConfig(num_envs=2), seed=0), cfg)
    try:
        kinds = [type(m).__name__ for m in algo.policy.modules() if not list(m.children())]
        layers = ["Linear", "LayerNorm", "ReLU", "Linear", "LayerNorm", "ReLU", "Linear"]
        assert kinds == [*layers, "QValueModule"]
        for _ in range(3):  # past learning_starts: gradient steps through the norms
            metrics = algo.train_step()
        assert math.isfinite(metrics["train/loss"])
    finally:
        algo.close()


def test_greedy_policy_outputs_actions(dqn):
    td = make_env(EnvConfig(num_envs=5)).reset()
    out = dqn.policy(td)
    assert out["action"].shape == (5,)
    assert out["action_value"].shape == (5, 2)
    assert torch.equal(out["action"], out["action_value"].argmax(-1))


def test_loss_forward_backward_moves_the_online_net_only(dqn):
    while len(dqn.buffer) < 16:
        dqn.train_step()
    batch = dqn.buffer.sample(dqn.cfg.batch_size)
    assert batch.batch_size == torch.Size([8])
    loss = dqn.loss(batch)["loss"]
    assert loss.ndim == 0 and torch.isfinite(loss)
    before = [p.detach().clone() for p in dqn.loss.parameters()]
    target_before = dqn.loss.target_value_network_params.clone()
    dqn.optimizer.zero_grad()
    loss.backward()
    assert all(p.grad is not None for p in dqn.loss.parameters())
    dqn.optimizer.step()
    assert any(not torch.equal(a, b) for a, b in zip(before, dqn.loss.parameters()))
    assert (dqn.loss.target_value_network_params == target_before).all()


def test_soft_update_moves_target_by_tau(dqn):
    online = dqn.loss.value_network_params.clone()
    target = dqn.loss.target_value_network_params
    with torch.no_grad():
        for t in target.values(True, True):
            t.zero_()
    dqn.target_updater.step()
    for key, value in target.items(True, True):
        torch.testing.assert_close(value, dqn.cfg.tau * online[key])


def test_n_step_transitions_stop_at_episode_ends_and_do_not_bootstrap_past_a_terminal():
    # one env copy, 6 steps; rewards 1..6; the episode terminates at step 2, then a new one
    # runs to the batch's end. Observations are the step index.
    steps = torch.arange(6.0).reshape(1, 6, 1)
    flag = torch.zeros(1, 6, 1, dtype=torch.bool)
    flag[0, 2] = True
    batch = TensorDict(
        {
            "observation": steps,
            "next": {
                "observation": steps + 0.5,
                "reward": steps + 1,
                "done": flag.clone(),
                "terminated": flag.clone(),
            },
        },
        batch_size=[1, 6],
    )
    out = n_step_transitions(batch, MultiStep(gamma=0.5, n_steps=3))
    assert out["steps_to_next_obs"][0].tolist() == [3, 2, 1, 3, 2, 1]
    # 1 + .5*2 + .25*3; 2 + .5*3; 3; 4 + .5*5 + .25*6; 5 + .5*6; 6
    assert out["next", "reward"][0, :, 0].tolist() == [2.75, 3.5, 3.0, 8.0, 8.0, 6.0]
    assert out["next", "observation"][0, :, 0].tolist() == [2.5, 2.5, 2.5, 5.5, 5.5, 5.5]
    # the windows of steps 0-2 end in the terminal state: none of them bootstraps
    assert out["next", "terminated"][0, :, 0].tolist() == [True, True, True, False, False, False]
    assert out["next", "done"][0, :, 0].tolist() == [True, True, True, False, False, False]
    assert batch["next", "reward"][0, 0, 0] == 1  # the collected batch is left as it was


def test_n_step_dqn_stores_the_discount_exponent_and_trains():
    torch.manual_seed(0)
    algo = DQN(partial(make_env, EnvConfig(num_envs=2), seed=0), DQNConfig(**SMALL, n_steps=3))
    try:
        for _ in range(4):
            metrics = algo.train_step()
        sample = algo.buffer.sample(algo.cfg.batch_size)
        assert set(sample["steps_to_next_obs"].unique().tolist()) <= {1, 2, 3}
        assert math.isfinite(metrics["train/loss"])
    finally:
        algo.close()


def test_n_steps_beyond_one_batch_is_refused():
    with pytest.raises(
        RlpipeError, match=r"algo.n_steps \(5\) is more than the 4 steps.*at least 10"
    ):
        DQN(partial(make_env, EnvConfig(num_envs=2), seed=0), DQNConfig(**SMALL, n_steps=5))


def test_epsilon_schedules():
    cfg = DQNConfig()  # notebook: 0.9 -> 0.05, exponential with time constant 1000
    assert epsilon(0, cfg) == pytest.approx(0.9)
    assert epsilon(1000, cfg) == pytest.approx(0.05 + 0.85 * math.exp(-1))
    assert epsilon(10**6, cfg) == pytest.approx(0.05)
    lin = DQNConfig(eps_schedule="linear", eps_start=1.0, eps_end=0.1, eps_decay=100)
    assert [round(epsilon(t, lin), 6) for t in (0, 50, 100, 1000)] == [1.0, 0.55, 0.1, 0.1]


def test_learning_rate_schedule():
    assert learning_rate(10**6, DQNConfig(lr=1e-3)) == 1e-3  # lr_end null: constant
    cfg = DQNConfig(lr=1e-3, lr_end=1e-4, total_frames=1000)
    assert [learning_rate(t, cfg) for t in (0, 500, 1000, 5000)] == pytest.approx(
        [1e-3, 5.5e-4, 1e-4, 1e-4]
    )


def _target_changes(algo: DQN) -> list[bool]:
    """Per train_step (after learning starts): whether the target net moved."""
    moved = []
    for _ in range(6):
        before = algo.loss.target_value_network_params.clone()
        algo.train_step()
        after = algo.loss.target_value_network_params
        moved.append(any(not torch.equal(before[k], v) for k, v in after.items(True, True)))
    return moved


def test_hard_target_update_copies_every_n_frames():
    # 8 frames a step: a copy each time the frames pass a multiple of 16 (every second step)
    cfg = DQNConfig(**SMALL, tau=1.0, target_update_every=16)
    algo = DQN(partial(make_env, EnvConfig(num_envs=2), seed=0), cfg)
    algo.train_step()  # 8 frames: the buffer reaches learning_starts here
    assert _target_changes(algo) == [True, False, True, False, True, False]
    online, target = algo.loss.value_network_params, algo.loss.target_value_network_params
    algo.train_step()  # frames 64: a copy
    for key, value in target.items(True, True):
        torch.testing.assert_close(value, online[key])
    algo.close()


def test_lr_and_grad_norm_follow_the_config():
    cfg = DQNConfig(**SMALL, lr=1e-2, lr_end=0.0, total_frames=80, max_grad_norm=1e-6)
    algo = DQN(partial(make_env, EnvConfig(num_envs=2), seed=0), cfg)
    for _ in range(5):
        before = [p.detach().clone() for p in algo.policy.parameters()]
        algo.train_step()
    assert algo.optimizer.param_groups[0]["lr"] == pytest.approx(1e-2 * (1 - 40 / 80))
    # AdamW normalises the step, so a tiny clipped norm still moves: it must stay finite
    assert all(torch.isfinite(p).all() for p in algo.policy.parameters())
    assert any(not torch.equal(b, p) for b, p in zip(before, algo.policy.parameters()))
    algo.close()


@pytest.mark.parametrize(
    "kwargs, message",
    [
        ({"lr_end": 1.0}, "lr_end"),
        ({"lr_end": -1.0}, "lr_end"),
        ({"max_grad_norm": 0.0}, "max_grad_norm"),
        ({"target_update_every": -1}, "target_update_every"),
        ({"eps_zeta": 1.0}, "algo.eps_zeta must be null or > 1"),
    ],
)
def test_bad_schedule_values(kwargs, message):
    with pytest.raises(RlpipeError, match=message):
        DQNConfig(**kwargs)


def test_train_step_collects_updates_and_reports(dqn):
    first = dqn.train_step()
    assert dqn.frames == 8 and len(dqn.buffer) == 8
    assert "train/loss" not in first or dqn.cfg.learning_starts <= 8
    metrics = {}
    while dqn.frames < 200:
        metrics.update(dqn.train_step())
    assert dqn.frames == 200
    assert metrics["train/epsilon"] == pytest.approx(epsilon(200, dqn.cfg))
    assert math.isfinite(metrics["train/loss"])
    assert all(r >= 1 for r in metrics["train/episode_return"])


def test_frames_per_batch_rounds_up_to_whole_env_steps():
    algo = DQN(
        partial(make_env, EnvConfig(num_envs=3)), DQNConfig(**{**SMALL, "frames_per_batch": 4})
    )
    algo.train_step()
    assert algo.frames == 6
    algo.close()


def test_state_dict_round_trip(dqn):
    for _ in range(5):
        dqn.train_step()
    state = dqn.state_dict()
    other = DQN(partial(make_env, EnvConfig(num_envs=2)), DQNConfig(**SMALL))
    other.load_state_dict(state)
    assert other.frames == dqn.frames
    td = make_env(EnvConfig(num_envs=4), seed=3).reset()
    assert torch.equal(other.policy(td.clone())["action"], dqn.policy(td.clone())["action"])
    other.close()


def test_continuous_actions_are_refused():
    with pytest.raises(RlpipeError, match="discrete action space"):
        DQN(partial(make_env, EnvConfig(id="Pendulum-v1")), DQNConfig())


@pytest.mark.parametrize(("total", "expected"), [(100, 100), (102, 104)])
def test_total_frames_is_exact_to_whole_steps_of_the_copies(tmp_path, total, expected):
    """The last batch stops at the budget (16 frames per batch on 4 copies): exact when the
    budget is a multiple of the copies, else the next whole step; the cut batch is fresh data."""
    from rlpipe.runner import Runner

    env_cfg = EnvConfig(num_envs=4)
    algo = DQN(
        partial(make_env, env_cfg, seed=0),
        DQNConfig(**{**SMALL, "frames_per_batch": 16, "buffer_size": 128}),
    )
    eval_env = make_env(env_cfg, num_envs=2, seed=1)
    result = Runner(algo, eval_env, RunDir(tmp_path), total_frames=total, progress=False).run()
    assert result.frames == algo.frames == len(algo.buffer) == expected
    steps = algo.buffer[:expected]["observation"]
    assert len(torch.unique(steps, dim=0)) == expected  # no step stored twice
    algo.close()
    eval_env.close()


def test_held_random_actions_last_zeta_distributed_steps_then_greedy_returns():
    torch.manual_seed(0)
    copies = 20_000
    held = HeldActions(2.0, copies, device=torch.device("cpu"))
    greedy, random = torch.zeros(copies, dtype=torch.long), torch.ones(copies, dtype=torch.long)
    start, never = torch.ones(copies, dtype=torch.bool), torch.zeros(copies, dtype=torch.bool)
    steps = [held(start, random, greedy)]  # every copy starts a hold of action 1
    steps += [held(never, random, greedy) for _ in range(200)]  # then no new holds
    steps = torch.stack(steps)
    lengths = (steps == 1).sum(0)
    # a hold, once over, is over: greedy's 0 from then on
    assert torch.equal(steps, (torch.arange(201).unsqueeze(1) < lengths).long())
    # P(n) = n^-2 / zeta(2) over n <= 10,000: P(1) ≈ 0.608, P(2) ≈ 0.152, P(n > 200) ≈ 0.003
    assert abs((lengths == 1).float().mean().item() - 0.608) < 0.02
    assert abs((lengths == 2).float().mean().item() - 0.152) < 0.015
    assert (lengths > 200).float().mean().item() < 0.01


def test_eps_zeta_holds_the_collecting_policy_s_random_actions():
    torch.manual_seed(0)
    env = partial(make_env, EnvConfig(num_envs=2), seed=0)
    algo = DQN(env, DQNConfig(**SMALL, eps_start=1.0, eps_end=1.0, eps_zeta=1.5))
    steps = iter(range(1000))
    values = torch.tensor([[0.0, 1.0], [1.0, 0.0]])
    algo._q_network = lambda obs: values[next(steps) % 2].expand(len(obs), 2)  # greedy flips
    obs = make_env(EnvConfig(num_envs=2), seed=1).reset()["observation"]
    actions = torch.stack([algo._explore(obs)["action"] for _ in range(400)])
    repeats = (actions[1:] == actions[:-1]).float().mean().item()
    assert repeats > 0.75  # every step random: plain ε-greedy repeats half the time (2 actions)
    algo.close()


def test_eps_zeta_on_torchrl_s_collector_is_one_line():
    with pytest.raises(RlpipeError, match="algo.eps_zeta needs an env made by rlpipe.make_env"):
        DQN(torchrl_stepped(EnvConfig(num_envs=2)), DQNConfig(**SMALL, eps_zeta=2.0))


@pytest.mark.parametrize("q_max", [None, 0.5])
def test_q_max_bounds_the_q_values_learned(q_max):
    """CartPole pays 1 a step, so every target is at least 1 without a bound: the learned
    values rise past 1; with ``q_max`` 0.5 they settle at or under it."""
    torch.manual_seed(0)
    cfg = DQNConfig(**{**SMALL, "updates_per_batch": 8}, lr=1e-2, q_max=q_max)
    algo = DQN(partial(make_env, EnvConfig(num_envs=2), seed=0), cfg)
    try:
        assert algo.loss.q_max == q_max
        q_means = [algo.train_step().get("train/q_mean") for _ in range(20)][-5:]
        assert min(q_means) > 1.0 if q_max is None else max(q_means) < 0.75
    finally:
        algo.close()
