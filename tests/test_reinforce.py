"""REINFORCE: returns, whole-episode collection, policies within bounds, runner and CLI."""

from __future__ import annotations

import inspect
import json

import gymnasium as gym
import pytest
import torch
from conftest import TINY
from tensordict import TensorDict
from torchrl.envs import ExplorationType, set_exploration_type

from rlpipe.algos import Reinforce, ReinforceConfig
from rlpipe.algos.reinforce import collect_episodes, make_policy, normalized_returns
from rlpipe.config import EnvConfig
from rlpipe.envs import make_env
from rlpipe.errors import RlpipeError
from rlpipe.evaluation import evaluate
from rlpipe.runner import Runner

CONTINUOUS = EnvConfig(id="rlpipe/CartPoleContinuous-v0", num_envs=4, max_episode_steps=50)


def test_returns_are_discounted_and_normalised_per_episode():
    done = torch.tensor([0, 0, 1, 0, 1], dtype=torch.bool).unsqueeze(-1)
    batch = TensorDict(
        {"next": {"reward": torch.tensor([1.0, 1, 1, 4, 0]).unsqueeze(-1), "done": done}},
        batch_size=[5],
    )
    first = torch.tensor([1 + 0.5 + 0.25, 1 + 0.5, 1])  # gamma 0.5
    second = torch.tensor([4.0, 0])
    expected = torch.cat([(g - g.mean()) / g.std() for g in (first, second)])
    assert torch.allclose(normalized_returns(batch, 0.5), expected, atol=1e-5)


def test_collects_exactly_the_asked_whole_episodes():
    env = make_env(CONTINUOUS, seed=0)
    policy, _ = make_policy(env, [])
    batch, frames = collect_episodes(policy, env, 10)
    done = batch["next", "done"].squeeze(-1)
    assert int(done.sum()) == 10 and bool(done[-1])
    starts = torch.cat([torch.tensor([True]), done[:-1]])
    assert (batch["step_count"].squeeze(-1)[starts] == 0).all()  # each episode from its reset
    assert frames % 4 == 0 and frames >= batch.numel()
    env.close()


def test_gaussian_actions_stay_in_bounds_and_greedy_is_the_clipped_mean():
    env = make_env(CONTINUOUS, seed=0)
    policy, key = make_policy(env, [])
    assert key == "sample"
    linear = next(m for m in policy.modules() if isinstance(m, torch.nn.Linear))
    with torch.no_grad():
        linear.weight.zero_()
        linear.bias.copy_(torch.tensor([3.0, 0.0]))  # mean 3, std sigmoid(0) = 0.5
    td = policy(env.reset())
    assert (td["action"] == 1.0).all() and (td["sample"] > 1.0).any()
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        assert (policy(env.reset())["action"] == 1.0).all()
    assert 0 < td["scale"].min() and td["scale"].max() < 1
    env.close()


def test_categorical_policy_for_discrete_actions():
    env = make_env(EnvConfig(id="rlpipe/CartPoleNoop-v0", num_envs=3), seed=0)
    policy, key = make_policy(env, [8])
    assert key == "action"
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        td = policy(env.reset())
    assert torch.equal(td["action"], td["logits"].argmax(-1))
    env.close()


def test_unsupported_action_space_is_a_clear_error():
    if "rlpipe/TestMultiDiscrete-v0" not in gym.registry:
        gym.register("rlpipe/TestMultiDiscrete-v0", entry_point=MultiDiscreteEnv)
    env = make_env(EnvConfig(id="rlpipe/TestMultiDiscrete-v0"))
    with pytest.raises(RlpipeError, match="REINFORCE's policy needs discrete actions"):
        Reinforce(env, ReinforceConfig())


class MultiDiscreteEnv(gym.Env):
    """A one-step env whose actions are a MultiDiscrete vector."""

    observation_space = gym.spaces.Box(-1, 1, (2,))
    action_space = gym.spaces.MultiDiscrete([2, 3])

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        return self.observation_space.sample(), {}

    def step(self, action):
        return self.observation_space.sample(), 0.0, True, False, {}


@pytest.mark.parametrize(
    "kwargs, message",
    [
        ({"episodes_per_epoch": 0}, "episodes_per_epoch"),
        ({"updates_per_epoch": -1}, "updates_per_epoch"),
        ({"gamma": 0.0}, "gamma"),
        ({"gamma": 1.01}, "gamma"),
        ({"batch_size": 0}, "batch_size"),
    ],
)
def test_bad_values(kwargs, message):
    with pytest.raises(RlpipeError, match=message):
        ReinforceConfig(**kwargs)


def test_learns_discrete_cartpole_and_resumes_exactly(tmp_path):
    torch.manual_seed(0)
    cfg = ReinforceConfig(hidden_sizes=[32], episodes_per_epoch=16, updates_per_epoch=20, lr=1e-2)
    env_cfg = EnvConfig(id="CartPole-v1", num_envs=8)
    algo = Reinforce(make_env(env_cfg, seed=0), cfg)
    eval_env = make_env(env_cfg, seed=1)
    before = evaluate(algo.policy, eval_env, 8).mean
    result = Runner(
        algo, eval_env, tmp_path, total_frames=8_000, eval_every=0, progress=False
    ).run()
    assert result.eval_mean > before + 50
    restored = Reinforce(make_env(env_cfg, seed=0), cfg)
    restored.load_state_dict(algo.state_dict())
    assert restored.frames == algo.frames >= 8_000
    td = eval_env.reset()
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        assert torch.equal(algo.policy(td.clone())["action"], restored.policy(td)["action"])
    algo.close()
    restored.close()


def test_cli_trains_on_the_continuous_cartpole(rlpipe_cli, tmp_path):
    proc = rlpipe_cli(
        "algo=reinforce", "env=cartpole_continuous", *TINY, "algo.episodes_per_epoch=8"
    )
    assert proc.returncode == 0, proc.stderr
    run = tmp_path / "run"
    assert json.loads((run / "summary.json").read_text())["frames"] >= 200
    assert (run / "metrics" / "scalars" / "train" / "episode_return.csv").exists()
    assert any((run / "checkpoints").iterdir())


BAD_INPUTS = [
    (["algo.episodes_per_epoch=0"], "algo.episodes_per_epoch must be >= 1, got 0"),
    (["algo.gamma=0"], "algo.gamma must be in (0, 1], got 0.0"),
    (["algo.gamma=1.5"], "algo.gamma must be in (0, 1], got 1.5"),
    (["env=gym", "env.id=multi_action:MultiAction-v0"], "REINFORCE's policy needs discrete"),
]


@pytest.mark.parametrize("args, message", BAD_INPUTS, ids=[" ".join(a) for a, _ in BAD_INPUTS])
def test_cli_bad_input_is_one_clear_line(rlpipe_cli, tmp_path, args, message):
    source = inspect.getsource(MultiDiscreteEnv)  # importable by the subprocess, from its cwd
    (tmp_path / "multi_action.py").write_text(
        f"import gymnasium as gym\n\n\n{source}\n\n"
        'gym.register("MultiAction-v0", entry_point=MultiDiscreteEnv)\n'
    )
    proc = rlpipe_cli("progress=false", "algo=reinforce", "env=cartpole_continuous", *args)
    assert proc.returncode == 2
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    assert len(lines) == 1, proc.stderr
    assert lines[0].startswith("rlpipe: error: ") and message in lines[0]
    assert not (tmp_path / "run" / "checkpoints").exists()
